"""What the assist's guards cost in training throughput: env-steps per second of the native vector
``WheelLoaderTarget-v3`` to ``-v6`` (the same driver actions, uniform in [-1, 1], on ``train`` draws), with
Gymnasium's Pendulum-v1 (64 copies, sync) as the reference measured in the same run. Medians of ``--repeats``
rounds. Usage::

    python scripts/bench_assist_cost.py [--num-envs 64] [--steps 300] [--repeats 5] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402

import wl_env  # noqa: E402,F401  (registers the envs)
from wl_env.atomic_io import write_json_atomic  # noqa: E402

MAX_ENV_STEPS = 10**7  # --steps x --num-envs: a round's actions, drawn at once (float64, then float32: 48 bytes each)


def steps_per_second(venv: gym.vector.VectorEnv, actions: np.ndarray, repeats: int) -> float:
    """Median env-steps per second over ``repeats`` rounds of ``actions`` (steps, num_envs, n)."""
    venv.reset(seed=0)
    rates = []
    for _ in range(repeats):
        t = time.perf_counter()
        for a in actions:
            venv.step(a)
        rates.append(actions.shape[0] * actions.shape[1] / (time.perf_counter() - t))
    return float(np.median(rates))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", metavar="PATH")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    from wl_env.params import MAX_NUM_ENVS

    for name, lo, hi in (("num_envs", 1, MAX_NUM_ENVS), ("steps", 1, 10**6), ("repeats", 1, 1000)):
        if not lo <= getattr(args, name) <= hi:  # (--num-envs -1 failed with an IndexError, --repeats 0 likewise)
            ap.error(f"--{name.replace('_', '-')} must be an integer in [{lo}, {hi}], got {getattr(args, name)}")
    if args.steps * args.num_envs > MAX_ENV_STEPS:  # (each round's actions are drawn at once: 10^6 x 16384 asked numpy
        # for 131 GB, a MemoryError's traceback)
        ap.error(f"--steps x --num-envs must be at most {MAX_ENV_STEPS:,} env-steps per round (its actions are drawn "
                 f"beforehand, 48 bytes each), got {args.steps} x {args.num_envs} = {args.steps * args.num_envs:,}")
    rng = np.random.default_rng(0)
    n, steps = args.num_envs, args.steps
    pendulum = gym.make_vec("Pendulum-v1", num_envs=n, vectorization_mode="sync")
    rows = {"Pendulum-v1 (sync)": steps_per_second(pendulum, rng.uniform(-2, 2, (steps, n, 1)).astype(np.float32), args.repeats)}
    for braking in ("service", "tc"):
        actions = rng.uniform(-1, 1, (steps, n, 4)).astype(np.float32)
        for env_id in ("WheelLoaderTarget-v3", "WheelLoaderTarget-v4", "WheelLoaderTarget-v5", "WheelLoaderTarget-v6"):
            venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", braking=braking,
                                scenario="train")
            rows[f"{env_id} {braking}"] = steps_per_second(venv, actions, args.repeats)
    ref = rows["Pendulum-v1 (sync)"]
    for name, rate in rows.items():
        print(f"{name:32s} {rate:9.0f} env-steps/s  {rate / ref:5.2f}x Pendulum-v1")
    for braking in ("service", "tc"):
        v3, v4, v5, v6 = (rows[f"WheelLoaderTarget-v{k} {braking}"] for k in (3, 4, 5, 6))
        print(f"{braking}: v4 / v3 = {v4 / v3:.2f}, v5 / v4 = {v5 / v4:.2f}, v6 / v5 = {v6 / v5:.2f}")
    if args.json:
        write_json_atomic(args.json, {"num_envs": n, "steps": steps, "repeats": args.repeats, "steps_per_second": rows})


if __name__ == "__main__":
    from wl_env.logs import run_script

    run_script("bench_assist_cost", main)  # (Ctrl-C was a traceback; the JSON is written only at the end)
