"""The MPC's first-step planning on new scenarios: where its time goes, and the cycles it leads to.

    python scripts/bench_planning.py --braking tc --scenarios 20 --out planning_tc.json
    python scripts/bench_planning.py --braking tc --scenarios 20 --reference-starts 0.3 0.5 0.7   # stop 48's reference

Issue #13 asks a first step to plan in <= 1 s once the process has built its solvers. Each of the first
``--scenarios`` cycles of ``--suite`` runs under the default synchronous MPC, at ``--target-ratio`` times the
scenario's estimated T_min (``0``: minimum time), each a new scenario to the process (one cycle before them builds
what every scenario shares). Per cycle: the first step's planning time and its parts
(``MPCController.planning_parts``: the continuous reference, the slot layout's build, the first solve, the schedule
search), the cycle's T, fuel and success, its T against the scenario's T_min (where an optimum is shipped or cached),
and its later steps' largest time and how many passed the 0.1 s interval. ``--reference-starts`` sets the target-time reference's template
starts (``mpc.controller.mpc.REFERENCE_STARTS``: the braking's acceleration fractions), to compare them on the same
cycles.
"""

from __future__ import annotations

import logging
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)
from agents.train_cli import refuse_repeated_values, tyro_options  # noqa: E402
from wl_env.atomic_io import check_output_file  # noqa: E402
from wl_env.cycle import check_braking  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

log = logging.getLogger("bench_planning")


@dataclass
class Options:
    braking: str = "tc"
    suite: str = "test"
    scenarios: int = 20  # the suite's first N of this braking
    target_ratio: float = 1.15  # the target, times the scenario's estimated T_min; 0: minimum time
    reference_starts: tuple[float, ...] = ()  # the braking's reference template starts (acceleration fractions); (): default
    out: str | None = None  # JSON of the per-cycle records and the summary


def check(o: Options) -> None:
    check_braking(o.braking)
    if not 1 <= o.scenarios <= 1000:
        raise ValueError(f"--scenarios must be an integer in [1, 1000], got {o.scenarios}")
    if o.target_ratio != 0 and not 1.0 <= o.target_ratio <= 3.0:
        raise ValueError(f"--target-ratio must be 0 (minimum time) or lie in [1, 3], got {o.target_ratio}")
    if not all(0.0 < a <= 1.0 for a in o.reference_starts):
        raise ValueError(f"--reference-starts must each lie in (0, 1], got {list(o.reference_starts)}")
    refuse_repeated_values("--reference-starts", o.reference_starts, "a start")  # (one start solved twice per plan)
    if o.out is not None:
        check_output_file(o.out, "--out")


def run(o: Options) -> dict[str, Any]:
    check(o)
    from bench_mpc import summary_line, write_with_speed

    from mpc.benchmark.reference import known_front
    from mpc.controller import mpc
    from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop
    from wl_env.suites import load_suite
    from wl_env.suites.min_time import estimate_min_time

    if o.reference_starts:
        mpc.REFERENCE_STARTS = {**mpc.REFERENCE_STARTS, o.braking: tuple(o.reference_starts)}
    scenarios = load_suite(o.suite).of(o.braking)
    if len(scenarios) < o.scenarios + 1:
        raise ValueError(f"--scenarios: the {o.suite} suite has {len(scenarios)} {o.braking} cycles; at most "
                         f"{len(scenarios) - 1} can be new to the process")

    def config(sc: Any) -> MPCConfig:
        if o.target_ratio == 0:
            return MPCConfig()
        return MPCConfig(mode="target_time", target_time=round(o.target_ratio * estimate_min_time(sc), 1))

    run_closed_loop(o.braking, config(scenarios[-1]), scenario=scenarios[-1], score=False)  # (builds what all share)
    records = []
    for i, sc in enumerate(scenarios[:o.scenarios]):
        cfg = config(sc)
        ctrl = MPCController(o.braking, sc.params(), cfg)
        res = run_closed_loop(o.braking, cfg, scenario=sc, score=False, controller=ctrl)
        ep = res.episode
        known = known_front(o.braking, sc.params())  # (the shipped optimum's T_min; nothing solved)
        T_min = None if known is None else known[0].T_min
        rec = {"scenario": i, "target_time": cfg.target_time, "planning_s": ctrl.planning_time,
               "T_min": T_min, "time_gap": None if T_min is None or not ep.completed else ep.T / T_min - 1.0,
               "parts_s": dict(ctrl.planning_parts), "first_plan_from": ctrl.first_plan_from,
               "T": ep.T, "fuel_g": ep.fuel_g, "success": ep.success, "max_violation": ep.max_violation,
               # (the steps after the first: a first plan that leaves work to the worker must not make them late)
               "step_max_s": max(res.solve_times_s[1:], default=0.0),
               "steps_over_interval": sum(t > ctrl.dt for t in res.solve_times_s[1:])}
        records.append(rec)
        log.info("%s[%d]: planning %.2f s (%s), T %.1f s, fuel %.3f g, success %s", o.suite, i, rec["planning_s"],
                 ", ".join(f"{k} {v:.2f}" for k, v in rec["parts_s"].items()), ep.T, ep.fuel_g, ep.success)
    planning = [r["planning_s"] for r in records]
    built = [r["planning_s"] - r["parts_s"].get("layout", 0.0) for r in records]
    summary = {"cycles": len(records), "success": sum(r["success"] for r in records),
               "planning_median_s": statistics.median(planning), "planning_max_s": max(planning),
               "planning_less_layout_median_s": statistics.median(built),
               "within_1s_less_layout": sum(b <= 1.0 for b in built), "within_1s": sum(p <= 1.0 for p in planning),
               "step_max_s": max(r["step_max_s"] for r in records),
               "steps_over_interval": sum(r["steps_over_interval"] for r in records),
               # (the cycle time against the scenario's T_min, where an optimum is shipped or cached: minimum time's gap)
               "time_gap_median": statistics.median(gaps) if (gaps := [r["time_gap"] for r in records
                                                                        if r["time_gap"] is not None]) else None,
               **{f"{part}_median_s": statistics.median(r["parts_s"].get(part, 0.0) for r in records)
                  for part in ("reference", "layout", "first_solve", "search")}}
    print(f"{o.braking}, {o.suite} x{len(records)} at {o.target_ratio or 'minimum time'}: {summary_line(summary)}")
    write_with_speed(o.out, o, summary, records)
    return summary


if __name__ == "__main__":
    run_script("bench_planning", lambda: run(tyro_options(Options)))
