#!/usr/bin/env python
"""Reproduce Section IV of Nezhadali & Eriksson with this project's model: Figs. 6-9 and a comparison table.

    python scripts/reproduce_paper.py                      # writes docs/paper/{fig6..fig9.png, table.md, results.json}
    python scripts/reproduce_paper.py --out /tmp/paper --cache /tmp/wlcache --points 8

The optima come from the Pareto cache of :func:`mpc.benchmark.pareto.pareto_front` (``min_time.json``,
``min_fuel.json`` and the front's points, per braking alternative); the two fuel-optimal 10 s cycles of
Fig. 9 are cached beside it (``<cache>/paper/``). A second run only reads the cache and redraws.

Outputs (each written atomically: a temporary file in the same folder, then ``os.replace``):

* ``fig6.png``: time-optimal (left) and fuel-optimal (right) controls and states of both alternatives;
* ``fig7.png``: engine operating points of the four optima on the engine map (torque limit lines,
  constant power in grey, constant brake efficiency in blue);
* ``fig8.png``: the Pareto fronts and the extra fuel of TC braking at equal cycle time;
* ``fig9.png``: the fuel-optimal 10 s cycles;
* ``table.md`` / ``results.json``: each quantitative statement of Section IV beside our number.

Our parameters are the specification's re-implementation values, not the paper's (unpublished) ones, so
agreement is expected in the shape of the results, not in every digit.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repo, if not installed

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from mpc.benchmark.ocp import OCPError, OCPResult, OCPSettings, solve_ocp, verification_passed  # noqa: E402
from mpc.benchmark.pareto import (  # noqa: E402
    ParetoFront,
    cache_dir,
    cached_result,
    front_folder,
    pareto_front,
    pchip,
    save_result,
)
from wl_env.atomic_io import atomic_path  # noqa: E402
from wl_env.cycle import BRAKING_MODES, phase_specs  # noqa: E402
from wl_env.model import outputs  # noqa: E402
from wl_env.params import LoaderParams, resolve  # noqa: E402
from wl_env.physics import engine  # noqa: E402

DPI = 150
COLORS = {"service": "tab:blue", "tc": "tab:red"}
LABELS = {"service": "service brakes", "tc": "TC braking"}
MARKERS = {"service": "o", "tc": "^"}
RAD_S_TO_RPM = 30.0 / math.pi
FIXED_T = 10.0  # s, the cycle of Fig. 9
PHI_TOL = 1e-3  # |phi| below this counts as phi = 0 (a standing machine), not as mode I
PRESSURE_ACTIVE = 0.995  # P_cyl / P_cyl_max at or above this: the pressure limit is active
LEAN_FACTOR = 1.001  # the leanest "time-optimal" cycle: minimum fuel at 1.001 T_min

# The paper's quantitative statements of Section IV (and its remark on the smoothing homotopy, Sec. III).
PAPER = {
    "dT_time_pct": 1.58,
    "dT_fuel_pct": 2.8,
    "half_fuel_opt_extra_fuel_pct": 10.0,  # "less than 10 %"
    "plus10_time_fuel_saving_pct": 35.0,  # "up to 35 %"
    "fuel_10s_tc_extra_pct": 2.7,
    "smoothing_change_pct": 0.3,  # "at most 0.3 %"
}


def say(msg: str) -> None:
    print(f"[reproduce_paper] {msg}", file=sys.stderr, flush=True)


# ====================================================================================================
# Atomic output
# ====================================================================================================
def _atomic_write(path: str | os.PathLike, write: Callable[[Any], None], binary: bool) -> Path:
    with atomic_path(path) as tmp, open(tmp, "wb" if binary else "w") as fh:
        write(fh)
    return Path(path)


def save_figure(fig: Figure, path: str | os.PathLike) -> Path:
    """Write a figure as PNG (DPI dots per inch), atomically."""
    return _atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=DPI), binary=True)


def write_text(path: str | os.PathLike, text: str) -> Path:
    return _atomic_write(path, lambda fh: fh.write(text), binary=False)


def write_json(path: str | os.PathLike, data: Any) -> Path:
    return write_text(path, json.dumps(_jsonable(data), indent=1, allow_nan=True) + "\n")


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


# ====================================================================================================
# The optima (from the Pareto cache where available)
# ====================================================================================================
def _load_or_solve(path: Path, solve: Callable[[], OCPResult], what: str) -> OCPResult:
    r = cached_result(path)  # a bad entry is reported, set aside and solved again
    if r is not None:
        return r
    say(f"solving {what} (not in the cache)")
    r = solve()
    save_result(r, path)
    return r


def load_alternative(braking: str, n_points: int, params: LoaderParams, cache: str | os.PathLike | None) -> dict:
    """Front, time- and fuel-optimal cycles and the front's points for one braking alternative."""
    t0 = time.perf_counter()
    front = pareto_front(braking, n_points=n_points, params=params, cache=cache, progress=say)
    folder = front_folder(braking, n_points, params, cache)
    r_time = _load_or_solve(folder / "min_time.json", lambda: solve_ocp(braking, "time", params=params),
                            f"the {braking} minimum-time cycle")
    r_fuel = _load_or_solve(folder / "min_fuel.json", lambda: solve_ocp(braking, "fuel", params=params),
                            f"the {braking} minimum-fuel cycle")
    solved = []
    for f in sorted(folder.glob("T_*.json")):  # forward and backward continuation solves
        r = cached_result(f)
        if r is not None:
            solved.append(r)
    points = []
    for T, fuel in zip(front.T, front.fuel_g, strict=True):  # the front's own points: the solve it kept
        same = [r for r in solved if abs(r.T - T) < 1e-6 and abs(r.fuel_g - fuel) <= 1e-9 * fuel]
        if same:
            points.append(same[0])
    say(f"[{braking}] front of {len(front.T)} points, T_min {front.T_min:.3f} s, min fuel "
        f"{front.fuel_min_g:.2f} g at {front.T_fuel_opt:.3f} s ({time.perf_counter() - t0:.1f} s)")
    first = points[0] if points and abs(points[0].T - front.T[0]) < 1e-6 else None
    return {"front": front, "time": r_time, "fuel": r_fuel, "points": points, "folder": folder, "front_first": first}


def paper_cache(cache: str | os.PathLike | None, braking: str, params: LoaderParams) -> Path:
    """Where this script caches the optima it solves itself (beside the Pareto cache)."""
    return cache_dir(cache) / "paper" / f"{braking}_{params.fingerprint()}_v2"  # v2: checked entries


def _passed(r: OCPResult) -> bool:
    v = r.verification or {}
    return bool(v.get("passed", verification_passed(v) if "reversing_error_m" in v else False))


def _load_cached(path: Path, T: float) -> OCPResult | None:
    """A cached fixed-time optimum, if present, readable and solved for this cycle time."""
    r = cached_result(path)
    if r is None:
        return None
    return r if abs(r.T - T) <= 1e-6 * max(1.0, T) else None


def multistart_fixed_time(braking: str, T: float, params: LoaderParams, settings: OCPSettings,
                          warm_starts: Sequence[OCPResult] = (), templates: bool = True) -> OCPResult | None:
    """Minimum fuel at cycle time T from several starts; the leanest is solved once more and verified.

    Starts: each of ``warm_starts`` and (``templates``) the OCP's template multi-start. Continuation
    from a neighbouring optimum alone can stay in a worse local optimum, which the templates often leave.
    Returns None if every start fails.
    """
    cands: list[tuple[str, OCPResult]] = []
    for ws in warm_starts:
        try:
            cands.append((f"warm start T = {ws.T:.3f} s",
                          solve_ocp(braking, "fuel_at_time", T=T, params=params, settings=settings, warm_start=ws,
                                    verify=False)))
        except OCPError:
            pass
    if templates:
        try:
            cands.append(("templates", solve_ocp(braking, "fuel_at_time", T=T, params=params, settings=settings,
                                                 verify=False)))
        except OCPError:
            pass
    if not cands:
        return None
    name, best = min(cands, key=lambda c: c[1].fuel_g)
    say(f"[{braking}]   T = {T:.3f} s: " + ", ".join(f"{n} {r.fuel_g:.3f} g" for n, r in cands) + f"; best: {name}")
    try:  # re-solve from the best start with the re-simulation check (and mesh refinement if it fails)
        final = solve_ocp(braking, "fuel_at_time", T=T, params=params, settings=settings, warm_start=best)
    except OCPError:
        return best
    final.starts = [{"start": n, "fuel_g": r.fuel_g} for n, r in cands] + final.starts
    return final


