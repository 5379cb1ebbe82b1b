"""Benchmark of the optimal control benchmark: NLP build, single solves, full solves, Pareto sweep.

Medians over repeats (the machine is noisy); IPOPT with its exact Hessian against IPOPT with a
limited-memory (L-BFGS) Hessian in the same run. Usage:

    python scripts/bench_ocp.py [--repeats 5] [--json PATH] [--skip-pareto]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time

from mpc.ocp import CycleOCP, OCPSettings, solve_ocp, template_guess, write_json_atomic


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument("--skip-pareto", action="store_true")
    args = ap.parse_args()
    rows = []
    for hessian in ("exact", "limited-memory"):
        for braking in ("service", "tc"):
            settings = OCPSettings(hessian=hessian)
            build, ocp = timed(lambda: CycleOCP(braking, settings=settings))
            for objective in ("time", "fuel"):
                z0 = ocp.guess_from_trajectory(**template_guess(ocp.params, 5.0, 0.7))
                times, values, iters, status = [], [], [], ""
                for _ in range(args.repeats):
                    try:
                        dt, (z, info) = timed(lambda: ocp.solve(z0, objective))
                    except RuntimeError as exc:
                        status = str(exc)[-60:]
                        break
                    fuel, T = ocp.objective_parts(z)
                    times.append(dt)
                    values.append(T if objective == "time" else fuel)
                    iters.append(info["iterations"])
                    status = info["status"]
                rows.append({"solver": f"ipopt/{hessian}", "braking": braking, "objective": objective,
                             "build_s": build, "solve_median_s": statistics.median(times) if times else None,
                             "solve_max_s": max(times) if times else None,
                             "iterations": statistics.median(iters) if iters else None,
                             "value": values[0] if values else None, "status": status})
                print(rows[-1], flush=True)
    # the full user-facing solve: multi-start, smoothing homotopy, re-simulation, mesh refinement
    full = []
    for braking in ("service", "tc"):
        for objective in ("time", "fuel"):
            dt, r = timed(lambda: solve_ocp(braking, objective))
            full.append({"braking": braking, "objective": objective, "wall_s": dt, "T": r.T, "fuel_g": r.fuel_g,
                         "mesh": r.mesh, "starts": len(r.starts), "verified": r.verification["passed"]})
            print(full[-1], flush=True)
    pareto = []
    if not args.skip_pareto:
        from mpc.pareto import pareto_front

        with tempfile.TemporaryDirectory() as cache:
            for braking in ("service", "tc"):
                dt, f = timed(lambda: pareto_front(braking, cache=cache))
                pareto.append({"braking": braking, "wall_s": dt, "points": len(f.T), "T_min": f.T_min,
                               "T_fuel_opt": f.T_fuel_opt, "fuel_min_g": f.fuel_min_g})
                print(pareto[-1], flush=True)
    out = {"single_solves": rows, "full_solves": full, "pareto": pareto, "cpu_count": os.cpu_count()}
    if args.json:
        write_json_atomic(args.json, out)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
