"""Several PPO runs: seeds and hyperparameter sweeps, on this machine or on a Ray cluster (``wl train --seeds``).

:func:`expand` turns one :class:`~agents.ppo_config.PPOConfig` into a run per (sweep point, seed), each
in its own run directory ``<log_dir>/<base>[_<field><value>...]_s<seed>``, the layout of a single run.
:func:`train_runs` trains them: one after another here, in ``workers`` processes at once, or as Ray tasks
(``ray_address``; ``"local"`` starts a Ray instance on this machine) writing to the same folders (a shared
filesystem on a cluster). A finished run is skipped, an interrupted one resumes from its newest
checkpoint, so a killed sweep rerun with the same command loses at most a checkpoint interval per run.
:func:`spread` gives each metric's median and interquartile range over the runs of a sweep point.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agents.ppo_config import MAX_RUN_JSON_BYTES, PPOConfig
from wl_env.atomic_io import read_regular_file

log = logging.getLogger(__name__)

SUMMARY_FILE = "runs_summary.json"  # in log_dir: every run's last evaluation and the spread over seeds


def parse_sweep(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["learning_rate=1e-4,3e-4", "n_epochs=5,10"]`` as ``{field: [values]}``; each value is parsed as
    the field's default is typed (ValueError naming the field otherwise)."""
    fields = {f.name: f for f in dataclasses.fields(PPOConfig)}
    sweep: dict[str, list[Any]] = {}
    for item in items:
        name, sep, values = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not values.strip():
            raise ValueError(f"--sweep expects FIELD=V1,V2,..., got {item!r}")
        if name not in fields or name in ("seed", "run_name", "log_dir"):
            raise ValueError(f"--sweep {name}: not a PPOConfig field that can be swept")
        if name in sweep:
            raise ValueError(f"--sweep {name} is given twice: give its values once, FIELD=V1,V2,...")
        default = getattr(PPOConfig(), name)
        kind = type(default) if default is not None else float
        if kind in (dict, tuple, list):
            raise ValueError(f"--sweep {name}: only fields with a single value (number, text, flag) can be swept")
        optional = "None" in str(fields[name].type)  # (target_kl, log_std_final: "none" is off, as their flags take it)
        parsed = []
        for text in values.split(","):
            text = text.strip()
            try:
                parsed.append(None if optional and text.lower() == "none" else
                              {"true": True, "false": False}[text.lower()] if kind is bool else kind(text))
            except (KeyError, ValueError):
                raise ValueError(f"--sweep {name}: {text!r} is not a {kind.__name__}") from None
        if len(set(parsed)) != len(parsed):
            raise ValueError(f"--sweep {name}: a value repeats in {values.strip()!r}")
        sweep[name] = parsed
    return sweep


def expand(cfg: PPOConfig, seeds: Sequence[int], sweep: dict[str, list[Any]] | None = None) -> list[PPOConfig]:
    """One config per sweep point and seed, each with its own run name (validated as PPOConfig is)."""
    if not seeds:
        raise ValueError("seeds is empty: give at least one seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds repeat: {list(seeds)}")
    base = cfg.run_name or f"ppo_{cfg.braking}"
    names = list((sweep or {}).keys())
    out, tagged = [], {}
    for point in itertools.product(*[(sweep or {})[n] for n in names]):
        tag = "".join(f"_{n}{v:g}" if isinstance(v, float) else f"_{n}{v}" for n, v in zip(names, point, strict=True))
        if tag in tagged:  # (train_runs then refused "two runs share a name", naming no --sweep value)
            a, b = (", ".join(f"{n}={v}" for n, v in zip(names, p, strict=True)) for p in (tagged[tag], point))
            raise ValueError(f"--sweep {a} and {b} would share the run name {base}{tag}_s<seed>: a run's name shows a "
                             f"number to 6 significant digits: give values that differ within their first 6")
        tagged[tag] = point
        for seed in seeds:
            d = {**cfg.to_dict(), **dict(zip(names, point, strict=True)), "seed": int(seed),
                 "run_name": f"{base}{tag}_s{seed}"}
            try:
                out.append(PPOConfig.from_dict(d))
            except ValueError as exc:  # (a swept value out of its field's range: said as the --sweep point)
                if not names:
                    raise
                point_text = ", ".join(f"{n}={v}" for n, v in zip(names, point, strict=True))
                raise ValueError(f"--sweep {point_text}: {exc}") from None
    return out


