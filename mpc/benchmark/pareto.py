"""The fuel-time Pareto front of the cycle: minimum fuel at fixed cycle times, cached on disk.

The sweep runs from the minimum-time cycle to the fuel-optimal one. Every point is warm-started from
its neighbour (continuation) on one mesh fine enough for the longest cycle; near the minimum time,
where the problem has several local optima (other splits of the time between the four phases), template
starts are tried beside it. A second pass continues back from the fuel-optimal end (a forward chain
that took a worse basin carries it along). The best verified solution of each point is kept. Each
solve is re-simulated and written to the cache as soon as it is done, so an interrupted sweep resumes
where it stopped. The cache key is the braking alternative, the parameter fingerprint and the number of
points. :func:`pareto_fronts` sweeps both braking alternatives in parallel processes
(:mod:`mpc.workers`: they stop on Ctrl-C and die with their parent).

Every file of the cache is an entry of :mod:`mpc.benchmark.store`: schema version, checksum, parameter
fingerprint, checked on load (:func:`check_result`, :func:`check_front`: fields, types, finite numbers,
a monotone front); a bad one is logged, set aside and solved again. An interrupted solve is never
cached (:mod:`mpc.interrupt`). Progress goes to this module's logger.
"""

from __future__ import annotations

import logging
import math
import numbers
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from mpc.benchmark import store
from mpc.benchmark.ocp import (
    MAX_CYCLE_TIME,
    OBJECTIVES,
    OCPError,
    OCPResult,
    OCPSettings,
    solve_ocp,
    verification_passed,
)
from wl_env import cycle
from wl_env.params import LoaderParams, check_flag, is_integer, is_real_number, plain, resolve, shown
from wl_env.scenario import param_distance

log = logging.getLogger(__name__)

CACHE_ENV = "WL_CACHE_DIR"
FRONT_KIND, RESULT_KIND = "pareto_front", "ocp_result"  # the kinds of cache entries (mpc.benchmark.store)
FIRST_POINT_SLACK = 1e-3  # the front starts at T_min * (1 + this): minimum fuel in the fastest cycle
# Template starts (leg = T/2, these acceleration fractions) beside the neighbour's warm start, at cycle
# times below MULTI_START_BELOW * T_min. Measured on both alternatives (7 points, templates 0.6/0.7/0.8):
# templates beat continuation by 0.3-1.2 % within 4 % of T_min (0.6 or 0.8 won; 0.7 never alone), never
# from 13 % on.
SWEEP_ACCEL_FRACTIONS = (0.6, 0.8)
MULTI_START_BELOW = 1.10
DEFAULT_POINTS = 11  # points per front (the shipped suites', the scoring's, `wl pareto`'s default)
NEAR_POINT_SLACK, SECOND_POINT_SLACK = 3e-3, 6e-3  # front_times: points at T_min * (1 + these)
END_REFINEMENTS = 3  # mesh refinements of a front's ends (solve_ocp's default; a point gets one)


def cache_dir(path: str | os.PathLike | None = None) -> Path:
    """Where solved optima are kept: ``path``, else $WL_CACHE_DIR, else ~/.cache/wheel-loader-gym. ValueError
    naming ``cache`` (or the variable) if that is no folder path, or it or a folder above it is a file (a file
    as the cache was a NotADirectoryError's traceback from the first lookup, or after a solve)."""
    if path is not None:
        if not isinstance(path, (str, os.PathLike)) or not str(path).strip():  # ("" is the working folder)
            raise ValueError(f"cache must be a folder path or None, got {shown(path)}")
        folder, name = Path(path), "cache"
    else:
        env = os.environ.get(CACHE_ENV)
        folder, name = (Path(env), f"${CACHE_ENV}") if env else (Path.home() / ".cache" / "wheel-loader-gym", "cache")
    above = folder
    while not os.path.lexists(above) and above != above.parent:
        above = above.parent
    if os.path.lexists(above) and not above.is_dir():
        raise ValueError(f"{name} must be a folder, but {above} is {'a file' if above.is_file() else 'no folder'}")
    return folder


