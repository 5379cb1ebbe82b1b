"""Closed-loop MPC against the optimum of each cycle, and its solver candidates side by side, in one run.

Per braking alternative (and per solver candidate, ``--solvers``):

(a) minimum-time mode: cycle time against the cycle's minimum time;
(b) target-time mode at several cycle times: fuel against the minimum fuel at the cycle time reached;
(c) model mismatch: the plant's payload +-20 % and rolling resistance +-30 % while the MPC keeps the
    nominal model (minimum-time mode): does the cycle complete within the limits?
(d) a sample of the ``test`` suite (``--suite-sample``), each scenario's own model and optimum, minimum
    time and a target of 1.15 T_min; with ``--corners`` also the ``corners`` suite in mismatch mode;
(e) per-step solve time (median, p99, max; the first step, which plans the cycle, apart) against the
    0.1 s control interval, and the controls' total variation against the optimum's at the same cycle
    time (:func:`mpc.benchmark.scoring.smoothness`).

``--horizons 10 20`` runs each synchronous candidate also with a short receding horizon of that many steps
(``MPCConfig.horizon_steps``: the rest of the cycle priced by the last full plan's value), as ``ipopt h10``;
``ipopt+sqp-rti`` solves those horizons by one real-time SQP iteration (IPOPT for the full plans and as the
fallback) and runs only with ``--horizons``. ``--replan-lag 10`` runs each short horizon also with its re-plans on
a worker thread (``MPCConfig.replan_lag_steps``), as ``ipopt h10 lag10``.

``--realtime both`` runs each candidate also as the real-time controller (``MPCConfig.realtime``): its
per-step time is then the time to the control, and the worker's solves (plan and schedule move, one
interval ahead) and the oldest plan a step applied are reported beside it.

``--safety-filter both`` runs each also without the one-step safety filter on the applied controls
(``MPCConfig.safety_filter``, :mod:`mpc.controller.safety`), as ``... no filter``.

``--codegen both`` runs each with the NLP's functions compiled (:mod:`mpc.controller.codegen`, the default
where a C compiler is found) and interpreted by CasADi, as ``... interpreted``.

The violation column is the environment's own (the driver's limits at every RK4 stage and step end).

Usage::

    python scripts/bench_mpc.py [--json PATH] [--targets 9 10 11 13 16] [--quick] [--no-mismatch]
        [--solvers ipopt fatrop] [--suite-sample 3] [--corners | --min-time-only] [--deadline-ms 100] [--realtime both]
        [--horizons 10 20] [--horizons-only] [--replan-lag 10] [--terminal-weight 1000] [--safety-filter both]
        [--codegen both]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from agents.train_cli import refuse_repeated_values  # noqa: E402
from mpc.benchmark.ocp import OCPError, write_json_atomic  # noqa: E402
from mpc.benchmark.reference import reference_at  # noqa: E402
from mpc.benchmark.scoring import smoothness  # noqa: E402
from mpc.controller import codegen  # noqa: E402
from mpc.controller.mpc import AUTO, MAX_WEIGHT, MIN_DEADLINE_MS, MPCConfig, forget_plans, run_closed_loop  # noqa: E402
from mpc.controller.solver import SOLVERS, release_solvers  # noqa: E402
from wl_env.params import DEFAULT_PARAMS  # noqa: E402
from wl_env.suites import load_suite  # noqa: E402

log = logging.getLogger("bench_mpc")
MISMATCH = ((0.8, 0.7), (0.8, 1.3), (1.2, 0.7), (1.2, 1.3))  # (payload scale, rolling-resistance scale)
# MPCConfig.horizon_solver per candidate on the short horizons ("ipopt" for the others: their own on the full)
HORIZON_SOLVER_OF = {"default": AUTO, "ipopt+sqp-rti": "sqp-rti"}


def closed_loop(braking: str, config: MPCConfig, solver: str, label: str, plant: Any = None, scenario: Any = None,
                mismatch: bool = False, target_ratio: float | None = None) -> dict[str, Any]:
    """One cycle under the MPC with one solver candidate, and what the table reports of it."""
    if target_ratio is not None:  # a target relative to the scenario's own minimum time
        T_min = reference_at(10.0, braking, scenario.params())["T_min"]
        config = dataclasses.replace(config, mode="target_time", target_time=target_ratio * T_min)
    t0 = time.perf_counter()
    candidate = None if solver in ("default", "ipopt") else SOLVERS[solver]()
    r = run_closed_loop(braking, config, plant_params=plant, score=plant is None and not mismatch, scenario=scenario,
                        mismatch=mismatch, solver=candidate)
    # (ipopt: the controller's own, with its wall-time limit at the deadline)
    ep = r.episode
    row = {"braking": braking, "solver": solver, "run": label, "mode": config.mode, "target_time": config.target_time,
           **ep.to_dict(trajectory=False), "solve_time": r.solve_time, "solve_times_s": r.solve_times_s,
           "worker_solve_times_s": r.worker_solve_times_s,
           "wall_s": time.perf_counter() - t0, "fallbacks": r.solve_time["fallbacks"], "first_plan_from": r.first_plan_from,
           "handed_over": r.solve_time["handed_over"]}  # (solves the candidate, or the default's RTI, left to IPOPT)
    if r.score is not None:
        row.update(time_gap=r.score.time_gap, fuel_gap=r.score.fuel_gap, T_min=r.score.T_min, fuel_opt_g=r.score.fuel_opt_g)
        plant_params = scenario.params() if scenario is not None else None
        try:
            row["smoothness"] = smoothness(ep.trajectory.controls, ep.T, braking, plant_params).to_dict()
        except OCPError as exc:  # (no verified optimum at T to compare with: the run's other figures stand)
            log.warning("%s %s: no total variation: %s", braking, label, exc)
            row["smoothness_error"] = str(exc)
    return row


def runs(braking: str, targets: list[float], mismatch: bool, suite_sample: int, corners: bool, deadline_ms: float | None,
         min_time_only: bool = False):
    """(label, config, keyword arguments of closed_loop) of every run of one braking alternative (``min_time_only``:
    the nominal cycle's and the suite sample's minimum-time runs alone)."""
    base = {"deadline_ms": deadline_ms}
    yield "min time", MPCConfig(mode="time", **base), {}
    for T in [] if min_time_only else targets:
        yield f"target {T:g} s", MPCConfig(mode="target_time", target_time=T, **base), {}
    for payload, rolling in (MISMATCH if mismatch and not min_time_only else []):
        plant = DEFAULT_PARAMS.variant(payload_scale=payload, rolling_scale=rolling)
        yield f"mismatch: payload x{payload}, rolling x{rolling}", MPCConfig(mode="time", **base), {"plant": plant}
    for i, sc in enumerate(load_suite("test").spread(braking, suite_sample) if suite_sample else ()):
        yield f"test[{i}] min time", MPCConfig(mode="time", **base), {"scenario": sc}
        if not min_time_only:
            yield f"test[{i}] 1.15 T_min", MPCConfig(mode="time", **base), {"scenario": sc, "target_ratio": 1.15}
    for i, sc in enumerate(load_suite("corners").of(braking) if corners else ()):
        yield f"corners[{i}] mismatch", MPCConfig(mode="time", **base), {"scenario": sc, "mismatch": True}


def rate_sweep(weights: list[float]) -> list[dict[str, Any]]:
    """The control-rate penalty's trade: total variation against fuel, one cycle per weight; the rows."""
    print("| rate weight | T (s) | fuel (g) | fuel gap | TV U_mf vs optimum | TV U_ab vs optimum | max violation |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for w in weights:
        r = closed_loop("tc", MPCConfig(mode="target_time", target_time=11.0, rate_weight=(w, w)), "default", f"w {w:g}")
        rows.append({**r, "rate_weight": w})
        # (a cycle not completed has no score, one without a verified optimum at its T no smoothness: a KeyError's
        # traceback after the sweep's cycles)
        s = r.get("smoothness")
        tv = (f"{s['ratio_fuel_injection']:.2f}x | {s['ratio_bucket_acceleration']:.2f}x" if s
              else "n/a | n/a")
        print(f"| {w:g} | {r['T']:.2f} | {r['fuel_g']:.3f} | {pct(r.get('fuel_gap'))} | {tv} "
              f"| {100 * r['max_violation']:.2f} % |")
    return rows


def worker(row: dict[str, Any]) -> str:
    st = row["solve_time"]
    if not row["realtime"]:
        return "-"
    return (f"{1e3 * st['background_median_s']:.1f} / {1e3 * st['background_p99_s']:.1f} / "
            f"{1e3 * st['background_max_s']:.0f}, {st['plan_age_max']}")


def pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:+.2f} %"


