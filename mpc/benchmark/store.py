"""Cache entries on disk: JSON with a schema version and a checksum, written atomically, checked on load.

An entry is its payload's fields plus ``schema`` (its kind and :data:`SCHEMA_VERSION`) and ``checksum``:
the sha256 of the canonical JSON (sorted keys, no spaces) of everything else, the fingerprint of the
parameters it was solved for included. Non-finite numbers are written as null and refused when read.

Reading (:func:`read_entry`) checks, in order: the file parses as UTF-8 JSON without NaN or infinite
numbers, carries this schema, passes the kind's own check (fields, types, shapes, e.g. a monotone
front), matches its checksum and, if the caller expects one, the parameter fingerprint. Any failure is a
:class:`BadEntry` that names the file. :func:`load_entry` turns it into a warning, moves the file aside
(``<name>.bad-<timestamp>``, kept for a look and never read again) and returns None, so the caller
recomputes the entry: a bad cache costs time, never a wrong number or a traceback.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from wl_env import atomic_io
from wl_env.atomic_io import _finite, _json_default, write_atomic  # the converters atomic_io writes JSON with
from wl_env.params import shown

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
Check = Callable[[dict[str, Any]], "str | None"]  # the problem with an entry's fields, or None


class BadEntry(ValueError):
    """A cache entry that cannot be used; the message names its file and what is wrong."""

    def __init__(self, path: str | os.PathLike, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path, self.problem = Path(path), problem


def canonical(obj: Any) -> str:
    """The JSON text a checksum is taken of: sorted keys, no whitespace, finite numbers only."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False, ensure_ascii=True)


def checksum(data: dict[str, Any]) -> str:
    """sha256 of the canonical JSON of ``data`` without its ``checksum`` field."""
    body = {k: v for k, v in data.items() if k != "checksum"}
    return "sha256:" + hashlib.sha256(canonical(body).encode()).hexdigest()


def as_read(payload: dict[str, Any]) -> dict[str, Any]:
    """``payload`` as an entry of it reads back: numpy -> Python, tuples -> lists, NaN -> null. (TypeError
    for what JSON cannot hold.)"""
    return json.loads(json.dumps(_finite(payload), default=_json_default, allow_nan=False))


def write_entry(path: str | os.PathLike, kind: str, payload: dict[str, Any], check: Check) -> Path:
    """Write ``payload`` as an entry of ``kind`` atomically; BadEntry (nothing written) if it fails ``check``."""
    data = as_read(payload)  # (so the checksum taken now is the one recomputed on load)
    data.pop("checksum", None)
    data["schema"] = {"kind": kind, "version": SCHEMA_VERSION}
    problem = check(data)
    if problem:
        raise BadEntry(path, f"refusing to write a bad {kind}: {problem}")
    data["checksum"] = checksum(data)
    return write_atomic(path, json.dumps(data, indent=1, allow_nan=False) + "\n")


def _reject_constant(name: str) -> Any:
    raise ValueError(f"non-finite number {name}")


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"non-finite number {text}")
    return v


def _float_sized_int(text: str) -> int:
    v = int(text)
    try:
        float(v)  # the entry's checks take numbers as floats: a larger int would fail them with OverflowError
    except OverflowError:
        raise ValueError(f"number too large for a float {text[:20]}...") from None
    return v


MAX_ENTRY_BYTES = 256 * 2**20  # (the largest entries, a suite's fronts, are a few MB)


def read_regular_file(path: str | os.PathLike, limit: int = MAX_ENTRY_BYTES) -> bytes:
    """:func:`wl_env.atomic_io.read_regular_file` with its errors as a BadEntry naming the file (FileNotFoundError
    if there is none)."""
    try:
        return atomic_io.read_regular_file(path, limit, "an entry holds")
    except ValueError as exc:
        raise BadEntry(path, str(exc)) from None