@dataclass
class ParetoFront:
    """Minimum fuel against cycle time for one braking alternative (points sorted by T)."""

    braking: str
    T: list[float]
    fuel_g: list[float]
    params_fingerprint: str
    T_min: float
    T_fuel_opt: float
    fuel_min_g: float
    mesh: list[int]
    wall_time: float = 0.0
    points: list[dict[str, Any]] = field(default_factory=list)  # per point: T, fuel, verification summary
    machine: str = ""  # mpc.benchmark.ocp.machine_key: the machine, whatever the scenario
    scenario_fields: dict[str, float] = field(default_factory=dict)  # the scenario's LoaderParams fields
    warm_started_from: str | None = None  # the neighbouring scenario's front folder, if one warm-started it
    scenario: dict[str, Any] | None = None  # the wl_env.scenario.Scenario (None: outside the scenario ranges)

    def fuel_at(self, T: float) -> float:
        """Optimal fuel (g) at cycle time T, interpolated on the front (T_min <= T < T_fuel_opt).

        Monotone cubic in u = sqrt(T - T_min): near T_min the fuel falls like sqrt(T - T_min) (measured on
        the nominal front: d fuel / d u stays within -46..-74 g/sqrt(s) from 1.001 to 1.12 T_min, where
        d fuel / d T runs from -610 to -89 g/s), so in u the front is nearly straight and the points,
        spaced evenly in u (:func:`front_times`), interpolate it closely. Between T_min and the first point
        (0.1 % above it) the first point's fuel is returned.
        """
        T = plain(T)  # (a float32 as the number it prints, not its binary value 9.1000003814)
        if not is_real_number(T):
            raise ValueError(f"cycle time must be a finite number of seconds, got {T!r}")
        T = float(T)
        problem = self.interpolation_problem()
        if problem:  # (unsorted or repeated times interpolated to NaN or any number; one point: an IndexError)
            raise ValueError(f"this {self.braking} front cannot be interpolated: {problem}")
        if T < self.T_min - 1e-6:
            raise ValueError(
                f"cycle time {T:.3f} s is impossible: the minimum cycle time with {self.braking} braking is "
                f"{self.T_min:.3f} s"
            )
        if T >= self.T_fuel_opt:
            raise ValueError(
                f"cycle time {T:.3f} s lies beyond the fuel-optimal cycle ({self.T_fuel_opt:.3f} s); "
                f"use optimal_fuel_at(), which solves such points on demand"
            )
        times, fuel = list(self.T), list(self.fuel_g)
        if T > times[-1] and times[-1] < self.T_fuel_opt - 1e-6:
            # A front whose fuel-optimal end was left out (or cut off) ends at a point short of T_fuel_opt: past it
            # the cubic was extrapolated (41.7 g at 15 s on a front ending at 11 s, under its fuel minimum of
            # 47.5 g). That end is a point of the front: interpolated up to it.
            times.append(float(self.T_fuel_opt))
            fuel.append(float(self.fuel_min_g))
        u = np.sqrt(np.asarray(times) - self.T_min)
        return float(pchip(u, np.asarray(fuel), math.sqrt(max(T, times[0]) - self.T_min)))

    def interpolation_problem(self) -> str | None:
        """What keeps :meth:`fuel_at` from interpolating this front (the rest of :func:`check_front` aside: a
        polished front may hold a local optimum), or None."""
        T, fuel = (list(v) if isinstance(v, (list, tuple, np.ndarray)) else None for v in (self.T, self.fuel_g))
        if not (_nums(T) and _nums(fuel) and len(T) == len(fuel) >= 2):
            return f"cycle times {_short(self.T)} and fuels {_short(self.fuel_g)} are not 2 or more finite pairs"
        if any(b <= a for a, b in pairwise(T)):
            return "the cycle times T do not increase"
        if not (is_real_number(self.T_min) and is_real_number(self.T_fuel_opt) and is_real_number(self.fuel_min_g)
                and self.T_min <= T[0] + 1e-9 and T[-1] <= self.T_fuel_opt + 1e-9):
            return f"T_min {self.T_min!r} and T_fuel_opt {self.T_fuel_opt!r} do not bound the points"
        return None

    def save(self, path: str | os.PathLike) -> Path:
        """Write as a checked cache entry (schema, checksum), atomically; ValueError if the front is bad."""
        return store.write_entry(path, FRONT_KIND, dict(self.__dict__), check_front)

    @classmethod
    def load(cls, path: str | os.PathLike, fingerprint: str | None = None) -> ParetoFront:
        """Read a front :meth:`save` wrote; :class:`mpc.benchmark.store.BadEntry` (a ValueError naming the
        file) if it is not a valid one (solved for the parameters ``fingerprint``, if given)."""
        return cls._from(store.read_entry(path, FRONT_KIND, check_front, fingerprint))

    @classmethod
    def _from(cls, data: dict[str, Any]) -> ParetoFront:
        return cls(**{k: v for k, v in data.items() if k in cls.__dataclass_fields__})


# ---------------------------------------------------------------------------------------------- entry checks
def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _nums(v: Any, n: int | None = None) -> bool:
    return isinstance(v, list) and (n is None or len(v) == n) and all(map(is_real_number, v))


def _rows(v: Any, n: int, width: int) -> bool:
    return isinstance(v, list) and len(v) == n and all(_nums(r, width) for r in v)


def _fields(d: dict[str, Any], spec: dict[str, Any]) -> str | None:
    for name, ok in spec.items():
        if name not in d:
            return f"missing field {name!r}"
        if not ok(d[name]):
            return f"field {name!r} has the wrong type or value ({_short(d[name])})"
    return None


def _short(v: Any) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _optional_num(v: Any) -> bool:
    return v is None or is_real_number(v)


_RESULT_FIELDS = {
    "braking": lambda v: v in cycle.BRAKING_MODES, "objective": lambda v: v in OBJECTIVES,
    "T": lambda v: is_real_number(v) and v > 0, "fuel_g": lambda v: is_real_number(v) and v > 0,
    "phase_durations": lambda v: _nums(v, 4) and min(v) >= 0, "t": lambda v: _nums(v) and len(v) >= 2,
    "states": lambda v: isinstance(v, list), "controls": lambda v: isinstance(v, list),
    "phase": lambda v: isinstance(v, list) and all(_int(k) and 1 <= k <= 4 for k in v),
    "position": lambda v: isinstance(v, list), "status": lambda v: isinstance(v, str),
    "success": lambda v: isinstance(v, bool), "iterations": _int, "wall_time": is_real_number, "w_fuel": _optional_num,
    "target_T": _optional_num, "params_fingerprint": lambda v: isinstance(v, str),
    "mesh": lambda v: isinstance(v, list) and len(v) == 4 and all(_int(n) and n >= 2 for n in v), "degree": _int,
    "solver": lambda v: isinstance(v, str), "smoothing": lambda v: isinstance(v, list),
    "starts": lambda v: isinstance(v, list) and all(isinstance(s, dict) for s in v),
    "verification": lambda v: isinstance(v, dict),
}


def _number_or_null(v: Any) -> bool:
    """A real number (NaN too: a re-simulation that never reversed) or null (a NaN as a cache entry writes it)."""
    return v is None or (isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)))


def _numbers_or_null(v: Any) -> bool:
    return isinstance(v, list) and all(map(_number_or_null, v))


