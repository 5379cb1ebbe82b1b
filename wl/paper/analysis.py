"""The numbers behind the paper's statements: signals of an optimal cycle and what they show.

Per optimal cycle (:class:`mpc.benchmark.ocp.OCPResult`): the model's outputs phase by phase
(:func:`cycle_signals`), the torque converter's mode per control interval (Table I: :func:`tc_mode`,
:func:`mode_summary`), the lift-cylinder pressure against its limit (:func:`pressure_summary`), the
change through the smoothing homotopy (:func:`smoothing_change`) and a few explaining facts
(:func:`cycle_facts`). Between two fronts: TC braking's extra fuel at equal cycle time
(:func:`extra_fuel_points`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mpc.benchmark.ocp import OCPResult
from mpc.benchmark.pareto import ParetoFront
from wl_env.cycle import phase_specs
from wl_env.model import outputs
from wl_env.params import LoaderParams

RAD_S_TO_RPM = 30.0 / math.pi
PHI_TOL = 1e-3  # |phi| below this counts as phi = 0 (a standing machine), not as mode I
PRESSURE_ACTIVE = 0.995  # P_cyl / P_cyl_max at or above this: the pressure limit is active


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



def extra_fuel_points(service: ParetoFront, tc: ParetoFront) -> list[tuple[float, float, float, float]]:
    """(T, service fuel, tc fuel, % extra) at the service front's times within the tc front's range."""
    out = []
    for T, f in zip(service.T, service.fuel_g, strict=True):
        if tc.T_min <= T < tc.T_fuel_opt:
            f_tc = tc.fuel_at(T)
            out.append((float(T), float(f), f_tc, 100.0 * (f_tc - f) / f))
    return out

