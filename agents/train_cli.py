"""The command line of PPO training, shared by ``wl train`` and ``scripts/train_ppo.py``.

Every field of :class:`agents.ppo_config.PPOConfig` is a flag of the same name (``--total-timesteps``,
``--reward KEY=VALUE ...``), generated from the dataclass so that a new option needs no parser code.
Building the parser does not import torch; :func:`run_train` does. (Kept instead of tyro: the flags are
``wl train`` subcommand flags of the project's argparse CLI, and ``--reward KEY=VALUE`` and a bare
``--curriculum-start`` (curriculum off), which users' commands and the shipped policies' recorded
commands spell, have no tyro spelling.)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import io
import itertools
import json
import logging
import os
import shlex
import sys
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

from agents.ppo_config import MAX_EVAL_EPISODES, MAX_SEED, ConfigError, PPOConfig
from mpc import interrupt
from wl_env.atomic_io import check_output_folder

log = logging.getLogger(__name__)
T = TypeVar("T")

# options that only name the run: with --resume everything else comes from the run's saved config
RUN_NAMING = {"braking", "seed", "run_name", "log_dir", "progress_bar"}


def _parse_bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected a boolean, got {text!r}")


def _optional(convert: Callable[[str], Any]) -> Callable[[str], Any]:
    return lambda text: None if text.lower() == "none" else convert(text)


def _key_value(text: str) -> tuple[str, float]:
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected key=value, got {text!r}")
    try:
        return key.strip(), float(value)
    except ValueError:  # (argparse said "invalid _key_value value", naming neither the key nor what a value is)
        raise argparse.ArgumentTypeError(f"{key.strip()}: expected a number, got {text!r}") from None


def ray_address(text: str) -> str:
    """An argparse type: a Ray address (:func:`mpc.workers.is_ray_address`), checked before any work."""
    from mpc.workers import RAY_ADDRESS_FORMS, is_ray_address

    if not is_ray_address(text):
        raise argparse.ArgumentTypeError(f"must be {RAY_ADDRESS_FORMS}, got {text!r}")
    return text


@functools.cache
def _once(cls: type[argparse.Action]) -> type[argparse.Action]:
    """``cls`` that refuses to be given again with another value in one command line (:func:`refuse_repeated_options`)."""
    class Once(cls):  # type: ignore[valid-type, misc]
        def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                     option_string: str | None = None) -> None:
            given = namespace.__dict__.setdefault("_options_given", {})
            super().__call__(parser, namespace, values, option_string)
            value = getattr(namespace, self.dest, None)
            if self.dest in given and given[self.dest] != value:
                parser.error(f"argument {'/'.join(self.option_strings)}: given twice with different values (give "
                             f"each option once)")
            given[self.dest] = value

    return Once


def refuse_repeated_values(option: str, values: Iterable[Any] | None, what: str = "a value",
                           key: Callable[[Any], Any] | None = None) -> None:
    """A ``ValueError`` naming ``option`` if its list names one value twice (``key``: what makes two values the same,
    e.g. another spelling of one number or one path): the scripts ran each value's work twice and counted its rows
    twice in their summaries."""
    values = list(values or ())
    seen: dict[Any, list[Any]] = {}
    for v in values:
        seen.setdefault(v if key is None else key(v), []).append(v)
    repeated = [given for given in seen.values() if len(given) > 1]
    if repeated:
        shown = "; ".join(" and ".join(map(str, given)) for given in repeated)
        raise ValueError(f"{option} names {what} twice: {shown} (give each once)")


def refuse_repeated_options(parser: argparse.ArgumentParser) -> None:
    """Every option of ``parser`` and of its subcommands an error when given twice with different values: argparse
    kept the last one without a word (``--episodes 1 ... --episodes 100`` ran 100; ``--reward failure=1 --reward shaping=2`` dropped
    ``failure``; ``--score ... --no-score`` did not score)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in {id(p): p for p in action.choices.values()}.values():
                refuse_repeated_options(sub)
        elif action.option_strings and not isinstance(action, (argparse._HelpAction, argparse._VersionAction,
                                                              argparse._AppendAction, argparse._CountAction)):
            action.__class__ = _once(type(action))


