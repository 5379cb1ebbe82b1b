"""The yardstick and the controllers at the corners of the scenario ranges: where the general case breaks first.

    python scripts/bench_corners.py --braking service --out corners_service.json
    python scripts/bench_corners.py --braking tc --mpc 8 --operator
    python scripts/bench_corners.py --braking tc --operator --learned --no-ocp

Every corner of the seven scenario ranges (2^7 = 128 per braking alternative; ``--corners N`` takes N of them,
drawn with ``--seed``): the minimum-time OCP, then the minimum fuel at ``--ratio`` T_min, each with
``solve_ocp``'s re-simulation check, and the environment's T_min estimate (``wl_env.suites.min_time``) against
the OCP's. ``--mpc N``: the default synchronous MPC on N of those corners (drawn with ``--seed``), in
minimum-time mode and at the ``--ratio`` T_min target, each scored (its fuel against the corner's minimum fuel
at the MPC's own cycle time, ``score_run``: two more solves per run, cached). ``--operator``: the rule-based
operator on every corner taken; ``--learned``: the shipped target-conditioned policies (ppo, bc) there at 1,
1.15 and 1.5 T_min (``--no-ocp``: these alone, in seconds). The corners' own OCPs are not cached: each is
solved (8-15 s per corner, both solves).
"""

from __future__ import annotations

import logging
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)

from agents.train_cli import tyro_options  # noqa: E402
from wl_env.atomic_io import check_output_file, write_json_atomic  # noqa: E402
from wl_env.cycle import check_braking  # noqa: E402
from wl_env.logs import run_script  # noqa: E402
from wl_env.scenario import FIELDS, Scenario  # noqa: E402
from wl_env.suites import corner_scenarios  # noqa: E402

log = logging.getLogger("bench_corners")


@dataclass
class Options:
    braking: str = "service"
    corners: int = 128  # of the 2^7 (all by default; fewer: drawn with --seed)
    ratio: float = 1.15  # the fixed-time solve's (and the MPC's target's) cycle time, times T_min
    mpc: int = 0  # corners to run the MPC on (of those taken)
    operator: bool = False  # also run the operator on every corner taken
    learned: bool = False  # also the shipped target-conditioned ppo and bc at 1, 1.15 and 1.5 T_min (estimated)
    ocp: bool = True  # --no-ocp: skip the yardstick (the operator's and policies' limits at every corner: seconds)
    seed: int = 37
    out: str | None = None  # JSON of the per-corner records and the summary


def check(o: Options) -> None:
    check_braking(o.braking)
    n = 2 ** len(FIELDS)
    if not 1 <= o.corners <= n:
        raise ValueError(f"--corners must be an integer in [1, {n}], got {o.corners}")
    if not 1.0 < o.ratio <= 3.0:
        raise ValueError(f"--ratio must lie in (1, 3], got {o.ratio}")
    if o.mpc and not o.ocp:
        raise ValueError("--mpc scores the MPC against each corner's T_min: it needs the OCPs (drop --no-ocp)")
    if not 0 <= o.mpc <= o.corners:
        raise ValueError(f"--mpc must be an integer in [0, --corners ({o.corners})], got {o.mpc}")
    if not 0 <= o.seed <= 2**32 - 1:
        raise ValueError(f"--seed must be an integer in [0, 2**32 - 1], got {o.seed}")
    if o.out is not None:  # (written at the end: checked before the corners' solves)
        check_output_file(o.out, "--out")


def run(o: Options) -> dict[str, Any]:
    check(o)
    from mpc.benchmark.ocp import OCPError, solve_ocp
    from wl_env.suites.min_time import estimate_min_time

    rng = np.random.default_rng(o.seed)
    every = corner_scenarios(o.braking)
    taken = sorted(rng.choice(len(every), o.corners, replace=False).tolist()) if o.corners < len(every) else list(range(len(every)))
    records = []
    for i in taken if o.ocp else ():
        sc, t0 = every[i], time.perf_counter()
        rec: dict[str, Any] = {"corner": i, "scenario": sc.to_dict()}
        try:
            r = solve_ocp(scenario=sc, objective="time")
            rec.update(T_min=r.T, min_time_ok=bool(r.success), min_time_status=r.status,
                       estimate_error=(estimate_min_time(sc) - r.T) / r.T)
            f = solve_ocp(scenario=sc, objective="fuel_at_time", T=o.ratio * r.T)
            rec.update(fuel_g=f.fuel_g, fixed_time_ok=bool(f.success), fixed_time_status=f.status)
        except OCPError as exc:  # (a corner without an optimum is a finding: recorded with the solver's status)
            rec.update(min_time_ok=rec.get("min_time_ok", False), fixed_time_ok=False, error=str(exc))
        rec["solve_s"] = time.perf_counter() - t0
        records.append(rec)
        log.info("corner %d: T_min %s, checks %s / %s (%.1f s)", i, f"{rec['T_min']:.3f} s" if "T_min" in rec else "-",
                 rec["min_time_ok"], rec["fixed_time_ok"], rec["solve_s"])
    ok = [r for r in records if r["min_time_ok"] and r["fixed_time_ok"]]
    errors = [r["estimate_error"] for r in records if "estimate_error" in r]
    summary: dict[str, Any] = {
        "corners": len(records), "both_checks_passed": len(ok),
        "failed": [(r["corner"], r.get("error") or r.get("fixed_time_status") or r.get("min_time_status")) for r in records
                   if r not in ok],
        "estimate_error_median": statistics.median(errors) if errors else None,
        "estimate_error_abs_max": max(map(abs, errors)) if errors else None,
        "solve_s_median": statistics.median(r["solve_s"] for r in records) if records else None}
    if o.mpc:
        summary["mpc"] = _mpc(o, [r for r in records if "T_min" in r], every, rng)
    if o.operator:
        summary["operator"] = _operator(o, every, taken)
    if o.learned:
        summary.update(_learned(o, every, taken))
    if o.ocp:
        print(f"{o.braking}: {summary['both_checks_passed']} of {summary['corners']} corners pass both re-simulation "
              f"checks (minimum time, minimum fuel at {o.ratio:g} T_min)"
              + (f"; T_min estimate error median {100 * summary['estimate_error_median']:+.2f} %, at most "
                 f"{100 * summary['estimate_error_abs_max']:.2f} %" if errors else ""))
    for name in [k for k in summary if k in ("mpc", "operator") or k.startswith(("ppo", "bc"))]:
        print(f"  {name}: " + ", ".join(f"{k} {v}" for k, v in summary[name].items() if k != "runs"))
    if o.out:
        write_json_atomic(o.out, {"options": asdict(o), "summary": summary, "records": records})
    return summary