def _named_numbers_or_null(v: Any) -> bool:
    return isinstance(v, dict) and all(map(_number_or_null, v.values()))


# The re-simulation's record (mpc.benchmark.verify.verify_result, with passed, mesh_history and fine_mesh_failed beside
# it): each field's type where it is present ({}: not re-simulated). "passed": "no" counted as passed, and a null
# reversing error was a TypeError in optima.passed.
_VERIFICATION_FIELDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    **{name: (_number_or_null, "a number or null") for name in (
        "reversing_error_m", "final_position_error_m", "final_height_error_m", "final_speed_mps",
        "final_bucket_speed_mps", "fuel_g_simulated", "fuel_rel_error", "max_violation", "max_substep_s",
        "engine_speed_gain")},
    "passed": (lambda v: isinstance(v, (bool, np.bool_)), "true or false"),
    "fine_mesh_failed": (lambda v: isinstance(v, (bool, np.bool_)), "true or false"),
    "check_version": (_int, "an integer"),
    "max_state_error": (_numbers_or_null, "a list of numbers"), "lift_gains": (_numbers_or_null, "a list of numbers"),
    "violations_ocp": (_named_numbers_or_null, "a mapping of numbers"),
    "violations_sim": (_named_numbers_or_null, "a mapping of numbers"),
    "open_loop": (_named_numbers_or_null, "a mapping of numbers"),
    "mesh_history": (lambda v: isinstance(v, list) and all(
        isinstance(h, dict) and isinstance(h.get("verified", False), (bool, np.bool_)) for h in v),
        "a list of records, each verified true or false"),
}


def _verification_problem(v: dict[str, Any]) -> str | None:
    """What is wrong with a result's ``verification`` record's fields (:data:`_VERIFICATION_FIELDS`), or None."""
    for name, (ok, what) in _VERIFICATION_FIELDS.items():
        if name in v and not ok(v[name]):
            return f"verification field {name!r} must be {what}, got {_short(v[name])}"
    return None


def check_result(d: dict[str, Any]) -> str | None:
    """What is wrong with an OCP result entry's fields (as :class:`OCPResult`), or None."""
    problem = _fields(d, _RESULT_FIELDS)
    if problem:
        return problem
    n = len(d["t"])
    if not (_rows(d["states"], n, 4) and _rows(d["controls"], n - 1, 3) and _nums(d["position"], n)
            and len(d["phase"]) == n):
        return f"states, controls, position and phase do not match the {n} sample times"
    if any(b < a for a, b in pairwise(d["t"])) or any(b < a for a, b in pairwise(d["phase"])):
        return "the sample times or phases decrease"
    return _verification_problem(d["verification"]) or _scenario_fields_problem(d.get("scenario_fields", {}))


def _scenario_fields_problem(sf: Any) -> str | None:
    """What is wrong with a result's ``scenario_fields`` (none, ``{}``, or every scenario field of a cycle), or None:
    a warm start is reshaped by them (:func:`mpc.benchmark.ocp.transport`), and one without a distance was a bare
    KeyError there, one with H_T = H_0 a ZeroDivisionError."""
    from wl_env.params import SCENARIO_FIELDS

    if sf is None or sf == {}:
        return None
    if not (isinstance(sf, dict) and set(sf) == set(SCENARIO_FIELDS) and all(map(is_real_number, sf.values()))):
        return f"field 'scenario_fields' must be {{}} or a number for each of {SCENARIO_FIELDS}, got {_short(sf)}"
    if not (sf["reverse_distance"] > 0 and sf["forward_distance"] > 0 and sf["H_T"] > sf["H_0"]):
        return f"field 'scenario_fields' holds no cycle (distances > 0 and H_T > H_0 needed): {_short(sf)}"
    return None


_FRONT_FIELDS = {
    "braking": lambda v: v in cycle.BRAKING_MODES, "T": lambda v: _nums(v) and len(v) >= 2,
    "fuel_g": lambda v: _nums(v) and len(v) >= 2 and min(v) > 0, "params_fingerprint": lambda v: isinstance(v, str),
    "T_min": lambda v: is_real_number(v) and v > 0, "T_fuel_opt": is_real_number, "fuel_min_g": lambda v: is_real_number(v) and v > 0,
    "mesh": lambda v: isinstance(v, list) and len(v) == 4 and all(_int(n) and n >= 2 for n in v),
    "wall_time": lambda v: is_real_number(v) and v >= 0,
    # (each with its cycle time: a shipped suite file's check reads p["T"], before the checksum)
    "points": lambda v: isinstance(v, list) and all(isinstance(p, dict) and is_real_number(p.get("T")) for p in v),
}


def check_n_points(n_points: Any) -> int:
    """``n_points`` (points per front) as an int (numpy's: its folder's name and the JSON); ValueError unless an
    integer in [3, 100]."""
    if not (is_integer(n_points) and 3 <= n_points <= 100):
        raise ValueError(f"n_points must be an integer in [3, 100], got {shown(n_points)}")
    return int(n_points)


