"""The comparison table: each quantitative statement of the paper's Section IV beside our number.

:func:`compute_results` collects every number (``results.json``), :func:`statement_rows` sets each of
the paper's statements beside ours with a sentence where they differ, :func:`build_table_markdown`
writes ``table.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from mpc.benchmark.ocp import OCPResult
from mpc.benchmark.optima import LEAN_FACTOR, FrontOptima
from wl.paper.analysis import (
    PHI_TOL,
    PRESSURE_ACTIVE,
    cycle_facts,
    extra_fuel_points,
    mean_engine_speed_rpm,
    mode_summary,
    pressure_summary,
    smoothing_change,
)
from wl_env.params import LoaderParams
from wl_env.physics import lift

FIXED_T = 10.0  # s, the cycle of Fig. 9
# The paper's quantitative statements of Section IV (and its remark on the smoothing homotopy, Sec. III).
PAPER = {
    "dT_time_pct": 1.58,
    "dT_fuel_pct": 2.8,
    "half_fuel_opt_extra_fuel_pct": 10.0,  # "less than 10 %"
    "plus10_time_fuel_saving_pct": 35.0,  # "up to 35 %"
    "fuel_10s_tc_extra_pct": 2.7,
    "smoothing_change_pct": 0.3,  # "at most 0.3 %"
}


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


def compute_results(alts: Mapping[str, FrontOptima], fixed: Mapping[str, OCPResult], params: LoaderParams) -> dict:
    """Every number of the table, machine-readable: ``alts`` per braking alternative (both), ``fixed`` the
    fuel-optimal cycles at FIXED_T."""
    p = params
    s, c = alts["service"].front, alts["tc"].front
    res: dict[str, Any] = {"params_fingerprint": p.fingerprint(), "fixed_T_s": FIXED_T, "paper": PAPER}
    summary = {}
    for b, a in alts.items():
        fr = a.front
        half = 0.5 * fr.T_fuel_opt
        plus10 = 1.1 * fr.T_min
        f_half = fr.fuel_at(half) if fr.T_min <= half < fr.T_fuel_opt else math.nan
        f_plus10 = fr.fuel_at(plus10) if plus10 < fr.T_fuel_opt else math.nan
        # slope of the front at its slow end: how flat the fuel minimum is
        slope = (fr.fuel_g[-2] - fr.fuel_g[-1]) / (fr.T[-1] - fr.T[-2])
        summary[b] = {
            "T_min_s": fr.T_min, "fuel_at_T_min_g": a.time.fuel_g,
            "fuel_min_g": fr.fuel_min_g, "T_fuel_opt_s": fr.T_fuel_opt,
            "fuel_at_10s_g": fixed[b].fuel_g if b in fixed else math.nan,
            "fuel_at_10s_front_g": fr.fuel_at(FIXED_T) if fr.T_min <= FIXED_T < fr.T_fuel_opt else math.nan,
            "fuel_10s_verified": bool(fixed[b].verification.get("passed")) if b in fixed else None,
            "phase_durations_time_opt_s": a.time.phase_durations,
            "phase_durations_fuel_opt_s": a.fuel.phase_durations,
            "half_fuel_opt_T_s": half, "fuel_at_half_g": f_half,
            "half_fuel_opt_extra_fuel_pct": 100.0 * (f_half / fr.fuel_min_g - 1.0),
            "plus10_T_s": plus10, "fuel_at_plus10_g": f_plus10,
            "plus10_time_fuel_saving_pct": 100.0 * (1.0 - f_plus10 / a.time.fuel_g),
            "lean_T_s": a.lean.T if a.lean is not None else math.nan,
            "lean_fuel_g": a.lean.fuel_g if a.lean is not None else math.nan,
            "plus10_fuel_saving_vs_lean_pct": (100.0 * (1.0 - f_plus10 / a.lean.fuel_g) if a.lean is not None
                                               else math.nan),
            "front_end_slope_g_per_s": slope,
            "front_T_s": list(fr.T), "front_fuel_g": list(fr.fuel_g),
            "mean_engine_speed_rpm": {"time": mean_engine_speed_rpm(a.time),
                                      "fuel": mean_engine_speed_rpm(a.fuel),
                                      "fixed_10s": mean_engine_speed_rpm(fixed[b]) if b in fixed else math.nan},
        }
    res["summary"] = summary
    res["pareto_cache_improvements"] = {b: a.improved for b, a in alts.items()}
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
        named += [(f"{b}/time", a.time), (f"{b}/fuel", a.fuel)]
        if b in fixed:
            named.append((f"{b}/fuel_at_{FIXED_T:g}s", fixed[b]))
    for name, r in named:
        cycles[name] = {"T_s": r.T, "fuel_g": r.fuel_g, "pressure": pressure_summary(r, p),
                        "modes": mode_summary(r, p), "smoothing": smoothing_change(r),
                        "facts": cycle_facts(r, p), "verified": r.verification.get("passed")}
    res["cycles"] = cycles
    extra = [(f"{b}/lean_time_opt", a.lean) for b, a in alts.items() if a.lean is not None]
    # smoothing over every optimum we hold (the four optima, the 10 s cycles and the fronts' points)
    all_changes = []
    seen = set()
    for name, r in named + extra + [(f"{b}/front_T{r.T:.3f}", r) for b, a in alts.items() for r in a.points]:
        sc = smoothing_change(r)
        if sc is not None and (r.braking, r.objective, round(r.T, 6)) not in seen:
            seen.add((r.braking, r.objective, round(r.T, 6)))
            all_changes.append({"cycle": name, **sc})
    res["smoothing_all"] = all_changes
    res["smoothing_max_abs_true_pct"] = max((abs(q["true_pct"]) for q in all_changes), default=math.nan)
    res["smoothing_max_abs_penalised_pct"] = max((abs(q["penalised_pct"]) for q in all_changes), default=math.nan)
    # the pressure limit: U_ab allowed by the pressure at the start height vs the U_ab bound
    res["U_ab_max_by_pressure_at_H0"] = float(lift.max_bucket_acceleration_for_pressure(p.H_0, p))
    res["U_ab_max_by_pressure_at_HT"] = float(lift.max_bucket_acceleration_for_pressure(p.H_T, p))
    res["U_ab_bound"] = float(p.U_ab_bounds[1])
    res["P_cyl_max_MPa"] = p.P_cyl_max / 1e6
    return res


def _modes_text(m: dict) -> str:
    c = m["counts"]
    parts = [f"{k}: {c[k]}" for k in ("I", "II", "III", "N") if c[k]]
    return ", ".join(parts)


def _sign_note(d: float, key: str, tol: float, opposite: str, why: str) -> str:
    """The note of a statement with a sign: ``opposite`` if d <= 0, "close" within ``tol`` of the paper's
    ``PAPER[key]``, else larger or smaller followed by ``why``."""
    if d <= 0:
        return opposite
    if abs(d - PAPER[key]) < tol:
        return "Same sign and close to the paper."
    return f"Same sign, {'larger' if d > PAPER[key] else 'smaller'}{why}"


def statement_rows(res: dict) -> list[dict[str, Any]]:
    """One row per statement: the paper's claim and number, ours, and a sentence where they differ."""
    S, C = res["summary"]["service"], res["summary"]["tc"]
    cyc = res["cycles"]
    fs, fc = cyc["service/time"]["facts"], cyc["tc/time"]["facts"]
    rows: list[dict[str, Any]] = []

    # 1: cycle time penalty of TC braking, time-optimal
    d = res["dT_time_pct"]
    note = _sign_note(
        d, "dT_time_pct", 0.5, "Opposite sign: TC braking is not slower in our model.",
        f". Our TC optimum starts braking "
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
    note = _sign_note(
        d, "dT_fuel_pct", 0.5, "Opposite sign: the TC fuel-optimal cycle is not longer in our model.",
        f". The fuel minimum is very flat "
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
    note = _sign_note(
        d, "fuel_10s_tc_extra_pct", 1.0, "Opposite sign: TC braking does not cost fuel in our 10 s cycle.",
        f": 10 s is "
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