def run_state(cfg: PPOConfig) -> str:
    """``"done"`` (final/summary.json), ``"started"`` (a checkpoint on disk) or ``"new"`` (a run stopped before
    its first checkpoint starts again with the config given now, not the one it saved)."""
    from agents.ppo import latest_checkpoint

    if (cfg.run_dir / "final" / "summary.json").exists():
        return "done"
    return "started" if latest_checkpoint(cfg.run_dir) is not None else "new"


def train_one(cfg_dict: dict[str, Any], command: str | None = None) -> dict[str, Any]:
    """Train (or resume, or just read back) one run; its summary. Plain data in and out: a worker's or a
    Ray task's entry point."""
    from agents.ppo import read_run_config, train

    cfg = PPOConfig.from_dict(cfg_dict)
    state = run_state(cfg)
    if state != "new":  # (a run on disk is taken as this one only if it was made with the same settings)
        saved, _ = read_run_config(cfg.run_dir / "config.json")
        # (how it shows and threads, not what it learns; and where its folder is: the same folder spelled otherwise,
        # relative or with a trailing slash, was "other settings", refusing its read-back and its resume)
        ignored = {"progress_bar", "torch_threads", "log_dir"}
        differ = sorted(k for k, v in cfg.to_dict().items() if k not in ignored and saved.to_dict().get(k) != v)
        if differ:
            then = "read it back" if state == "done" else "resume it"
            raise ValueError(f"{cfg.run_dir} holds a run made with other settings ({', '.join(differ)}): give another "
                             f"--log-dir or --run-name, or the same settings to {then}")
    if state == "done":
        return read_summary(cfg.run_dir / "final" / "summary.json")
    return train(cfg, resume=state == "started", command=command)


def train_chain(cfg_dicts: Sequence[dict[str, Any]], commands: Sequence[str | None]) -> list[dict[str, Any]]:
    """Runs one after another, each (as a rule) starting from the one before's policy: a staged recipe
    (scripts/train_plan_policy.py); :func:`train_one` each, so finished ones are read back and a started one resumes.
    Plain data in and out: a Ray task's entry point."""
    return [train_one(c, command) for c, command in zip(cfg_dicts, commands, strict=True)]


def read_summary(path: Path) -> dict[str, Any]:
    """A finished run's summary.json, checked for what :func:`spread` reads (ValueError naming the file): a
    corrupt or tampered one was returned as it was, and failed later without a name or counted a wrong number."""
    try:
        # (a regular file, bounded: a FIFO in its place hung the read-back of a finished run for good)
        summary = json.loads(read_regular_file(path, MAX_RUN_JSON_BYTES, "a run summary holds"))
        if not isinstance(summary, dict):
            raise ValueError(f"a JSON {type(summary).__name__}, not an object")
        step, wall, last = summary.get("num_timesteps"), summary.get("wall_time"), summary.get("last_eval")
        if type(step) is not int or step < 0:
            raise ValueError(f"num_timesteps must be an integer >= 0, got {step!r}"[:200])
        if type(wall) not in (int, float) or not (math.isfinite(wall) and wall >= 0):
            raise ValueError(f"wall_time must be a finite number of seconds >= 0, got {wall!r}"[:200])
        if last is not None and not isinstance(last, dict):
            raise ValueError(f"last_eval must be an object of metrics or null, got {type(last).__name__}")
        for m in METRICS:  # (NaN is a metric not measured; True was counted as 1, 10**400 raised OverflowError)
            v = (last or {}).get(m)
            if v is not None and (type(v) not in (int, float) or abs(v) > 1e300):
                raise ValueError(f"last_eval.{m} must be a number or null, got {v!r}"[:200])
        return summary
    except (OSError, ValueError, TypeError, OverflowError, RecursionError) as exc:
        raise ValueError(f"{path} is not a readable run summary: {' '.join(str(exc).split())[:300]}") from None


