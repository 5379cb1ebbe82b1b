"""Closed-loop MPC against the optimal control benchmark, both braking alternatives, in one run.

For each braking alternative:

(a) minimum-time mode: cycle time against the OCP's minimum time (target: within 2 %);
(b) target-time mode at several cycle times: fuel against the Pareto fuel at the cycle time reached
    (target: within 3 %);
(c) model mismatch: the plant's payload +-20 % and rolling resistance +-30 % while the MPC keeps the
    nominal model (minimum-time mode): does the cycle complete within the constraints?
(d) per-step solve time (median, p95, max; the first step, which plans the cycle, separately) against
    the 0.1 s control interval (target: median below it; aim 20 ms).

The violation column is the environment's own: since WheelLoader-v1 it checks the driver's limits at every
RK4 stage and step end, so an excess within the steps is in it.

Usage::

    python scripts/bench_mpc.py [--json PATH] [--targets 9 10 11 13 16] [--quick]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mpc.benchmark.ocp import write_json_atomic  # noqa: E402
from mpc.benchmark.pareto import pareto_fronts  # noqa: E402
from mpc.benchmark.scoring import score_run  # noqa: E402
from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop  # noqa: E402
from wl_env.params import DEFAULT_PARAMS  # noqa: E402

MISMATCH = ((0.8, 0.7), (0.8, 1.3), (1.2, 0.7), (1.2, 1.3))  # (payload scale, rolling-resistance scale)


def closed_loop(braking: str, config: MPCConfig, front: Any, plant: Any = None) -> dict[str, Any]:
    ctrl = MPCController(braking, config=config)
    t0 = time.perf_counter()
    r = run_closed_loop(braking, config, plant_params=plant, score=False, controller=ctrl)
    wall = time.perf_counter() - t0
    ep = r.episode
    row = {"braking": braking, "mode": config.mode, "target_time": config.target_time,
           **ep.to_dict(trajectory=False), "solve_time": r.solve_time, "solve_times_s": r.solve_times_s, "wall_s": wall,
           "steps_with_schedule_move": sum(1 for n in ctrl.step_solves[1:] if n > 1), "fallbacks": ctrl.fallbacks}
    if ep.completed and plant is None:  # the gaps every controller gets (mpc.benchmark.scoring)
        s = score_run(ep.T, ep.fuel_g, braking, front=front)
        row.update(time_gap=s.time_gap, fuel_gap=s.fuel_gap, fuel_opt_g=s.fuel_opt_g)
    return row


def pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:+.2f} %"


def p95(values: list[float]) -> float:
    return sorted(values)[int(0.95 * (len(values) - 1))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers")
    ap.add_argument("--targets", type=float, nargs="+", default=[9.0, 10.0, 11.0, 13.0, 16.0],
                    help="cycle times (s) of the target-time runs")
    ap.add_argument("--quick", action="store_true", help="one target time, no mismatch runs")
    args = ap.parse_args()
    targets = args.targets[:1] if args.quick else args.targets
    fronts = pareto_fronts(progress=True)
    rows: list[dict[str, Any]] = []
    for b in ("service", "tc"):
        print(f"[{b}] minimum time", file=sys.stderr, flush=True)
        rows.append(closed_loop(b, MPCConfig(mode="time"), fronts[b]))
        for T in targets:
            print(f"[{b}] target time {T:g} s", file=sys.stderr, flush=True)
            rows.append(closed_loop(b, MPCConfig(mode="target_time", target_time=T), fronts[b]))
        for payload, rolling in ([] if args.quick else MISMATCH):
            print(f"[{b}] mismatch: payload x{payload}, rolling x{rolling}", file=sys.stderr, flush=True)
            plant = DEFAULT_PARAMS.variant(payload_scale=payload, rolling_scale=rolling)
            row = closed_loop(b, MPCConfig(mode="time"), fronts[b], plant)
            row.update(payload_scale=payload, rolling_scale=rolling)
            rows.append(row)

    print("\n| braking | mode | T (s) | fuel (g) | OCP reference | time gap | fuel gap | success | max violation "
          "| solve median / p95 / max (ms) | steps with a move | planning (s) |")
    print("|---|---|---:|---:|---|---:|---:|---|---:|---|---:|---:|")
    for r in rows:
        if "payload_scale" in r:
            mode = f"min time, plant payload x{r['payload_scale']}, rolling x{r['rolling_scale']}"
            ref = "-"
        elif r["mode"] == "time":
            mode, ref = "min time", f"T_min {fronts[r['braking']].T_min:.3f} s"
        else:
            mode = f"target {r['target_time']:g} s"
            ref = f"{r['fuel_opt_g']:.2f} g at {r['T']:.2f} s" if "fuel_opt_g" in r else "-"
        later = r["solve_times_s"][1:] or r["solve_times_s"]
        print(f"| {r['braking']} | {mode} | {r['T']:.2f} | {r['fuel_g']:.2f} | {ref} | {pct(r.get('time_gap'))} | "
              f"{pct(r.get('fuel_gap'))} | {'yes' if r['success'] else 'no'} | {100 * r['max_violation']:.2f} % | "
              f"{1e3 * statistics.median(later):.1f} / {1e3 * p95(later):.1f} / "
              f"{1e3 * max(later):.0f} | {r['steps_with_schedule_move']} | {r['solve_time']['planning_s']:.1f} |")
    every = [s for r in rows for s in r["solve_times_s"][1:]]
    print(f"\nall runs, steps after the first: median {1e3 * statistics.median(every):.1f} ms, "
          f"p95 {1e3 * p95(every):.1f} ms, max {1e3 * max(every):.0f} ms ({len(every)} steps); control interval 100 ms")
    if args.json:
        write_json_atomic(args.json, {"rows": rows, "cpu_count": os.cpu_count(), "python": platform.python_version()})


if __name__ == "__main__":
    from wl_env.logs import cli_logging

    with cli_logging():  # the Pareto sweep's progress, as `wl` shows it
        main()
