"""Train a PPO policy for WheelLoader-v0 (stable-baselines3 on the native vector env).

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
so an interrupted run ends with the same step budget and appended logs. ``--export PATH`` copies the
final policy to ``PATH.zip`` + ``PATH_vecnormalize.pkl`` and writes ``PATH.json`` (command, seed,
steps, wall time, a fresh deterministic evaluation).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import types
import typing
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.ppo import PPOConfig, export_policy, train  # noqa: E402


def _parse_bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean, got {text!r}")


def _optional(convert):
    return lambda text: None if text.lower() == "none" else convert(text)


def _key_value(text: str) -> tuple[str, float]:
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected key=value, got {text!r}")
    return key.strip(), float(value)


def add_dataclass_args(parser: argparse.ArgumentParser, cls: type) -> None:
    """One flag per dataclass field (``--field-name``); the field's metadata["help"] is the help text.

    Handles bool (``--x/--no-x``), int, float, str, ``X | None`` (the word ``none``), ``tuple[int, ...]``
    (several values) and ``dict[str, float]`` (several ``key=value``).
    """
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp, flag = hints[f.name], "--" + f.name.replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        help_text = f"{f.metadata.get('help', '')} (default: {default})"
        args = typing.get_args(tp)
        origin = typing.get_origin(tp)
        if tp is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        elif origin in (typing.Union, types.UnionType) and type(None) in args:
            inner = next(a for a in args if a is not type(None))
            parser.add_argument(flag, type=_optional(inner), default=None, help=help_text)
        elif origin is tuple:
            parser.add_argument(flag, type=args[0], nargs="+", default=None, help=help_text)
        elif origin is dict:
            parser.add_argument(flag, type=_key_value, nargs="*", default=None, metavar="KEY=VALUE", help=help_text)
        else:
            parser.add_argument(flag, type=_parse_bool if tp is bool else tp, default=None, help=help_text)


def config_from_args(cls: type, ns: argparse.Namespace):
    """The dataclass with the given flags applied over its defaults (flags not given keep the default)."""
    hints, given = typing.get_type_hints(cls), {}
    for f in dataclasses.fields(cls):
        v = getattr(ns, f.name, None)
        if v is not None:
            given[f.name] = dict(v) if typing.get_origin(hints[f.name]) is dict else v
    return cls(**given), given


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataclass_args(parser, PPOConfig)
    parser.add_argument("--resume", action="store_true", help="continue the run from its newest checkpoint")
    parser.add_argument("--export", metavar="PATH", default=None,
                        help="after training, ship the policy as PATH.zip, PATH_vecnormalize.pkl, PATH.json")
    parser.add_argument("--export-episodes", type=int, default=100, help="evaluation episodes of --export")
    argv = sys.argv[1:] if argv is None else argv
    ns = parser.parse_args(argv)
    cfg, given = config_from_args(PPOConfig, ns)
    if "reward" in given:  # --reward overrides single fields; the other defaults stay
        cfg.reward = {**PPOConfig().reward, **cfg.reward}
    command = "python scripts/train_ppo.py " + " ".join(shlex.quote(a) for a in argv)
    if ns.resume and set(given) - {"braking", "seed", "run_name", "log_dir", "progress_bar"}:
        print("note: --resume uses the run's saved config; options other than the run's name are ignored",
              file=sys.stderr)

    try:
        summary = train(cfg, resume=ns.resume, command=command)
    except KeyboardInterrupt:
        print(f"\ninterrupted; continue with: python scripts/train_ppo.py --run-name {cfg.name} "
              f"--log-dir {cfg.log_dir} --resume", file=sys.stderr)
        return 130
    print(json.dumps({k: summary[k] for k in ("num_timesteps", "wall_time", "last_eval")}, indent=2, default=str))
    if ns.export:
        meta = export_policy(cfg.run_dir, Path(ns.export).parent, Path(ns.export).name, n_episodes=ns.export_episodes)
        print(json.dumps(meta["evaluation"], indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
