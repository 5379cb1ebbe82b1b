"""Benchmark of the optimal control benchmark: NLP build, single solves, full solves, Pareto sweep.

Medians over repeats (the machine is noisy). Single solves (one template start, the smoothing homotopy
k = 1e-4 -> 0, default mesh) compare, in the same run, IPOPT with MUMPS and its exact Hessian (the
default) against two alternatives: IPOPT with SPRAL as linear solver, and IPOPT with a limited-memory
(L-BFGS) Hessian. Full solves are the user-facing ``solve_ocp`` (multi-start, homotopy, re-simulation,
mesh refinement). The Pareto sweep (8 points per alternative) is timed for both braking alternatives in
parallel processes (``pareto_fronts``, as ``wl pareto`` and ``wl run`` run it) and one after the other,
each from an empty cache and with no NLP built beforehand in the process. Usage::

    python scripts/bench_ocp.py [--repeats 5] [--pareto-repeats 3] [--json PATH] [--skip-pareto | --pareto-only]
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mpc.benchmark import ocp as ocp_module  # noqa: E402
from mpc.benchmark.ocp import CycleOCP, OCPError, OCPSettings, solve_ocp, template_guess, write_json_atomic  # noqa: E402
from mpc.benchmark.pareto import pareto_front, pareto_fronts  # noqa: E402

BRAKINGS = ("service", "tc")
SOLVERS = {"ipopt/mumps (default)": OCPSettings(), "ipopt/spral": OCPSettings(linear_solver="spral"),
           "ipopt/mumps/L-BFGS": OCPSettings(hessian="limited-memory")}


def timed(fn: Any) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def single_solves(repeats: int) -> list[dict[str, Any]]:
    rows = []
    for name, settings in SOLVERS.items():
        for braking in BRAKINGS:
            build, ocp = timed(functools.partial(CycleOCP, braking, settings=settings))
            z0 = ocp.guess_from_trajectory(**template_guess(ocp.params, 5.0, 0.7))
            for objective in ("time", "fuel"):
                times, iters, value, status = [], [], None, ""
                for _ in range(repeats):
                    try:
                        dt, (z, info) = timed(functools.partial(ocp.solve, z0, objective))
                    except OCPError as exc:
                        status = str(exc).rsplit("status ", 1)[-1]
                        break
                    fuel, T = ocp.objective_parts(z)
                    times.append(dt)
                    iters.append(info["iterations"])
                    value, status = (T if objective == "time" else fuel), info["status"]
                rows.append({"solver": name, "braking": braking, "objective": objective, "build_s": build,
                             "solve_median_s": statistics.median(times) if times else None,
                             "solve_max_s": max(times) if times else None,
                             "iterations": statistics.median(iters) if iters else None, "value": value,
                             "status": status})
                print(rows[-1], file=sys.stderr, flush=True)
    return rows


def full_solves(repeats: int) -> list[dict[str, Any]]:
    rows = []
    for braking in BRAKINGS:
        for objective in ("time", "fuel"):
            walls = []
            for _ in range(repeats):
                ocp_module.release_nlps()  # each repeat builds its NLPs, as a fresh process does
                dt, r = timed(functools.partial(solve_ocp, braking, objective))
                walls.append(dt)
            rows.append({"braking": braking, "objective": objective, "wall_median_s": statistics.median(walls),
                         "T": r.T, "fuel_g": r.fuel_g, "mesh": r.mesh, "starts": len(r.starts),
                         "verified": r.verification["passed"]})
            print(rows[-1], file=sys.stderr, flush=True)
    return rows


def pareto_sweeps(repeats: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    rows, fronts = [], {}
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as cache:
            dt, fronts = timed(functools.partial(pareto_fronts, cache=cache))
        rows.append({"mode": "parallel", "wall_s": dt, **{f"{b}_s": f.wall_time for b, f in fronts.items()}})
        print(rows[-1], file=sys.stderr, flush=True)
        ocp_module.release_nlps()
        with tempfile.TemporaryDirectory() as cache:
            walls = {b: timed(functools.partial(pareto_front, b, cache=cache))[0] for b in BRAKINGS}
        rows.append({"mode": "sequential", "wall_s": sum(walls.values()), **{f"{b}_s": w for b, w in walls.items()}})
        print(rows[-1], file=sys.stderr, flush=True)
    points = {b: {"T": f.T, "fuel_g": f.fuel_g, "verified": [p["verified"] for p in f.points]} for b, f in fronts.items()}
    return rows, points


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timings of each single and full solve")
    ap.add_argument("--pareto-repeats", type=int, default=3, help="timings of each Pareto sweep mode")
    ap.add_argument("--json", metavar="PATH", help="also write the raw numbers")
    which = ap.add_mutually_exclusive_group()  # (both: nothing timed, exit 0, an empty --json written)
    which.add_argument("--skip-pareto", action="store_true")
    which.add_argument("--pareto-only", action="store_true", help="time the Pareto sweeps only")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    for name in ("repeats", "pareto_repeats"):  # (0 timed nothing and still ran the full solves for minutes)
        if not 1 <= getattr(args, name) <= 1000:
            ap.error(f"--{name.replace('_', '-')} must be an integer in [1, 1000], got {getattr(args, name)}")
    single = [] if args.pareto_only else single_solves(args.repeats)
    full = [] if args.pareto_only else full_solves(max(1, args.repeats // 2))
    pareto, points = ([], {}) if args.skip_pareto else pareto_sweeps(args.pareto_repeats)

    print("| solver | braking | objective | NLP build (s) | solve median (s) | iterations | optimum | status |")
    print("|---|---|---|---:|---:|---:|---:|---|")
    for r in single:
        med = "failed" if r["solve_median_s"] is None else f"{r['solve_median_s']:.2f}"
        val = "-" if r["value"] is None else f"{r['value']:.3f} {'s' if r['objective'] == 'time' else 'g'}"
        print(f"| {r['solver']} | {r['braking']} | {r['objective']} | {r['build_s']:.2f} | {med} | "
              f"{r['iterations'] or '-'} | {val} | {r['status']} |")
    print("\n| braking | objective | wall median (s) | T (s) | fuel (g) | final mesh | starts | re-simulation |")
    print("|---|---|---:|---:|---:|---|---:|---|")
    for r in full:
        print(f"| {r['braking']} | {r['objective']} | {r['wall_median_s']:.2f} | {r['T']:.3f} | {r['fuel_g']:.2f} | "
              f"{r['mesh']} | {r['starts']} | {'passed' if r['verified'] else 'FAILED'} |")
    for mode in ("parallel", "sequential"):
        walls = [r["wall_s"] for r in pareto if r["mode"] == mode]
        if walls:
            print(f"\nPareto sweep, both alternatives, {mode}: median {statistics.median(walls):.1f} s "
                  f"(runs: {', '.join(f'{w:.1f}' for w in walls)})")
    if args.json:
        write_json_atomic(args.json, {"single_solves": single, "full_solves": full, "pareto": pareto,
                                      "pareto_points": points, "cpu_count": os.cpu_count()})



if __name__ == "__main__":
    from wl_env.logs import run_script

    run_script("bench_ocp", main)  # (Ctrl-C: exit 130, no traceback; a ValueError: one line, exit 2)