def polish_front(braking: str, alt: dict, params: LoaderParams, cache: str | os.PathLike | None) -> dict:
    """Re-solve each interior point of the cached front from templates; keep whichever is leaner and verified.

    ``pareto_front`` continues each point from its neighbour, which can follow a worse local optimum;
    the polished points are cached under ``<cache>/paper/`` (the Pareto cache is left as it is).
    Returns the alternative with ``front`` and ``points`` polished, ``front_cache`` the original front and
    ``improved`` the points that changed.
    """
    front: ParetoFront = alt["front"]
    folder = paper_cache(cache, braking, params) / f"front_n{len(front.T)}"
    settings = OCPSettings(intervals=tuple(int(n) for n in front.mesh))
    by_T = {round(r.T, 6): r for r in alt["points"]}
    fuel = list(front.fuel_g)
    points: list[OCPResult] = []
    improved = []
    for i, T in enumerate(front.T):
        if i in (0, len(front.T) - 1):  # the time and fuel optima themselves
            continue
        path = folder / f"T_{T:.4f}.json"
        r = _load_cached(path, T)
        if r is None:
            old = by_T.get(round(T, 6))
            say(f"[{braking}] checking front point {i + 1}/{len(front.T)} (T = {T:.3f} s, {fuel[i]:.3f} g) "
                f"from templates")
            new = multistart_fixed_time(braking, T, params, settings)
            if new is not None and new.fuel_g < fuel[i] * (1 - 1e-6) and _passed(new):
                r = new
            else:
                r = old if old is not None else new
            if r is None:
                continue
            save_result(r, path)
        if r.fuel_g < fuel[i] * (1 - 1e-6):
            improved.append({"T_s": T, "pareto_cache_g": fuel[i], "polished_g": r.fuel_g,
                             "change_pct": 100.0 * (r.fuel_g - fuel[i]) / fuel[i], "mesh": list(r.mesh)})
            say(f"[{braking}] T = {T:.3f} s: {fuel[i]:.3f} g in the Pareto cache, {r.fuel_g:.3f} g from templates")
            fuel[i] = r.fuel_g
        elif by_T.get(round(T, 6)) is not None:
            r = by_T[round(T, 6)]  # the Pareto cache's point is at least as lean
        points.append(r)
    polished = replace(front, fuel_g=fuel)
    return {**alt, "front": polished, "front_cache": front, "points": points, "improved": improved}


def fixed_time_optimum(braking: str, T: float, params: LoaderParams, cache: str | os.PathLike | None,
                       front: ParetoFront, points: Sequence[OCPResult]) -> OCPResult:
    """Minimum fuel at the cycle time T (cached) on the front's mesh: warm starts from the front's two
    neighbouring points and the template multi-start, the leanest kept."""
    path = paper_cache(cache, braking, params) / f"fuel_at_T{T:.4f}.json"
    cached = _load_cached(path, T)
    if cached is not None:
        return cached
    settings = OCPSettings(intervals=tuple(int(n) for n in front.mesh))
    below = [r for r in points if r.T <= T]
    above = [r for r in points if r.T > T]
    neighbours = ([max(below, key=lambda r: r.T)] if below else []) + ([min(above, key=lambda r: r.T)] if above else [])
    say(f"[{braking}] minimum fuel at T = {T:g} s")
    r = multistart_fixed_time(braking, T, params, settings, neighbours)
    if r is None:
        raise OCPError(f"no optimum found for the {braking} cycle at T = {T:g} s")
    say(f"[{braking}] fuel at T = {T:g} s: {r.fuel_g:.3f} g{'' if _passed(r) else ' (re-simulation check NOT passed)'}")
    save_result(r, path)
    return r


def lean_time_optimum(braking: str, r_time: OCPResult, params: LoaderParams, cache: str | os.PathLike | None,
                      factor: float = LEAN_FACTOR, first_point: OCPResult | None = None) -> OCPResult | None:
    """Minimum fuel at T = factor * T_min (cached): the leanest practically time-optimal cycle.

    The time-optimal problem leaves the fuel free wherever it does not cost time, so the fuel of its
    solution is one of many. The Pareto front starts at exactly this point (multi-started on its fine
    mesh); ``first_point`` is used if it lies at this T, else it is solved here.
    """
    T = factor * r_time.T
    if first_point is not None and abs(first_point.T - T) <= 1e-6 * T:
        return first_point
    path = paper_cache(cache, braking, params) / f"lean_time_opt_x{factor:.4f}.json"
    cached = _load_cached(path, T)
    if cached is not None:
        return cached
    say(f"[{braking}] leanest cycle at {factor:g} x T_min = {T:.4f} s")
    r = multistart_fixed_time(braking, T, params, OCPSettings(intervals=tuple(int(n) for n in r_time.mesh)), [r_time])
    if r is None:
        say(f"[{braking}]   no solution")
        return None
    save_result(r, path)
    return r


# ====================================================================================================
# Signals of an optimal cycle
# ====================================================================================================
def phase_slices(result: OCPResult) -> list[tuple[int, int, int]]:
    """(phase, first sample, last sample) per phase; the last sample is the boundary closing the phase."""
    ph = np.asarray(result.phase)[: len(result.controls)]
    out = []
    for k in (1, 2, 3, 4):
        idx = np.flatnonzero(ph == k)
        if len(idx):
            out.append((k, int(idx[0]), int(idx[-1]) + 1))
    return out


def phase_boundaries(result: OCPResult) -> list[float]:
    """The switching times t1, t2, t3 (s)."""
    return [float(v) for v in np.cumsum(result.phase_durations)[:3]]


def cycle_signals(result: OCPResult, params: LoaderParams) -> dict[str, Any]:
    """Per phase: the model's outputs at the samples of the phase, each with the control applied there.

    A sample's control is the control of the interval it starts; the boundary sample closing a phase is
    evaluated with the phase's last control (so each phase's curve is continuous up to its boundary).
    """
    p = params
    t = np.asarray(result.t)
    x = np.asarray(result.states)
    u = np.asarray(result.controls)
    specs = phase_specs(result.braking, p)
    segments = []
    for k, i0, i1 in phase_slices(result):
        spec = specs[k - 1]
        xs = x[i0:i1 + 1]
        us = np.vstack([u[i0:i1], u[i1 - 1]])
        out = outputs(xs.T, us.T, spec.gear, spec.direction, p)
        segments.append({
            "phase": k, "gear": spec.gear, "i0": i0, "i1": i1, "t": t[i0:i1 + 1],
            "phi": np.asarray(out["phi"], dtype=float) * (1.0 if spec.gear != 0 else np.nan),
            "N_rpm": np.asarray(out["N_rpm"], dtype=float), "T_ice": np.asarray(out["T_ice"], dtype=float),
            "P_cyl": np.asarray(out["P_cyl"], dtype=float),
            # P_cyl also with the interval's control at the interval's end (the height has moved on)
            "P_cyl_end": np.asarray(outputs(x[i0 + 1:i1 + 1].T, u[i0:i1].T, spec.gear, spec.direction, p)["P_cyl"],
                                    dtype=float),
        })
    return {"t": t, "states": x, "controls": u, "segments": segments}


def tc_mode(phi: np.ndarray, gear: float, tol: float = PHI_TOL) -> np.ndarray:
    """Table I mode per sample: 'I' (phi < 0), 'II' (0 <= phi <= 1), 'III' (phi > 1), 'N' (neutral)."""
    phi = np.asarray(phi, dtype=float)
    if gear == 0:
        return np.full(phi.shape, "N")
    return np.where(phi < -tol, "I", np.where(phi > 1.0 + tol, "III", "II"))


def mode_summary(result: OCPResult, params: LoaderParams) -> dict[str, Any]:
    """Control intervals per TC mode (whole cycle and per phase), and where mode III occurs."""
    sig = cycle_signals(result, params)
    counts = {"I": 0, "II": 0, "III": 0, "N": 0}
    per_phase: dict[str, dict[str, int]] = {}
    mode3_windows = []
    for seg in sig["segments"]:
        modes = tc_mode(seg["phi"][:-1], seg["gear"])  # one per control interval (boundary sample excluded)
        pc = {m: int(np.sum(modes == m)) for m in counts}
        per_phase[str(seg["phase"])] = {m: c for m, c in pc.items() if c}
        for m, c in pc.items():
            counts[m] += c
        all_modes = tc_mode(seg["phi"], seg["gear"])
        if np.any(all_modes == "III"):
            ts = seg["t"][all_modes == "III"]
            mode3_windows.append({"phase": seg["phase"], "t_from": float(ts[0]), "t_to": float(ts[-1]),
                                  "phase_end": float(seg["t"][-1]), "phi_max": float(np.nanmax(seg["phi"]))})
    return {"counts": counts, "per_phase": per_phase, "mode_III": mode3_windows,
            "phi_min": float(min(np.nanmin(s["phi"]) for s in sig["segments"] if s["gear"] != 0)),
            "phi_max": float(max(np.nanmax(s["phi"]) for s in sig["segments"] if s["gear"] != 0))}