def ms(values: list[float], q: float | None = None) -> float:
    return 1e3 * (float(np.max(values)) if q is None else float(np.percentile(values, q)))


def check_options(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The numbers' ranges, as ``ap.error`` naming the option, before any run (a bad --targets failed with a traceback
    after the minimum-time runs)."""
    from wl_env.env import check_target_time
    from wl_env.suites import MAX_SAMPLE

    try:
        for t in args.targets:
            check_target_time(t, "--targets")
    except ValueError as exc:
        ap.error(str(exc))
    if not (args.min_time_only or args.rate_sweep):
        # (a target under the nominal cycle's minimum time failed after the minimum-time runs, naming
        # MPCConfig.target_time: checked against its estimate, 2 % allowed, as `wl mpc --target-time` is)
        from wl_env.scenario import Scenario
        from wl_env.suites.min_time import estimate_min_time

        for b in args.braking:
            t_min = estimate_min_time(Scenario.nominal(b))
            short = [t for t in (args.targets[:1] if args.quick else args.targets) if t < 0.98 * t_min]
            if short:
                ap.error(f"--targets {' '.join(f'{t:g}' for t in short)} s lie below the nominal cycle's minimum cycle "
                         f"time with {b} braking (about {t_min:.2f} s)")
    # (a value given twice ran its cycles twice, each row counted twice in the candidates' summaries)
    try:
        for option, values in (("--targets", args.targets), ("--braking", args.braking), ("--solvers", args.solvers),
                               ("--horizons", args.horizons), ("--rate-sweep", args.rate_sweep)):
            refuse_repeated_values(option, values)
    except ValueError as exc:
        ap.error(str(exc))
    if not 0 <= args.suite_sample <= MAX_SAMPLE:
        ap.error(f"--suite-sample must be an integer in [0, {MAX_SAMPLE}], got {args.suite_sample}")
    # (MPCConfig's and the controller's range: 500 or 1e-9 failed as deadline_ms, naming no option)
    if args.deadline_ms is not None and not (math.isfinite(args.deadline_ms) and MIN_DEADLINE_MS <= args.deadline_ms <= 100):
        ap.error(f"--deadline-ms must be a number > 0, in [{MIN_DEADLINE_MS:g}, 100] ms (at most the control interval), "
                 f"got {args.deadline_ms:g}")
    if not (math.isfinite(args.terminal_weight) and 0 <= args.terminal_weight <= MAX_WEIGHT):
        ap.error(f"--terminal-weight must be a number in [0, {MAX_WEIGHT:g}], got {args.terminal_weight:g}")
    # (MPCConfig.rate_weight's range: a weight over 1e6 failed after the sweep's cycles before it, naming rate_weight)
    if args.rate_sweep and not all(math.isfinite(w) and 0 <= w <= MAX_WEIGHT for w in args.rate_sweep):
        ap.error(f"--rate-sweep weights must each be a number >= 0, at most {MAX_WEIGHT:g}, got "
                 f"{' '.join(f'{w:g}' for w in args.rate_sweep)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers")
    ap.add_argument("--targets", type=float, nargs="+", default=[9.0, 10.0, 11.0, 13.0, 16.0],
                    help="cycle times (s) of the target-time runs")
    ap.add_argument("--quick", action="store_true", help="one target time, no mismatch runs")
    ap.add_argument("--no-mismatch", action="store_true", help="no mismatch runs")
    ap.add_argument("--solvers", nargs="+", default=["default"], choices=["default", *sorted(SOLVERS)],
                    help="the candidates to compare (default: MPCConfig's own, the 10-step RTI; ipopt: the full horizon)")
    ap.add_argument("--suite-sample", type=int, default=0, metavar="N", help="test-suite scenarios per braking")
    ap.add_argument("--corners", action="store_true", help="the corners suite in mismatch mode")
    ap.add_argument("--min-time-only", action="store_true",
                    help="only the minimum-time runs: the nominal cycle and the --suite-sample scenarios")
    ap.add_argument("--deadline-ms", type=float, default=None, help="MPCConfig.deadline_ms of every run")
    ap.add_argument("--realtime", choices=["off", "on", "both"], default="off",
                    help="MPCConfig.realtime: the synchronous controller (off), the real-time one (on), or both side by side")
    ap.add_argument("--horizons", type=int, nargs="+", default=[], metavar="N",
                    help="also run each synchronous candidate with a short horizon of N steps (MPCConfig.horizon_steps)")
    ap.add_argument("--horizons-only", action="store_true", help="only the short-horizon runs (--horizons)")
    ap.add_argument("--replan-lag", type=int, metavar="N", help="also run each short horizon with its re-plans on the "
                    "worker, due N steps later (MPCConfig.replan_lag_steps), as '... h10 lag10'")
    ap.add_argument("--terminal-weight", type=float, default=MPCConfig.terminal_weight,
                    help="MPCConfig.terminal_weight of the short-horizon runs")
    ap.add_argument("--safety-filter", choices=["on", "off", "both"], default="on",
                    help="MPCConfig.safety_filter (the one-step filter on the applied controls): on, off, or both side by side")
    ap.add_argument("--codegen", choices=["auto", "on", "off", "both"], default="auto",
                    help="the NLP's functions (mpc.controller.codegen, $WL_CODEGEN): compiled where a C compiler is "
                    "found (auto), compiled (on), interpreted (off, as '... interpreted'), or both side by side")
    ap.add_argument("--braking", nargs="+", default=["service", "tc"], choices=["service", "tc"])
    ap.add_argument("--rate-sweep", type=float, nargs="+", metavar="W",
                    help="instead: the TC cycle at 11 s with each control-rate weight W (on U_mf and U_ab)")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    check_options(ap, args)
    if args.rate_sweep:  # (its --json was checked, then never written: exit 0, no file)
        rows = rate_sweep(args.rate_sweep)
        if args.json:
            write_json_atomic(args.json, {"rate_sweep": rows, "cpu_count": os.cpu_count(),
                                          "python": platform.python_version()})
        return None
    targets = args.targets[:1] if args.quick else args.targets
    rows: list[dict[str, Any]] = []
    realtime = {"off": [False], "on": [True], "both": [False, True]}[args.realtime]
    if args.deadline_ms is not None and True in realtime:
        ap.error("--deadline-ms applies to the synchronous controller (a real-time step's deadline is its interval)")
    if args.replan_lag is not None and not (args.horizons and 1 <= args.replan_lag <= 100):
        ap.error("--replan-lag N needs --horizons and N in [1, 100]")
    if args.min_time_only and args.corners:
        ap.error("--min-time-only runs no corner (they are mismatch runs): drop one of them")
    if args.horizons_only and not args.horizons:
        ap.error("--horizons-only needs --horizons")
    if not all(2 <= h <= 1000 for h in args.horizons):  # (0 failed after the full-horizon runs, a traceback)
        ap.error(f"--horizons must be integers in [2, 1000] (MPCConfig.horizon_steps), got {args.horizons}")
    if args.horizons and args.deadline_ms is not None:
        ap.error("--horizons runs the synchronous controller without a deadline (MPCConfig.horizon_steps)")
    # (a candidate that takes only the short horizons' NLPs is IPOPT on the full horizon: not run there)
    filters = {"on": [True], "off": [False], "both": [True, False]}[args.safety_filter]
    codegens = ["on", "off"] if args.codegen == "both" else [args.codegen]
    # ("default" keeps MPCConfig's horizon and re-plan lag, AUTO: the 10-step RTI, its re-plans on the worker 5 steps
    # ahead; the full horizon in real time or with a deadline; an explicit horizon re-plans in the step, or --replan-lag)
    variants = [(solver, rt, auto, auto, f, cg) for solver in args.solvers for auto in [AUTO if solver == "default" else None]
                for rt in realtime for f in filters for cg in codegens
                if not (args.horizons_only or solver != "default" and getattr(SOLVERS[solver](), "short_only", False))]
    variants += [(solver, False, h, lag, f, cg) for solver in args.solvers if solver != "default" for h in args.horizons
                 for lag in [None] + ([args.replan_lag] if args.replan_lag else []) for f in filters for cg in codegens]
    if not variants:
        ap.error("no run: a short-horizon candidate (ipopt+sqp-rti) runs only with --horizons")
    for solver, rt, horizon, lag, safety, cg in variants:
        if cg != codegen.mode():  # (solvers built on the other build released, its plans forgotten: a fresh start)
            release_solvers()
            forget_plans()
            codegen.set_mode(cg)
        name = ((f"{solver} realtime" if rt else solver if horizon in (None, AUTO) else f"{solver} h{horizon}")
                + (f" lag{lag}" if lag not in (None, AUTO) else "") + ("" if safety else " no filter") + (" interpreted" if cg == "off" else ""))
        for b in args.braking:
            for label, config, kw in runs(b, targets, not (args.quick or args.no_mismatch), args.suite_sample, args.corners, args.deadline_ms,
                                          args.min_time_only):
                print(f"[{name}] [{b}] {label}", file=sys.stderr, flush=True)
                config = dataclasses.replace(config, realtime=rt, horizon_steps=horizon, terminal_weight=args.terminal_weight,
                                             horizon_solver=HORIZON_SOLVER_OF.get(solver, "ipopt"), replan_lag_steps=lag,
                                             safety_filter=safety)
                row = closed_loop(b, config, solver, label, **kw)
                rows.append({**row, "solver": name, "realtime": rt, "horizon_steps": config.horizon, "replan_lag_steps": config.replan_lag,
                             "codegen": cg})

    print("\n| solver | braking | run | T (s) | fuel (g) | time gap | fuel gap | success | max violation "
          "| TV U_mf / U_ab vs optimum | solve median / p99 / max (ms) | fallbacks | planning (s) "
          "| realtime: worker median / p99 / max (ms), oldest plan (steps) |")
    print("|---|---|---|---:|---:|---:|---:|---|---:|---|---|---:|---:|---|")
    for r in rows:
        later = r["solve_times_s"][1:] or r["solve_times_s"]
        sm = r.get("smoothness")
        tv = f"{sm['ratio_fuel_injection']:.2f}x / {sm['ratio_bucket_acceleration']:.2f}x" if sm else "-"
        print(f"| {r['solver']} | {r['braking']} | {r['run']} | {r['T']:.2f} | {r['fuel_g']:.2f} | {pct(r.get('time_gap'))} "
              f"| {pct(r.get('fuel_gap'))} | {'yes' if r['success'] else 'no'} | {100 * r['max_violation']:.2f} % | {tv} "
              f"| {ms(later, 50):.1f} / {ms(later, 99):.1f} / {ms(later):.0f} | {r['fallbacks']} "
              f"| {r['solve_time']['planning_s']:.2f} ({r['first_plan_from']}) | {worker(r)} |")
    for solver in dict.fromkeys(r["solver"] for r in rows):
        every = [s for r in rows if r["solver"] == solver for s in r["solve_times_s"][1:]]
        plans = [r["solve_time"]["planning_s"] for r in rows if r["solver"] == solver]
        print(f"\n[{solver}] all runs, steps after the first: median {ms(every, 50):.1f} ms, p99 {ms(every, 99):.1f} ms, "
              f"max {ms(every):.0f} ms ({len(every)} steps); first-step planning median {np.median(plans):.1f} s, "
              f"max {max(plans):.1f} s; success {sum(r['success'] for r in rows if r['solver'] == solver)}"
              f"/{sum(1 for r in rows if r['solver'] == solver)}; control interval 100 ms")
        warm = [r["solve_time"]["planning_s"] for r in rows if r["solver"] == solver and r["first_plan_from"] != "reference"]
        if warm:  # (a real-time controller's plans from a stored or neighbouring plan: NLPs and solvers built)
            print(f"[{solver}] first-step planning from a stored or neighbouring plan ({len(warm)} of {len(plans)} runs): "
                  f"median {np.median(warm):.2f} s, max {max(warm):.2f} s")
        if any(r.get("horizon_steps") for r in rows if r["solver"] == solver):
            print(f"[{solver}] steps that planned the whole cycle again (the plant estimate moved, or the horizon "
                  f"missed a target): {sum(r['solve_time']['replans'] for r in rows if r['solver'] == solver)}")
        eased = [r["solve_time"]["safety_eased"] for r in rows if r["solver"] == solver]
        print(f"[{solver}] controls the safety filter eased: {sum(eased)} (in {sum(e > 0 for e in eased)} runs)")
        handed = sum(r["handed_over"] for r in rows if r["solver"] == solver)
        if handed:
            print(f"[{solver}] solves the candidate failed and IPOPT took: {handed}")
        jobs = [s for r in rows if r["solver"] == solver for s in r["worker_solve_times_s"]]
        if jobs:
            print(f"[{solver}] the worker's solves (one interval ahead): median {ms(jobs, 50):.1f} ms, p99 "
                  f"{ms(jobs, 99):.1f} ms, max {ms(jobs):.0f} ms ({len(jobs)} jobs); steps applying an overdue plan "
                  f"(older than the solves take): {sum(r['solve_time']['fallbacks'] for r in rows if r['solver'] == solver)}")
    loop_s = python_loop_seconds()
    print(f"\nthe machine's speed in this run: a 10^7-addition Python loop took {loop_s:.2f} s (median of 3; a quiet day "
          f"here 0.65 s, a loaded one 1.2-1.4 s): read the step times against it")
    if args.json:
        write_json_atomic(args.json, {"rows": rows, "cpu_count": os.cpu_count(), "python": platform.python_version(),
                                      "python_loop_s": loop_s, "compiler": codegen.compiler()})


def python_loop_seconds() -> float:
    """Seconds a 10^7-addition Python loop takes (median of 3): the machine's speed and load in this run, the
    reference the step times are read against."""
    times = []
    for _ in range(3):
        t, total = time.perf_counter(), 0
        for i in range(10**7):
            total += i
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def summary_line(summary: dict[str, Any], digits: int = 3) -> str:
    """A bench summary's figures on one line: ``name value, ...``, floats to ``digits`` significant digits."""
    return ", ".join(f"{k} {v:.{digits}g}" if isinstance(v, float) else f"{k} {v}" for k, v in summary.items())


def write_with_speed(out: str | None, options: Any, summary: dict[str, Any], records: list[dict[str, Any]]) -> None:
    """A one-process A/B bench's end: the machine's speed in this run printed and, with ``out``, the JSON of its
    ``options`` (a dataclass), the speed, ``summary`` and ``records``, written atomically."""
    loop_s = python_loop_seconds()
    print(f"the machine's speed: a 10^7-addition Python loop took {loop_s:.2f} s")
    if out:
        write_json_atomic(out, {"options": dataclasses.asdict(options), "python_loop_s": loop_s, "summary": summary,
                                "records": records})


if __name__ == "__main__":
    from wl_env.logs import PACKAGES, run_script

    # the optima's progress, as `wl` shows it; Ctrl-C or SIGTERM (also what CasADi made of it) exit 130 / 143
    run_script("bench_mpc", main, PACKAGES)
