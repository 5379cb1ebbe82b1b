"""Atomic file output: readers see a file's old content or its new one, never a part of it.

Results, caches, checkpoints, figures and animations are all written through :func:`atomic_path`: a
temporary file beside the target (same file system, so the rename is atomic), flushed to disk, renamed
over the target when the writing succeeded and removed when it failed.
"""

from __future__ import annotations

import json
import math
import os
import stat
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on leaving the block it replaces ``path`` (or is removed if
    the block raised). ``suffix`` keeps a file type for writers that go by the extension (".gif"). A symbolic
    link is written through (its target replaced, not the link); a path that exists and is not a regular file
    (a device, a pipe) is refused with ValueError: the rename would replace it (as root, ``/dev/null`` itself)."""
    path = _regular_file(Path(path), "output file")
    tmp = None
    # (the folders it makes removed again if the write fails: Ctrl-C left a new cache folder empty)
    with folders_kept_if_used(path.parent):
        try:  # (from the file's creation on: Ctrl-C while the umask was read left the temporary file behind)
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + suffix)
            os.close(fd)
            os.chmod(tmp, 0o666 & ~current_umask())  # as an ordinary file, not mkstemp's 0600
            yield Path(tmp)
            with open(tmp, "rb+") as fh:  # on disk before it becomes the file readers see
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException as exc:
            if tmp is not None:
                Path(tmp).unlink(missing_ok=True)
            if isinstance(exc, OSError) and exc.filename is None:  # (a full disk: "[Errno 28] No space left on device")
                raise type(exc)(exc.errno, f"{exc.strerror or exc} writing {path}") from None
            raise


def missing_folders(folder: str | os.PathLike) -> list[Path]:
    """``folder`` and those of its parents that do not exist yet, the deepest first: the folders a write there makes."""
    missing, folder = [], Path(folder)
    while not os.path.lexists(folder) and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


def remove_empty_folders(folders: Sequence[Path]) -> None:
    """Those of ``folders`` (:func:`missing_folders`, the deepest first) that are empty, removed: a command stopped
    (Ctrl-C, an error) leaves no empty folder it made. A folder holding anything stays."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            pass


@contextmanager
def folders_kept_if_used(folder: str | os.PathLike) -> Iterator[Path]:
    """A block that makes ``folder`` (or a file in it): those of it and its parents it made are removed again if the
    block raises (Ctrl-C, an error) and leaves them empty."""
    made = missing_folders(folder)
    try:
        yield Path(folder)
    except BaseException:
        remove_empty_folders(made)
        raise


def current_umask() -> int:
    """The process's umask, read without changing it where the system says it (Linux: /proc/self/status). Setting it
    to 0 and back to read it left a window in which a file or folder another thread created (the MPC's worker, a
    logger, a Ray client) got mode 0666 or 0777, writable by anyone."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    umask = os.umask(0o077)  # (elsewhere: read it by setting it, to a mask that opens nothing up meanwhile)
    os.umask(umask)
    return umask


def read_regular_file(path: str | os.PathLike, limit: int | None, holds: str = "") -> bytes:
    """The bytes of the regular file ``path`` (a symbolic link followed), checked on the file opened and read no
    further than ``limit`` bytes (None: no limit): a FIFO blocked a read for good, /dev/zero never ended one, and a
    file swapped in after a check was read. FileNotFoundError if there is none; else a ValueError saying what is
    wrong, to follow the file's name ("not a regular file", "N bytes, more than <holds> (<limit>)", ...)."""
    if limit is not None:
        most = f"{holds} ({limit // 2**20} MiB)" if limit % 2**20 == 0 else f"{holds} ({limit} bytes)"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))  # (a FIFO with no writer: no wait)
        try:
            info = os.fstat(fd)
            if stat.S_ISDIR(info.st_mode):
                raise ValueError("a folder, not a file")
            if not stat.S_ISREG(info.st_mode):
                raise ValueError("not a regular file")
            if limit is not None and info.st_size > limit:
                raise ValueError(f"{info.st_size} bytes, more than {most}")
            with os.fdopen(fd, "rb", closefd=False) as f:
                # (a file that grows, or says it is empty as /proc's do, is read no further)
                data = f.read() if limit is None else f.read(limit + 1)
        finally:
            os.close(fd)
    except FileNotFoundError:
        raise
    except OSError as exc:  # a symbolic link loop, no permission, ...
        raise ValueError(f"unreadable ({exc.strerror or exc})") from None
    if limit is not None and len(data) > limit:
        raise ValueError(f"larger than {most}")
    return data


