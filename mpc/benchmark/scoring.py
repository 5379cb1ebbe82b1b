"""Scoring a controller's cycle against the optimum of its own cycle.

Cycle time against that cycle's minimum cycle time; fuel against its minimum fuel at the *same* cycle
time (the Pareto front), as the paper compares the braking alternatives. "Its own cycle" is the
scenario and the start state the episode ran (:mod:`mpc.benchmark.reference` finds or solves it):
nothing is scored against another cycle's front.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from mpc.benchmark.ocp import MAX_CYCLE_TIME, as_plain
from mpc.benchmark.pareto import ParetoFront, check_front_of
from mpc.benchmark.reference import reference_at
from wl_env.cycle import check_braking
from wl_env.params import LoaderParams, check_flag, is_real_number, plain, resolve, shown


@dataclass(frozen=True)
class Score:
    """A cycle's gaps to the optimum: its time T (s) against the minimum cycle time T_min, its fuel
    against the minimum fuel at the same cycle time, fuel_opt_g. Gaps are relative: 0.05 = 5 % above.
    ``reference`` says where the optimum came from (a shipped, cached or given front, or a direct solve)."""

    braking: str
    T: float
    fuel_g: float
    T_min: float
    time_gap: float
    fuel_opt_g: float
    fuel_gap: float
    reference: str = ""

    def to_dict(self) -> dict[str, Any]:
        return as_plain(asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Score:
        """The score :meth:`to_dict` gave; ValueError naming the field that is missing, no number, out of its range
        (T, fuel_g, T_min and fuel_opt_g > 0, T and T_min at most MAX_CYCLE_TIME s), or a gap that is not its T or
        fuel against T_min or fuel_opt_g (a negative T, a numeric ``reference`` and made-up gaps were taken)."""
        if not isinstance(data, dict):
            raise ValueError(f"a score is a mapping, got {type(data).__name__}")
        for name in cls.__dataclass_fields__:
            if name not in data and name != "reference":
                raise ValueError(f"not a score: missing field {name!r}")
            if name not in ("braking", "reference") and not is_real_number(data[name]):
                raise ValueError(f"score field {name!r} must be a finite number, got {data[name]!r}")
        check_braking(data["braking"])
        if not isinstance(data.get("reference", ""), str):
            raise ValueError(f"score field 'reference' must be a string, got {shown(data['reference'])}")
        for name in ("T", "fuel_g", "T_min", "fuel_opt_g"):
            if not data[name] > 0 or (name in ("T", "T_min") and data[name] > MAX_CYCLE_TIME):
                most = f" and at most {MAX_CYCLE_TIME:g} s" if name in ("T", "T_min") else ""
                raise ValueError(f"score field {name!r} must be > 0{most}, got {data[name]!r}")
        for gap, of, against in (("time_gap", "T", "T_min"), ("fuel_gap", "fuel_g", "fuel_opt_g")):
            ratio = data[of] / data[against]  # (score_run's gap is ratio - 1: equal to the last bit, read back)
            if abs(data[gap] - (ratio - 1.0)) > 1e-9 * max(1.0, ratio):
                raise ValueError(f"score field {gap!r} {data[gap]!r} is not {of} / {against} - 1 = {ratio - 1.0!r}")
        return cls(**{k: v for k, v in data.items() if k in cls.__dataclass_fields__})


def score_run(
    T: float,
    fuel_g: float,
    braking: str,
    params: LoaderParams | dict | None = None,
    front: ParetoFront | None = None,
    cache: str | os.PathLike | None = None,
    solve: bool = True,
) -> Score:
    """Score one cycle (its time T in s and fuel in g, as run in the environment with ``params``, its
    scenario and start state included): the one scoring of the project, for every controller and every
    evaluation. ``front`` must be that cycle's own front if given. ``solve`` False: only shipped or
    cached optima (LookupError if there is none)."""
    T, fuel_g = plain(T), plain(fuel_g)  # (a float32 as the number it prints: np.float32(9.1) was 9.1000003814)
    for name, v in (("T", T), ("fuel_g", fuel_g)):
        if not (is_real_number(v) and v > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    if T > MAX_CYCLE_TIME:  # (no optimum holds it: 1e300 s was solved for, then an OSError, its file name too long)
        raise ValueError(f"T must be a cycle time in (0, {MAX_CYCLE_TIME:g}] s (the longest cycle the OCP holds), "
                         f"got {T!r}")
    T, fuel_g = float(T), float(fuel_g)
    check_braking(braking)
    check_flag("solve", solve)  # (solve="no" solved)
    p = resolve(params)
    if front is not None:
        check_front_of(front, braking, p)
    ref = reference_at(T, braking, p, cache, front=front, solve=solve)
    return Score(braking=braking, T=float(T), fuel_g=float(fuel_g), T_min=ref["T_min"], time_gap=T / ref["T_min"] - 1.0,
                 fuel_opt_g=float(ref["fuel_opt_g"]), fuel_gap=fuel_g / ref["fuel_opt_g"] - 1.0,
                 reference=ref["reference"])


@dataclass(frozen=True)
class Smoothness:
    """How much a cycle's controls move: the total variation (sum of |change| from one held value to the
    next) of U_mf (mg) and U_ab (m/s^2), against the optimum's at the same cycle time (its OCP, whose
    objective has the paper's control-rate penalty, eq. (33)); ratio 1.5 = 50 % more movement."""

    tv_fuel_injection_mg: float
    tv_bucket_acceleration: float
    optimum_tv_fuel_injection_mg: float
    optimum_tv_bucket_acceleration: float
    ratio_fuel_injection: float
    ratio_bucket_acceleration: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def total_variation(controls: Any) -> tuple[float, float]:
    """Total variation of U_mf (mg) and U_ab (m/s^2) over a sequence of held controls (rows [U_mf, U_ab, ...])."""
    # (numbers only: strings were read as numbers, bools as 0 and 1, a dict or a complex number was a bare TypeError,
    # ragged rows numpy's "inhomogeneous shape")
    if isinstance(controls, np.ndarray) and controls.dtype.kind in "iuf":
        raw = controls
    else:  # each entry checked: numpy turned [[0.0, False]] into floats, [["1", "2"]] into strings it then converted
        try:
            raw = np.asarray(controls, dtype=object)
        except ValueError:  # (ragged rows)
            raw = np.asarray(None, dtype=object)
        if not (raw.ndim == 2 and all(map(is_real_number, raw.ravel()))):
            raise ValueError(f"controls must be finite rows [U_mf, U_ab, ...] of real numbers, got {shown(controls)}")
    u = raw.astype(float)
    if u.ndim != 2 or u.shape[1] < 2 or len(u) < 1 or not np.isfinite(u[:, :2]).all():
        raise ValueError(f"controls must be finite rows [U_mf, U_ab, ...], got shape {u.shape}")
    tv = np.abs(np.diff(u[:, :2], axis=0)).sum(axis=0)
    return float(tv[0]), float(tv[1])


def smoothness(controls: Any, T: float, braking: str, params: LoaderParams | dict | None = None,
               cache: str | os.PathLike | None = None) -> Smoothness:
    """A cycle's control movement (:func:`total_variation`) against the optimum's at its cycle time T (s)
    (the minimum-fuel OCP at T, :func:`mpc.benchmark.reference.direct_fuel_at`, cached)."""
    from mpc.benchmark.ocp import check_cycle_time
    from mpc.benchmark.reference import direct_fuel_at

    tv_mf, tv_ab = total_variation(controls)  # (checked before the solve: an empty trajectory failed after it)
    T, p = check_cycle_time(T), resolve(params)
    opt = direct_fuel_at(check_braking(braking), T, p, cache)
    o_mf, o_ab = total_variation(opt.controls)
    return Smoothness(tv_fuel_injection_mg=tv_mf, tv_bucket_acceleration=tv_ab, optimum_tv_fuel_injection_mg=o_mf,
                      optimum_tv_bucket_acceleration=o_ab, ratio_fuel_injection=tv_mf / max(o_mf, 1e-9),
                      ratio_bucket_acceleration=tv_ab / max(o_ab, 1e-9))