def _mpc(o: Options, solved: list[dict[str, Any]], every: list[Scenario], rng: np.random.Generator) -> dict[str, Any]:
    from mpc.controller.mpc import MPCConfig, run_closed_loop

    runs = []
    for rec in (solved[k] for k in sorted(rng.choice(len(solved), min(o.mpc, len(solved)), replace=False))):
        sc, T_min = every[rec["corner"]], rec["T_min"]
        for cfg in (MPCConfig(), MPCConfig(mode="target_time", target_time=round(o.ratio * T_min, 1))):
            res = run_closed_loop(o.braking, cfg, scenario=sc)  # (scored: fuel against the optimum at its own T)
            ep = res.episode
            runs.append({"corner": rec["corner"], "target_time": cfg.target_time, "T": ep.T, "T_min": T_min,
                         "success": ep.success, "max_violation": ep.max_violation, "fuel_g": ep.fuel_g,
                         "fuel_opt_g": res.score.fuel_opt_g if res.score else None,
                         "fuel_gap": res.score.fuel_gap if res.score else None,
                         "planning_s": res.solve_time.get("planning_s")})
            log.info("MPC corner %d, %s: T %.1f s (T_min %.3f s), success %s, violation %.3g", rec["corner"],
                     f"target {cfg.target_time} s" if cfg.target_time else "minimum time", ep.T, T_min, ep.success,
                     ep.max_violation)
    fastest = [r["T"] / r["T_min"] - 1.0 for r in runs if r["target_time"] is None]
    gaps = {mode: [r["fuel_gap"] for r in runs if r["fuel_gap"] is not None and (r["target_time"] is None) == (mode == "min_time")]
            for mode in ("min_time", "target")}
    return {"cycles": len(runs), "on_marks": sum(r["success"] for r in runs),
            **{f"fuel_gap_{mode}_median_p90_max": [round(float(np.median(g)), 4), round(float(np.percentile(g, 90)), 4),
                                                   round(max(g), 4)] for mode, g in gaps.items() if g},
            "with_violation": sum(r["max_violation"] > 0 for r in runs),
            "targets_met": sum(r["T"] <= r["target_time"] + 1e-9 for r in runs if r["target_time"] is not None),
            "min_time_gap_range": [round(min(fastest), 4), round(max(fastest), 4)] if fastest else None, "runs": runs}


def _limits(res: dict[str, Any], taken: list[int]) -> dict[str, Any]:
    """On the marks and within the limits, of an evaluation of the corners ``taken`` (their numbers)."""
    eps = res["per_episode"]
    return {"cycles": len(eps), "on_marks": sum(e["success"] for e in eps),
            "with_violation": sum(e["max_violation"] > 0 for e in eps),
            "max_violation": max(e["max_violation"] for e in eps),
            "corners_with_violation": [c for c, e in zip(taken, eps, strict=True) if e["max_violation"] > 0]}


def _operator(o: Options, every: list[Scenario], taken: list[int]) -> dict[str, Any]:
    from agents.evaluate import evaluate_controller, load_controller

    res = evaluate_controller(load_controller("operator", o.braking), o.braking, scenarios=[every[i] for i in taken],
                              score=False)
    return _limits(res, taken)


def _learned(o: Options, every: list[Scenario], taken: list[int]) -> dict[str, Any]:
    """The shipped target-conditioned policies (ppo, bc) at each corner, at 1, 1.15 and 1.5 times its estimated
    T_min (nothing solved): whether they keep the limits where they were not trained (they learn on draws)."""
    from agents.evaluate import evaluate_controller, load_controller

    out = {}
    for name in ("ppo", "bc"):
        controller = load_controller(name, o.braking, targeted=True)
        for ratio in (1.0, 1.15, 1.5):
            res = evaluate_controller(controller, o.braking, scenarios=[every[i] for i in taken], score=False,
                                      target_ratio=ratio, min_time="estimate")
            late = [e.get("lateness") or 0.0 for e in res["per_episode"]]
            out[f"{name} at {ratio:g} T_min"] = {**_limits(res, taken),
                                                "lateness_median": statistics.median(late)}
    return out


if __name__ == "__main__":
    run_script("bench_corners", lambda: run(tyro_options(Options)))