def check_front(d: dict[str, Any]) -> str | None:
    """What is wrong with a Pareto front entry (as :class:`ParetoFront`), or None: fields and types,
    at least 2 points, cycle times increasing from T_min to T_fuel_opt, fuel not increasing."""
    problem = _fields(d, _FRONT_FIELDS)
    if problem:
        return problem
    if not d["params_fingerprint"]:  # (such a file scored any scenario's cycle: check_front_of matched it to every one)
        return "field 'params_fingerprint' is empty: a front kept in a file names the parameters it was solved for"
    T, fuel = d["T"], d["fuel_g"]
    if len(T) != len(fuel):
        return f"{len(T)} cycle times but {len(fuel)} fuels"
    if any(b <= a for a, b in pairwise(T)):
        return "the cycle times T do not increase"
    if any(b > a for a, b in pairwise(fuel)):
        return "the fuel rises with the cycle time (on a front it falls)"
    if not (d["T_min"] <= T[0] + 1e-9 and T[-1] <= d["T_fuel_opt"] + 1e-9 and d["fuel_min_g"] <= fuel[-1] + 1e-9):
        return "T_min, T_fuel_opt or fuel_min_g do not bound the points"
    if T[-1] >= d["T_fuel_opt"] - 1e-9 and abs(fuel[-1] - d["fuel_min_g"]) > 1e-9 * max(1.0, abs(fuel[-1])):
        # (the last point is the fuel-optimal cycle: fuel_min_g is its fuel; a report drew one that was not)
        return f"the fuel-optimal point's fuel {fuel[-1]!r} g is not fuel_min_g {d['fuel_min_g']!r} g"
    # (a neighbouring scenario's front is found by them: {"x": 1} was a bare KeyError in nearest_front, and so every
    # other scenario's front of that machine failed before its first solve)
    return _scenario_fields_problem(d.get("scenario_fields", {}))


def check_front_points(d: dict[str, Any], n_points: int) -> str | None:
    """:func:`check_front`, and ``points`` one record per cycle time of an ``n_points`` front, as :func:`pareto_front`
    writes it (each solved or failed point; ``T``/``fuel_g`` hold the verified ones only), or what is wrong."""
    problem = check_front(d)
    # (a front of another size copied into an n<N> folder was taken as that folder's front)
    if problem is None and len(d["points"]) != n_points:
        return (f"field 'points' holds {len(d['points'])} point records, expected {n_points} (n_points, the point "
                f"count its folder is named for)")
    return problem


def save_result(r: OCPResult, path: str | os.PathLike) -> Path:
    """Write an OCP result as a checked entry (schema, checksum), atomically."""
    return store.write_entry(path, RESULT_KIND, r.to_dict(), check_result)


def load_result(path: str | os.PathLike, fingerprint: str | None = None) -> OCPResult:
    """An OCP result :func:`save_result` wrote; BadEntry (a ValueError naming the file) if it is not
    a valid one, FileNotFoundError if there is none."""
    return _result_from(store.read_entry(path, RESULT_KIND, check_result, fingerprint))


def _result_from(data: dict[str, Any]) -> OCPResult:
    return OCPResult(**{k: v for k, v in data.items() if k in OCPResult.__dataclass_fields__})


def solved_at(result: OCPResult | None, T: float) -> bool:
    """``result`` is an optimum for the cycle time ``T`` (s), to 1e-6 of it: the one match of a cached or given
    optimum to the T asked for (four checks wrote it, two of them with another tolerance)."""
    return result is not None and abs(result.T - T) <= 1e-6 * max(1.0, T)


def cached_result(path: str | os.PathLike, fingerprint: str | None = None, objective: str | None = None,
                  braking: str | None = None, params: LoaderParams | None = None) -> OCPResult | None:
    """The valid cached OCP result at ``path`` (solved for ``fingerprint``, or ``params``'s, of ``objective``
    and ``braking``, each if given), or None: missing, or bad (then logged and set aside). Given ``params``, a
    result that failed an older re-simulation check is checked by the current one and saved so."""
    if params is not None:
        fingerprint = params.fingerprint()
    expect = {k: v for k, v in (("objective", objective), ("braking", braking)) if v is not None}
    data = store.load_entry(path, RESULT_KIND, check_result, fingerprint, expect)
    if data is None:
        return None
    r = _result_from(data)
    return r if params is None else _checked_again(r, params, Path(path))


def _checked_again(r: OCPResult, params: LoaderParams, path: Path) -> OCPResult:
    """``r``, or, where it failed an older re-simulation check, checked by the current one (a second: its
    cycle is kept) and saved so: else a cache would serve the old failure for good (``wl evaluate``: "no
    verified optimum"; a front point left out on every rerun)."""
    from mpc.benchmark.verify import CHECK_VERSION, verify_result

    v = r.verification or {}
    if r.success or not v or v.get("check_version") == CHECK_VERSION:
        return r
    r.verification = {**verify_result(r, params), "mesh_history": v.get("mesh_history", [])}
    r.verification["passed"] = verification_passed(r.verification)
    log.info(f"{path}: failed an older re-simulation check; "
             f"{'passes' if r.verification['passed'] else 'fails'} the current one")
    if r.verification["passed"]:
        r.success, r.status = True, r.status.replace(" (re-simulation check failed)", "")
    save_result(r, path)
    return r


def pchip(x: np.ndarray, y: np.ndarray, xq: float) -> float:
    """Monotone piecewise-cubic interpolation (Fritsch-Carlson): follows the convex front between points
    without overshoot, where a straight chord would overstate the optimal fuel."""
    h = np.diff(x)
    delta = np.diff(y) / h
    m = np.zeros_like(y)
    m[0], m[-1] = delta[0], delta[-1]
    for k in range(1, len(x) - 1):
        if delta[k - 1] * delta[k] > 0:
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            m[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])
    k = int(np.clip(np.searchsorted(x, xq) - 1, 0, len(x) - 2))
    t = (xq - x[k]) / h[k]
    h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
    return float(h00 * y[k] + h10 * h[k] * m[k] + h01 * y[k + 1] + h11 * h[k] * m[k + 1])


# The cached optima's version: v6, scenarios (two leg distances, exactly 1500 rpm; points named point_<i>,
# unverified ones out of the front); v5, checked entries (mpc.benchmark.store), re-simulated by
# WheelLoader-v1's step (its saturations within the step, its limits at every RK4 stage).
CACHE_VERSION = "v6"