def refuse_repeated_argv(argv: Sequence[str]) -> None:
    """A ``ValueError`` naming the first ``--option`` of ``argv`` given twice with different values, for parsers
    :func:`refuse_repeated_options` cannot reach (tyro's; one built inside a library): they keep the last one without a
    word. The values compared are the words up to the next ``--option`` (``--x=v`` is ``--x v``, ``--no-x`` is ``--x``
    turned off, ``_`` is ``-``); a bare ``--`` ends the options."""
    given: dict[str, tuple[str, ...]] = {}
    name, values = None, []
    for word in [*argv, "--"]:
        if word.startswith("--"):
            if name is not None:
                if name in given and given[name] != tuple(values):
                    raise ValueError(f"argument --{name}: given twice with different values (give each option once)")
                given[name] = tuple(values)
            if word == "--":
                return
            name, sep, value = word[2:].replace("_", "-").partition("=")
            values = [value] if sep else []
            if name.startswith("no-") and not sep:  # (tyro's --no-x of a bool --x)
                name, values = name[3:], ["\0off"]
        elif name is not None:
            values.append(word)


def tyro_options(cls: type[T], args: Sequence[str] | None = None) -> T:
    """``tyro.cli(cls, args=args)`` whose errors are a ``ValueError`` of one line (tyro draws a multi-line box; under
    :func:`wl_env.logs.run_script` it becomes ``name: error: ...``, exit 2), an option given twice with different
    values among them (:func:`refuse_repeated_argv`). ``--help`` prints and exits as before."""
    import tyro

    argv = list(sys.argv[1:] if args is None else args)
    refuse_repeated_argv(argv)
    captured, columns = io.StringIO(), os.environ.get("COLUMNS")
    if not {"-h", "--help"} & set(argv):  # (tyro wraps its error box to the terminal: a message of one line stays one)
        os.environ["COLUMNS"] = "100000"
    try:
        with contextlib.redirect_stderr(captured):
            options = tyro.cli(cls, args=argv)
    except SystemExit as exc:
        if exc.code in (0, None):  # (--help)
            sys.stderr.write(captured.getvalue())
            raise
        lines = [line.strip(" │╭╮╰╯") for line in captured.getvalue().splitlines()]
        if lines and lines[0].startswith("─"):  # a box: its title, then the message down to the first rule
            lines = list(itertools.takewhile(lambda line: not line.startswith("─"), lines[1:]))
        raise ValueError(" ".join(" ".join(lines).split()) or f"bad options (exit status {exc.code})") from None
    finally:
        if columns is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = columns
    sys.stderr.write(captured.getvalue())  # (tyro's warnings, if any)
    return options


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


