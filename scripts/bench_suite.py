"""Benchmark: a scenario's Pareto fronts (both braking alternatives) and a suite's solve, local and on Ray.

    python scripts/bench_suite.py --scenarios 6 --points 10 --out results/bench_suite.json

Each run solves in a fresh cache: first the nominal cycle (the chain's start, not timed), then the first
``--scenarios`` scenarios of each braking alternative's chain of the ``test`` suite (`wl suite solve`),
with two local processes (one per braking alternative): ``chain``, each warm-started from the nearest
one solved before; ``cold``, each from the templates alone (no neighbour); ``ray``, the chain on a local
Ray instance. Per scenario: its front's own wall time per braking alternative (median, max), and the
suite's wall time per scenario (both alternatives in parallel).
"""

from __future__ import annotations

import logging
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)

from agents.train_cli import tyro_options  # noqa: E402
from mpc.benchmark.suite import solve_suite  # noqa: E402
from wl_env.atomic_io import check_output_file, write_json_atomic  # noqa: E402
from wl_env.logs import cli_logging, run_script  # noqa: E402

log = logging.getLogger("bench_suite")


MODES = ("chain", "cold", "ray")


@dataclass
class Options:
    scenarios: int = 6  # scenarios per braking alternative
    points: int = 10  # points per front
    modes: tuple[str, ...] = MODES  # which solves to time
    out: str = "results/bench_suite.json"

    def __post_init__(self) -> None:
        """Checked by name before the solves (--modes foo or an unwritable --out failed after them, --scenarios 0
        divided by zero, --points 0 failed with a traceback)."""
        from mpc.benchmark.suite import load_suite

        n = min(len(load_suite("test").of(b)) for b in ("service", "tc"))
        for name, lo, hi in (("scenarios", 1, n), ("points", 3, 100)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"--{name} must be an integer in [{lo}, {hi}], got {v!r}")
        if not self.modes or not set(self.modes) <= set(MODES) or len(set(self.modes)) < len(self.modes):
            raise ValueError(f"--modes must be one or more of {', '.join(MODES)}, each once, got {list(self.modes)}")
        check_output_file(self.out, "--out")


def solve_cold(scenario, cache, n_points):
    """A suite job: the scenario's front from the templates alone, warm-started from no neighbour."""
    from mpc.benchmark.pareto import pareto_front

    t0 = time.perf_counter()
    front = pareto_front(scenario=scenario, n_points=n_points, cache=cache, progress=log.debug, neighbour=False)
    return {**front.__dict__, "scenario": scenario.to_dict(), "solve_s": time.perf_counter() - t0}


def timed_suite(n: int, points: int, mode: str) -> dict[str, float]:
    ray = "local" if mode == "ray" else None
    job = "bench_suite:solve_cold" if mode == "cold" else "mpc.benchmark.suite:solve_one"
    with tempfile.TemporaryDirectory(prefix="wl-bench-") as cache:
        solve_suite("nominal", cache=cache, n_points=points, ray_address=ray, job=job)  # the chain's start (untimed)
        t0 = time.perf_counter()
        r = solve_suite("test", cache=cache, n_points=points, limit=n, ray_address=ray, job=job)
        wall = time.perf_counter() - t0
    per = r.per_scenario_s
    return {"scenarios": n, "wall_s": wall, "wall_per_scenario_s": wall / n, "front_median_s": statistics.median(per),
            "front_max_s": max(per), "failed": len(r.failed)}


def main(o: Options) -> dict[str, dict[str, float]]:
    out = {}
    for mode in o.modes:
        out[mode] = timed_suite(o.scenarios, o.points, mode)
        log.info(f"{mode}: {out[mode]}")
    for name, r in out.items():
        print(f"{name:6s} {r['scenarios']} scenarios x 2 brakings, {o.points} points: {r['wall_s']:.0f} s, "
              f"{r['wall_per_scenario_s']:.1f} s per scenario (both alternatives); one front median "
              f"{r['front_median_s']:.1f} s, max {r['front_max_s']:.1f} s; {r['failed']} failed")
    write_json_atomic(o.out, {"options": o.__dict__, **out})
    return out


if __name__ == "__main__":
    with cli_logging():  # the solves' progress, as before; run_script: a bad option as one line, exit 2
        run_script("bench_suite", lambda: main(tyro_options(Options)))