def _key(braking: str, p: LoaderParams, n_points: int) -> str:
    return f"{braking}_{p.fingerprint()}_n{n_points}_{CACHE_VERSION}"


def front_folder(braking: str, n_points: int = DEFAULT_POINTS, params: LoaderParams | dict | None = None,
                 cache: str | os.PathLike | None = None) -> Path:
    """Where :func:`pareto_front` keeps a front: ``front.json``, ``min_time.json``, ``min_fuel.json``
    and one ``T_<cycle time>.json`` per point (each an :class:`mpc.benchmark.ocp.OCPResult`)."""
    # (n_points checked: 11.0 named another folder, "n11.0", and missed the cache without a word; "../x" another path)
    key, root = _key(cycle.check_braking(braking), resolve(params), check_n_points(n_points)), cache_dir(cache)
    return store.entry_folder(root / "pareto" / key, root)


def min_time_result(braking: str, n_points: int = DEFAULT_POINTS, params: LoaderParams | dict | None = None,
                    cache: str | os.PathLike | None = None) -> OCPResult:
    """The minimum-time cycle a front was swept from (its ``min_time.json``), solved again if that entry is
    missing or bad."""
    p = resolve(params)
    path = front_folder(braking, n_points, p, cache) / "min_time.json"
    r = cached_result(path, objective="time", braking=braking, params=p)
    # (a cycle that failed its re-simulation, solved here or cached by a sweep that then refused it as the front's
    # end, was returned as the minimum-time optimum: `wl run` reported it as the "optimum (min time)" row)
    if r is None or not r.success:
        r = solve_ocp(braking, "time", params=p)
        if not r.success:
            raise OCPError(f"no verified {braking} minimum-time cycle: {r.status}")
        save_result(r, path)
    return r


# Intervals per phase a point's mesh is rounded up to (driving phases 1 and 3, braking phases 2 and 4): few
# distinct meshes, so that the points of every scenario share a handful of NLPs (each takes seconds to build).
MESH_LADDER = ((24, 32, 40, 48, 64, 80, 96, 128, 160, 192, 256), (12, 16, 24, 32, 48, 64, 96))


def point_mesh(durations: list[float], max_interval: float) -> tuple[int, int, int, int]:
    """The mesh of a cycle with these phase durations: no interval longer than ``max_interval`` in the
    driving phases, half that in the braking phases 2 and 4, rounded up on MESH_LADDER.

    Measured on the service front: with 0.15 s in the braking phases the re-simulated bucket height of
    the 9.2 s cycle missed by 3.6 cm (limit 2 cm); the lift rides the pump limit there while the engine
    speed falls fast, and 0.075 s brings the miss under 1 cm.
    """
    out = []
    for k, d in enumerate(durations):
        ladder = MESH_LADDER[k % 2]
        need = math.ceil(d / (max_interval if k % 2 == 0 else max_interval / 2))
        out.append(next((n for n in ladder if n >= need), max(need, ladder[-1])))
    return tuple(out)  # type: ignore[return-value]


def front_times(T_min: float, T_fuel_opt: float, n_points: int) -> np.ndarray:
    """The front's cycle times: the first at (1 + FIRST_POINT_SLACK) T_min, one at (1 + NEAR_POINT_SLACK)
    T_min and one at (1 + SECOND_POINT_SLACK) T_min (the front curves most there, even in u), then evenly
    spaced in u = sqrt(T - T_min) up to T_fuel_opt (see :meth:`ParetoFront.fuel_at`). Fewer than 5 points:
    evenly in u from the first."""
    u_end = math.sqrt(T_fuel_opt - T_min)
    u_first = math.sqrt(T_min * FIRST_POINT_SLACK)
    if n_points < 5 or math.sqrt(T_min * SECOND_POINT_SLACK) >= 0.5 * (u_first + u_end):
        return T_min + np.linspace(u_first, u_end, n_points) ** 2
    u_near, u_second = math.sqrt(T_min * NEAR_POINT_SLACK), math.sqrt(T_min * SECOND_POINT_SLACK)
    return T_min + np.concatenate([[u_first, u_near], np.linspace(u_second, u_end, n_points - 2)]) ** 2


def nearest_front(braking: str, n_points: int, p: LoaderParams, cache: str | os.PathLike | None = None) -> Path | None:
    """The folder of the nearest front already solved for another scenario of the same machine and braking
    alternative (same number of points), or None."""
    from mpc.benchmark.ocp import machine_key, scenario_fields

    machine, own = machine_key(p), scenario_fields(p)
    best, best_d = None, math.inf
    # (sorted: of two fronts at the same distance the first by name, not by the file system's listing order)
    for f in sorted((cache_dir(cache) / "pareto").glob(f"{braking}_*_n{n_points}_{CACHE_VERSION}/front.json")):
        # (its point count checked as pareto_front checks its own: a 3-point front copied into an n11 folder guided
        # every point of a neighbouring scenario's 11-point sweep)
        data = store.load_entry(f, FRONT_KIND, lambda d: check_front_points(d, n_points), expect={"braking": braking})
        if data is None or data.get("machine") != machine or not data.get("scenario_fields"):
            continue
        d = param_distance(own, data["scenario_fields"])
        if 0.0 < d < best_d:
            best, best_d = f.parent, d
    return best


def check_sweep_arguments(max_interval: Any = 0.15, progress: Any = None, **flags: Any) -> None:
    """:func:`pareto_front`'s arguments, each refused by name before any solve (``max_interval`` 0 was an
    OverflowError after the front's two ends were solved, NaN a bare ValueError, -1 the coarsest mesh without a
    word; a ``progress`` that is no function a TypeError)."""
    if not (is_real_number(max_interval) and 0.001 <= max_interval <= 10.0):
        raise ValueError(f"max_interval must lie in [0.001, 10] s (the longest mesh interval of a driving phase), "
                         f"got {shown(max_interval)}")
    if progress is not None and not callable(progress):
        raise ValueError(f"progress must be a function taking a message, or None, got {shown(progress)}")
    for name, value in flags.items():
        check_flag(name, value)


