"""Throughput of WheelLoader-v1 against Gymnasium's Pendulum-v1, measured in one run.

(a) single environment: ``step`` calls per second of ``gym.make("WheelLoader-v1")`` (braking "service"
    and "tc") and of ``gym.make("Pendulum-v1")``;
(b) vector environment: env-steps per second of ``gymnasium.make_vec("WheelLoader-v1", num_envs=N,
    vectorization_mode="vector_entry_point")`` for N = 1, 64, 1024, each compared with Pendulum-v1's
    single-env rate.

Actions are fixed uniform random numbers in the action space (seeded), pre-generated outside the timed
loop. Single envs are reset on termination/truncation; the resets are done but not timed (the timer
runs over each stretch of steps between resets). The vector env autoresets inside ``step``, so its
resets are part of its time. Each configuration is timed ``--repeats`` times, interleaved (rounds of
one timing of every configuration) so that background load hits them alike; the table shows medians,
by wall clock and by this process's CPU time (robust to other processes competing for the cores).
Usage::

    python scripts/bench_env.py                      # default sizes, ~30 s
    python scripts/bench_env.py --quick              # a smoke run
    python scripts/bench_env.py --json bench.json    # also write the raw numbers
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)
import wl_env  # noqa: E402, F401  (registers WheelLoader-v1)
from agents.train_cli import refuse_repeated_values  # noqa: E402

TARGET_SINGLE_RATIO = 0.5  # single WheelLoader-v1 >= 0.5 x Pendulum-v1's step rate
TARGET_VECTOR_RATE = 500_000.0  # env-steps/s of the vector env at N = 1024
TARGET_VECTOR_N = 1024
NOISY_SPREAD = 0.10  # (max - min) / median above this -> warn that the machine was noisy


def time_single(env: gym.Env, actions: np.ndarray, seed: int) -> tuple[float, float]:
    """(wall, CPU) seconds spent in ``env.step`` over ``len(actions)`` steps (resets not timed)."""
    env.reset(seed=seed)
    step = env.step
    wall = cpu = 0.0
    gc.collect()
    w0, c0 = time.perf_counter(), time.process_time()
    for a in actions:
        _, _, terminated, truncated, _ = step(a)
        if terminated or truncated:
            wall += time.perf_counter() - w0
            cpu += time.process_time() - c0
            env.reset()
            w0, c0 = time.perf_counter(), time.process_time()
    return wall + (time.perf_counter() - w0), cpu + (time.process_time() - c0)


def time_vector(venv: Any, actions: np.ndarray, seed: int) -> tuple[float, float]:
    """(wall, CPU) seconds for ``len(actions)`` calls of the vector env's ``step`` (autoresets included)."""
    venv.reset(seed=seed)
    step = venv.step
    gc.collect()
    w0, c0 = time.perf_counter(), time.process_time()
    for a in actions:
        step(a)
    return time.perf_counter() - w0, time.process_time() - c0