def _regular_file(path: Path, what: str) -> Path:
    """``path`` with its symbolic links resolved; ValueError starting with ``what`` if it exists and is not a
    regular file."""
    try:  # (a name too long for the system was an OSError that named no option)
        real = Path(os.path.realpath(path))
        if real.exists() and not real.is_file():
            kind = "a folder" if real.is_dir() else "not a regular file (a device, a pipe or a socket)"
            raise ValueError(f"{what}: {path} is {kind}; give a file name")
    except OSError as exc:
        raise ValueError(f"{what}: cannot use the path {path} ({exc.strerror or exc})") from None
    return real


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 150) -> Path:
    """A matplotlib figure written atomically, in the format of the path's suffix (PNG without one)."""
    path = Path(path)
    with atomic_path(path) as tmp:  # the temporary's name ends in .tmp: the format is passed, not guessed
        fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", dpi=dpi)
    return path


def check_output_folder(folder: str | os.PathLike, what: str) -> Path:
    """Create ``folder`` if missing and probe it with a real write (permission bits say nothing for root or
    a read-only file system), so a bad output path fails before the work, not after it. ValueError
    starting with ``what`` (e.g. ``"--out results/x.json"``) if it is a file, cannot be created or is
    not writable, or an empty string (``Path("")`` is the working folder: outputs would land there unasked)."""
    if not str(folder).strip():
        raise ValueError(f"{what.strip()}: an empty path names no folder")
    folder = Path(folder)
    try:  # (exists() too: a name too long for the system was an OSError that named no option)
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"{what}: {folder} is not a folder")
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ValueError(f"{what}: cannot create or write in the folder {folder} ({exc.strerror or exc})") from None
    return folder


def check_output_file(path: str | os.PathLike, option: str) -> Path:
    """An output file's path checked before the work (:func:`check_output_folder` on its folder): ValueError
    naming ``option`` (e.g. ``"--json"``) if it is empty, a folder, or its folder cannot be created or written
    in. (The benchmarks wrote their ``--json`` only after minutes of work.)"""
    if not str(path).strip():
        raise ValueError(f"{option} must name a file, got an empty string")
    if str(path).endswith(("/", os.sep)):  # (Path drops the slash: `--out newdir/` became a file named newdir)
        raise ValueError(f"{option} {path} names a folder (its trailing /): give a file name")
    real = _regular_file(Path(path), option)
    check_output_folder(real.parent, f"{option} {path}")
    return Path(path)


def check_output_option(parser: Any, path: str | os.PathLike | None, option: str) -> None:
    """:func:`check_output_file` for a script's option (None: not given), as its ``parser.error``: one line, exit 2."""
    if path is not None:
        try:
            check_output_file(path, option)
        except ValueError as exc:
            parser.error(str(exc))


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    return Path(path)


def json_text(obj: Any, indent: int = 1, nan_as_null: bool = False) -> str:
    """``obj`` as JSON text ending in a newline. numpy scalars and arrays, tuples and paths are converted;
    non-finite floats are written as NaN/Infinity (Python's json reads them back) or, with ``nan_as_null``, as
    null (strict JSON)."""
    return json.dumps(_finite(obj) if nan_as_null else obj, indent=indent, default=_json_default,
                      allow_nan=not nan_as_null) + "\n"


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int = 1, nan_as_null: bool = False) -> Path:
    """``obj`` as JSON (:func:`json_text`), atomically."""
    return write_atomic(path, json_text(obj, indent, nan_as_null))


def _finite(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer, np.bool_, np.ndarray)):  # (an array's NaN was "Out of range float values")
        o = o.tolist()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (tuple, set)):
        return list(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serializable")


def check_not_an_input(out: str | Path, inputs: Sequence[str | Path], option: str) -> None:
    """ValueError if the output file ``out`` is one of the files the command reads, by any path (links too): the result
    was written over its input (``distill_plans.py --policy P --out P`` replaced the policy it distils), as ``wl``
    refuses it."""
    try:
        written = os.stat(out)
    except OSError:  # (a new file is no input)
        return
    for path in inputs:
        try:
            same = os.path.samestat(written, os.stat(path))
        except OSError:
            continue
        if same:
            raise ValueError(f"{option} {out} is the input file {path}: the result would replace it; give another path")


def refuse_one_path_twice(outputs: Sequence[tuple[str, str | os.PathLike]]) -> None:
    """ValueError naming both if two of a command's outputs ``(option, path)`` are one path, by any spelling (a relative
    path, a link): the later write replaced the earlier, or failed on the folder the earlier made, after the work
    (``fit_min_time.py --cache X --out X``: its solves, then "X is a folder")."""
    seen: dict[str, str] = {}
    for option, path in outputs:
        real = os.path.realpath(path)
        if real in seen:
            raise ValueError(f"{option} {path} is the same path as {seen[real]}: one would replace or block the other "
                             "after the work; give another path")
        seen[real] = f"{option} {path}"
