"""How close the plan driver of ``WheelLoaderPlan-v1`` (or ``-v0``, ``--env-id``) can come to the optimum: its 14 numbers searched per
scenario and target by CMA-ES (pycma), nothing learned. A policy over the scenarios can only approach this.

    python scripts/bench_plan_ceiling.py --braking service --scenarios 0 1 2 3 --ratios 1.0 1.15 1.5 [--json PATH]

Each search runs ``--generations`` generations of ``--population`` cycles on the plan's vector env with the
scenario fixed (the ``test`` suite's i-th of the braking) and its target the ratio times the scenario's
T_min (its shipped optimum). A plan's cost is the fuel (g) plus ``--late-cost`` g per 1 % of lateness; a
failed or violating cycle costs 10^4. The best plan's cycle is scored against the scenario's own optimum at
its cycle time (the one scoring of the project).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from agents.train_cli import refuse_repeated_values, tyro_options
from wl_env.atomic_io import check_output_file, write_json_atomic
from wl_env.logs import run_script

CMA_MAX_SEED = 2**32 - 1  # the largest seed pycma takes (numpy's legacy seeding)


@dataclass
class Options:
    braking: str = "service"
    env_id: str = "WheelLoaderPlan-v1"  # the plan env searched (v0: on WheelLoaderTarget-v6, stops 53-55's ceilings)
    scenarios: tuple[int, ...] = (0, 1, 2, 3)  # indices among the test suite's scenarios of the braking
    ratios: tuple[float, ...] = (1.0, 1.15, 1.5)  # target / T_min
    generations: int = 150
    population: int = 32
    late_cost: float = 30.0  # g per 1 % of lateness
    seed: int = 1
    json: Path | None = None


@dataclass
class Ceiling:
    """The best plan found for one scenario and target."""

    scenario: int
    ratio: float
    target_time: float  # s
    T: float  # s
    fuel_g: float
    fuel_gap: float | None  # against the optimum at T (None: no plan completed the cycle)
    lateness: float | None
    search_s: float
    plan: list[float] = field(default_factory=list)


def search(o: Options, index: int, ratio: float) -> Ceiling:
    import cma
    import gymnasium as gym

    import wl_env  # noqa: F401
    from mpc.benchmark.reference import min_time_of
    from mpc.benchmark.scoring import score_run
    from wl_env.plan import N_PLAN_ACTIONS
    from wl_env.suites import load_suite

    scenario = load_suite("test").of(o.braking)[index]
    env = gym.make_vec(o.env_id, num_envs=o.population, vectorization_mode="vector_entry_point",
                       braking=o.braking, scenario=scenario)
    native = env.unwrapped
    params = scenario.params(native.machine)
    target = ratio * min_time_of(o.braking, params, solve=False)
    es = cma.CMAEvolutionStrategy(np.zeros(N_PLAN_ACTIONS), 0.5, {"bounds": [-1, 1], "popsize": o.population,
                                                                 "verbose": -9, "seed": o.seed})
    best: tuple[float, np.ndarray, float, float] | None = None
    t0 = time.perf_counter()
    for _ in range(o.generations):
        plans = np.array(es.ask())
        env.reset(seed=0)
        native.target_time[:] = target  # (the env draws its target from the estimate: the optimum's is set)
        _, _, _, _, info = env.step(plans)
        late = np.maximum(info["t"] - target, 0.0) / target
        ok = info["is_success"] & (info["violation"] <= 0.0)
        cost = np.where(ok, info["fuel_g"] + o.late_cost * 100.0 * late, 1e4)
        es.tell(list(plans), list(cost))
        j = int(np.argmin(cost))
        if ok[j] and (best is None or cost[j] < best[0]):
            best = (float(cost[j]), plans[j].copy(), float(info["t"][j]), float(info["fuel_g"][j]))
    took = time.perf_counter() - t0
    if best is None:
        return Ceiling(index, ratio, target, float("nan"), float("nan"), None, None, took)
    _, plan, T, fuel = best
    score = score_run(T, fuel, o.braking, params=params, solve=False)
    return Ceiling(index, ratio, target, T, fuel, score.fuel_gap, max(T - target, 0.0) / target, took,
                   [round(float(v), 4) for v in plan])


def check(o: Options) -> None:
    """ValueError naming the option and its range (before any search)."""
    from wl_env.cycle import check_braking
    from wl_env.suites import load_suite

    check_braking(o.braking)
    n = len(load_suite("test").of(o.braking))
    if not o.scenarios or not all(0 <= i < n for i in o.scenarios):
        raise ValueError(f"--scenarios must be indices in [0, {n - 1}] (the test suite's {o.braking} cycles), got {o.scenarios}")
    from wl_env.plan import driven_on

    driven_on(o.env_id, "--env-id")
    if not o.ratios or not all(1.0 <= r <= 3.0 for r in o.ratios):
        raise ValueError(f"--ratios must be target ratios to T_min in [1, 3], got {o.ratios}")
    refuse_repeated_values("--scenarios", o.scenarios, "a scenario")  # (each searched twice, its rows twice)
    refuse_repeated_values("--ratios", o.ratios, "a ratio")
    for name, lo, hi in (("generations", 1, 10_000), ("population", 2, 4096)):
        if not lo <= getattr(o, name) <= hi:
            raise ValueError(f"--{name} must be an integer in [{lo}, {hi}], got {getattr(o, name)}")
    if isinstance(o.seed, bool) or not isinstance(o.seed, int) or not 1 <= o.seed <= CMA_MAX_SEED:
        # (pycma's seed: -1 or 2**32 failed at the first search, naming no option; 0 drew one from the clock)
        raise ValueError(f"--seed must be an integer in [1, 2**32 - 1] (CMA-ES's; pycma takes 0 for a seed from the "
                         f"clock: a search not repeatable), got {o.seed!r}")
    if not 0.0 <= o.late_cost < float("inf"):
        raise ValueError(f"--late-cost must be a finite number >= 0 (g per 1 % of lateness), got {o.late_cost}")


def main(o: Options) -> list[Ceiling]:
    check(o)
    if o.json is not None:
        check_output_file(o.json, "--json")
    rows = []
    for index in o.scenarios:
        for ratio in o.ratios:
            c = search(o, index, ratio)
            rows.append(c)
            gap = "-" if c.fuel_gap is None else f"{100 * c.fuel_gap:+.1f} %"
            late = "-" if c.lateness is None else f"{100 * c.lateness:.1f} %"
            print(f"{o.braking} test[{index}] at {ratio:g} T_min ({c.target_time:.2f} s): T {c.T:.2f} s, fuel "
                  f"{c.fuel_g:.1f} g, fuel gap {gap}, lateness {late} ({c.search_s:.0f} s)", flush=True)
    if o.json is not None:
        write_json_atomic(o.json, {"options": asdict(o), "rows": [asdict(r) for r in rows]})
    return rows


if __name__ == "__main__":
    run_script("bench_plan_ceiling", lambda: main(tyro_options(Options)))