def pressure_summary(result: OCPResult, params: LoaderParams) -> dict[str, float]:
    """Largest P_cyl / P_cyl,max over the cycle (at both ends of every interval) and when it occurs."""
    sig = cycle_signals(result, params)
    best, t_best, active = -math.inf, math.nan, 0.0
    for seg in sig["segments"]:
        for vals, ts in ((seg["P_cyl"][:-1], seg["t"][:-1]), (seg["P_cyl_end"], seg["t"][1:])):
            ratio = vals / params.P_cyl_max
            j = int(np.argmax(ratio))
            if ratio[j] > best:
                best, t_best = float(ratio[j]), float(ts[j])
        ratio = seg["P_cyl"][:-1] / params.P_cyl_max
        active += float(np.sum(np.diff(seg["t"])[ratio >= PRESSURE_ACTIVE]))
    return {"max_ratio": best, "t_at_max": t_best, "active_time_s": active}


def smoothing_change(result: OCPResult) -> dict[str, float] | None:
    """Change of the objective through the smoothing homotopy (first k > 0 -> k = 0), in percent.

    ``true_pct`` compares the unpenalised objective (T for minimum time, fuel otherwise) of the smoothed
    and the final solution; ``penalised_pct`` the solver's objective value including the penalty.
    """
    h = result.smoothing or []
    if len(h) < 2:
        return None
    first, last = h[0], h[-1]
    key = "T" if result.objective == "time" else "fuel_g"
    return {
        "true_pct": 100.0 * (first[key] - last[key]) / last[key],
        "penalised_pct": 100.0 * (first["objective"] - last["objective"]) / last["objective"],
        "k_first": float(first["k"]),
    }


def cycle_facts(result: OCPResult, params: LoaderParams) -> dict[str, float]:
    """A few numbers that explain a cycle: leg times, reversing speed, height at the reversing point,
    engine speed at the end of phase 1, converter power in phase 2, oscillation of U_ab."""
    x = np.asarray(result.states)
    u = np.asarray(result.controls)
    sig = cycle_signals(result, params)
    seg = {s["phase"]: s for s in sig["segments"]}
    d = result.phase_durations
    i_rev = seg[3]["i0"] if 3 in seg else len(x) - 1
    p2 = seg.get(2)
    p_trac2 = 0.0
    if p2 is not None and p2["gear"] != 0:
        spec = phase_specs(result.braking, params)[1]
        xs, us = x[p2["i0"]:p2["i1"]], u[p2["i0"]:p2["i1"]]
        p_trac2 = float(np.max(outputs(xs.T, us.T, spec.gear, spec.direction, params)["P_trac"])) / 1000.0
    t = np.asarray(result.t)
    rpm2 = math.nan
    if p2 is not None:
        sl = slice(p2["i0"], p2["i1"] + 1)
        trapezoid = getattr(np, "trapezoid", None) or np.trapz
        rpm2 = float(trapezoid(x[sl, 0], t[sl]) / max(t[p2["i1"]] - t[p2["i0"]], 1e-9) * RAD_S_TO_RPM)
    du = np.diff(u[:, 1])
    zigzags = int(np.sum((du[1:] * du[:-1] < 0) & (np.abs(du[1:]) > 0.5) & (np.abs(du[:-1]) > 0.5)))
    return {
        "reversing_leg_s": float(d[0] + d[1]), "forwarding_leg_s": float(d[2] + d[3]),
        "peak_reversing_speed_mps": float(-np.min(x[:, 1])), "peak_forward_speed_mps": float(np.max(x[:, 1])),
        "H_at_reversing_point_m": float(x[i_rev, 2]),
        "engine_speed_end_phase1_rpm": float(x[seg[1]["i1"], 0] * RAD_S_TO_RPM) if 1 in seg else math.nan,
        "min_engine_speed_rpm": float(np.min(x[:, 0]) * RAD_S_TO_RPM),
        "max_P_trac_phase2_kW": p_trac2,
        "mean_engine_speed_phase2_rpm": rpm2,
        "U_ab_zigzags": zigzags,
    }


def mean_engine_speed_rpm(result: OCPResult) -> float:
    """Time-averaged engine speed over the cycle (rpm)."""
    t = np.asarray(result.t)
    w = np.asarray(result.states)[:, 0]
    trapezoid = getattr(np, "trapezoid", None) or np.trapz
    return float(trapezoid(w, t) / (t[-1] - t[0]) * RAD_S_TO_RPM)


# ====================================================================================================
# Figures
# ====================================================================================================
PANELS = (
    ("U_mf", "$U_{mf}$ (mg/cycle)"),
    ("U_ab", "$U_{ab}$ (m/s²)"),
    ("U_b", "$U_b$ (kN m)"),
    ("omega", "ω (rpm)"),
    ("V", "V (m/s)"),
    ("H", "H (m)"),
    ("V_b", "$V_b$ (m/s)"),
    ("phi", "φ (–)"),
)
MODE_BANDS = (("I", -math.inf, 0.0, "#f4cccc"), ("II", 0.0, 1.0, "#d9ead3"), ("III", 1.0, math.inf, "#fff2cc"))


def draw_cycle_column(axes: Sequence[Any], results: Mapping[str, OCPResult], params: LoaderParams,
                      title: str | None = None, ylabels: bool = True) -> None:
    """The eight panels of one column of Fig. 6 (controls as steps, states at the mesh points, phi with
    the TC mode bands), one colour per braking alternative, dashed phase boundaries in that colour."""
    phi_lo, phi_hi = -0.5, 1.5
    t_end = 0.0
    for braking, r in results.items():
        col = COLORS.get(braking, "k")
        sig = cycle_signals(r, params)
        t, x, u = sig["t"], sig["states"], sig["controls"]
        t_end = max(t_end, float(t[-1]))
        label = f"{LABELS.get(braking, braking)}: T = {r.T:.2f} s, {r.fuel_g:.1f} g"
        axes[0].stairs(u[:, 0], t, color=col, baseline=None, lw=1.4, label=label)
        axes[1].stairs(u[:, 1], t, color=col, baseline=None, lw=1.4)
        axes[2].stairs(u[:, 2] / 1000.0, t, color=col, baseline=None, lw=1.4)
        axes[3].plot(t, x[:, 0] * RAD_S_TO_RPM, color=col, lw=1.4)
        axes[4].plot(t, x[:, 1], color=col, lw=1.4)
        axes[5].plot(t, x[:, 2], color=col, lw=1.4)
        axes[6].plot(t, x[:, 3], color=col, lw=1.4)
        for seg in sig["segments"]:
            if seg["gear"] == 0:
                continue
            axes[7].plot(seg["t"], seg["phi"], color=col, lw=1.4)
            phi_lo = min(phi_lo, float(np.nanmin(seg["phi"])))
            phi_hi = max(phi_hi, float(np.nanmax(seg["phi"])))
        for tb in phase_boundaries(r):
            for ax in axes:
                ax.axvline(tb, color=col, ls="--", lw=0.9, alpha=0.7)
    lo, hi = phi_lo - 0.15 * (phi_hi - phi_lo), phi_hi + 0.15 * (phi_hi - phi_lo)
    for name, a, b, colour in MODE_BANDS:
        a, b = max(a, lo), min(b, hi)
        if b > a:
            axes[7].axhspan(a, b, color=colour, zorder=0, lw=0)
            axes[7].text(1.005, (a + b) / 2, name, transform=axes[7].get_yaxis_transform(), va="center",
                         ha="left", fontsize=8, fontweight="bold", color="0.3")
    axes[7].set_ylim(lo, hi)
    axes[7].text(0.01, 0.04, "mode I: φ<0, II: 0–1, III: φ>1; not drawn in neutral", transform=axes[7].transAxes,
                 fontsize=7, color="0.3")
    for ax, (_, lab) in zip(axes, PANELS, strict=True):
        ax.set_xlim(0.0, t_end)
        ax.grid(True, lw=0.4, alpha=0.5)
        if ylabels:
            ax.set_ylabel(lab, fontsize=9)
        ax.tick_params(labelsize=8)
    for ax in axes[:-1]:
        ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("time (s)", fontsize=9)
    # legend above the column, under the column's title, so it hides no curve
    axes[0].legend(title=title, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, fontsize=8,
                   title_fontsize=10, frameon=False, borderaxespad=0.2)