def pareto_front(
    braking: str | None = None,
    n_points: int = DEFAULT_POINTS,
    params: LoaderParams | dict | None = None,
    cache: str | os.PathLike | None = None,
    use_cache: bool = True,
    progress: Callable[[str], None] | None = None,
    max_interval: float = 0.15,
    scenario: Any = None,
    neighbour: bool = True,
) -> ParetoFront:
    """The Pareto front with ``n_points`` cycle times from the minimum time to the fuel optimum, of
    ``scenario``'s cycle (:class:`wl_env.scenario.Scenario`, on the machine ``params``) or of ``params``.

    Solved points are cached (one entry per point plus the front, keyed by the braking alternative and
    the parameters' fingerprint); a valid cached front is returned at once, a bad one is set aside and
    rebuilt from the cached points. With ``neighbour``, the front of the nearest scenario already solved
    (:func:`nearest_front`) warm-starts every point. A point whose cycle fails the re-simulation check is
    kept in ``points`` with ``verified`` False and left out of the front. ``progress`` gets each step
    (default: this module's logger at INFO).
    """
    from mpc.benchmark.ocp import machine_key, scenario_fields, scenario_of, with_scenario

    braking, p = with_scenario(braking, params, scenario)
    n_points = check_n_points(n_points)
    check_sweep_arguments(max_interval=max_interval, progress=progress, use_cache=use_cache, neighbour=neighbour)
    fingerprint = p.fingerprint()
    say = progress or log.info
    folder = front_folder(braking, n_points, p, cache)
    front_file = folder / "front.json"

    if use_cache:
        data = store.load_entry(front_file, FRONT_KIND, lambda d: check_front_points(d, n_points), fingerprint,
                                {"braking": braking})
        if data is not None:
            return ParetoFront._from(data)
    near = nearest_front(braking, n_points, p, cache) if neighbour else None
    guide: dict[str, OCPResult] = {}
    if near is not None:  # the neighbour's solves, by name
        for f in near.glob("*.json"):
            r = cached_result(f, braking=braking) if f.name != "front.json" else None
            if r is not None:
                guide[f.stem] = r
    say(f"[{braking}] solving the Pareto front ({n_points} points; each solved point is cached in {folder})"
        + (f", warm-started from {near.name}" if guide else ""))
    # (the folder made by its first entry's write: made here, Ctrl-C before any point was solved left it empty)
    t0 = time.perf_counter()

    def cached_solve(name: str, refinements: int = 1, **kwargs: Any) -> OCPResult:
        path = folder / f"{name}.json"
        if use_cache:
            cached = cached_result(path, objective=kwargs["objective"], braking=braking, params=p)
            T = kwargs.get("T")
            if cached is not None and (T is None or solved_at(cached, T)) and (cached.success or refinements == 1):
                return cached
        # One refinement at most for a point: one that still fails its re-simulation is left out of the front (its
        # neighbours span it), not refined on into NLPs of hundreds of intervals per phase.
        result = solve_ocp(braking, params=p, max_refinements=refinements, **kwargs)  # an interrupt: nothing saved
        save_result(result, path)
        return result

    def end(name: str, objective: str) -> OCPResult:
        """The minimum-time or -fuel cycle: from the neighbour's if there is one (else the templates). From a
        neighbouring scenario's optimum, which is smooth already, the smoothing homotopy of eq. (33) is left
        out (one solve instead of two), on a mesh sized for the neighbour's phase durations."""
        # (refined as `wl ocp` is: an end that fails its re-simulation leaves no front at all; a TC corner's minimum
        # time failed it on one refinement, 2.3 % over a limit, and passed on the second, as `wl ocp` solves it)
        if name in guide:
            guided = OCPSettings(intervals=point_mesh(guide[name].phase_durations, max_interval), smoothing=(0.0,))
            try:
                return cached_solve(name, END_REFINEMENTS, objective=objective, warm_start=guide[name], starts=(),
                                    settings=guided)
            except OCPError:
                pass
        return cached_solve(name, END_REFINEMENTS, objective=objective)

    say(f"[{braking}] minimum time")
    r_time = end("min_time", "time")
    say(f"[{braking}] minimum time {r_time.T:.3f} s, {r_time.fuel_g:.2f} g; minimum fuel")
    r_fuel = end("min_fuel", "fuel")
    say(f"[{braking}] minimum fuel {r_fuel.fuel_g:.2f} g at {r_fuel.T:.3f} s")
    for r, what in ((r_time, "minimum-time"), (r_fuel, "minimum-fuel")):
        if not r.verification.get("passed"):  # (its T_min, T_fuel_opt or fuel_min_g bound the front and score cycles)
            raise OCPError(f"the {braking} {what} cycle fails its re-simulation, no end of a front: {r.status}")
    times = front_times(r_time.T, r_fuel.T, n_points)

    def mesh_at(i: int) -> OCPSettings:
        """Point i's mesh: sized for its phase durations (its guide's, else interpolated between the ends)."""
        if guides[i] is not None:
            durations = guides[i].phase_durations
        else:
            w = (times[i] - r_time.T) / max(r_fuel.T - r_time.T, 1e-9)
            durations = [a + w * (b - a) for a, b in zip(r_time.phase_durations, r_fuel.phase_durations, strict=True)]
        return OCPSettings(intervals=point_mesh(durations, max_interval))

    def named(i: int) -> str:  # a point's file: its number on the front and its cycle time
        return f"point_{i}_T{times[i]:.4f}"

    def guide_at(i: int) -> OCPResult | None:  # the neighbour's point i: the leaner of its forward and back solves
        own = [r for name, r in sorted(guide.items()) if name.startswith(f"point_{i}_T")]
        return min(own, key=lambda r: (not r.verification.get("passed"), r.fuel_g), default=None)

    guides = [guide_at(i) for i in range(n_points)]
    points: list[OCPResult] = []
    failed: list[dict[str, Any]] = []  # points no start solved
    index: list[int] = []  # each solved point's number
    meshes: list[list[int]] = []
    previous = r_time
    for i, T in enumerate(times[:-1]):
        say(f"[{braking}] point {i + 1}/{n_points}: minimum fuel at T = {T:.3f} s")
        # Continuation from the neighbouring point, or from the neighbouring scenario's same point; near
        # T_min also fresh template starts, which can end in other local optima (other splits of the time
        # between the phases). The best one is kept.
        templates = tuple((T / 2.0, a) for a in SWEEP_ACCEL_FRACTIONS) if T < MULTI_START_BELOW * r_time.T else ()
        warm = guides[i] if guides[i] is not None else previous
        settings = mesh_at(i)
        meshes.append(list(settings.intervals))
        try:
            # (near T_min the templates beside a neighbouring scenario's point too: measured on a test cycle,
            # the guide alone stayed 0.7 % above a multi-started solve at 1.002 T_min)
            r = cached_solve(named(i), objective="fuel_at_time", T=float(T), warm_start=warm,
                             settings=settings if guides[i] is None else replace(settings, smoothing=(0.0,)),
                             starts=templates)
        except OCPError:
            r = None
        # Continuation lost the way: start afresh from the templates; then from the minimum-time cycle on its
        # own mesh (just above T_min another mesh's discretization can make the cycle time infeasible).
        retries = ((settings, None, tuple((T / 2.0, a) for a in SWEEP_ACCEL_FRACTIONS)),
                   (OCPSettings(intervals=tuple(r_time.mesh)), r_time, ()))
        for st, ws, starts in retries if r is None else ():
            try:
                r = cached_solve(named(i), objective="fuel_at_time", T=float(T), settings=st, warm_start=ws,
                                 starts=starts)
                break
            except OCPError as exc:
                failure = exc
        if r is None:
            log.warning(f"[{braking}] no optimum at T = {T:.3f} s ({failure}): the point is left out of the front")
            failed.append({"T": float(T), "fuel_g": None, "verified": False, "status": str(failure)})
            continue
        points.append(r)
        index.append(i)
        previous = r
    points.append(r_fuel)
    # Continuation back from the fuel-optimal end: a forward chain that took a worse basin near T_min
    # carries it along; the neighbour on the long side may lead into a better one. Fronts warm-started from
    # a neighbouring scenario take it too: each point there came from its guide alone, and 3 of 8 shipped
    # service `test` fronts sat 0.78-1.24 % above a fresh solve at one slow point (stop 65).
    for i in range(len(points) - 2, 0, -1):
        T, k = float(points[i].T), index[i]
        say(f"[{braking}] point {k + 1}/{n_points}: continuation from T = {points[i + 1].T:.3f} s")
        try:
            alt = cached_solve(f"{named(k)}_back", objective="fuel_at_time", T=T, settings=mesh_at(k),
                               warm_start=points[i + 1], starts=())
        except OCPError:  # the forward point stands
            continue
        if alt.verification.get("passed") and alt.fuel_g < points[i].fuel_g - 1e-6:
            alt.starts = points[i].starts + alt.starts
            points[i] = alt
    good = [r for r in points if r.verification.get("passed")]
    if len(good) < 2:
        raise OCPError(f"the {braking} front has {len(good)} verified point(s) of {len(points)}: no front to "
                       f"interpolate (statuses: {', '.join(sorted({r.status for r in points}))})")
    for r in points:
        if not r.verification.get("passed"):
            log.warning(f"[{braking}] the point at T = {r.T:.3f} s fails the re-simulation check: left out of the front")
    fuel = np.minimum.accumulate([r.fuel_g for r in good]).tolist()  # (a local optimum above a later point: capped)
    front = ParetoFront(
        braking=braking, T=[float(r.T) for r in good], fuel_g=fuel, params_fingerprint=fingerprint,
        T_min=float(r_time.T),  # the minimum time itself; the first point lies 0.1 % above it
        T_fuel_opt=float(r_fuel.T), fuel_min_g=float(r_fuel.fuel_g), mesh=np.max(meshes + [r_fuel.mesh], axis=0).tolist(),
        wall_time=time.perf_counter() - t0,
        points=[{"T": r.T, "fuel_g": r.fuel_g, "mesh": r.mesh, "verified": bool(r.verification.get("passed")),
                 "final_position_error_m": r.verification.get("final_position_error_m"),
                 "final_height_error_m": r.verification.get("final_height_error_m"),
                 "max_violation": r.verification.get("max_violation")} for r in points] + failed,
        machine=machine_key(p), scenario_fields=scenario_fields(p),
        warm_started_from=near.name if guide else None, scenario=scenario_of(p, braking),
    )
    front.save(front_file)
    return front