def read_entry(path: str | os.PathLike, kind: str, check: Check, fingerprint: str | None = None,
               expect: dict[str, Any] | None = None) -> dict[str, Any]:
    """The payload of the entry at ``path`` (without schema and checksum); BadEntry if it is not a good
    entry of ``kind`` (solved for ``fingerprint``, and holding the field values of ``expect``, if given:
    e.g. its braking alternative and objective, which the file's name alone does not vouch for).
    FileNotFoundError if there is none."""
    path = Path(path)
    raw = read_regular_file(path)
    try:
        data = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant, parse_float=_finite_float,
                          parse_int=_float_sized_int)
    except UnicodeDecodeError:
        raise BadEntry(path, "not UTF-8 text") from None
    except ValueError as exc:  # JSONDecodeError is one; so are the non-finite numbers
        raise BadEntry(path, f"not valid JSON ({exc})") from None
    except RecursionError:  # (a RuntimeError)
        raise BadEntry(path, "not valid JSON (nested too deeply)") from None
    if not isinstance(data, dict):
        raise BadEntry(path, f"a JSON {type(data).__name__}, not an object")
    schema = data.get("schema")
    if schema != {"kind": kind, "version": SCHEMA_VERSION}:
        raise BadEntry(path, f"schema {shown(schema)}, expected {kind} version {SCHEMA_VERSION}")
    problem = check(data)
    if problem:
        raise BadEntry(path, problem)
    if data.get("checksum") != checksum(data):
        raise BadEntry(path, "checksum mismatch (the content was changed after it was written)")
    if fingerprint is not None and data.get("params_fingerprint") != fingerprint:
        raise BadEntry(path, f"solved for parameters {shown(data.get('params_fingerprint'))}, not {fingerprint!r}")
    for name, value in (expect or {}).items():
        if data.get(name) != value:
            raise BadEntry(path, f"{name} {shown(data.get(name))}, expected {value!r}")
    return {k: v for k, v in data.items() if k not in ("schema", "checksum")}


def set_aside(path: str | os.PathLike, seen: os.stat_result | None = None) -> Path | None:
    """Rename a bad entry to ``<name>.bad-<timestamp>``; returns the new path, or None if the file is
    gone or was replaced since ``seen`` was taken (its lstat; another process already recomputed it)."""
    path = Path(path)
    try:
        now = path.lstat()  # (the entry itself: a bad symlink is set aside, not its target)
        if seen is not None and (now.st_ino, now.st_mtime_ns, now.st_size) != (
                seen.st_ino, seen.st_mtime_ns, seen.st_size):
            return None
        stamp = time.strftime("%Y%m%dT%H%M%S") + f".{time.time_ns() % 10**9:09d}"
        target = path.with_name(f"{path.name}.bad-{stamp}")
        os.replace(path, target)
        return target
    except FileNotFoundError:
        return None


def entry_folder(folder: str | os.PathLike, root: str | os.PathLike) -> Path:
    """``folder`` (in the cache folder ``root``), where entries are written: anything in its place, or in the place of
    a folder between ``root`` and it, that is no folder (a file, a dangling link) is a bad entry, logged and set aside
    as :func:`load_entry` sets one aside. (A file there was a FileExistsError's traceback at the first write, once the
    first optimum was solved.)"""
    folder, at = Path(folder), Path(root)
    for part in folder.relative_to(root).parts:
        at = at / part
        if os.path.lexists(at) and not at.is_dir():
            try:
                moved = set_aside(at)
                where = f"moved to {moved.name}" if moved else "already replaced"
            except OSError as err:
                where = f"left in place, it cannot be moved aside ({err.strerror or err})"
            log.warning(f"bad cache entry {at}: no folder, where a folder of entries belongs -- {where}")
            break
    return folder


def load_entry(path: str | os.PathLike, kind: str, check: Check, fingerprint: str | None = None,
               expect: dict[str, Any] | None = None) -> dict[str, Any] | None:
    """:func:`read_entry`, or None if there is no entry or a bad one (which is logged and set aside)."""
    path = Path(path)
    try:
        seen = path.lstat()
        return read_entry(path, kind, check, fingerprint, expect)
    except (FileNotFoundError, NotADirectoryError):  # (a file where a folder above it belongs: no entry there)
        return None
    except PermissionError as exc:  # (the lstat: a folder on the way that may not be searched)
        log.warning(f"bad cache entry {path}: unreadable ({exc.strerror or exc}); recomputing it")
        return None
    except BadEntry as exc:
        try:
            moved = set_aside(path, seen)
            where = f"moved to {moved.name}" if moved else "already replaced"
        except OSError as err:  # (a read-only cache: the rename's PermissionError or EROFS was a traceback)
            where = f"left in place, it cannot be moved aside ({err.strerror or err})"
        log.warning(f"bad cache entry {exc} -- {where}; recomputing it")
        return None