def cycles_figure(columns: Sequence[tuple[str, Mapping[str, OCPResult]]], params: LoaderParams,
                  suptitle: str = "") -> Figure:
    """Fig. 6 / Fig. 9 layout: one column of eight panels per (title, {braking: result})."""
    n = len(columns)
    fig = Figure(figsize=(6.2 * n + 0.6, 15.5), layout="constrained")
    axes = fig.subplots(len(PANELS), n, squeeze=False)
    for j, (title, results) in enumerate(columns):
        draw_cycle_column(axes[:, j], results, params, title=title, ylabels=True)
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    return fig


def engine_map_grid(params: LoaderParams, n_rpm: int = 160, n_torque: int = 160,
                    torque_range: tuple[float, float] = (20.0, 2400.0)) -> dict[str, np.ndarray]:
    """Brake power (kW) and brake efficiency P / (m_f q_hv) of our engine model on an (N, T) grid.

    Points above the torque limit or needing more than U_mf,max are NaN.
    """
    p = params
    N = np.linspace(p.omega_min * RAD_S_TO_RPM, p.omega_max * RAD_S_TO_RPM, n_rpm)
    T = np.linspace(*torque_range, n_torque)
    NN, TT = np.meshgrid(N, T)
    omega = NN / RAD_S_TO_RPM
    u_mf = (TT + engine.friction_torque(omega, p)) / p.T_ig_per_mg
    fuel = engine.fuel_mass_rate(omega, u_mf, p)  # kg/s
    power = TT * omega  # W
    eff = power / (fuel * p.q_hv)
    feasible = (TT <= engine.max_engine_torque(omega, p)) & (u_mf <= p.U_mf_max)
    return {"N": NN, "T": TT, "P_kW": np.where(feasible, power / 1000.0, np.nan),
            "eff": np.where(feasible, eff, np.nan)}


def operating_points(result: OCPResult, params: LoaderParams) -> tuple[np.ndarray, np.ndarray]:
    """(N rpm, T_ice N m) at every sample with the control applied there."""
    sig = cycle_signals(result, params)
    N = np.concatenate([s["N_rpm"][:-1] for s in sig["segments"]] + [sig["segments"][-1]["N_rpm"][-1:]])
    T = np.concatenate([s["T_ice"][:-1] for s in sig["segments"]] + [sig["segments"][-1]["T_ice"][-1:]])
    return N, T


