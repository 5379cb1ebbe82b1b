"""Scenarios: the loading cycles a real site has (payload, distances, ground, truck, start state, braking).

A :class:`Scenario` is what changes from cycle to cycle on a site; everything else (the machine) stays a
:class:`~wl_env.params.LoaderParams`. ``scenario.params(base)`` is the machine driving that cycle: the
environment, the OCP, the MPC and the scoring all take it, so a scenario is one parameter set of the
one model. ``Scenario.nominal()`` is the paper's cycle and maps onto the default parameters exactly.

| field               | unit | range          | nominal | model                      |
|---------------------|------|----------------|---------|----------------------------|
| payload             | kg   | 6 000 - 13 000 | 10 000  | M_load (bucket plus load)  |
| reverse_distance    | m    | 4 - 10         | 6.6     | pile -> reversing point    |
| forward_distance    | m    | 4 - 10         | 6.6     | reversing point -> truck   |
| rolling_resistance  | -    | 0.015 - 0.05   | 0.03    | c_r                        |
| dump_height         | m    | 3.5 - 5.1      | 5.0     | H_T (the boom reaches 5.2) |
| start_engine_speed  | rpm  | 800 - 2 000    | 1 500   | omega_0                    |
| start_bucket_height | m    | 0.5 - 1.2      | 0.7     | H_0                        |
| braking             | -    | service, tc    | service | the braking alternative    |
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wl_env.atomic_io import read_regular_file
from wl_env.cycle import BRAKING_MODES
from wl_env.params import DEFAULT_PARAMS, LoaderParams, is_finite, plain, shown

RPM = math.pi / 30.0  # rad/s per rpm


@dataclass(frozen=True)
class FieldSpec:
    """A scenario field: unit, allowed range, nominal value and the LoaderParams field it sets."""

    unit: str
    lo: float
    hi: float
    nominal: float
    param: str
    to_param: float = 1.0  # LoaderParams value = scenario value * to_param


FIELDS: dict[str, FieldSpec] = {
    "payload": FieldSpec("kg", 6000.0, 13000.0, 10000.0, "M_load"),
    "reverse_distance": FieldSpec("m", 4.0, 10.0, 6.6, "reverse_distance"),
    "forward_distance": FieldSpec("m", 4.0, 10.0, 6.6, "forward_distance"),
    "rolling_resistance": FieldSpec("-", 0.015, 0.05, 0.03, "c_r"),
    "dump_height": FieldSpec("m", 3.5, 5.1, 5.0, "H_T"),
    "start_engine_speed": FieldSpec("rpm", 800.0, 2000.0, 1500.0, "omega_0", RPM),
    "start_bucket_height": FieldSpec("m", 0.5, 1.2, 0.7, "H_0"),
}
NUMERIC_FIELDS = tuple(FIELDS)


@dataclass(frozen=True)
class Scenario:
    """One loading cycle (see the module's table). Frozen and validated: a value outside its range raises
    ``ValueError`` naming the field and the range. Numbers are stored as floats, so equal scenarios
    compare, hash and fingerprint equal however they were spelled."""

    payload: float = 10000.0  # kg, the paper's M_load (bucket plus load)
    reverse_distance: float = 6.6  # m, pile -> reversing point
    forward_distance: float = 6.6  # m, reversing point -> truck
    rolling_resistance: float = 0.03  # c_r
    dump_height: float = 5.0  # m, H_T
    start_engine_speed: float = 1500.0  # rpm
    start_bucket_height: float = 0.7  # m, H_0
    braking: str = "service"

    def __post_init__(self) -> None:
        for name, spec in FIELDS.items():
            v = plain(getattr(self, name))
            allowed = f"[{spec.lo:g}, {spec.hi:g}]" + ("" if spec.unit == "-" else f" {spec.unit}")
            if isinstance(v, bool) or not isinstance(v, numbers.Real):
                raise ValueError(f"Scenario.{name} must be a number in {allowed}, got {shown(v)} ({type(v).__name__})")
            if not (is_finite(v) and spec.lo <= float(v) <= spec.hi):  # (is_finite: ints too large for a float)
                raise ValueError(f"Scenario.{name} must lie in {allowed}, got {shown(v)}")
            object.__setattr__(self, name, float(v))
        if isinstance(self.braking, str):  # (a str subclass, np.str_ say, as the str it holds: its == may say yes to anything)
            object.__setattr__(self, "braking", str.__str__(self.braking))
        if self.braking not in BRAKING_MODES:
            raise ValueError(f"Scenario.braking must be one of {BRAKING_MODES}, got {shown(self.braking)}")

    # ------------------------------------------------------------------ construction
    @classmethod
    def nominal(cls, braking: str = "service") -> Scenario:
        """The paper's cycle: 10 t payload, 6.6 m each way, c_r 0.03, 5 m dump height, 1500 rpm, H = 0.7 m."""
        return cls(braking=braking)

    @classmethod
    def from_dict(cls, data: Any) -> Scenario:
        """A scenario from a mapping of its fields; a missing field takes its nominal value."""
        if not isinstance(data, dict):
            raise ValueError(f"a scenario must be a JSON object of its fields, got {type(data).__name__}")
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(map(str, data)) - set(known))
        if unknown:
            raise ValueError(f"unknown Scenario field(s) {shown(unknown, 200)}; known: {known}")
        return cls(**data)

    @classmethod
    def parse(cls, text: str, name: str = "--scenario", braking: str | None = None) -> Scenario:
        """A scenario from JSON text or from the path of a JSON file; errors name it ``name`` (the CLI's
        ``--scenario`` by default; the library's ``scenario``) and the file. ``braking``: the braking of JSON that
        names none (default: the field's default)."""
        if isinstance(text, Path):  # (a path as the CLI's text names it)
            text = str(text)
        if not isinstance(text, str):  # (an int or bytes failed in strip(): an AttributeError, a TypeError)
            raise ValueError(f"{name} takes JSON text or the path of a JSON file, got {shown(text)} ({type(text).__name__})")
        text, what = text.strip(), name
        if not text:  # (Path("") is the working folder: the error said "'' is a folder")
            raise ValueError(f"{name} takes JSON text or a JSON file, got an empty text")
        if not text.startswith(("{", "[")):  # (a JSON list is read to say it is not an object)
            path = Path(text)
            if not is_file(path):
                try:
                    what_is = "is a folder" if path.is_dir() else "is not a regular file" if path.exists() else ""
                except OSError:  # (a name too long)
                    what_is = ""
                raise ValueError(f"{name} takes JSON text or a JSON file; "
                                 + (f"{shown(text)} {what_is}" if what_is else f"no file {shown(text)}"))
            what = f"{name} file {text}"
            text = read_scenario_file(path, what)
        try:
            data = json.loads(text, object_pairs_hook=no_duplicate_keys)
        except ValueError as exc:  # (JSONDecodeError, and an integer of more digits than Python converts)
            raise ValueError(f"{what} is not valid JSON: {' '.join(str(exc).split())[:200]}") from None
        except RecursionError:  # (a RuntimeError, not a JSONDecodeError)
            raise ValueError(f"{what} is not a scenario: its JSON is nested too deeply") from None
        except DuplicateKey as exc:
            raise ValueError(f"{what}: the field {exc.args[0]!r} is given twice") from None
        if braking is not None and isinstance(data, dict) and "braking" not in data:
            data = {"braking": braking, **data}
        try:
            return cls.from_dict(data)
        except ValueError as exc:  # (which file: a field's range alone did not say)
            if what == name:
                raise
            raise ValueError(f"{what}: {exc}") from None

    @classmethod
    def from_params(cls, params: LoaderParams, braking: str = "service") -> Scenario:
        """The scenario a parameter set drives (raises if one of its scenario fields is out of range)."""
        if not isinstance(params, LoaderParams):  # (None or a dict was an AttributeError)
            raise ValueError(f"params must be a LoaderParams, got {shown(params)} ({type(params).__name__})")
        # (rounded to 9 decimals: rpm from rad/s is not exact in floats)
        return cls(braking=braking, **{name: round(getattr(params, s.param) / s.to_param, 9) for name, s in FIELDS.items()})

    def replace(self, **changes: Any) -> Scenario:
        """A copy with some fields changed (validated); an unknown name is a ValueError naming it (it was a TypeError)."""
        known = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(changes) - set(known))
        if unknown:
            raise ValueError(f"unknown Scenario field(s) {shown(unknown, 200)}; known: {known}")
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ what it means for the model
    def params(self, base: LoaderParams = DEFAULT_PARAMS) -> LoaderParams:
        """The machine ``base`` driving this cycle (``Scenario.nominal().params()`` is DEFAULT_PARAMS); a
        ValueError naming the scenario's field if the machine cannot take it (a start engine speed above its
        omega_max, say)."""
        if not isinstance(base, LoaderParams):  # (None or a dict was an AttributeError; a ParamsView has no replace())
            raise ValueError(f"base must be a LoaderParams (the machine), got {shown(base)} ({type(base).__name__})")
        try:
            return base.replace(**{s.param: getattr(self, name) * s.to_param for name, s in FIELDS.items()})
        except ValueError as exc:  # (LoaderParams names its own field, in its units: say which of ours set it)
            name = next((n for n, s in FIELDS.items() if f"LoaderParams.{s.param} " in str(exc)), None)
            if name is None:
                raise
            raise ValueError(f"Scenario.{name} = {getattr(self, name):g} {FIELDS[name].unit} does not fit this "
                             f"machine: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def fingerprint(self, base: LoaderParams = DEFAULT_PARAMS) -> str:
        """A short stable hash of the cycle (its parameters on ``base`` and the braking): the cache key."""
        text = json.dumps({"braking": self.braking, "params": self.params(base).fingerprint()}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def features(self) -> np.ndarray:
        """The numeric fields normalized to [-1, 1] over their ranges (the observation's scenario part)."""
        return np.array([feature(name, getattr(self, name)) for name in NUMERIC_FIELDS])

    def label(self) -> str:
        return (f"{self.braking} {self.payload / 1000:g} t, {self.reverse_distance:g}/{self.forward_distance:g} m, "
                f"c_r {self.rolling_resistance:g}, H_T {self.dump_height:g} m, {self.start_engine_speed:.0f} rpm, "
                f"H_0 {self.start_bucket_height:g} m")


# bytes a scenario file may hold: a scenario is a JSON object of 8 fields (~250 bytes); a 3 GB file was read whole
# (20 s, 6 GB)
MAX_SCENARIO_FILE_BYTES = 2**20


def read_scenario_file(path: Path, what: str) -> str:
    """The text of the scenario file ``path`` (``what`` names it in errors): a regular file of at most
    MAX_SCENARIO_FILE_BYTES (:func:`wl_env.atomic_io.read_regular_file`)."""
    try:
        data = read_regular_file(path, MAX_SCENARIO_FILE_BYTES, "a scenario's JSON holds")
    except OSError as exc:  # (gone since the caller saw it)
        raise ValueError(f"{what}: cannot read it ({exc})") from None
    except ValueError as exc:
        raise ValueError(f"{what} is {exc}") from None
    try:
        return data.decode("utf-8-sig")  # (a byte order mark, as some editors write, was "not valid JSON")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{what}: cannot read it as text ({exc})") from None


def is_file(path: str | Path) -> bool:
    """``Path(path).is_file()``, False (not OSError) for a name too long to be a path, e.g. mistyped JSON."""
    try:
        return Path(path).is_file()
    except (OSError, ValueError):  # ENAMETOOLONG; a NUL character
        return False


def feature(name: str, value: Any) -> Any:
    """A scenario field's value (a float or an array) normalized to [-1, 1] over its range."""
    s = FIELDS[name]
    return (value - 0.5 * (s.lo + s.hi)) / (0.5 * (s.hi - s.lo))


def param_distance(a: dict[str, float], b: dict[str, float]) -> float:
    """How far two cycles lie apart: their scenario fields (by LoaderParams name, e.g. ``M_load``), each
    over its range's width, squared and summed."""
    return math.fsum(((a[s.param] - b[s.param]) / ((s.hi - s.lo) * s.to_param)) ** 2 for s in FIELDS.values())


def param_features(params: Any) -> tuple[Any, ...]:
    """The scenario features of a parameter set (LoaderParams or a batch :class:`~wl_env.params.ParamsView`)."""
    return tuple(feature(name, getattr(params, s.param) / s.to_param) for name, s in FIELDS.items())


class DuplicateKey(Exception):
    """A JSON object that names a key twice (json keeps the last without a word)."""


def no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """json's ``object_pairs_hook`` that raises DuplicateKey for a key given twice."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKey(key[:80])
        out[key] = value
    return out


def resolve_scenario(scenario: Scenario | dict | str | Path | None, braking: str | None = None) -> Scenario:
    """A Scenario from a Scenario, a dict of fields, JSON text or a file path (text or a Path); ``None`` is the
    nominal cycle. ``braking``, if given, must agree with the scenario's (a dict without one takes it)."""
    if scenario is None:
        return Scenario.nominal(braking or "service")
    if isinstance(scenario, dict):
        scenario = Scenario.from_dict({"braking": braking, **scenario} if braking and "braking" not in scenario else scenario)
    elif isinstance(scenario, (str, Path)):  # (as a dict: JSON without a braking takes this one; a Path was refused)
        scenario = Scenario.parse(scenario, "scenario", braking)
    elif not isinstance(scenario, Scenario):
        raise ValueError(f"scenario must be a Scenario, a dict of its fields, JSON or a JSON file's path, got "
                         f"{type(scenario).__name__}")
    if braking is not None and braking != scenario.braking:
        raise ValueError(f"braking={braking!r} contradicts the scenario's braking {scenario.braking!r}")
    return scenario
