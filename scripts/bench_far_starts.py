"""The re-plans' warm-start push, near (1e-6 everywhere) against far (``solver.far_starts``), in one process.

    python scripts/bench_far_starts.py --out docs/bench_mpc_far_starts_ab_stop50.json

Each cycle of ``bench_mpc.py``'s mismatch corners (minimum time, nominal model, the plant's payload and rolling
resistance scaled) and the nominal cycle, for each braking, runs under the default MPC twice: with
``WARM_START_PUSH_FAR`` at its value (a re-plan for a moved plant estimate starts 1e-3 off its bounds) and at
``WARM_START_PUSH_NEAR`` (the rule off), the order alternating, the stored plans forgotten between runs. Per
variant: the steps' time (the first, planning, apart) and IPOPT iterations, and the cycles' T, fuel and success.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)
from agents.train_cli import refuse_repeated_values, tyro_options  # noqa: E402
from wl_env.atomic_io import check_output_file  # noqa: E402
from wl_env.cycle import check_braking  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

log = logging.getLogger("bench_far_starts")


@dataclass
class Options:
    brakings: tuple[str, ...] = ("service", "tc")
    out: str | None = None  # JSON of the per-run records and the summary


def run(o: Options) -> dict[str, Any]:
    if not o.brakings:  # (an empty list failed in numpy: "need at least one array to concatenate")
        raise ValueError("--brakings needs at least one of service, tc")
    for b in o.brakings:
        check_braking(b)
    refuse_repeated_values("--brakings", o.brakings, "a braking alternative")  # (each run twice, counted twice)
    if o.out is not None:
        check_output_file(o.out, "--out")
    from bench_mpc import MISMATCH, summary_line, write_with_speed

    from mpc.controller import mpc, solver
    from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop
    from wl_env.params import DEFAULT_PARAMS

    far = solver.WARM_START_PUSH_FAR
    variants = {"near": solver.WARM_START_PUSH_NEAR, "far": far}
    records = []
    try:
        for b in o.brakings:
            cases = [("nominal", None)] + [(f"x{p}/x{r}", DEFAULT_PARAMS.variant(payload_scale=p, rolling_scale=r))
                                           for p, r in MISMATCH]
            for i, (label, plant) in enumerate(cases):
                for name in (("near", "far") if i % 2 == 0 else ("far", "near")):
                    solver.WARM_START_PUSH_FAR = variants[name]
                    mpc.forget_plans()
                    ctrl = MPCController(b, config=MPCConfig(mode="time"))
                    ep = run_closed_loop(b, ctrl.config, plant_params=plant, score=False, controller=ctrl).episode
                    rec = {"braking": b, "run": label, "variant": name, "T": ep.T, "fuel_g": ep.fuel_g,
                           "success": ep.success, "max_violation": ep.max_violation,
                           "step_times_s": ctrl.solve_times[1:], "step_iterations": ctrl.step_iterations[1:]}
                    records.append(rec)
                    log.info("%s %s %s: T %.1f s, fuel %.3f g, success %s, slowest step %.0f ms", b, label, name, ep.T,
                             ep.fuel_g, ep.success, 1e3 * max(rec["step_times_s"], default=0.0))
    finally:
        solver.WARM_START_PUSH_FAR = far
    summary = {}
    for name in variants:
        for group, mismatch in (("nominal", False), ("mismatch", True)):
            rows = [r for r in records if r["variant"] == name and (r["run"] != "nominal") == mismatch]
            ms = 1e3 * np.concatenate([r["step_times_s"] for r in rows])
            its = np.concatenate([r["step_iterations"] for r in rows])
            summary[f"{name}_{group}"] = {
                "steps": len(ms), "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
                "max_ms": float(ms.max()), "over_100ms": int((ms > 100).sum()), "iterations": int(its.sum()),
                "iterations_max": int(its.max()), "success": sum(r["success"] for r in rows), "runs": len(rows)}
            print(f"{name:4s} {group:8s}: {summary_line(summary[f'{name}_{group}'], 4)}")
    write_with_speed(o.out, o, summary, records)
    return summary


if __name__ == "__main__":
    run_script("bench_far_starts", lambda: run(tyro_options(Options)))