def engine_map_figure(panels: Sequence[tuple[str, Mapping[str, OCPResult]]], params: LoaderParams) -> Figure:
    """Fig. 7: operating points over the torque-limit lines, constant power (grey) and efficiency (blue)."""
    p = params
    grid = engine_map_grid(p)
    N_line = np.linspace(p.omega_min * RAD_S_TO_RPM, p.omega_max * RAD_S_TO_RPM, 300)
    lines = [a + b * N_line for a, b in p.T_max_lines]
    envelope = np.minimum.reduce(lines)
    t_lo = min(min(float(np.min(operating_points(r, p)[1])) for r in res.values()) for _, res in panels)
    y_lo = min(0.0, t_lo) - 100.0
    y_hi = float(envelope.max()) * 1.12
    fig = Figure(figsize=(6.3 * len(panels), 5.6), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    eff_levels = [0.25, 0.30, 0.34, 0.37, 0.39, 0.40, 0.41, 0.42]
    p_levels = [25, 50, 100, 150, 200, 250]
    for ax, (title, results) in zip(axes, panels, strict=True):
        cp = ax.contour(grid["N"], grid["T"], grid["P_kW"], levels=p_levels, colors="0.55", linewidths=0.8)
        ax.clabel(cp, fmt="%d kW", fontsize=7)
        ce = ax.contour(grid["N"], grid["T"], grid["eff"], levels=eff_levels, colors="tab:blue", linewidths=0.8,
                        linestyles="-", alpha=0.8)
        ax.clabel(ce, fmt=lambda v: f"{100 * v:.0f} %", fontsize=7)
        for ln in lines:
            ax.plot(N_line, ln, color="k", lw=0.8, ls=":", alpha=0.7)
        ax.plot(N_line, envelope, color="k", lw=2.0)
        ax.axhline(0.0, color="0.3", lw=0.6)
        for braking, r in results.items():
            N, T = operating_points(r, p)
            ax.plot(N, T, color=COLORS[braking], lw=0.5, alpha=0.5)
            ax.scatter(N, T, s=14, color=COLORS[braking], marker=MARKERS[braking], edgecolors="none", zorder=3,
                       alpha=0.85)
        ax.set_xlim(N_line[0] - 20, N_line[-1] + 20)
        ax.set_ylim(y_lo, y_hi)
        ax.set_xlabel("engine speed N (rpm)")
        ax.set_ylabel("engine torque $T_{ice}$ (N m)")
        ax.set_title(title, fontsize=10)
        ax.grid(True, lw=0.3, alpha=0.4)
        handles = [Line2D([], [], color=COLORS[b], marker=MARKERS[b], ls="", label=LABELS[b]) for b in results]
        handles += [Line2D([], [], color="k", lw=2, label="torque limit (min of 3 lines)"),
                    Line2D([], [], color="k", lw=0.8, ls=":", label="the 3 lines $a_i + b_i N$"),
                    Line2D([], [], color="0.55", lw=0.8, label="constant power (kW)"),
                    Line2D([], [], color="tab:blue", lw=0.8, label="constant brake efficiency")]
        ax.legend(handles=handles, fontsize=7, loc="upper right", framealpha=0.9)
    return fig


def extra_fuel_points(service: ParetoFront, tc: ParetoFront) -> list[tuple[float, float, float, float]]:
    """(T, service fuel, tc fuel, % extra) at the service front's times within the tc front's range."""
    out = []
    for T, f in zip(service.T, service.fuel_g, strict=True):
        if tc.T_min <= T < tc.T_fuel_opt:
            f_tc = tc.fuel_at(T)
            out.append((float(T), float(f), f_tc, 100.0 * (f_tc - f) / f))
    return out


def pareto_figure(fronts: Mapping[str, ParetoFront], fixed: Mapping[str, OCPResult] | None = None,
                  lean: Mapping[str, OCPResult] | None = None,
                  cache_fronts: Mapping[str, ParetoFront] | None = None) -> Figure:
    """Fig. 8: fuel against cycle time for both alternatives (top) and TC braking's extra fuel (bottom)."""
    fig = Figure(figsize=(7.5, 8.0), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    for b, fr in fronts.items():
        T, F = np.asarray(fr.T), np.asarray(fr.fuel_g)
        Td = np.linspace(T[0], T[-1], 300)
        ax1.plot(Td, [pchip(T, F, v) for v in Td], color=COLORS[b], lw=1.3)
        ax1.plot(T, F, MARKERS[b], color=COLORS[b], ms=6, label=f"{LABELS[b]} ({len(T)} optima)")
        if lean and b in lean:
            ax1.plot([lean[b].T], [lean[b].fuel_g], MARKERS[b], color=COLORS[b], ms=9, mfc="none", mew=1.4,
                     label=f"{LABELS[b]}: leanest at {LEAN_FACTOR:g} × T_min")
        if fixed and b in fixed:
            ax1.plot([fixed[b].T], [fixed[b].fuel_g], "*", color=COLORS[b], ms=12, mec="k", mew=0.6,
                     label=f"{LABELS[b]}: solved at {fixed[b].T:g} s")
    labelled = False
    for b, fr0 in (cache_fronts or {}).items():
        fr = fronts.get(b)
        bad = [(T, f0) for T, f0, f in zip(fr0.T, fr0.fuel_g, fr.fuel_g if fr else fr0.fuel_g, strict=True) if f < f0 * (1 - 1e-6)]
        if bad:
            ax1.plot([q[0] for q in bad], [q[1] for q in bad], "x", color="0.35", ms=8, mew=1.5,
                     label=None if labelled else "Pareto cache point bettered by a re-solve")
            labelled = True
    ax1.set_ylabel("fuel per cycle (g)")
    ax1.set_title("Pareto fronts: minimum fuel at fixed cycle time", fontsize=10)
    ax1.grid(True, lw=0.4, alpha=0.5)
    ax1.legend(fontsize=8)
    if "service" in fronts and "tc" in fronts:
        pts = extra_fuel_points(fronts["service"], fronts["tc"])
        s, c = fronts["service"], fronts["tc"]
        lo, hi = max(s.T_min, c.T_min), min(s.T_fuel_opt, c.T_fuel_opt)
        Td = np.linspace(lo, hi - 1e-6, 300)
        dense = [100.0 * (c.fuel_at(v) - s.fuel_at(v)) / s.fuel_at(v) for v in Td]
        ax2.plot(Td, dense, color="0.5", lw=1.0, ls="--", label="both fronts interpolated")
        if pts:
            ax2.plot([q[0] for q in pts], [q[3] for q in pts], "o-", color="tab:purple", ms=6,
                     label="at the service front's cycle times")
        ax2.axhline(0.0, color="k", lw=0.6)
    ax2.set_xlabel("cycle time T (s)")
    ax2.set_ylabel("extra fuel with TC braking (%)")
    ax2.grid(True, lw=0.4, alpha=0.5)
    ax2.legend(fontsize=8)
    return fig


# ====================================================================================================
# The comparison table
# ====================================================================================================
def fmt_num(v: float | None, digits: int = 2, unit: str = "") -> str:
    """A number with a fixed number of decimals (and a unit), '–' when missing."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    s = f"{v:.{digits}f}"
    return f"{s} {unit}" if unit else s


def fmt_pct(v: float | None, digits: int = 2, signed: bool = True) -> str:
    """A percentage, signed by default: +2.63 %."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:+.{digits}f} %" if signed else f"{v:.{digits}f} %"


def _md_escape(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    out = ["| " + " | ".join(_md_escape(h) for h in header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(_md_escape(c) for c in row) + " |" for row in rows]
    return "\n".join(out) + "\n"


def compute_results(alts: Mapping[str, dict], fixed: Mapping[str, OCPResult], params: LoaderParams) -> dict:
    """Every number of the table, machine-readable."""
    p = params
    s, c = alts["service"]["front"], alts["tc"]["front"]
    res: dict[str, Any] = {"params_fingerprint": p.fingerprint(), "fixed_T_s": FIXED_T, "paper": PAPER}
    summary = {}
    for b, a in alts.items():
        fr: ParetoFront = a["front"]
        half = 0.5 * fr.T_fuel_opt
        plus10 = 1.1 * fr.T_min
        f_half = fr.fuel_at(half) if fr.T_min <= half < fr.T_fuel_opt else math.nan
        f_plus10 = fr.fuel_at(plus10) if plus10 < fr.T_fuel_opt else math.nan
        # slope of the front at its slow end: how flat the fuel minimum is
        slope = (fr.fuel_g[-2] - fr.fuel_g[-1]) / (fr.T[-1] - fr.T[-2])
        summary[b] = {
            "T_min_s": fr.T_min, "fuel_at_T_min_g": a["time"].fuel_g,
            "fuel_min_g": fr.fuel_min_g, "T_fuel_opt_s": fr.T_fuel_opt,
            "fuel_at_10s_g": fixed[b].fuel_g if b in fixed else math.nan,
            "fuel_at_10s_front_g": fr.fuel_at(FIXED_T) if fr.T_min <= FIXED_T < fr.T_fuel_opt else math.nan,
            "fuel_10s_verified": bool(fixed[b].verification.get("passed")) if b in fixed else None,
            "phase_durations_time_opt_s": a["time"].phase_durations,
            "phase_durations_fuel_opt_s": a["fuel"].phase_durations,
            "half_fuel_opt_T_s": half, "fuel_at_half_g": f_half,
            "half_fuel_opt_extra_fuel_pct": 100.0 * (f_half / fr.fuel_min_g - 1.0),
            "plus10_T_s": plus10, "fuel_at_plus10_g": f_plus10,
            "plus10_time_fuel_saving_pct": 100.0 * (1.0 - f_plus10 / a["time"].fuel_g),
            "lean_T_s": a["lean"].T if a.get("lean") else math.nan,
            "lean_fuel_g": a["lean"].fuel_g if a.get("lean") else math.nan,
            "plus10_fuel_saving_vs_lean_pct": (100.0 * (1.0 - f_plus10 / a["lean"].fuel_g) if a.get("lean")
                                               else math.nan),
            "front_end_slope_g_per_s": slope,
            "front_T_s": list(fr.T), "front_fuel_g": list(fr.fuel_g),
            "mean_engine_speed_rpm": {"time": mean_engine_speed_rpm(a["time"]),
                                      "fuel": mean_engine_speed_rpm(a["fuel"]),
                                      "fixed_10s": mean_engine_speed_rpm(fixed[b]) if b in fixed else math.nan},
        }
    res["summary"] = summary
    res["pareto_cache_improvements"] = {b: a.get("improved", []) for b, a in alts.items()}
    res["dT_time_pct"] = 100.0 * (c.T_min - s.T_min) / s.T_min
    res["dT_fuel_pct"] = 100.0 * (c.T_fuel_opt - s.T_fuel_opt) / s.T_fuel_opt
    res["fuel_10s_tc_extra_pct"] = (100.0 * (fixed["tc"].fuel_g - fixed["service"].fuel_g) / fixed["service"].fuel_g
                                    if "tc" in fixed and "service" in fixed else math.nan)
    f10s, f10c = summary["service"]["fuel_at_10s_front_g"], summary["tc"]["fuel_at_10s_front_g"]
    res["fuel_10s_tc_extra_front_pct"] = 100.0 * (f10c - f10s) / f10s
    res["extra_fuel_tc"] = [{"T_s": q[0], "service_g": q[1], "tc_g": q[2], "extra_pct": q[3]}
                            for q in extra_fuel_points(s, c)]
    # per cycle: pressure, modes, smoothing
    cycles: dict[str, Any] = {}
    named = []
    for b, a in alts.items():
        named += [(f"{b}/time", a["time"]), (f"{b}/fuel", a["fuel"])]
        if b in fixed:
            named.append((f"{b}/fuel_at_{FIXED_T:g}s", fixed[b]))
    for name, r in named:
        cycles[name] = {"T_s": r.T, "fuel_g": r.fuel_g, "pressure": pressure_summary(r, p),
                        "modes": mode_summary(r, p), "smoothing": smoothing_change(r),
                        "facts": cycle_facts(r, p), "verified": r.verification.get("passed")}
    res["cycles"] = cycles
    extra = [(f"{b}/lean_time_opt", a["lean"]) for b, a in alts.items() if a.get("lean")]
    # smoothing over every optimum we hold (the four optima, the 10 s cycles and the fronts' points)
    all_changes = []
    seen = set()
    for name, r in named + extra + [(f"{b}/front_T{r.T:.3f}", r) for b, a in alts.items() for r in a["points"]]:
        sc = smoothing_change(r)
        if sc is not None and (r.braking, r.objective, round(r.T, 6)) not in seen:
            seen.add((r.braking, r.objective, round(r.T, 6)))
            all_changes.append({"cycle": name, **sc})
    res["smoothing_all"] = all_changes
    res["smoothing_max_abs_true_pct"] = max((abs(q["true_pct"]) for q in all_changes), default=math.nan)
    res["smoothing_max_abs_penalised_pct"] = max((abs(q["penalised_pct"]) for q in all_changes), default=math.nan)
    # the pressure limit: U_ab allowed by the pressure at the start height vs the U_ab bound
    from wl_env.physics import lift

    res["U_ab_max_by_pressure_at_H0"] = float(lift.max_bucket_acceleration_for_pressure(p.H_0, p))
    res["U_ab_max_by_pressure_at_HT"] = float(lift.max_bucket_acceleration_for_pressure(p.H_T, p))
    res["U_ab_bound"] = float(p.U_ab_bounds[1])
    res["P_cyl_max_MPa"] = p.P_cyl_max / 1e6
    return res


def _modes_text(m: dict) -> str:
    c = m["counts"]
    parts = [f"{k}: {c[k]}" for k in ("I", "II", "III", "N") if c[k]]
    return ", ".join(parts)


def _pairs(values: Sequence[float], fmt: str = "{:.2f}") -> str:
    return ", ".join(fmt.format(v) for v in values)


def statement_rows(res: dict) -> list[dict[str, Any]]:
    """One row per statement: the paper's claim and number, ours, and a sentence where they differ."""
    S, C = res["summary"]["service"], res["summary"]["tc"]
    cyc = res["cycles"]
    fs, fc = cyc["service/time"]["facts"], cyc["tc/time"]["facts"]
    rows: list[dict[str, Any]] = []

    # 1: cycle time penalty of TC braking, time-optimal
    d = res["dT_time_pct"]
    if d <= 0:
        note = "Opposite sign: TC braking is not slower in our model."
    elif abs(d - PAPER["dT_time_pct"]) < 0.5:
        note = "Same sign and close to the paper."
    else:
        note = (f"Same sign, {'larger' if d > PAPER['dT_time_pct'] else 'smaller'}. Our TC optimum starts braking "
                f"already at the end of phase 1 (fuel cut, engine {fc['engine_speed_end_phase1_rpm']:.0f} rpm at t1, "
                f"converter in mode III), reverses at a lower peak speed ({fc['peak_reversing_speed_mps']:.2f} vs "
                f"{fs['peak_reversing_speed_mps']:.2f} m/s) and spends up to {fc['max_P_trac_phase2_kW']:.0f} kW of "
                f"engine power on braking in phase 2, so it lifts less before the reversing point "
                f"({fc['H_at_reversing_point_m']:.2f} vs {fs['H_at_reversing_point_m']:.2f} m): both legs get longer "
                f"(reversing {fc['reversing_leg_s']:.2f} vs {fs['reversing_leg_s']:.2f} s, forwarding "
                f"{fc['forwarding_leg_s']:.2f} vs {fs['forwarding_leg_s']:.2f} s). How much depends on ξ and κ "
                f"outside 0 ≤ φ ≤ 1.5 (continued linearly by the spec) and on the digitized torque lines, so the "
                f"size differs from the paper's.")
    rows.append({"id": "dT_time", "statement": "TC braking lengthens the time-optimal cycle by 1.58 %",
                 "paper": fmt_pct(PAPER["dT_time_pct"]),
                 "ours": f"{fmt_pct(d)} ({S['T_min_s']:.3f} → {C['T_min_s']:.3f} s)", "value": d, "note": note})

    # 2: cycle time penalty of TC braking, fuel-optimal
    d = res["dT_fuel_pct"]
    rel = 100.0 * S["front_end_slope_g_per_s"] * (PAPER["dT_fuel_pct"] / 100.0) * S["T_fuel_opt_s"] / S["fuel_min_g"]
    if d <= 0:
        note = "Opposite sign: the TC fuel-optimal cycle is not longer in our model."
    elif abs(d - PAPER["dT_fuel_pct"]) < 0.5:
        note = "Same sign and close to the paper."
    else:
        note = (f"Same sign, {'larger' if d > PAPER['dT_fuel_pct'] else 'smaller'}. The fuel minimum is very flat "
                f"(near it our front falls by only {S['front_end_slope_g_per_s']:.2f} g/s, so 2.8 % more cycle time "
                f"changes the fuel by about {rel:.2f} %): the time of minimum fuel is ill-determined, and small "
                f"differences in the engine's low-speed friction and the converter curves move it by percents.")
    rows.append({"id": "dT_fuel", "statement": "TC braking lengthens the fuel-optimal cycle by 2.8 %",
                 "paper": fmt_pct(PAPER["dT_fuel_pct"]),
                 "ours": f"{fmt_pct(d)} ({S['T_fuel_opt_s']:.2f} → {C['T_fuel_opt_s']:.2f} s)", "value": d,
                 "note": note})

    # 3: halving the fuel-optimal cycle
    vs, vc = S["half_fuel_opt_extra_fuel_pct"], C["half_fuel_opt_extra_fuel_pct"]
    if max(vs, vc) < PAPER["half_fuel_opt_extra_fuel_pct"]:
        note = "Agrees."
    else:
        note = (f"About {max(vs, vc) / PAPER['half_fuel_opt_extra_fuel_pct']:.0f}× the paper's bound. Our fuel-optimal "
                f"cycle is long ({S['T_fuel_opt_s'] / S['T_min_s']:.2f} × T_min), so half of it "
                f"({S['half_fuel_opt_T_s']:.2f} s = {S['half_fuel_opt_T_s'] / S['T_min_s']:.2f} × T_min) is already "
                f"on the steep part of the front. Slow cycles are cheap in our model because the fuel-optimal engine "
                f"runs slowly (mean {S['mean_engine_speed_rpm']['fuel']:.0f} rpm, down to ω_min ≈ "
                f"{cyc['service/fuel']['facts']['min_engine_speed_rpm']:.0f} rpm) where the re-implemented friction "
                f"(quadratic in speed) is about a quarter of its value at 2000 rpm; a different friction map or "
                f"ω_min in the paper makes slow cycles less rewarding and the front flatter.")
    rows.append({"id": "half_fuel_opt", "statement": "halving the fuel-optimal cycle costs less than 10 % more fuel",
                 "paper": "< +10 %", "ours": f"service {fmt_pct(vs, 1)} (at {S['half_fuel_opt_T_s']:.2f} s), "
                 f"TC {fmt_pct(vc, 1)} (at {C['half_fuel_opt_T_s']:.2f} s)", "value": {"service": vs, "tc": vc},
                 "note": note})

    # 4: +10 % cycle time from the time optimum
    vs, vc = S["plus10_time_fuel_saving_pct"], C["plus10_time_fuel_saving_pct"]
    ls, lc = S["plus10_fuel_saving_vs_lean_pct"], C["plus10_fuel_saving_vs_lean_pct"]
    close = abs(max(vs, vc) - PAPER["plus10_time_fuel_saving_pct"]) < 5.0
    note = (("Close in size for service brakes, measured like the paper from the time-optimal solution's fuel. "
             if close else
             f"{'Smaller' if max(vs, vc) < PAPER['plus10_time_fuel_saving_pct'] else 'Larger'} saving. ")
            + f"That reference is soft: the time-optimal problem leaves the fuel free wherever it does not cost "
            f"time, so its solution's fuel ({S['fuel_at_T_min_g']:.1f} g service, {C['fuel_at_T_min_g']:.1f} g TC) "
            f"is one of many; the leanest cycle at {LEAN_FACTOR:g} × T_min needs {S['lean_fuel_g']:.1f} / "
            f"{C['lean_fuel_g']:.1f} g, against which +10 % time saves {ls:.1f} / {lc:.1f} %. The paper's 35 % "
            f"likely has the same softness; beyond it the engine map and torque lines decide how much 10 % more "
            f"time buys.")
    rows.append({"id": "plus10_time", "statement": "+10 % cycle time from the time optimum saves up to 35 % fuel",
                 "paper": "up to −35 %", "ours": f"service {fmt_pct(-vs, 1)} (at {S['plus10_T_s']:.2f} s), "
                 f"TC {fmt_pct(-vc, 1)} (at {C['plus10_T_s']:.2f} s); against the leanest cycle at "
                 f"{LEAN_FACTOR:g} × T_min: {fmt_pct(-ls, 1)} / {fmt_pct(-lc, 1)}",
                 "value": {"service": -vs, "tc": -vc, "service_vs_lean": -ls, "tc_vs_lean": -lc}, "note": note})

    # 5: 10 s cycle
    d = res["fuel_10s_tc_extra_pct"]
    df = res["fuel_10s_tc_extra_front_pct"]
    if d <= 0:
        note = "Opposite sign: TC braking does not cost fuel in our 10 s cycle."
    elif abs(d - PAPER["fuel_10s_tc_extra_pct"]) < 1.0:
        note = "Same sign and close to the paper."
    else:
        note = (f"Same sign, {'larger' if d > PAPER['fuel_10s_tc_extra_pct'] else 'smaller'}: 10 s is "
                f"{FIXED_T / S['T_min_s']:.2f} × our T_min, and the nearer a cycle is to T_min the more TC braking "
                f"costs (Fig. 8, bottom); the converter's braking power again depends on ξ(φ < 0).")
    rows.append({"id": "fuel_10s", "statement": "fuel-optimal 10 s cycle: TC braking uses 2.7 % more fuel",
                 "paper": fmt_pct(PAPER["fuel_10s_tc_extra_pct"]),
                 "ours": f"{fmt_pct(d)} ({S['fuel_at_10s_g']:.2f} → {C['fuel_at_10s_g']:.2f} g); interpolated on "
                 f"the fronts {fmt_pct(df)}", "value": d, "note": note})

    # 6: extra fuel of TC braking at all cycle times, growing in faster cycles
    ext = res["extra_fuel_tc"]
    if ext:
        allpos = all(q["extra_pct"] > 0 for q in ext)
        monotone = all(a["extra_pct"] >= b["extra_pct"] for a, b in zip(ext, ext[1:], strict=False))
        grows = ext[0]["extra_pct"] > ext[-1]["extra_pct"]
        ours = ", ".join(f"{q['T_s']:.1f} s: {fmt_pct(q['extra_pct'], 1)}" for q in ext)
        if not allpos:
            note = ("Not positive at every cycle time: where the fronts nearly meet, the difference is within the "
                    "solver's local-optimum noise.")
        elif grows and monotone:
            note = ("Agrees. Both fronts start at the minimum fuel 0.1 % above their own minimum time, so the "
                    "fastest values compare minimised fuels.")
        elif grows:
            note = ("Agrees in trend (largest in the fastest cycles, smallest in the slowest) but not monotone: "
                    "each point is a local optimum, and a front point can sit in a different local optimum from "
                    "its neighbours.")
        else:
            note = "Positive everywhere, but not largest in the fastest cycles."
    else:
        ours, note, allpos, grows = "–", "The fronts do not overlap.", None, None
    rows.append({"id": "extra_fuel_trend", "statement": "TC braking costs more fuel at all cycle times, most in "
                 "the fastest cycles (Fig. 8 bottom, Sec. V)", "paper": "> 0, larger in faster cycles", "ours": ours,
                 "value": {"all_positive": allpos, "largest_in_fastest": grows}, "note": note})

    # 7: the lift-cylinder pressure limit
    pr = {k: v["pressure"] for k, v in cyc.items()}
    mx = max(v["max_ratio"] for v in pr.values())
    active = [k for k, v in pr.items() if v["max_ratio"] >= PRESSURE_ACTIVE]
    ours = "max P_cyl / P_cyl,max: " + "; ".join(f"{k} {v['max_ratio']:.2f}" for k, v in pr.items())
    if active:
        note = f"Active in {', '.join(active)}."
    else:
        note = (f"Never active in our optima (at most {mx:.2f} × P_cyl,max). The spec's assumed P_cyl,max = "
                f"{res['P_cyl_max_MPa']:.0f} MPa would allow U_ab up to {res['U_ab_max_by_pressure_at_H0']:.1f} m/s² "
                f"at H_0 ({res['U_ab_max_by_pressure_at_HT']:.1f} at H_T), far above the U_ab bound of "
                f"{res['U_ab_bound']:.1f} m/s², so in our time optima it is that bound which caps U_ab at the start "
                f"of the lift; the paper's cylinder data and pressure limit are not published.")
    rows.append({"id": "pressure", "statement": "the lift-cylinder pressure limit is active briefly in the "
                 "time-optimal cycles (U_ab rises more slowly at 1.1–1.4 s)", "paper": "active, 1.1–1.4 s",
                 "ours": ours, "value": {k: v["max_ratio"] for k, v in pr.items()}, "note": note})

    # 8: TC modes
    mt = cyc["tc/time"]["modes"]
    w = [m for m in mt["mode_III"] if m["phase"] == 1]
    m3 = (f"yes, φ > 1 from {w[0]['t_from']:.2f} s to the end of phase 1 at {w[0]['phase_end']:.2f} s, up to "
          f"φ = {w[0]['phi_max']:.2f}" if w else "no")
    ours = "; ".join(f"{k}: {_modes_text(v['modes'])}" for k, v in cyc.items())
    parts = ["Time-optimal TC cycle, mode III at the end of phase 1: " + m3 + "."]
    svc_III = cyc["service/time"]["modes"]["counts"]["III"]
    parts.append("Time-optimal service cycle: " + ("no mode III, as in the paper." if svc_III == 0 else
                                                   f"{svc_III} intervals in mode III (the paper has none)."))
    fuel_III = [k for k, v in cyc.items() if k.endswith("/fuel") and v["modes"]["counts"]["III"]]
    parts.append("Fuel-optimal cycles: " + (
        "mode II while driving, mode I while the converter brakes, neutral in phase 4, as in the paper (whose text "
        "calls the TC-braking phase 'mode III', against its own Table I: φ < 0 is mode I)." if not fuel_III else
        f"mode III also occurs in {', '.join(fuel_III)}."))
    ten_III = {k: v["modes"]["counts"]["III"] for k, v in cyc.items() if "fuel_at" in k}
    parts.append("10 s cycles: " + ("modes II and III while accelerating in both, as in the paper." if all(
        ten_III.values()) else "mode III only in " + (", ".join(k for k, v in ten_III.items() if v) or "neither")
        + " (the paper has II and III in both)."))
    rows.append({"id": "tc_modes", "statement": "TC modes: III at the end of phase 1 of the time-optimal TC cycle; "
                 "no III with service brakes (time-optimal); fuel-optimal cycles in II except while the converter "
                 "brakes and in neutral; II and III in the 10 s cycles", "paper": "as stated",
                 "ours": f"control intervals per mode (I: φ < 0, II: 0..1, III: φ > 1, N: neutral): {ours}",
                 "value": {k: v["modes"]["counts"] for k, v in cyc.items()}, "note": " ".join(parts)})

    # 9: smoothing homotopy
    v = res["smoothing_max_abs_true_pct"]
    vp = res["smoothing_max_abs_penalised_pct"]
    note = ("Within the paper's 0.3 %." if v <= PAPER["smoothing_change_pct"] else
            "Larger than 0.3 %: our first homotopy step weighs the penalty more than the paper's.")
    rows.append({"id": "smoothing", "statement": "the smoothing homotopy (k → 0) changes the objective by at most "
                 "0.3 %", "paper": "≤ 0.3 %", "ours": f"≤ {fmt_num(v, 3)} % (objective itself), ≤ {fmt_num(vp, 3)} % "
                 f"(with the penalty term), over {len(res['smoothing_all'])} optima", "value": v, "note": note})

    # 10: engine speed lower with TC braking (abstract)
    sm = {b: res["summary"][b]["mean_engine_speed_rpm"] for b in ("service", "tc")}
    names = {"time": "time-optimal", "fuel": "fuel-optimal", "fixed_10s": f"{FIXED_T:g} s"}
    lower = {k: sm["tc"][k] < sm["service"][k] for k in names}
    ours = "; ".join(f"{names[k]} {sm['service'][k]:.0f} → {sm['tc'][k]:.0f} rpm" for k in names)
    if all(lower.values()):
        note = "Agrees in every pair."
    else:
        n_low = sum(lower.values())
        note = ("Lower with TC braking in the " + " and ".join(names[k] for k, v in lower.items() if v) +
                (" pairs" if n_low > 1 else " pair") + ", not in the " +
                " and ".join(names[k] for k, v in lower.items() if not v) +
                " one" + "".join(
                    f" ({names[k]}: phase 2 mean {cyc[f'service/{key}']['facts']['mean_engine_speed_phase2_rpm']:.0f}"
                    f" rpm with service brakes, {cyc[f'tc/{key}']['facts']['mean_engine_speed_phase2_rpm']:.0f} rpm "
                    f"with TC braking)" for k, key in (("time", "time"), ("fuel", "fuel"),
                                                        ("fixed_10s", f"fuel_at_{FIXED_T:g}s")) if not lower[k])
                + "; the converter's braking torque grows with ω², so how fast the engine runs while braking is a "
                "trade-off between braking and lifting that the optimum sets differently per cycle time.")
    rows.append({"id": "engine_speed", "statement": "with TC braking the engine runs at lower speeds, yet uses "
                 "more fuel (abstract)", "paper": "lower", "ours": f"mean engine speed, service → TC: {ours}",
                 "value": sm, "note": note})
    return rows


def build_table_markdown(res: dict, rows: Sequence[dict[str, Any]], fig_names: Sequence[str] = ()) -> str:
    """table.md: the paper's statements beside our numbers, then our key figures."""
    S, C = res["summary"]["service"], res["summary"]["tc"]
    lines = ["# Nezhadali & Eriksson, Section IV, reproduced with this project's model", "",
             "Generated by `scripts/reproduce_paper.py`; parameters are the specification's re-implementation "
             f"defaults (fingerprint `{res['params_fingerprint']}`), not the paper's unpublished values. "
             "Numbers for both braking alternatives come from the cached Pareto fronts "
             f"({len(S['front_T_s'])} optima each) and from fuel-optimal cycles solved at {FIXED_T:g} s.", "",
             "## The paper's statements and ours", ""]
    lines.append(markdown_table(["statement (paper, Sec. IV)", "paper", "ours", "where they differ, and why"],
                                [[r["statement"], r["paper"], r["ours"], r["note"]] for r in rows]))
    lines += ["## Our key numbers", ""]
    lines.append(markdown_table(
        ["", "service brakes", "TC braking"],
        [["minimum cycle time T_min", fmt_num(S["T_min_s"], 3, "s"), fmt_num(C["T_min_s"], 3, "s")],
         ["fuel of the time-optimal cycle", fmt_num(S["fuel_at_T_min_g"], 2, "g"), fmt_num(C["fuel_at_T_min_g"], 2, "g")],
         [f"minimum fuel at {LEAN_FACTOR:g} × T_min (leanest near-time-optimal cycle)", fmt_num(S["lean_fuel_g"], 2, "g"),
          fmt_num(C["lean_fuel_g"], 2, "g")],
         ["minimum fuel", fmt_num(S["fuel_min_g"], 2, "g"), fmt_num(C["fuel_min_g"], 2, "g")],
         ["cycle time at minimum fuel", fmt_num(S["T_fuel_opt_s"], 3, "s"), fmt_num(C["T_fuel_opt_s"], 3, "s")],
         [f"minimum fuel at T = {FIXED_T:g} s (solved)", fmt_num(S["fuel_at_10s_g"], 2, "g"),
          fmt_num(C["fuel_at_10s_g"], 2, "g")],
         [f"minimum fuel at T = {FIXED_T:g} s (front, interpolated)", fmt_num(S["fuel_at_10s_front_g"], 2, "g"),
          fmt_num(C["fuel_at_10s_front_g"], 2, "g")],
         ["phase durations, time-optimal", ", ".join(f"{v:.2f}" for v in S["phase_durations_time_opt_s"]) + " s",
          ", ".join(f"{v:.2f}" for v in C["phase_durations_time_opt_s"]) + " s"],
         ["phase durations, fuel-optimal", ", ".join(f"{v:.2f}" for v in S["phase_durations_fuel_opt_s"]) + " s",
          ", ".join(f"{v:.2f}" for v in C["phase_durations_fuel_opt_s"]) + " s"]]))
    lines += ["## Pareto fronts", ""]
    n = max(len(S["front_T_s"]), len(C["front_T_s"]))
    prow = []
    for i in range(n):
        row = []
        for F in (S, C):
            row += ([fmt_num(F["front_T_s"][i], 3), fmt_num(F["front_fuel_g"][i], 2)] if i < len(F["front_T_s"])
                    else ["", ""])
        prow.append(row)
    lines.append(markdown_table(["service T (s)", "service fuel (g)", "TC T (s)", "TC fuel (g)"], prow))
    lines += ["## Remarks", ""] + [f"- {r}" for r in remarks(res)] + [""]
    if fig_names:
        lines += ["## Figures", ""] + [f"![{f}]({f})" for f in fig_names] + [""]
    return "\n".join(lines)


def remarks(res: dict) -> list[str]:
    """Notes on how the numbers were obtained and on anything odd in the optima."""
    out = []
    imp = res.get("pareto_cache_improvements", {})
    if any(imp.values()):
        items = [f"{b} T = {q['T_s']:.3f} s: {q['pareto_cache_g']:.3f} → {q['polished_g']:.3f} g "
                 f"({fmt_pct(q['change_pct'])})" for b, qs in imp.items() for q in qs]
        out.append("Some points of the cached Pareto fronts (`mpc.benchmark.pareto.pareto_front`, continued from neighbour to "
                   "neighbour) are local optima: re-solved from the OCP's template multi-start they come out leaner "
                   "(" + "; ".join(items) + "). The fronts above and in Fig. 8 use the leaner points; the Pareto "
                   "cache is left as it is.")
    else:
        out.append("Every interior point of the cached Pareto fronts was re-solved from the OCP's template "
                   "multi-start without finding a leaner optimum.")
    chat = {k: v["facts"]["U_ab_zigzags"] for k, v in res["cycles"].items() if v["facts"]["U_ab_zigzags"] >= 6}
    if chat:
        sm = {k: res["cycles"][k]["smoothing"] for k in chat}
        out.append("U_ab chatters (bang-bang zigzags between successive intervals) in " + ", ".join(
            f"{k} ({n} reversals; smoothed solution {fmt_num(abs(sm[k]['true_pct']) if sm[k] else None, 4)} % "
            f"off the final objective)" for k, n in chat.items()) + ": the homotopy's last step, k = 0, leaves a "
            "singular arc on which the objective hardly depends on U_ab. The paper removes exactly these "
            "oscillations with the penalty (33); the final k = 0 solve brings them back.")
    out.append(f"TC modes are counted per control interval with φ evaluated at the interval start with the phase's "
               f"gear; |φ| < {PHI_TOL:g} counts as mode II (a standing machine), neutral phases as N. P_cyl is "
               f"evaluated at both ends of every interval with that interval's U_ab.")
    out.append("The extra fuel of TC braking at equal cycle time interpolates the TC front (monotone cubic, "
               "`ParetoFront.fuel_at`) at the service front's cycle times inside the TC front's range.")
    return out


# ====================================================================================================
# Main
# ====================================================================================================
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--out", default="docs/paper", help="output folder for the figures, table.md and results.json")
    ap.add_argument("--cache", default=None,
                    help="cache folder of solved optima (default $WL_CACHE_DIR or ~/.cache/wheel-loader-gym)")
    ap.add_argument("--points", type=int, default=8, help="cycle times on each Pareto front")
    args = ap.parse_args(argv)
    if not 3 <= args.points <= 100:
        ap.error(f"--points must lie in [3, 100], got {args.points}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    p = resolve(None)
    out = Path(args.out)
    t0 = time.perf_counter()
    say(f"parameters {p.fingerprint()}, cache {cache_dir(args.cache)}, {args.points} points per front -> {out}")
    alts = {b: load_alternative(b, args.points, p, args.cache) for b in BRAKING_MODES}
    for b in BRAKING_MODES:
        alts[b] = polish_front(b, alts[b], p, args.cache)
        alts[b]["lean"] = lean_time_optimum(b, alts[b]["time"], p, args.cache, first_point=alts[b]["front_first"])
    fixed = {b: fixed_time_optimum(b, FIXED_T, p, args.cache, alts[b]["front"], alts[b]["points"])
             for b in BRAKING_MODES}
    figs = []
    say("drawing fig6 (time- and fuel-optimal transients)")
    fig = cycles_figure([("time-optimal", {b: alts[b]["time"] for b in BRAKING_MODES}),
                         ("fuel-optimal", {b: alts[b]["fuel"] for b in BRAKING_MODES})], p,
                        "Time-optimal (left) and fuel-optimal (right) cycles; dashed: phase boundaries")
    figs.append(save_figure(fig, out / "fig6.png").name)
    say("drawing fig7 (engine operating points)")
    fig = engine_map_figure([("time-optimal cycles", {b: alts[b]["time"] for b in BRAKING_MODES}),
                             ("fuel-optimal cycles", {b: alts[b]["fuel"] for b in BRAKING_MODES})], p)
    figs.append(save_figure(fig, out / "fig7.png").name)
    say("drawing fig8 (Pareto fronts)")
    lean = {b: alts[b]["lean"] for b in BRAKING_MODES if alts[b].get("lean") is not None}
    figs.append(save_figure(pareto_figure({b: alts[b]["front"] for b in BRAKING_MODES}, fixed, lean,
                                          {b: alts[b]["front_cache"] for b in BRAKING_MODES if "front_cache" in alts[b]}),
                            out / "fig8.png").name)
    say("drawing fig9 (fuel-optimal 10 s cycles)")
    fig = cycles_figure([(f"fuel-optimal {FIXED_T:g} s cycle", fixed)], p,
                        f"Minimum fuel at T = {FIXED_T:g} s; dashed: phase boundaries")
    figs.append(save_figure(fig, out / "fig9.png").name)
    say("computing the table")
    res = compute_results(alts, fixed, p)
    rows = statement_rows(res)
    res["statements"] = rows
    write_text(out / "table.md", build_table_markdown(res, rows, figs))
    write_json(out / "results.json", res)
    say(f"wrote {', '.join(figs)}, table.md, results.json to {out} in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