def config_from_args(cls: type, ns: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """The dataclass with the given flags applied over its defaults (flags not given keep the default),
    and the given flags."""
    hints, given = typing.get_type_hints(cls), {}
    for f in dataclasses.fields(cls):
        v = getattr(ns, f.name, None)
        if v is not None:
            if typing.get_origin(hints[f.name]) is dict:  # (KEY=VALUE pairs: a key given twice kept the last)
                values: dict[str, list[Any]] = {}
                for key, value in (v.items() if isinstance(v, dict) else v):
                    values.setdefault(key, []).append(value)
                twice = {k: vs for k, vs in values.items() if len(set(vs)) > 1}
                if twice:
                    k, vs = next(iter(twice.items()))
                    raise ValueError(f"--{f.name.replace('_', '-')} gives {k} twice ({' and '.join(f'{x:g}' for x in vs)}): "
                                     f"give each key once")
                v = dict(v)
            given[f.name] = v
    try:
        return cls(**given), given
    except ConfigError as exc:
        raise flag_error(exc) from None


def flag_error(exc: ConfigError) -> ValueError:
    """A PPOConfig field's error said as the flag of the same name the user typed (``--num-envs``, not
    ``PPOConfig.num_envs``)."""
    return ValueError(f"--{exc.field.replace('_', '-')} must be {exc.requirement}, got {exc.value!r}")


def _count(text: str, most: int | None = None) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0 or (most is not None and value > most):
        raise argparse.ArgumentTypeError(f"must be an integer >= 0{'' if most is None else f', at most {most}'}, "
                                         f"got {value}")
    return value


def _seed(text: str) -> int:
    """``--seeds``: each in PPOConfig.seed's range, said as this flag's (not as the field's, after the parse)."""
    return _count(text, MAX_SEED)


def _episodes(text: str) -> int:
    """``--export-episodes``: a count in [0, MAX_EVAL_EPISODES], checked before the training, not after it."""
    return _count(text, MAX_EVAL_EPISODES)


def add_train_args(parser: argparse.ArgumentParser) -> None:
    """The training options: every PPOConfig field, ``--resume``, ``--export PATH``, ``--export-episodes``."""
    add_dataclass_args(parser, PPOConfig)
    parser.add_argument("--resume", action="store_true", help="continue the run from its newest checkpoint")
    parser.add_argument("--export", metavar="PATH", default=None,
                        help="after training, ship the policy pickle-free as PATH.safetensors, PATH_vecnormalize.npz, "
                        "PATH.json")
    parser.add_argument("--export-episodes", type=_episodes, default=100,
                        help=f"evaluation episodes of --export, 0..{MAX_EVAL_EPISODES}")
    parser.add_argument("--seeds", type=_seed, nargs="+", default=None, metavar="SEED",
                        help="several runs, one per seed, each in <log-dir>/<run-name or ppo_<braking>>_s<seed>; a "
                        "finished run is skipped, an interrupted one resumed (agents.seeds)")
    parser.add_argument("--sweep", nargs="+", default=None, metavar="FIELD=V1,V2",
                        help="a hyperparameter grid: a run per combination (and per seed of --seeds)")
    parser.add_argument("--workers", type=_count, default=1,
                        help="with --seeds/--sweep: runs trained at once on this machine, each in its own process")
    parser.add_argument("--ray", nargs="?", const="local", default=None, type=ray_address, metavar="ADDRESS",
                        help="with --seeds/--sweep: run them as Ray tasks on the cluster at ADDRESS (no ADDRESS: a "
                        "local Ray instance); the run directories are the same")
    parser.add_argument("--cache", metavar="DIR", default=None,
                        help="cache folder of the Pareto front the evaluations are scored against (default "
                        "$WL_CACHE_DIR or ~/.cache/wheel-loader-gym); a front not cached there is solved first")


def run_train(ns: argparse.Namespace, command: str, prog: str) -> int:
    """Train (or resume) the run the parsed options describe, export it if asked; returns the exit code.

    ``command`` (the command line) is recorded in the run's config.json; ``prog`` is how the user called
    the trainer, for the hint that continues an interrupted run.
    """
    cfg, given = config_from_args(PPOConfig, ns)
    if "reward" in given:  # --reward overrides single fields; the other defaults stay
        cfg.reward = {**PPOConfig().reward, **cfg.reward}
    # output paths checked before the training, not after it
    check_output_folder(cfg.log_dir, f"--log-dir {cfg.log_dir}")
    if ns.export is not None:  # (each of its files: a pipe at PATH.json failed after the training)
        from agents.policy_files import check_policy_output

        check_policy_output(ns.export, "--export")
    if getattr(ns, "cache", None) is not None:
        check_output_folder(ns.cache, f"--cache {ns.cache}")
    if cfg.init_policy and not ns.resume:  # (its files read now: a missing one failed after the env's build)
        from agents.policy_files import PolicyFileError, read_policy
        from agents.ppo import _safe_stem

        try:
            stem = _safe_stem(Path(cfg.init_policy).expanduser())
            if stem is None:
                raise PolicyFileError("not a pickle-free policy (STEM.safetensors with its normalization and metadata)")
            read_policy(stem)
        except PolicyFileError as exc:
            raise ValueError(f"--init-policy {cfg.init_policy}: {exc}") from None
    if cfg.bc_demos and not ns.resume:  # (listed now, named by the option: a name too long for the system was
        from agents.imitation import demo_paths  # "[Errno 36] File name too long", naming none)

        demo_paths(cfg.bc_demos, "--bc-demos")
    if ns.resume and set(given) - RUN_NAMING:
        log.warning("--resume uses the run's saved config; options other than the run's name are ignored")
    from agents.ppo import export_policy, train
    from mpc.benchmark.pareto import CACHE_ENV

    # the trainer reads the front from the default cache (mpc.benchmark.pareto.cache_dir): point it there
    previous_cache = os.environ.get(CACHE_ENV)
    if getattr(ns, "cache", None):
        os.environ[CACHE_ENV] = str(ns.cache)
    many = bool(getattr(ns, "seeds", None) or getattr(ns, "sweep", None))
    if not many and (getattr(ns, "ray", None) or getattr(ns, "workers", 1) != 1):
        raise ValueError("--ray and --workers run several runs: give --seeds and/or --sweep")
    try:
        if many:
            return _run_many(cfg, ns, command, prog)
        from wl_env.atomic_io import remove_empty_folders

        fresh = [] if cfg.run_dir.exists() else [cfg.run_dir]
        try:
            summary = train(cfg, resume=ns.resume, command=command)
        except KeyboardInterrupt:
            remove_empty_folders(fresh)  # (an interrupt before its config.json left the new run's folder empty)
            if not (cfg.run_dir / "config.json").exists():  # (--resume said "nothing to resume", exit 2)
                log.info("\ninterrupted before the run was recorded; the same command starts it again")
                return interrupt.exit_code()
            log.info("\ninterrupted; continue with: %s --run-name %s --log-dir %s --resume", prog,
                     shlex.quote(cfg.name), shlex.quote(cfg.log_dir))
            return interrupt.exit_code()  # (130, or 143 for SIGTERM)
        print(json.dumps({k: summary[k] for k in ("num_timesteps", "wall_time", "last_eval")}, indent=2, default=str))
        if ns.export:
            meta = export_policy(cfg.run_dir, Path(ns.export).parent, Path(ns.export).name,
                                 n_episodes=ns.export_episodes, score=cfg.score)  # (--no-score: no front solved)
            print(json.dumps(meta["evaluation"], indent=2, default=str))
        return 0
    finally:
        if previous_cache is None:
            os.environ.pop(CACHE_ENV, None)
        else:
            os.environ[CACHE_ENV] = previous_cache


def _run_many(cfg: PPOConfig, ns: argparse.Namespace, command: str, prog: str) -> int:
    """``--seeds``/``--sweep``: every run (agents.seeds), then each exported as ``<--export>_<run name>``."""
    from agents.ppo import export_policy
    from agents.seeds import SUMMARY_FILE, expand, parse_sweep, train_runs
    from mpc.workers import check_workers

    check_workers(ns.workers, "--workers")
    if ns.ray is not None and ns.workers != 1:  # (the Ray tasks took no notice of it, without a word)
        raise ValueError("--workers sets the local processes; with --ray the cluster runs the trainings: give one of them")
    cfgs = expand(cfg, ns.seeds or [cfg.seed], parse_sweep(ns.sweep or []))
    if ns.export:  # (each run's export files, checked before the training: a folder in the way failed after all of it)
        from agents.policy_files import check_policy_output

        for c in cfgs:
            check_policy_output(run_export(ns.export, c), "--export")
    try:
        results = train_runs(cfgs, command=command, workers=ns.workers, ray_address=ns.ray)
    except KeyboardInterrupt:
        log.info("\ninterrupted; the same command resumes every run from its newest checkpoint")
        return interrupt.exit_code()
    print(json.dumps({name: {k: s.get(k) for k in ("num_timesteps", "wall_time")} for name, s in results.items()},
                     indent=2))
    log.info("spread over the seeds: %s", Path(cfg.log_dir) / SUMMARY_FILE)
    if ns.export:
        for c in cfgs:
            path = run_export(ns.export, c)
            export_policy(c.run_dir, path.parent, path.name, n_episodes=ns.export_episodes, score=c.score)
    return 0


def run_export(export: str, cfg: PPOConfig) -> Path:
    """The stem one of several runs is exported to: ``<--export>_<run name>``."""
    path = Path(export)
    return path.parent / f"{path.name}_{cfg.name}"