def _debug(msg: str) -> None:
    log.debug(msg)


def _front_job(braking: str, n_points: int, params: dict[str, Any], cache: str | None, use_cache: bool,
               progress: bool) -> ParetoFront:
    """One front in a worker process (:func:`pareto_fronts`); plain arguments, so the worker imports
    nothing heavy before its interrupt handler is in place."""
    return pareto_front(braking, n_points, params, cache, use_cache, None if progress else _debug)


def pareto_fronts(
    brakings: tuple[str, ...] = cycle.BRAKING_MODES,
    n_points: int = DEFAULT_POINTS,
    params: LoaderParams | dict | None = None,
    cache: str | os.PathLike | None = None,
    use_cache: bool = True,
    progress: bool = False,
    workers: int | None = None,
) -> dict[str, ParetoFront]:
    """The fronts of several braking alternatives, swept in parallel processes (one per alternative,
    if ``workers``, default the CPU count, allows more than one). ``progress`` logs each step at INFO
    (else DEBUG); the workers log to stderr.

    The processes are spawned, so they import the caller's main module: a script that calls this needs
    the usual ``if __name__ == "__main__":`` guard (``wl`` and pytest have it). Ctrl-C or an error in one
    front stops all of them within about a second (:mod:`mpc.workers`); the points solved so far stay cached.
    """
    # (each checked before a worker starts: a string was taken letter by letter, "braking ... got 's'", workers "x"
    # was a TypeError, 0 or -1 the default or one worker without a word)
    if not isinstance(brakings, (tuple, list)):
        raise ValueError(f"brakings must be a tuple of braking alternatives {cycle.BRAKING_MODES}, got {shown(brakings)}")
    for b in brakings:
        cycle.check_braking(b)
    n_points = check_n_points(n_points)
    check_flag("use_cache", use_cache), check_flag("progress", progress)
    if workers is not None:
        from mpc.workers import check_workers

        check_workers(workers)
    p = resolve(params)
    if cache is not None:  # (the workers got str(cache): 5 or b"x" solved into a folder "5" or "b'x'" of the working one)
        cache_dir(cache)
    workers = min(len(brakings), workers or os.cpu_count() or 1)
    if workers <= 1:
        return {b: pareto_front(b, n_points, p, cache, use_cache, None if progress else _debug) for b in brakings}
    from mpc.workers import run_in_workers

    args = (n_points, p.to_dict(), None if cache is None else str(cache), use_cache, progress)
    return run_in_workers({b: (f"{__name__}:_front_job", (b, *args)) for b in brakings},
                          log_level=logging.INFO if progress else logging.WARNING)


