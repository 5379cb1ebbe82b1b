"""Train a PPO policy for WheelLoader-v1 (stable-baselines3 on the native vector env); the same as ``wl train``.

Every option is a field of ``agents.ppo.PPOConfig`` and a command-line flag of the same name
(``--reward KEY=VALUE ...`` overrides single RewardConfig fields; ``--curriculum-start`` without values
turns the curriculum off)::

    python scripts/train_ppo.py --braking tc                       # the shipped recipe (PPOConfig defaults)
    python scripts/train_ppo.py --braking tc --seed 1 --total-timesteps 2000000 --time-limit 1800
    python scripts/train_ppo.py --braking tc --reward target_distance=100 --w-time 4 --curriculum-start
    python scripts/train_ppo.py --braking tc --resume              # continue runs/ppo_tc_s0
    python scripts/train_ppo.py --braking tc --export agents/policies/ppo_tc
    tensorboard --logdir runs/                                    # learning curves

A run lives in ``runs/<run-name>/`` (config.json, tb/, eval.csv, checkpoints/, final/). Checkpoints
(model + optimizer, VecNormalize statistics, progress) are written atomically every
``--checkpoint-freq`` steps; ``--resume`` continues from the newest one with the run's saved config,
so an interrupted run ends with the same step budget and appended logs. ``--export PATH`` ships the
final policy pickle-free as ``PATH.safetensors`` + ``PATH_vecnormalize.npz`` + ``PATH.json`` (network,
command, seed, steps, wall time, a fresh deterministic evaluation).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.train_cli import add_train_args, refuse_repeated_options, run_train  # noqa: E402
from wl_env.logs import cli_logging  # noqa: E402

PROG = "python scripts/train_ppo.py"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_train_args(parser)
    refuse_repeated_options(parser)
    argv = sys.argv[1:] if argv is None else argv
    ns = parser.parse_args(argv)
    with cli_logging():
        try:
            return run_train(ns, command=f"{PROG} " + " ".join(shlex.quote(a) for a in argv), prog=PROG)
        except (ValueError, OSError) as exc:  # a bad option, named in the message: no traceback (as `wl train`)
            print(f"train_ppo: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:  # (before the training's own handler: reading the options, importing torch)
            print("train_ppo: interrupted", file=sys.stderr)
            return 130


if __name__ == "__main__":
    sys.exit(main())
