"""The mismatch corners' re-plans in their steps against on the worker at a lag, side by side in one run.

    python scripts/bench_replan_lag.py --lags 5 --out docs/bench_replan_lag_stop56.json
    python scripts/bench_replan_lag.py --lags 3 4 5 7 --brakings tc

Per braking and mismatch corner (``bench_mpc.py``'s: the plant's payload x0.8 / x1.2 and rolling resistance
x0.7 / x1.3, the model nominal; minimum time), the default MPC runs once with its re-plans for a moved plant
estimate in the step that finds the plan stale (``replan_lag_steps=None``) and once per ``--lags`` value (the
re-plan on the worker, taken up that many steps later; the default since stop 56 is 5). Per run: T, fuel, on the
marks, the largest violation, the re-plans (on the worker and in all), the later steps' solve times (median, p99,
max, over 100 ms) and the steps over 100 ms with their solves and IPOPT iterations (a whole-cycle re-plan in a
step has 2-3 solves; a step that waits for a late worker has 1).
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

log = logging.getLogger("bench_replan_lag")


@dataclass
class Options:
    brakings: tuple[str, ...] = ("service", "tc")
    lags: tuple[int, ...] = (5,)  # replan_lag_steps values, each beside the re-plans in their steps
    out: str | None = None  # JSON of the per-run records and the summary


def check(o: Options) -> None:
    for b in o.brakings:
        check_braking(b)
    refuse_repeated_values("--brakings", o.brakings, "a braking alternative")  # (each run twice, counted twice)
    if not o.lags or not all(1 <= lag <= 100 for lag in o.lags) or len(set(o.lags)) != len(o.lags):
        raise ValueError(f"--lags must be distinct integers in [1, 100], got {list(o.lags)}")
    if o.out is not None:
        check_output_file(o.out, "--out")


def run_one(braking: str, payload: float, rolling: float, lag: int | None) -> dict[str, Any]:
    from mpc.controller.mpc import MPCConfig, MPCController, forget_plans, run_closed_loop
    from wl_env.params import DEFAULT_PARAMS

    forget_plans()  # (each run plans as a fresh process would)
    config = MPCConfig(mode="time", replan_lag_steps=lag)
    ctrl = MPCController(braking, None, config)
    plant = DEFAULT_PARAMS.variant(payload_scale=payload, rolling_scale=rolling)
    ep = run_closed_loop(braking, config, plant_params=plant, score=False, controller=ctrl).episode
    later = 1e3 * np.asarray(ctrl.solve_times[1:])
    slow = [{"step": k, "ms": float(later[k - 1]), "solves": ctrl.step_solves[k], "iterations": ctrl.step_iterations[k]}
            for k in range(1, len(ctrl.solve_times)) if later[k - 1] > 100.0]
    return {"braking": braking, "payload_scale": payload, "rolling_scale": rolling, "lag": lag, "T": ep.T,
            "fuel_g": ep.fuel_g, "success": ep.success, "max_violation": ep.max_violation,
            "replans": ctrl.replans, "worker_replans_ms": [1e3 * t for t in ctrl.worker_solve_times],
            "step_median_ms": float(np.median(later)), "step_p99_ms": float(np.percentile(later, 99)),
            "step_max_ms": float(later.max()), "steps_over_100ms": len(slow), "slow_steps": slow}


def run(o: Options) -> dict[str, Any]:
    check(o)
    from bench_mpc import MISMATCH, summary_line, write_with_speed

    records = []
    for b in o.brakings:
        for payload, rolling in MISMATCH:
            for lag in (None, *o.lags):  # (interleaved: a slower hour hits both alike)
                rec = run_one(b, payload, rolling, lag)
                records.append(rec)
                log.info("%s x%g / x%g, %s: T %.1f s, fuel %.2f g, success %s, violation %.3g, %d re-plans (%d on the "
                         "worker), steps median %.1f / max %.0f ms, %d over 100 ms", b, payload, rolling,
                         "in the step" if lag is None else f"lag {lag}", rec["T"], rec["fuel_g"], rec["success"],
                         rec["max_violation"], rec["replans"], len(rec["worker_replans_ms"]), rec["step_median_ms"],
                         rec["step_max_ms"], rec["steps_over_100ms"])
    summary = {}
    for lag in (None, *o.lags):
        runs = [r for r in records if r["lag"] == lag]
        steps = [r["steps_over_100ms"] for r in runs]
        summary["in the step" if lag is None else f"lag {lag}"] = {
            "runs": len(runs), "off_marks": sum(not r["success"] for r in runs),
            "with_violation": sum(r["max_violation"] > 0 for r in runs), "steps_over_100ms": sum(steps),
            "runs_without_a_step_over_100ms": sum(n == 0 for n in steps), "step_max_ms": max(r["step_max_ms"] for r in runs)}
    for name, s in summary.items():
        print(f"{name}: {summary_line(s)}")
    write_with_speed(o.out, o, summary, records)
    return summary


if __name__ == "__main__":
    run_script("bench_replan_lag", lambda: run(tyro_options(Options)))