def check_front_of(front: ParetoFront, braking: str, params: LoaderParams | None) -> None:
    """A front given to score a cycle must be that cycle's: the same braking and parameters (ValueError; ``params``
    None: the braking only, the caller matching the parameters per cycle). A front built in memory with an empty
    ``params_fingerprint`` is matched by its braking only; no front read from a file has one (:func:`check_front`)."""
    if not isinstance(front, ParetoFront):
        raise ValueError(f"front must be a mpc.benchmark.pareto.ParetoFront or None, got {type(front).__name__}")
    try:  # (as a cached front is checked: unsorted, repeated or NaN points scored any number, NaN included)
        d = store.as_read(front.__dict__)
        problem = check_front({**d, "params_fingerprint": d.get("params_fingerprint") or "built in memory"})
    except (TypeError, ValueError) as exc:
        problem = f"not JSON-like ({exc})"
    if problem:
        raise ValueError(f"front is no valid Pareto front: {problem}")
    if front.braking != braking:
        raise ValueError(f"the front given is the {front.braking!r} braking's, the cycle's is {braking!r}: a cycle is "
                         f"scored against its own optimum only")
    if params is not None and front.params_fingerprint not in ("", params.fingerprint()):
        raise ValueError(f"the front given was solved for parameters {front.params_fingerprint}, the cycle ran "
                         f"{params.fingerprint()}: a cycle is scored against its own optimum only")


def optimal_fuel_at(T: float, braking: str = "service", params: LoaderParams | dict | None = None,
                    cache: str | os.PathLike | None = None, front: ParetoFront | None = None) -> float:
    """Minimum fuel (g) at cycle time T: interpolated on the front, solved on demand past the fuel optimum.

    Raises ``ValueError`` for a cycle time below the minimum, or a ``front`` of another cycle.
    """
    T = plain(T)  # (a float32 as the number it prints, as score_run takes it)
    if not (is_real_number(T) and 0 < T <= MAX_CYCLE_TIME):  # (1e300 s: an OSError, its cache file's name too long)
        raise ValueError(f"T (the cycle time) must be a number in (0, {MAX_CYCLE_TIME:g}] s, got {T!r}")
    T = float(T)
    cycle.check_braking(braking)
    if front is not None:
        check_front_of(front, braking, resolve(params))
    front = front or pareto_front(braking, params=params, cache=cache)
    if T < front.T_fuel_opt:
        return front.fuel_at(T)
    # Slower than the fuel-optimal cycle: fuel at that T is its own optimum (cached like the front).
    p = resolve(params)
    root = cache_dir(cache)
    path = store.entry_folder(root / "pareto" / f"slow_{braking}_{p.fingerprint()}_{CACHE_VERSION}", root) / f"T_{T:.3f}.json"
    cached = cached_result(path, objective="fuel_at_time", braking=braking, params=p)
    # (a failed one, cached before it was refused, is solved again; so is one of another T under the same file name:
    # T_30.000.json held 30.0004 s's optimum after that call, and 30.0 s then got its fuel, the result depending on
    # what the cache saw first)
    if solved_at(cached, T) and cached.success:
        return cached.fuel_g
    r = solve_ocp(braking, objective="fuel_at_time", T=float(T), params=p,
                  settings=replace(OCPSettings(), intervals=tuple(front.mesh)))
    if not r.success:  # (its fuel was returned and cached: a cycle that fails its re-simulation is no optimum)
        raise OCPError(f"no verified {braking} optimum at T = {float(T):.3f} s: {r.status}")
    save_result(r, path)
    return r.fuel_g
