"""Peak memory and planning time of one MPC cycle per fresh process: the full horizon against a short one.

Each run is a process of its own (its peak resident set is then the cycle's alone): the controller is
built, drives one cycle of ``WheelLoader-v2``, and reports its first step's planning, its per-step solve
times and the process's peak resident set (``ru_maxrss``).

Usage::

    python scripts/bench_mpc_memory.py [--braking service tc] [--target-time 11] [--horizon-steps 10]
        [--horizon-solver sqp-rti] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from agents.train_cli import refuse_repeated_values  # noqa: E402
from wl_env.atomic_io import write_json_atomic  # noqa: E402


def one_cycle(braking: str, target_time: float | None, horizon_steps: int | None, horizon_solver: str) -> dict:
    """One cycle in this process: planning (s), solve times per step after the first (ms), peak RSS (MB)."""
    import numpy as np

    from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop

    mode = {"mode": "target_time", "target_time": target_time} if target_time else {"mode": "time"}
    horizon = {"horizon_steps": horizon_steps or None, "horizon_solver": horizon_solver if horizon_steps else "ipopt"}
    config = MPCConfig(**mode, **horizon)
    ctrl = MPCController(braking, config=config)
    t0 = time.perf_counter()
    r = run_closed_loop(braking, config, score=False, controller=ctrl)
    steps = 1e3 * np.asarray(r.solve_times_s[1:])
    return {"braking": braking, "target_time": target_time, "horizon_steps": horizon_steps,
            "horizon_solver": horizon_solver if horizon_steps else "ipopt", "T": r.episode.T,
            "fuel_g": r.episode.fuel_g, "success": r.episode.success, "max_violation": r.episode.max_violation,
            "planning_s": ctrl.planning_time, "cycle_wall_s": time.perf_counter() - t0,
            "step_median_ms": float(np.median(steps)), "step_p99_ms": float(np.percentile(steps, 99)),
            "step_max_ms": float(steps.max()),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}  # (Linux: kB)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--braking", nargs="+", choices=("service", "tc"), default=["service", "tc"])
    ap.add_argument("--target-time", type=float, default=None, help="s; default: minimum-time mode")
    ap.add_argument("--horizon-steps", type=int, default=10, help="the short horizon compared with the full one")
    ap.add_argument("--horizon-solver", choices=("ipopt", "sqp-rti"), default="sqp-rti")
    ap.add_argument("--json", metavar="PATH", help="also write the rows")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # (a child: one cycle, JSON on stdout)
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    from wl_env.env import check_target_time

    try:  # (checked here, not in the child processes: a NaN was their CalledProcessError, a traceback)
        if args.target_time is not None:
            check_target_time(args.target_time, "--target-time")
            # (a target under a cycle's minimum time failed in that cycle's process after the ones before it, naming
            # MPCConfig.target_time: checked against the estimate, 2 % allowed, as `wl mpc --target-time` is)
            from wl_env.scenario import Scenario
            from wl_env.suites.min_time import estimate_min_time

            for braking in args.braking:
                t_min = estimate_min_time(Scenario.nominal(braking))
                if args.target_time < 0.98 * t_min:
                    raise ValueError(f"--target-time {args.target_time:g} s lies below the nominal cycle's minimum "
                                     f"cycle time with {braking} braking (about {t_min:.2f} s)")
        if not 2 <= args.horizon_steps <= 1000 and not (args.one and args.horizon_steps == 0):
            raise ValueError(f"--horizon-steps must be an integer in [2, 1000], got {args.horizon_steps}")
        refuse_repeated_values("--braking", args.braking, "a braking alternative")  # (each cycle's process run twice)
    except ValueError as exc:
        ap.error(str(exc))
    if args.one:
        h = args.horizon_steps or None
        print(json.dumps(one_cycle(args.braking[0], args.target_time, h, args.horizon_solver)))
        return
    rows = []
    for braking in args.braking:
        for h in (0, args.horizon_steps):
            cmd = [sys.executable, os.path.abspath(__file__), "--one", "--braking", braking, "--horizon-steps", str(h),
                   "--horizon-solver", args.horizon_solver]
            if args.target_time:
                cmd += ["--target-time", str(args.target_time)]
            done = subprocess.run(cmd, capture_output=True, text=True)
            name = "full horizon" if not h else f"h{h} {args.horizon_solver}"
            try:
                if done.returncode:  # (was a CalledProcessError's traceback, the child's own error unsaid)
                    said = [line for line in done.stderr.splitlines() if line.strip()]
                    raise ValueError(f"exit {done.returncode}: {' '.join(said[-1].split())[:300] if said else 'no message'}")
                row = json.loads(done.stdout.strip().splitlines()[-1])
            except (ValueError, IndexError) as exc:  # (its exit, or no JSON row: a JSONDecodeError, an IndexError)
                raise ValueError(f"the {braking} cycle's process ({name}) failed (nothing written): "
                                 f"{' '.join(str(exc).split())[:400]}") from None
            rows.append(row)
            print(f"{braking} {name}: T {row['T']:.1f} s, fuel {row['fuel_g']:.2f} g, planning {row['planning_s']:.1f} s, "
                  f"step median / p99 / max {row['step_median_ms']:.1f} / {row['step_p99_ms']:.0f} / "
                  f"{row['step_max_ms']:.0f} ms, peak RSS {row['peak_rss_mb']:.0f} MB", flush=True)
    if args.json:
        write_json_atomic(Path(args.json), {"rows": rows})


if __name__ == "__main__":
    from wl_env.logs import run_script

    run_script("bench_mpc_memory", main)  # (Ctrl-C: exit 130, no traceback; a ValueError: one line, exit 2)
