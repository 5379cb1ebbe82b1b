"""The default MPC on fresh draws of the scenario ranges: cases no suite holds, where the general case breaks.

    python scripts/bench_draws.py --braking tc --draws 12 --seed 101 --out draws_tc.json
    python scripts/bench_draws.py --braking service --draws 12 --seed 202 --modes time 1.15

``--draws`` scenarios drawn from the seven ranges (``wl_env.suites.draw``, generator seeded with ``--seed``: not the
suites' streams), each run under the default synchronous MPC in each of ``--modes``: ``time`` (minimum time), a
number (a target of that ratio times the scenario's estimated T_min, ``wl_env.suites.min_time``) and ``mismatch``
(minimum time on the nominal payload and rolling resistance, the plant the draw's: its ranges are wider than
#13's +-20 % / +-30 %). ``--in-step`` makes the re-plans for a moved plant estimate in the step that needs one,
as before stop 56, not on the worker; ``--within-13`` keeps only draws whose payload and rolling resistance lie
within #13's ranges (the others are drawn again). Per run: T, fuel, on the marks, the largest violation, the
target met, the first step's planning and the later steps' solve times (median, max, over 100 ms). Nothing is
scored against an optimum, so a draw costs seconds; an exception is a finding, recorded with its message. The
summary counts the runs per mode that missed their marks, broke a limit, ended past their target or raised.
"""

from __future__ import annotations

import dataclasses
import logging
import statistics
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

log = logging.getLogger("bench_draws")


@dataclass
class Options:
    braking: str = "tc"
    draws: int = 12
    seed: int = 101
    modes: tuple[str, ...] = ("time", "1.02", "1.15", "2.5", "mismatch")  # time, mismatch, or a target ratio of T_min
    out: str | None = None  # JSON of the per-run records and the summary
    in_step: bool = False  # the re-plans for a moved plant estimate in the step that needs one, not on the worker
    within_13: bool = False  # only draws whose payload and rolling resistance lie within #13's mismatch ranges


def target_ratio(mode: str) -> float | None:
    """A mode's target ratio (None: minimum time, alone or mismatched); ValueError naming --modes otherwise."""
    if mode in ("time", "mismatch"):
        return None
    try:
        ratio = float(mode)
    except ValueError:
        ratio = float("nan")
    if not 1.0 <= ratio <= 3.0:
        raise ValueError(f"--modes must each be 'time', 'mismatch' or a target ratio in [1, 3], got {mode!r}")
    return ratio


def check(o: Options) -> None:
    check_braking(o.braking)
    if not 1 <= o.draws <= 1000:
        raise ValueError(f"--draws must be an integer in [1, 1000], got {o.draws}")
    if not 0 <= o.seed <= 2**32 - 1:
        raise ValueError(f"--seed must be an integer in [0, 2**32 - 1], got {o.seed}")
    if not o.modes:
        raise ValueError("--modes must name at least one mode")
    for mode in o.modes:
        target_ratio(mode)
    # (a mode given twice, also as another spelling of one ratio, 1.15 and 1.150: every draw run twice, its records
    # and the summary's counts doubled)
    refuse_repeated_values("--modes", o.modes, "a mode", key=lambda m: m if m in ("time", "mismatch") else target_ratio(m))
    if o.out is not None:
        check_output_file(o.out, "--out")


def within_13(scenario: Any) -> bool:
    """The draw's payload and rolling resistance lie within #13's mismatch ranges of the nominal model's: the box
    of ``bench_mpc.py``'s mismatch corners."""
    from bench_mpc import MISMATCH

    from wl_env.params import DEFAULT_PARAMS

    payloads, rollings = zip(*MISMATCH, strict=True)
    return (min(payloads) - 1e-9 <= scenario.payload / DEFAULT_PARAMS.M_load <= max(payloads) + 1e-9
            and min(rollings) - 1e-9 <= scenario.rolling_resistance / DEFAULT_PARAMS.c_r <= max(rollings) + 1e-9)


def run_one(braking: str, scenario: Any, mode: str, settings: dict[str, Any] | None = None,
            mismatch: bool = False) -> dict[str, Any]:
    """One cycle of the MPC in ``mode`` (--modes'), with ``settings`` (MPCConfig fields) over the default's, the plant
    mismatched (``mismatch``, or the mode "mismatch"): its record."""
    from mpc.controller.mpc import MPCConfig, run_closed_loop
    from wl_env.suites.min_time import estimate_min_time

    ratio = target_ratio(mode)
    cfg = MPCConfig() if ratio is None else MPCConfig(mode="target_time",
                                                      target_time=round(ratio * estimate_min_time(scenario), 2))
    cfg = dataclasses.replace(cfg, **(settings or {}))
    try:
        res = run_closed_loop(braking, cfg, scenario=scenario, score=False, mismatch=mismatch or mode == "mismatch")
    except Exception as exc:  # (a finding: the draw and the message go in the record)
        return {"mode": mode, "target_time": cfg.target_time, "error": f"{type(exc).__name__}: {exc}"}
    ep, later = res.episode, 1e3 * np.asarray(res.solve_times_s[1:])
    return {"mode": mode, "target_time": cfg.target_time, "T": ep.T, "fuel_g": ep.fuel_g, "success": ep.success,
            "max_violation": ep.max_violation,
            "target_met": None if cfg.target_time is None else ep.T <= cfg.target_time + 1e-9,
            "planning_s": res.solve_times_s[0], "step_median_ms": float(np.median(later)) if later.size else 0.0,
            "step_max_ms": float(later.max(initial=0.0)), "steps_over_100ms": int((later > 100.0).sum())}


def run(o: Options) -> dict[str, Any]:
    check(o)
    from bench_mpc import summary_line, write_with_speed

    from wl_env.suites import draw

    rng = np.random.default_rng(o.seed)
    records = []
    for i in range(o.draws):
        sc = draw(rng, o.braking)
        while o.within_13 and not within_13(sc):
            sc = draw(rng, o.braking)
        for mode in o.modes:
            rec = {"draw": i, "scenario": sc.to_dict(),
                   **run_one(o.braking, sc, mode, {"replan_lag_steps": None} if o.in_step else None)}
            records.append(rec)
            log.info("draw %d %s: %s", i, mode, rec.get("error") or
                     f"T {rec['T']:.1f} s, fuel {rec['fuel_g']:.2f} g, success {rec['success']}, violation "
                     f"{rec['max_violation']:.3g}, planning {rec['planning_s']:.2f} s, max step {rec['step_max_ms']:.0f} ms")
    summary = {}
    for mode in o.modes:
        summary[mode] = summarize([r for r in records if r["mode"] == mode])
        print(f"{o.braking} {mode}: {summary_line(summary[mode])}")
    write_with_speed(o.out, o, summary, records)
    return summary


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The counts of a group of run_one's records: those that raised, missed their marks, broke a limit or ended past
    their target, the first steps' planning and the later steps over 100 ms."""
    done = [r for r in runs if "error" not in r]
    return {"runs": len(runs), "errors": len(runs) - len(done), "off_marks": sum(not r["success"] for r in done),
            "with_violation": sum(r["max_violation"] > 0 for r in done),
            "targets_missed": sum(r["target_met"] is False for r in done),
            "planning_median_s": statistics.median(r["planning_s"] for r in done) if done else None,
            "planning_max_s": max((r["planning_s"] for r in done), default=None),
            "step_max_ms": max((r["step_max_ms"] for r in done), default=None),
            "steps_over_100ms": sum(r["steps_over_100ms"] for r in done)}


if __name__ == "__main__":
    run_script("bench_draws", lambda: run(tyro_options(Options)))