def spread(values: list[float]) -> float:
    """(max - min) / median."""
    return (max(values) - min(values)) / statistics.median(values)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--repeats", type=int, default=15, help="timed rounds (default 15)")
    ap.add_argument("--single-steps", type=int, default=5_000, help="single-env steps per round (default 5000)")
    ap.add_argument(
        "--vector-env-steps",
        type=int,
        default=100_000,
        help="vector env-steps per round: step calls = this / N, clamped to [50, 500] (default 100000)",
    )
    ap.add_argument("--num-envs", type=int, nargs="+", default=[1, 64, 1024], help="vector sizes (default 1 64 1024)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the actions and the resets")
    ap.add_argument("--quick", action="store_true", help="small sizes and 3 rounds (a smoke test, not a measurement)")
    ap.add_argument("--json", metavar="PATH", help="also write the raw timings and the summary as JSON")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args(argv)
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    for flag, value, hi in (("--repeats", args.repeats, 1000), ("--single-steps", args.single_steps, 10**7),
                            ("--vector-env-steps", args.vector_env_steps, 10**9)):
        # (10^11 single steps failed allocating 745 GiB of actions, in a traceback)
        if not 1 <= value <= hi:
            ap.error(f"{flag} must be an integer in [1, {hi}], got {value}")
    if min(args.num_envs) < 1:
        ap.error("--num-envs must be >= 1")
    try:  # (a size given twice: its vector env built twice, one of them timed)
        refuse_repeated_values("--num-envs", args.num_envs, "a size")
    except ValueError as exc:
        ap.error(str(exc))
    if args.quick:  # (after the checks: a bad --repeats was not refused with --quick)
        args.repeats, args.single_steps, args.vector_env_steps = 3, 1_000, 10_000
    from wl_env.params import MAX_NUM_ENVS

    if max(args.num_envs) > MAX_NUM_ENVS:  # (the env refused it with a traceback)
        ap.error(f"--num-envs must be integers in [1, {MAX_NUM_ENVS}], got {max(args.num_envs)}")
    if not 0 <= args.seed < 2**32:
        ap.error(f"--seed must be an integer in [0, 2**32 - 1], got {args.seed}")

    rng = np.random.default_rng(args.seed)
    load_before = os.getloadavg()

    # ---- configurations: name -> (callable timing one round, env-steps per round)
    singles = {
        "Pendulum-v1": gym.make("Pendulum-v1"),
        "WheelLoader-v1 (service)": gym.make("WheelLoader-v1", braking="service"),
        "WheelLoader-v1 (tc)": gym.make("WheelLoader-v1", braking="tc"),
    }
    runs: dict[str, tuple[Any, int]] = {}
    for name, env in singles.items():
        space = env.action_space
        acts = rng.uniform(space.low, space.high, (args.single_steps, *space.shape)).astype(space.dtype)
        runs[name] = (lambda env=env, acts=acts: time_single(env, acts, args.seed), args.single_steps)
    vectors = {}
    for n in args.num_envs:
        venv = gym.make_vec("WheelLoader-v1", num_envs=n, vectorization_mode="vector_entry_point")
        steps = min(500, max(50, args.vector_env_steps // n))  # N = 1 is slow per env-step
        acts = rng.uniform(-1.0, 1.0, (steps, n, 4)).astype(np.float32)
        name = f"WheelLoader-v1 vector N={n}"
        vectors[name] = venv
        runs[name] = (lambda venv=venv, acts=acts: time_vector(venv, acts, args.seed), steps * n)

    # ---- warm-up (first-call costs), then rounds that time every configuration once, interleaved
    for fn, _ in runs.values():
        fn()
    rates: dict[str, dict[str, list[float]]] = {name: {"wall": [], "cpu": []} for name in runs}
    for k in range(args.repeats):
        for name, (fn, env_steps) in runs.items():
            wall, cpu = fn()
            rates[name]["wall"].append(env_steps / wall)
            rates[name]["cpu"].append(env_steps / cpu)
        print(f"  round {k + 1}/{args.repeats} done", file=sys.stderr)
    load_after = os.getloadavg()

    # ---- summary
    ref = "Pendulum-v1"
    rows = []
    for name, r in rates.items():
        row: dict[str, Any] = {"config": name}
        for clock in ("wall", "cpu"):
            med = statistics.median(r[clock])
            row[clock] = {
                "median_env_steps_per_s": med,
                "median_us_per_env_step": 1e6 / med,
                "ratio_to_pendulum": med / statistics.median(rates[ref][clock]),
                "spread": spread(r[clock]),
                "rates": r[clock],
            }
        rows.append(row)
    by_name = {row["config"]: row for row in rows}
    checks = {
        f"single env >= {TARGET_SINGLE_RATIO} x Pendulum-v1": all(
            by_name[n]["wall"]["ratio_to_pendulum"] >= TARGET_SINGLE_RATIO for n in singles if n != ref
        ),
    }
    vec = f"WheelLoader-v1 vector N={TARGET_VECTOR_N}"
    if vec in by_name:
        checks[f"vector N={TARGET_VECTOR_N} >= {TARGET_VECTOR_RATE:,.0f} env-steps/s"] = (
            by_name[vec]["wall"]["median_env_steps_per_s"] >= TARGET_VECTOR_RATE
        )
    noisy = [row["config"] for row in rows if row["wall"]["spread"] > NOISY_SPREAD]

    print()
    print(
        f"Python {platform.python_version()}, numpy {np.__version__}, gymnasium {gym.__version__}, "
        f"{os.cpu_count()} CPUs, {args.repeats} rounds, load average {load_before[0]:.2f} -> {load_after[0]:.2f}"
    )
    print()
    print(
        "| configuration | env-steps/s | us/env-step | x Pendulum-v1 | spread | us/env-step (CPU) | x Pendulum-v1 (CPU) | spread (CPU) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        w, c = row["wall"], row["cpu"]
        print(
            f"| {row['config']} | {w['median_env_steps_per_s']:,.0f} | {w['median_us_per_env_step']:.2f} | "
            f"{w['ratio_to_pendulum']:.2f} | {100 * w['spread']:.0f} % | {c['median_us_per_env_step']:.2f} | "
            f"{c['ratio_to_pendulum']:.2f} | {100 * c['spread']:.0f} % |"
        )
    print()
    print(
        "Medians over the rounds; x Pendulum-v1 = median rate / Pendulum-v1's median single-env rate; spread = "
        "(max - min) / median. The first columns use wall-clock time, the (CPU) ones this process's CPU time, "
        "which other processes on the machine disturb much less."
    )
    for name, ok in checks.items():
        print(f"target {name} (wall clock): {'met' if ok else 'NOT met'}")
    if noisy:
        print(
            f"WARNING: large wall-clock spread (> {100 * NOISY_SPREAD:.0f} %) for {', '.join(noisy)}. The machine was "
            f"noisy ({os.cpu_count()} CPUs, load average up to {max(load_before[0], load_after[0]):.2f}: other processes, "
            "e.g. an optimization run, were competing for the cores). Prefer the ratios and the CPU-time columns."
        )

    if args.json:
        out = {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "gymnasium": gym.__version__,
            "cpus": os.cpu_count(),
            "argv": sys.argv,
            "args": vars(args),
            "load_average_before_after": [load_before[0], load_after[0]],
            "results": rows,
            "targets_wall_clock": checks,
            "noisy": noisy,
        }
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"wrote {args.json}")
    for env in singles.values():
        env.close()
    for venv in vectors.values():
        venv.close()
    return 0


if __name__ == "__main__":
    from wl_env.logs import run_script

    run_script("bench_env", lambda: sys.exit(main()))  # (Ctrl-C: exit 130, no traceback)