def train_runs(cfgs: Sequence[PPOConfig], command: str | None = None, workers: int = 1,
               ray_address: str | None = None) -> dict[str, dict[str, Any]]:
    """Train every run (skipping finished ones, resuming started ones); ``{run name: summary}``.

    Writes ``<log_dir>/runs_summary.json`` (:func:`spread`) once all are done. KeyboardInterrupt stops
    every run; each resumes from its newest checkpoint when the same command is run again.
    """
    from mpc.workers import check_workers

    check_workers(workers)
    names = [c.name for c in cfgs]
    if len(set(names)) != len(names):
        raise ValueError(f"two runs share a name: {names}")
    for c in cfgs:
        log.info("%s: %s", c.name, run_state(c))
    fresh = [c.run_dir for c in cfgs if not c.run_dir.exists()]
    try:
        if ray_address is not None:
            results = on_ray({c.name: (train_one, (c.to_dict(), command)) for c in cfgs}, ray_address)
        elif workers > 1:
            from mpc.workers import run_in_workers

            results = {}
            for i in range(0, len(cfgs), workers):  # ``workers`` runs at a time, each in its own process
                batch = cfgs[i:i + workers]
                results.update(run_in_workers({c.name: ("agents.seeds:train_one", (c.to_dict(), command))
                                               for c in batch}, log_level=logging.INFO))
        else:
            results = {c.name: train_one(c.to_dict(), command) for c in cfgs}
    except KeyboardInterrupt:  # (a run stopped before its config.json left its new folder empty: `--ray` at 35 s)
        from wl_env.atomic_io import remove_empty_folders

        remove_empty_folders(fresh)
        raise
    from wl_env.atomic_io import write_json_atomic

    for d in {c.log_dir for c in cfgs}:
        mine = [c for c in cfgs if c.log_dir == d]
        write_json_atomic(Path(d) / SUMMARY_FILE, spread(mine, results), indent=2, nan_as_null=True)
    return results


def on_ray(jobs: dict[str, tuple[Any, tuple]], address: str) -> dict[str, Any]:
    """``{name: (function, arguments)}`` as Ray tasks (one CPU each; the functions write to their run
    directories); ``{name: result}``. Ctrl-C cancels the tasks still running."""
    from mpc.workers import ray_session

    with ray_session(address) as ray:
        refs = {ray.remote(num_cpus=1, max_retries=0)(fn).remote(*args): name for name, (fn, args) in jobs.items()}
        results: dict[str, Any] = {}
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                results[refs[ready[0]]] = ray.get(ready[0])
                log.info("%s: done (%d of %d)", refs[ready[0]], len(results), len(refs))
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        except ray.exceptions.RayTaskError as exc:  # a run failed: the others stop, as local workers do
            for ref in pending:
                ray.cancel(ref, force=True)
            cause = getattr(exc, "cause", None)
            if isinstance(cause, Exception):  # (the run's own error: one line, not Ray's coloured traceback)
                raise cause from None
            raise
        return results


METRICS = ("success_rate", "time_gap", "fuel_gap", "lateness_median", "fuel_gap_median", "time_gap_fastest",
           "mean_return", "max_violation")


def quartiles(values: Sequence[float]) -> dict[str, float] | None:
    """Median, 25th and 75th percentile and count of the finite values (None if there are none)."""
    v = [float(x) for x in values if x is not None and math.isfinite(x)]
    if not v:
        return None
    return {"median": float(np.median(v)), "q25": float(np.percentile(v, 25)), "q75": float(np.percentile(v, 75)),
            "n": len(v)}


def spread(cfgs: Sequence[PPOConfig], results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per sweep point (the runs that differ only in their seed): the seeds, and each metric of the runs' last
    evaluations as median, 25th and 75th percentile (``n`` says over how many runs)."""
    groups: dict[str, list[PPOConfig]] = {}
    for c in cfgs:
        groups.setdefault(c.name.rsplit("_s", 1)[0], []).append(c)
    out: dict[str, Any] = {"runs": {}, "points": {}}
    for point, members in groups.items():
        evals = []
        for c in members:
            summary = results.get(c.name, {})
            last = summary.get("last_eval") or {}
            out["runs"][c.name] = {"seed": c.seed, "num_timesteps": summary.get("num_timesteps"),
                                   "wall_time_s": summary.get("wall_time"), "last_eval": last}
            evals.append(last)
        stats = {m: quartiles([e[m] for e in evals if isinstance(e.get(m), (int, float))]) for m in METRICS}
        out["points"][point] = {"seeds": [c.seed for c in members], **stats}
    return out
