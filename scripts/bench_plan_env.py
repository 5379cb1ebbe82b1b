"""Throughput of ``WheelLoaderPlan-v1`` as PPO sees it (the stable-baselines3 vector env) against the number of loaders
stepped together, with Gymnasium's Pendulum-v1 measured in the same run as the reference.

    python scripts/bench_plan_env.py [--num-envs 256 1024 2048 4096] [--rounds 3] [--json PATH]

One plan env step drives a whole cycle per loader, ~80-400 WheelLoaderTarget-v7 steps, all loaders together
until the slowest has ended; each v6 step is a handful of numpy operations on arrays of N loaders, so its cost
barely grows with N. The plans are fixed uniform random numbers (seeded); each configuration is timed once per
round, the rounds interleaved, and the table gives the medians: cycles/s, v6 steps/s (the cycles' own steps) and
v6 steps/s against Pendulum-v1's single-env steps/s.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from agents.train_cli import tyro_options
from wl_env.atomic_io import check_output_file, write_json_atomic
from wl_env.logs import run_script


@dataclass
class Options:
    num_envs: tuple[int, ...] = (256, 1024, 2048, 4096)  # loaders stepped together
    braking: str = "service"
    calls: int = 3  # plan env steps (cycles per loader) per timing
    rounds: int = 3  # timings per configuration, interleaved
    pendulum_steps: int = 20_000  # Pendulum-v1 steps per timing
    seed: int = 0
    json: Path | None = None


@dataclass
class Row:
    """One configuration's medians over the rounds."""

    num_envs: int
    cycles_per_s: float
    v6_steps_per_s: float
    x_pendulum: float  # v6 steps/s over Pendulum-v1's steps/s
    ms_per_call: float  # one plan env step of all loaders (a cycle each, with the finished loaders' resets)


def check(o: Options) -> None:
    """ValueError naming the option and its range."""
    from wl_env.cycle import check_braking
    from wl_env.params import MAX_NUM_ENVS

    check_braking(o.braking)
    if not o.num_envs or not all(1 <= n <= MAX_NUM_ENVS for n in o.num_envs):
        raise ValueError(f"--num-envs must be integers in [1, {MAX_NUM_ENVS}], got {o.num_envs}")
    for name, lo, hi in (("calls", 1, 1000), ("rounds", 1, 100), ("pendulum_steps", 1, 10**7), ("seed", 0, 2**31 - 1)):
        if not lo <= getattr(o, name) <= hi:
            raise ValueError(f"--{name.replace('_', '-')} must be an integer in [{lo}, {hi}], got {getattr(o, name)}")


def main(o: Options) -> list[Row]:
    check(o)
    if o.json is not None:
        check_output_file(o.json, "--json")
    import gymnasium as gym

    from agents.sb3_vec import make_sb3_vec_env
    from wl_env.plan import N_PLAN_ACTIONS

    rng = np.random.default_rng(o.seed)
    envs = {n: make_sb3_vec_env(n, braking=o.braking, seed=o.seed, env_id="WheelLoaderPlan-v1", scenario="train")
            for n in o.num_envs}
    plans = {n: rng.uniform(-1, 1, (o.calls, n, N_PLAN_ACTIONS)).astype(np.float32) for n in o.num_envs}
    pendulum = gym.make("Pendulum-v1")
    torques = rng.uniform(-2, 2, (o.pendulum_steps, 1)).astype(np.float32)

    def time_plan(n: int) -> tuple[float, int]:
        env = envs[n]
        env.seed(o.seed)
        env.reset()
        steps = 0
        t0 = time.perf_counter()
        for a in plans[n]:
            env.step_async(a)
            _, _, _, infos = env.step_wait()
            steps += sum(int(i["steps"]) for i in infos)
        return time.perf_counter() - t0, steps

    def time_pendulum() -> float:
        pendulum.reset(seed=o.seed)
        t0 = time.perf_counter()
        for u in torques:  # (Pendulum-v1 never terminates; its 200-step truncation is not reset here)
            pendulum.step(u)
        return time.perf_counter() - t0

    samples: dict[int, list[tuple[float, int]]] = {n: [] for n in o.num_envs}
    ref: list[float] = []
    for _ in range(o.rounds):
        ref.append(o.pendulum_steps / time_pendulum())
        for n in o.num_envs:
            samples[n].append(time_plan(n))
    pendulum_rate = statistics.median(ref)
    rows = []
    print(f"Pendulum-v1: {pendulum_rate:,.0f} steps/s (median of {o.rounds})")
    print("| loaders | cycles/s | v6 steps/s | x Pendulum-v1 | ms per plan env step |")
    print("|---:|---:|---:|---:|---:|")
    for n in o.num_envs:
        wall = statistics.median(s[0] for s in samples[n])
        steps = statistics.median(s[1] / s[0] for s in samples[n])
        row = Row(n, o.calls * n / wall, steps, steps / pendulum_rate, 1e3 * wall / o.calls)
        rows.append(row)
        print(f"| {n} | {row.cycles_per_s:,.0f} | {row.v6_steps_per_s:,.0f} | {row.x_pendulum:.2f} | {row.ms_per_call:,.0f} |")
    if o.json is not None:
        write_json_atomic(o.json, {"options": asdict(o), "pendulum_steps_per_s": pendulum_rate,
                                   "rows": [asdict(r) for r in rows]})
    return rows


if __name__ == "__main__":
    run_script("bench_plan_env", lambda: main(tyro_options(Options)))
