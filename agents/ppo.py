"""PPO agents for ``WheelLoader-v1`` (stable-baselines3), the logic behind ``wl train`` and ``scripts/train_ppo.py``.

* :class:`PPOConfig` - every option of a run (environment, reward, PPO hyperparameters, logging); it
  lives in :mod:`agents.ppo_config` (importable without torch) and the command line in :mod:`agents.train_cli`.
* :func:`make_env` - the native vector env as an SB3 ``VecEnv`` (:mod:`agents.sb3_vec`), with episode
  statistics (``VecMonitor``) and optional ``VecNormalize``.
* :func:`train` - trains one policy in a run directory, with periodic deterministic evaluations (logged
  to ``eval.csv`` and TensorBoard), atomic checkpoints and ``resume``.
* :func:`load_policy` - a trained policy as an object with ``act(obs) -> action`` (deterministic, with
  the saved observation normalization), e.g. for :func:`agents.operator.run_episode`; from the
  pickle-free files of :mod:`agents.policy_files`, or a stable-baselines3 zip only with ``trust_pickle``.
* :func:`export_policy` - a run's final policy shipped as pickle-free files with a fresh evaluation.
* :func:`evaluate` - the training-time evaluation: deterministic episodes through the project's one
  evaluation path (:func:`agents.evaluate.evaluate_controller`), as a row of the learning curve.

Run directory layout (``<log_dir>/<run_name>/``)::

    config.json                      the run's PPOConfig (``resume`` reads it back)
    tb/PPO_1/                        TensorBoard events (a resumed run appends to the same folder)
    eval.csv                         one row per evaluation (the learning curve)
    checkpoints/latest.json          points at the newest complete checkpoint
    checkpoints/step_<n>/            policy.safetensors, policy_vecnormalize.npz, policy.json, optimizer.safetensors,
                                     training.json, progress.json (pickle-free: :func:`save_checkpoint`)
    final/                           model.zip, vecnormalize.pkl, summary.json after the last step, and
                                     policy.safetensors, policy_vecnormalize.npz, policy.json (pickle-free)

Resuming reads only pickle-free files, so a run folder from anywhere can be resumed safely. ``final/model.zip``
is a stable-baselines3 zip (a pickle), loaded only with ``trust_pickle``; what is shipped or shared is the
pickle-free policy.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import logging
import math
import os
import pickle
import re
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.distributions import DiagGaussianDistribution, Distribution
from stable_baselines3.common.policies import ActorCriticPolicy

import wl_env  # noqa: F401  (registers WheelLoader-v1)
from agents.policy_files import (
    METADATA_SUFFIX,
    NORMALIZATION_SUFFIX,
    PICKLE_SUFFIXES,
    WEIGHTS_SUFFIX,
    ObsNormalization,
    PolicyFileError,
    PolicyFiles,
    brief,
    check_metadata_fields,
    checked_normalization,
    read_policy,
    write_policy,
)
from agents.ppo_config import (
    COAST_ENV_IDS,
    MAX_EVAL_EPISODES,
    MAX_RUN_JSON_BYTES,
    PLAN_ENV_IDS,
    TARGET_ENV_IDS,
    TARGETED_ENV_IDS,
    PPOConfig,
)
from agents.sb3_vec import ENV_ID, make_sb3_vec_env
from wl_env import atomic_io
from wl_env.assist import N_ASSIST_ACTIONS
from wl_env.atomic_io import write_atomic
from wl_env.codec import N_OBS, N_SCENARIO_OBS, N_TARGET_OBS, check_within, real_observations
from wl_env.params import is_integer, plain, shown
from wl_env.plan import N_PLAN_ACTIONS

ENV_OF_OBS = {N_OBS: "WheelLoader-v1", N_SCENARIO_OBS: "WheelLoader-v2", N_TARGET_OBS: "WheelLoaderTarget-v0"}
N_OBS_OF_ENV = {**{v: k for k, v in ENV_OF_OBS.items()}, **dict.fromkeys(TARGETED_ENV_IDS, N_TARGET_OBS)}

log = logging.getLogger(__name__)

# a checkpoint's optimizer.safetensors at most (bytes): Adam's two moments of each weight, of a policy's at most
# agents.policy_files.MAX_WEIGHTS_BYTES, and their headers
MAX_OPTIMIZER_BYTES = 2 * 2**30 + 2**20
MAX_EVAL_CSV_BYTES = 2**26  # a run's eval.csv read back on resume (a row of ~300 bytes per evaluation)
MAX_STEPS = 10**15  # a checkpoint's step count at most (10^23 failed as a seed: "Seed must be between 0 and 2**32 - 1")
EVAL_TARGET_RATIOS = (1.0, 1.15, 1.5)  # the targets of the leaderboard (#14): fastest, 1.15 and 1.5 T_min
EVAL_FIELDS = (
    "step", "wall_time", "nominal_success", "nominal_completed", "nominal_return", "T", "fuel_g",
    "time_gap", "fuel_gap", "reversing_error_m", "final_position_error_m", "final_height_error_m", "max_violation",
    "success_rate", "completion_rate", "mean_return", "mean_T", "mean_fuel_g", "train_w_fuel", "train_w_time",
    "train_target_distance", "lateness_median", "fuel_gap_median", "time_gap_fastest",
)


# ---------------------------------------------------------------------------------------------- files
def write_json_atomic(path: str | os.PathLike, obj: Any) -> Path:
    """JSON (NaN written as null, so that strict parsers read it too), atomically."""
    return atomic_io.write_json_atomic(path, obj, indent=2, nan_as_null=True)


def save_model_files(model: Any, vecnorm: Any, folder: Path, extra: dict[str, Any], export: bool = False,
                     summary: bool = False) -> Path:
    """model.zip + vecnormalize.pkl + progress.json into ``folder``, made visible at once (dir rename).

    ``export`` also writes the pickle-free policy (policy.safetensors, policy_vecnormalize.npz, policy.json
    with ``extra`` as metadata) that :func:`load_policy` and :func:`export_policy` read without trust;
    ``summary`` also ``extra`` as summary.json, the mark of a finished run.
    """
    folder = Path(folder)
    tmp = folder.parent / f".{folder.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    model.save(tmp / "model.zip")
    if vecnorm is not None:
        vecnorm.save(tmp / "vecnormalize.pkl")
    if export:
        write_policy(model.policy, ObsNormalization.of_vecnormalize(vecnorm), tmp / "policy", extra)
    write_json_atomic(tmp / "progress.json", extra)
    if summary:  # (staged too: written after the rename, a kill between left a finished run that read as none)
        write_json_atomic(tmp / "summary.json", extra)
    return _replace_folder(tmp, folder)


CHECKPOINT_FILES = ("policy.json", "optimizer.safetensors", "training.json", "progress.json")
CHECKPOINT_NAME = re.compile(r"step_\d{10}")


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or does not fit its run; the message names the folder."""


def save_checkpoint(model: Any, vecnorm: Any, folder: Path, progress: dict[str, Any]) -> Path:
    """A resumable checkpoint in ``folder``, pickle-free (resuming never unpickles, whoever wrote the run
    folder): the policy as exported (``policy.*``), the optimizer's tensors (``optimizer.safetensors``) and its
    settings, update count and the normalization's running statistics (``training.json``), and ``progress``
    (``progress.json``); staged and made visible at once (a kill never leaves half a checkpoint)."""
    folder = Path(folder)
    tmp = folder.parent / f".{folder.name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        _stage_checkpoint(model, vecnorm, tmp, progress)
    except BaseException:  # (an interrupt while staging left the .tmp folder until the next resume)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return _replace_folder(tmp, folder)


def _stage_checkpoint(model: Any, vecnorm: Any, tmp: Path, progress: dict[str, Any]) -> None:
    from safetensors.torch import save as save_tensors

    write_policy(model.policy, ObsNormalization.of_vecnormalize(vecnorm), tmp / "policy", {"num_timesteps": model.num_timesteps})
    opt = model.policy.optimizer.state_dict()
    tensors = {f"{i}/{name}": v.detach().cpu().contiguous() for i, st in opt["state"].items()
               for name, v in st.items() if th.is_tensor(v)}
    scalars = {f"{i}/{name}": v for i, st in opt["state"].items() for name, v in st.items() if not th.is_tensor(v)}
    write_atomic(tmp / "optimizer.safetensors", save_tensors(tensors))

    def stats(rms: Any) -> dict[str, Any]:
        return {"mean": np.asarray(rms.mean, float).tolist(), "var": np.asarray(rms.var, float).tolist(), "count": float(rms.count)}

    write_json_atomic(tmp / "training.json", {
        "optimizer": {"param_groups": opt["param_groups"], "scalars": scalars}, "n_updates": int(model._n_updates),
        "obs_rms": stats(vecnorm.obs_rms) if vecnorm is not None else None,
        "ret_rms": stats(vecnorm.ret_rms) if vecnorm is not None else None})
    write_json_atomic(tmp / "progress.json", progress)


def _plain_setting(v: Any) -> bool:
    """A plain setting of an optimizer (a finite number, a flag, None, or a list of finite numbers)."""
    if v is None or isinstance(v, bool):
        return True
    if isinstance(v, list):
        return all(type(x) in (int, float) and math.isfinite(x) for x in v)
    return type(v) in (int, float) and math.isfinite(v)


def restore_checkpoint(model: Any, vecnorm: Any, folder: Path) -> None:
    """Load a checkpoint of :func:`save_checkpoint` into a freshly built ``model`` (and its ``vecnorm``):
    CheckpointError naming the folder if a file is missing, unreadable or does not fit the run."""
    from safetensors import SafetensorError
    from safetensors.torch import load as load_tensors

    folder = Path(folder)
    try:
        network, _, _ = read_policy(folder / "policy")
        model.policy.load_state_dict(network.state_dict(), strict=True)
        # (regular files, bounded: a FIFO in their place hung the resume for good, a huge file was read whole)
        training = json.loads(atomic_io.read_regular_file(folder / "training.json", MAX_RUN_JSON_BYTES,
                                                          "a checkpoint's training.json holds"))
        if not isinstance(training, dict):
            raise ValueError("training.json holds no JSON object")
        opt = training["optimizer"]
        groups, scalars = opt["param_groups"], opt["scalars"]
        if not (isinstance(groups, list) and all(isinstance(g, dict) and all(_plain_setting(v) for v in g.values())
                                                 for g in groups) and isinstance(scalars, dict)
                and all(_plain_setting(v) for v in scalars.values())):
            raise ValueError("training.json: optimizer settings must be plain numbers, flags or lists of numbers")
        state: dict[int, dict[str, Any]] = {}
        optimizer = atomic_io.read_regular_file(folder / "optimizer.safetensors", MAX_OPTIMIZER_BYTES,
                                                "a checkpoint's optimizer state holds")
        entries = [*load_tensors(optimizer).items(), *scalars.items()]
        for key, value in entries:
            index, name = key.split("/", 1)
            state.setdefault(int(index), {})[name] = value
        groups = [{k: tuple(v) if isinstance(v, list) and k != "params" else v for k, v in g.items()} for g in groups]
        model.policy.optimizer.load_state_dict({"state": state, "param_groups": groups})  # (betas as torch keeps them)
        n_updates = training["n_updates"]
        if type(n_updates) is not int or not 0 <= n_updates <= MAX_STEPS:
            raise ValueError(f"training.json: n_updates must be an integer in [0, {MAX_STEPS}], got {str(n_updates)[:40]}")
        model._n_updates = n_updates
        if vecnorm is not None:
            for name in ("obs_rms", "ret_rms"):
                rms, saved = getattr(vecnorm, name), training[name]
                mean, var = (np.asarray(saved[k], dtype=np.float64).reshape(np.shape(rms.mean)) for k in ("mean", "var"))
                count = float(saved["count"])
                if not (np.isfinite(mean).all() and np.isfinite(var).all() and (var >= 0).all() and math.isfinite(count)
                        and count > 0):
                    raise ValueError(f"training.json: {name} must hold finite statistics (var >= 0, count > 0)")
                rms.mean, rms.var, rms.count = mean, var, count
    except (OSError, ValueError, KeyError, TypeError, IndexError, RuntimeError, SafetensorError, RecursionError,
            OverflowError) as exc:
        raise CheckpointError(f"checkpoint {folder} cannot be resumed from: {brief(exc, 300)}") from None


def _replace_folder(tmp: Path, folder: Path) -> Path:
    """Make the complete folder ``tmp`` visible as ``folder`` at once (a rename), replacing an old one."""
    if folder.exists():
        old = folder.parent / f".{folder.name}.old"
        shutil.rmtree(old, ignore_errors=True)
        os.replace(folder, old)
        os.replace(tmp, folder)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, folder)
    return folder


# ---------------------------------------------------------------------------------------------- env
def make_env(cfg: PPOConfig, num_envs: int | None = None, seed: int | None = None):
    """The training env: native vector env -> SB3 VecEnv -> VecMonitor (-> VecNormalize, fresh: a checkpoint's
    statistics are restored by :func:`restore_checkpoint`)."""
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    env = make_sb3_vec_env(num_envs or cfg.num_envs, seed=cfg.seed if seed is None else seed, env_id=cfg.env_id,
                           init_noise=cfg.init_noise, **cfg.env_kwargs())
    env = VecMonitor(env)
    if not (cfg.norm_obs or cfg.norm_reward):
        return env
    return VecNormalize(env, norm_obs=cfg.norm_obs, norm_reward=cfg.norm_reward, gamma=cfg.gamma, clip_obs=10.0)


def _vecnorm_of(env: Any) -> Any:
    from stable_baselines3.common.vec_env import VecNormalize

    return env if isinstance(env, VecNormalize) else None


def _native_of(env: Any) -> Any:
    """The WheelLoaderVectorEnv under the SB3 wrappers."""
    e = env
    while hasattr(e, "venv"):
        e = e.venv
    return e


def reward_config(cfg: PPOConfig, step: int | None = None):
    """The run's RewardConfig at a training step (``None``: the final one, after the curriculum)."""
    from wl_env.env import make_reward_config

    kwargs = cfg.env_kwargs()
    final = make_reward_config(kwargs["reward"], kwargs["w_fuel"], kwargs["w_time"])
    if step is None or not cfg.curriculum_start:
        return final
    frac = min(1.0, step / max(1.0, cfg.curriculum_fraction * cfg.total_timesteps))
    changes = {k: v0 + frac * (getattr(final, k) - v0) for k, v0 in cfg.curriculum_start.items()}
    return dataclasses.replace(final, **changes)


# ---------------------------------------------------------------------------------------------- policy
@functools.cache
def _env_spaces(env_id: str) -> tuple[int, np.ndarray, np.ndarray]:
    """A registered env's action size and observation bounds (low, high; float32, read-only), as the registry's env
    has them (built once per id)."""
    import warnings

    import gymnasium as gym

    with warnings.catch_warnings():  # (an older env's deprecation: said where an env of it is run)
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make(env_id)
    try:
        low, high = (np.array(b, dtype=np.float32) for b in (env.observation_space.low, env.observation_space.high))
        low.flags.writeable = high.flags.writeable = False
        return int(env.action_space.shape[0]), low, high
    finally:
        env.close()


def check_policy_env(network: Any, env_id: str) -> None:
    """PolicyFileError unless the env ``env_id`` (a policy's ``config.env_id``) takes the observations the policy
    ``network`` takes (their shape and bounds) and the actions it gives (their shape): what loading a policy and
    :func:`agents.policy_files.write_policy` both refuse."""
    obs, act = tuple(network.observation_space.shape), tuple(network.action_space.shape)
    mapping = f"the policy maps observations {obs} to actions {act}"
    if env_id not in N_OBS_OF_ENV:  # (checked before gym.make: any registered id, CartPole-v1 say, would be built)
        raise PolicyFileError(f"{mapping}; its env {env_id!r} (config.env_id) is none of {sorted(N_OBS_OF_ENV)}")
    wanted, low, high = _env_spaces(env_id)
    env_shapes = f"{env_id!r} takes observations ({low.size},) and actions ({wanted},)"
    if obs != (low.size,):
        raise PolicyFileError(f"the policy takes {int(np.prod(obs))} observations; its env {env_id!r} (config.env_id) has "
                              f"{low.size}: {mapping}, {env_shapes}")
    if act != (wanted,):  # (it failed at the first step, naming the controller: a 4-number policy on WheelLoaderPlan-v0)
        raise PolicyFileError(f"the policy gives {int(np.prod(act))} numbers per action; its env {env_id!r} takes {wanted}: "
                              f"{mapping}, {env_shapes}")
    # (the bounds its observations were checked against in training: other ones, narrower say, were accepted and
    # refused the env's own observations at the first act())
    space = network.observation_space
    differ = np.flatnonzero((np.asarray(space.low, np.float32) != low) | (np.asarray(space.high, np.float32) != high))
    if differ.size:
        i = int(differ[0])
        raise PolicyFileError(
            f"the policy's observation space differs from its env {env_id!r}'s at {differ.size} entr"
            f"{'y' if differ.size == 1 else 'ies'} {differ[:8].tolist()}{' ...' if differ.size > 8 else ''} (entry {i}: "
            f"[{float(space.low[i]):.6g}, {float(space.high[i]):.6g}], the env's [{float(low[i]):.6g}, "
            f"{float(high[i]):.6g}]): it was made for other observations")


class PPOPolicy:
    """A trained PPO policy: ``act(obs)`` returns the deterministic action (mean of the Gaussian, clipped
    to the action space) for one observation (shape (12,)) or a batch (shape (n, 12)).

    ``network`` is the SB3 ``ActorCriticPolicy`` (torch module), ``normalization`` the VecNormalize
    observation statistics it was trained with (None: raw observations), ``meta`` the policy's metadata.
    """

    def __init__(self, network: Any, normalization: ObsNormalization | None = None,
                 meta: dict[str, Any] | None = None) -> None:
        self.network = network
        self.normalization = normalization
        self.meta = meta or {}
        self.braking = self.meta.get("braking")
        # the env it was trained on (its config), else the one whose observations it takes: v1's 12 entries
        # (the nominal policies), v2's 19 or the target env's 21
        n_obs = network.observation_space.shape[0]
        self.env_id = (self.meta.get("config") or {}).get("env_id") or ENV_OF_OBS[n_obs]
        check_policy_env(network, self.env_id)

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        if self.normalization is None:
            return np.asarray(obs, dtype=np.float32)
        return self.normalization.apply(obs)

    def reset(self) -> None:  # stateless; present for the controller protocol of run_episode
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        space = self.network.observation_space
        # (real numbers only, checked before any cast: a complex observation lost its imaginary part with a warning, a
        # bool one was read as numbers, a masked entry as the value under its mask, strings were numpy's bare error)
        o = real_observations(obs) if isinstance(obs, (np.ndarray, list, tuple)) else None
        # (each refused by name: a 1-number obs was given an action, NaN was torch's error)
        shaped = o is not None and o.ndim in (1, 2) and o.shape[-1:] == space.shape  # (one, or a batch (N, n))
        if not shaped or not np.isfinite(o).all():
            raise ValueError(f"obs must be {space.shape[0]} finite numbers ({self.env_id}'s observation), or a batch of "
                             f"them, got {'shape ' + str(o.shape) if o is not None else type(obs).__name__}"
                             f"{' with non-finite entries' if shaped else ''}")
        check_within(o, space.low, space.high, where=f" ({self.env_id}'s observation space)")
        action, _ = self.network.predict(self.normalize(o), deterministic=True)
        return np.asarray(action, dtype=np.float32)

    __call__ = act


def load_policy(path: str | os.PathLike, device: str = "cpu", *, trust_pickle: bool = False) -> PPOPolicy:
    """Load a policy exported by :func:`export_policy` or :func:`train`, or shipped in ``agents/policies/``.

    ``path`` names a pickle-free policy (:mod:`agents.policy_files`): any of its three files, its stem
    (``agents/policies/ppo_tc``), a run's ``final/`` folder or a run directory. Nothing in these files
    is executed; a missing, corrupt or mismatched file is a :class:`PolicyFileError` naming it.

    A stable-baselines3 zip (``model.zip`` of a run or checkpoint, with ``vecnormalize.pkl`` and
    ``progress.json``/``summary.json`` beside it) is unpickled, which can run code: it is loaded only with
    ``trust_pickle=True``, for files you trust (your own training runs).
    """
    p = Path(path).expanduser()
    stem = _safe_stem(p)
    if stem is not None:
        network, normalization, meta = read_policy(stem)
        metadata = PolicyFiles.of(stem).metadata
        _check_spaces(network, metadata)
        return _policy(network, normalization, meta, metadata)
    zip_path = _sb3_zip(p)
    if not trust_pickle:
        raise PolicyFileError(
            f"{zip_path} is a stable-baselines3 zip: loading it unpickles objects, which can run code. Pass "
            f"--trust-pickle (trust_pickle=True) only for files you trust (e.g. your own training runs), or use "
            f"the pickle-free export: `wl train --export PATH` or `python -m agents.policy_files {zip_path} OUT "
            f"--trust-pickle`")
    return _load_sb3(zip_path, device)


def policy_source(path: str | os.PathLike) -> Path:
    """The file :func:`load_policy` reads the policy ``path`` from, its links resolved: a pickle-free policy's weights
    or a stable-baselines3 zip (``path`` itself, resolved, if it names neither: loading it says why). One policy by two
    spellings (``P`` and ``P.safetensors`` or ``P.json``; a run folder and its ``final/``) gives one file."""
    p = Path(path).expanduser()
    try:
        stem = _safe_stem(p)
        found = PolicyFiles.of(stem).weights if stem is not None else _sb3_zip(p)
    except OSError:  # (FileNotFoundError: no policy there; a name too long to look up)
        found = p
    return Path(os.path.realpath(found))


def _policy(network: Any, normalization: ObsNormalization | None, meta: dict[str, Any], path: Path) -> PPOPolicy:
    """:class:`PPOPolicy`, its refusal (the env its metadata names takes other observations or actions) naming the
    file ``path`` the policy was read from."""
    try:
        return PPOPolicy(network, normalization, meta)
    except PolicyFileError as exc:
        raise PolicyFileError(f"policy {path}: {exc}") from None


def _safe_stem(p: Path) -> Path | None:
    """The stem of the pickle-free policy ``p`` names, or None if it names a stable-baselines3 zip; PolicyFileError
    naming ``p`` if it cannot be looked at (a name too long for the system was a bare OSError)."""
    try:
        return _stem_of(p)
    except OSError as exc:
        raise PolicyFileError(f"no policy at {p}: {exc.strerror or exc}") from None


def _stem_of(p: Path) -> Path | None:
    if p.is_dir():
        for stem in (p / "policy", p / "final" / "policy"):
            if PolicyFiles.of(stem).weights.exists():
                return stem
        return None
    name = p.name
    if name.endswith((WEIGHTS_SUFFIX, METADATA_SUFFIX, NORMALIZATION_SUFFIX)):
        return p
    if p.with_name(name + WEIGHTS_SUFFIX).exists() or (p.suffix not in PICKLE_SUFFIXES and not p.exists()
                                                        and p.with_name(name + METADATA_SUFFIX).exists()):
        return p
    return None


def _sb3_zip(p: Path) -> Path:
    if p.is_dir():
        for zip_path in (p / "model.zip", p / "final" / "model.zip"):
            if zip_path.exists():
                return zip_path
        raise FileNotFoundError(f"no policy in {p}: expected policy{WEIGHTS_SUFFIX} (pickle-free) or model.zip, "
                                f"there or in {p / 'final'}")
    given = p
    if p.suffix == ".pkl":  # the normalization pickle named instead of its model
        stem = p.name[: -len("_vecnormalize.pkl")] if p.name.endswith("_vecnormalize.pkl") else "model"
        p = p.with_name(stem + ".zip")
    if p.suffix != ".zip":
        raise FileNotFoundError(f"no policy at {p}: expected STEM{WEIGHTS_SUFFIX} + STEM{NORMALIZATION_SUFFIX} + "
                                f"STEM{METADATA_SUFFIX}, or a stable-baselines3 .zip")
    if not p.exists():
        raise FileNotFoundError(f"no policy at {given}" + (f" (a normalization file; its model would be {p})" if p != given else ""))
    return p


def _load_sb3(p: Path, device: str) -> PPOPolicy:
    """A stable-baselines3 zip with its VecNormalize pickle and metadata beside it (unpickles: trusted only)."""
    from stable_baselines3 import PPO

    stem = p.with_suffix("")
    norm_files = [stem.parent / f"{stem.name}_vecnormalize.pkl", p.parent / "vecnormalize.pkl"]
    meta_files = [stem.parent / f"{stem.name}.json", p.parent / "summary.json", p.parent / "progress.json"]
    meta_path = next((c for c in meta_files if c.exists()), None)
    if meta_path is None:
        raise PolicyFileError(f"policy {p} has no metadata: expected one of {', '.join(str(c) for c in meta_files)}")
    try:  # (a regular file, bounded: a FIFO in its place hung the load for good)
        meta = json.loads(atomic_io.read_regular_file(meta_path, MAX_RUN_JSON_BYTES, "policy metadata holds"))
    except (OSError, ValueError, RecursionError) as exc:
        raise PolicyFileError(f"policy metadata {meta_path} is unreadable: {brief(exc)}") from None
    if not isinstance(meta, dict):
        raise PolicyFileError(f"policy metadata {meta_path} is not a JSON object")
    config = meta.get("config") if isinstance(meta.get("config"), dict) else {}
    if "braking" not in meta and "braking" in config:
        meta["braking"] = config["braking"]
    # (as a pickle-free policy's: a braking "x" was taken, a config "abc" an AttributeError at the load's end)
    check_metadata_fields(meta, meta_path)
    norm_path = next((c for c in norm_files if c.exists()), None)
    normalization, norm_from = None, norm_path
    if norm_path is not None:
        try:
            with open(norm_path, "rb") as f:
                normalization = ObsNormalization.of_vecnormalize(pickle.load(f))
        except Exception as exc:  # noqa: BLE001 - truncated or foreign pickles fail in many ways
            raise PolicyFileError(f"normalization file {norm_path} is unreadable: {brief(exc)}") from None
    elif isinstance(meta.get("obs_normalization"), dict):  # the JSON copy of older exports
        n, norm_from = meta["obs_normalization"], meta_path
        try:  # (a missing entry was a bare KeyError, a string one numpy's error)
            normalization = ObsNormalization(np.asarray(n["mean"], np.float64), np.asarray(n["var"], np.float64),
                                             float(n["clip_obs"]), float(n["epsilon"]))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise PolicyFileError(f"policy metadata {meta_path}: obs_normalization must hold mean, var, clip_obs and "
                                  f"epsilon as numbers, got {brief(exc)}") from None
    elif config.get("norm_obs", True):
        raise PolicyFileError(
            f"policy {p} has no normalization file: expected {norm_files[0]} or {norm_files[1]} (the VecNormalize "
            f"statistics it was trained with; without them it acts on wrongly scaled observations)")
    try:
        model = PPO.load(str(p), device=device)
    except Exception as exc:  # noqa: BLE001 - a corrupt zip or policy.pth, as above
        raise PolicyFileError(f"policy zip {p} is unreadable: {brief(exc)}") from None
    _check_spaces(model.policy, p)
    if normalization is not None:  # (checked as a pickle-free policy's, for the network's observations)
        normalization = checked_normalization(normalization.mean, normalization.var, normalization.clip_obs,
                                              normalization.epsilon, model.policy.observation_space.shape[0],
                                              f"normalization of {norm_from}")
    return _policy(model.policy, normalization, meta, p)


def _check_spaces(network: Any, path: Path) -> None:
    """The policy must take the observations of one of the envs (:data:`ENV_OF_OBS`) and give its actions: (4,),
    (3,) for WheelLoaderTarget-v2's driver or (14,) for WheelLoaderPlan-v0/-v1's plan (the target env's observations)."""
    obs, act = network.observation_space.shape, network.action_space.shape
    if len(obs) != 1 or obs[0] not in ENV_OF_OBS or act not in ((4,), (N_ASSIST_ACTIONS,), (N_PLAN_ACTIONS,)) or (
            act in ((N_ASSIST_ACTIONS,), (N_PLAN_ACTIONS,)) and obs[0] != N_TARGET_OBS):
        raise PolicyFileError(f"policy {path} maps observations {obs} to actions {act}; WheelLoader-v1 has "
                              f"({N_OBS},) and (4,), v2 ({N_SCENARIO_OBS},), WheelLoaderTarget-v0 ({N_TARGET_OBS},), "
                              f"WheelLoaderTarget-v2 ({N_TARGET_OBS},) and ({N_ASSIST_ACTIONS},), WheelLoaderPlan-v0 "
                              f"({N_TARGET_OBS},) and ({N_PLAN_ACTIONS},)")
    space = network.action_space  # (predict clips its actions to these bounds: other ones change every action)
    if not (np.all(space.low == -1.0) and np.all(space.high == 1.0)):
        raise PolicyFileError(f"policy {path}: its action space must be the envs' Box(-1, 1), got low "
                              f"{space.low.tolist()}, high {space.high.tolist()}")


# ---------------------------------------------------------------------------------------------- evaluation
class _Deterministic:
    """A batched ``act(obs) -> actions`` as a controller of the protocol (training-time evaluation)."""

    def __init__(self, act: Any, env_id: str = ENV_ID) -> None:
        self._act = act
        self.env_id = env_id  # what the policy is trained on

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.asarray(self._act(np.asarray(obs, dtype=np.float32)[None]), dtype=np.float32).reshape(-1)


def _without_scenario(env_kwargs: Any) -> Any:
    """The training env's kwargs without its scenario source: the evaluation's episodes are the paper's cycle and its
    perturbed starts, or the validation draws (evaluate_controller refuses a scenario there)."""
    return {k: v for k, v in env_kwargs.items() if k != "scenario"} if isinstance(env_kwargs, dict) else env_kwargs


def evaluate(act: Any, braking: str, n_episodes: int = 100, init_noise: float = 1.0, seed: int = 10_000,
             env_kwargs: dict[str, Any] | None = None, with_score: bool = True, front: Any = None,
             env_id: str = ENV_ID) -> dict[str, Any]:
    """Deterministic evaluation through the one evaluation path (:func:`agents.evaluate.evaluate_controller`):
    the nominal start (init_noise 0, what the optimum is computed for) and ``n_episodes`` perturbed starts,
    as one row of the learning curve (:data:`EVAL_FIELDS`): the nominal start's numbers and the perturbed
    starts' rates and means apart. Gaps are relative (0.1 = 10 % above)."""
    from agents.evaluate import evaluate_controller

    n_episodes = check_n_episodes(n_episodes)
    env_kwargs = _without_scenario(env_kwargs)
    if env_id in TARGETED_ENV_IDS:
        return evaluate_targets(act, braking, n_episodes, seed, env_kwargs, with_score, front, env_id=env_id)
    # Scored where the optimum is known without solving (the nominal start: shipped); a perturbed start's
    # own optimum would cost a solve per episode at every evaluation.
    # (on the policy's own env: WheelLoader-v2's 19 observations were fed v1's 12, and no v2 run could train)
    res = evaluate_controller(_Deterministic(act, env_id), braking, episodes=1 + n_episodes, init_noise=init_noise, seed=seed,
                              score=with_score, front=front, env_kwargs=env_kwargs, name="policy", solve=False,
                              unknown="skip")
    nominal = res["per_episode"][0]
    perturbed = res["per_episode"][1:] or res["per_episode"]
    scored = [e for e in perturbed if e["completed"] and e["time_gap"] is not None]
    out = _curve_row(nominal, perturbed)
    if scored:
        out.update(mean_time_gap=float(np.mean([e["time_gap"] for e in scored])),
                   mean_fuel_gap=float(np.mean([e["fuel_gap"] for e in scored])),
                   max_time_gap=float(np.max([e["time_gap"] for e in scored])),
                   max_fuel_gap=float(np.max([e["fuel_gap"] for e in scored])))
    return out


def check_n_episodes(n_episodes: Any) -> int:
    """``n_episodes`` (the perturbed starts or validation draws of an evaluation, numpy's integers too) as an int in
    [0, MAX_EVAL_EPISODES], else ValueError naming it."""
    # (evaluate_targets drew range(n_episodes) unchecked: -3 ran the paper's cycle alone, True one draw, 2.5 was
    # range()'s TypeError; evaluate named its episodes=1+n_episodes instead)
    n = plain(n_episodes)
    if not (is_integer(n) and 0 <= n <= MAX_EVAL_EPISODES):
        raise ValueError(f"n_episodes must be an integer in [0, {MAX_EVAL_EPISODES}], got {shown(n_episodes)}")
    return int(n)


def evaluate_targets(act: Any, braking: str, n_episodes: int = 16, seed: int = 10_000,
                     env_kwargs: dict[str, Any] | None = None, with_score: bool = True, front: Any = None,
                     ratios: tuple[float, ...] = EVAL_TARGET_RATIOS, env_id: str = TARGET_ENV_IDS[0]) -> dict[str, Any]:
    """The learning-curve row of a target-conditioned policy (``env_id``, WheelLoaderTarget-v0 or v1): at each target ratio,
    the paper's cycle (scored against its shipped front) and ``n_episodes`` validation draws of the ``train``
    distribution (seed stream ``seed``, which no training env draws from; unscored: nothing is solved),
    each target that ratio times the scenario's estimated T_min. ``nominal_*`` is the paper's cycle at the
    middle ratio; rates, means and ``lateness_median`` cover every episode; ``fuel_gap_median`` the paper's
    cycle over the ratios; ``time_gap_fastest`` its time gap at the first ratio."""
    from agents.evaluate import check_settings, evaluate_controller
    from wl_env.scenario import Scenario
    from wl_env.suites import TRAIN_STREAM, draw, stream

    n_episodes, seed = check_n_episodes(n_episodes), plain(seed)
    env_kwargs = _without_scenario(env_kwargs)
    # (the seed before the draws' stream takes it: -1 was numpy's "expected non-negative integer", "3" drew as 3)
    check_settings(1 + n_episodes, 0.0, seed)
    rng = stream(TRAIN_STREAM, seed)
    plan = [Scenario.nominal(braking)] + [draw(rng, braking) for _ in range(n_episodes)]
    runs = [evaluate_controller(_Deterministic(act, env_id), braking, scenarios=plan, seed=seed,
                                score=with_score, front=front, env_kwargs=env_kwargs, name="policy", solve=False,
                                unknown="skip", target_ratio=r, min_time="estimate") for r in ratios]
    episodes = [e for run in runs for e in run["per_episode"]]
    nominals = [run["per_episode"][0] for run in runs]

    def median(values: list[float]) -> float:
        return float(np.median(values)) if values else math.nan

    return {
        **_curve_row(nominals[len(nominals) // 2], episodes),
        "max_violation": max(e["max_violation"] for e in episodes),
        "lateness_median": median([e["lateness"] for e in episodes if e["completed"]]),
        "fuel_gap_median": median([e["fuel_gap"] for e in nominals if e["success"] and e["fuel_gap"] is not None]),
        "time_gap_fastest": _nan(nominals[0]["time_gap"]),
    }


def _nan(v: Any) -> float:
    return math.nan if v is None else float(v)


def _curve_row(nominal: dict[str, Any], episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """A learning-curve row: one episode's numbers (``nominal_*``, T, fuel, gaps, errors, violation) and the
    rates and means over ``episodes`` (evaluation records of :func:`agents.evaluate.evaluate_controller`)."""
    done = [e for e in episodes if e["completed"]]
    return {
        "nominal_success": float(nominal["success"]), "nominal_completed": float(nominal["completed"]),
        "nominal_return": nominal["episode_return"], "T": nominal["T"], "fuel_g": nominal["fuel_g"],
        "time_gap": _nan(nominal["time_gap"]), "fuel_gap": _nan(nominal["fuel_gap"]),
        "reversing_error_m": _nan(nominal["reversing_error_m"]), "final_position_error_m": nominal["final_position_error_m"],
        "final_height_error_m": nominal["final_height_error_m"], "max_violation": nominal["max_violation"],
        "success_rate": float(np.mean([e["success"] for e in episodes])),
        "completion_rate": len(done) / len(episodes),
        "mean_return": float(np.mean([e["episode_return"] for e in episodes])),
        "mean_T": float(np.mean([e["T"] for e in done])) if done else math.nan,
        "mean_fuel_g": float(np.mean([e["fuel_g"] for e in done])) if done else math.nan,
    }


# ---------------------------------------------------------------------------------------------- training
def _callbacks(cfg: PPOConfig, run_dir: Path, state: dict[str, Any],
               demos: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[Any, Any]:
    """The run's callbacks (a ``CallbackList``) and its evaluation (``train`` evaluates once more at the end);
    ``demos`` (raw observations, action labels, weights: :func:`agents.imitation.demo_samples`) for
    ``cfg.bc_demos``' regularization.

    stable-baselines3's ``EveryNTimesteps`` triggers the evaluations. What SB3 lacks (or saves as pickles: the
    checkpoints) is kept, each said why below.
    """
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList, EveryNTimesteps

    class Curriculum(BaseCallback):
        # Kept: SB3 has no reward curriculum nor a schedule on the policy's std.
        def _on_training_start(self) -> None:
            self._apply()

        def _on_rollout_start(self) -> None:
            self._apply()

        def _on_step(self) -> bool:
            return True

        def _apply(self) -> None:
            if cfg.log_std_final is not None and not cfg.use_sde:
                # Exploration annealing: a noisy policy aims short of targets it cannot undo (the bucket
                # is never lowered), and the deterministic policy inherits that offset; capping the
                # std late in training removes it.
                frac = min(1.0, self.num_timesteps / max(1, cfg.total_timesteps))
                cap = cfg.log_std_init + frac * (cfg.log_std_final - cfg.log_std_init)
                with th.no_grad():
                    self.model.policy.log_std.clamp_(max=cap)
                self.logger.record("train/log_std_cap", cap)
            native = _native_of(self.training_env)
            rc = reward_config(cfg, self.num_timesteps)
            if native.core.reward != rc:
                native.core.reward = rc  # the vector env reads its RewardConfig at every step
            for k in cfg.curriculum_start:
                self.logger.record(f"curriculum/{k}", getattr(rc, k))

    class ScoredEvaluation(BaseCallback):
        # Kept: EvalCallback reports mean returns only; the project's evaluation scores cycle time and fuel
        # against the optimum and appends them to eval.csv (the learning curve, continued on resume).
        def __init__(self) -> None:
            super().__init__()
            self.front = None

        def _on_training_start(self) -> None:
            if cfg.score:
                try:
                    from mpc.benchmark.pareto import pareto_front

                    self.front = pareto_front(cfg.braking)
                except Exception as e:  # noqa: BLE001
                    log.warning("no Pareto front, evaluations are not scored (%s)", e)
            if state["last_eval"] is None:
                self.evaluate()  # the untrained policy: step 0 of the learning curve

        def _on_step(self) -> bool:
            self.evaluate()
            return True

        def evaluate(self) -> None:
            step = self.model.num_timesteps
            vn = _vecnorm_of(self.model.get_env())

            def act(obs: np.ndarray) -> np.ndarray:
                if vn is not None:
                    obs = vn.normalize_obs(obs)
                return self.model.predict(obs, deterministic=True)[0]

            res = evaluate(act, cfg.braking, cfg.eval_episodes, cfg.eval_init_noise, seed=10_000,
                           env_kwargs=cfg.env_kwargs(), with_score=cfg.score and self.front is not None,
                           front=self.front, env_id=cfg.env_id)
            rc = reward_config(cfg, step)
            row = {"step": step, "wall_time": state["wall_time"] + time.time() - state["t0"],
                   "train_w_time": rc.w_time, "train_w_fuel": rc.w_fuel, "train_target_distance": rc.target_distance,
                   **res}
            for k, v in res.items():
                if isinstance(v, (int, float)) and v is not None and math.isfinite(v):
                    self.model.logger.record(f"eval/{k}", v)
            _append_eval_row(run_dir / "eval.csv", row)
            state["last_eval_row"] = row
            state["last_eval"] = step
            # shown by the CLI unless a progress bar is drawn (the lines would break it)
            log.log(logging.INFO if self.verbose or cfg.progress_bar is False else logging.DEBUG, "%s", _eval_line(row))

    class RunCheckpoint(BaseCallback):
        # Not SB3's CheckpointCallback: its checkpoints are zips of pickles, written in place. These are
        # pickle-free (save_checkpoint), staged and renamed at once, with progress.json for resume (wall time,
        # last evaluation), and only the newest keep_checkpoints are kept. A checkpoint falls due at a step and is
        # written once the rollout's update is done (the next rollout's start, or the training's end): written at the
        # step, it held the weights before the update of the rollout its step count included, so a resumed run never
        # learned from that rollout, and a finished run's last one was not its final policy.
        def __init__(self) -> None:
            super().__init__()
            self.due = False

        def _on_step(self) -> bool:
            if self.n_calls % max(cfg.checkpoint_freq // cfg.num_envs, 1) == 0:
                self.due = True
            return True

        def _on_rollout_start(self) -> None:  # (first in the list: before the curriculum and the BC steps act on it)
            if self.due:
                self._save()

        def _on_training_end(self) -> None:
            if self.due:
                self._save()

        def _save(self) -> None:
            self.due = False
            step = self.num_timesteps
            root = run_dir / "checkpoints"
            folder = save_checkpoint(self.model, _vecnorm_of(self.model.get_env()), root / f"step_{step:010d}", {
                "num_timesteps": step, "total_timesteps": cfg.total_timesteps,
                "wall_time": state["wall_time"] + time.time() - state["t0"], "last_eval": state["last_eval"],
                "time": time.strftime("%Y-%m-%dT%H:%M:%S"), "braking": cfg.braking, "seed": cfg.seed})
            write_json_atomic(root / "latest.json", {"checkpoint": folder.name, "num_timesteps": step})
            complete = sorted(p for p in root.glob("step_*") if (p / "progress.json").exists())
            broken = [p for p in root.glob("step_*") if p.is_dir() and not (p / "progress.json").exists()]
            for old in complete[: -max(1, cfg.keep_checkpoints)] + broken + list(root.glob(".step_*.tmp")):
                shutil.rmtree(old, ignore_errors=True)  # older ones, and what a killed save left
            for part in root.glob(".latest.json.*.tmp"):  # ... and a killed write of the pointer
                part.unlink(missing_ok=True)

    class WallTimeLimit(BaseCallback):
        # Kept: SB3 stops on reward, episodes or no improvement, not on wall time (summed over resumes).
        def _on_step(self) -> bool:
            if cfg.time_limit > 0 and state["wall_time"] + time.time() - state["t0"] >= cfg.time_limit:
                if not state.get("timed_out"):
                    log.info("time limit: %.0f s of training reached at step %d", cfg.time_limit, self.num_timesteps)
                state["timed_out"] = True
                return False
            return True

    class BehaviourCloningRegularizer(BaseCallback):
        # Kept: SB3 has no demonstration-augmented policy gradient (DAPG's idea: the expert's actions pull
        # on the actor with a weight that decays). Before each rollout the actor takes as many steps on the
        # demos' weighted squared action error (clone's loss) as PPO takes on its own loss, through PPO's own
        # optimizer, so that the weight sets the pull against PPO's steps (a separate Adam would normalize
        # it away); before the rollout, so that PPO's ratios start at 1 on the policy that collected it.
        def __init__(self) -> None:
            super().__init__()
            obs, act, weights = demos
            self.obs, self.act, self.weights = obs, th.as_tensor(act, dtype=th.float32), th.as_tensor(weights)

        def _on_step(self) -> bool:
            return True

        def _on_rollout_start(self) -> None:
            frac = self.num_timesteps / max(1, cfg.total_timesteps)
            weight = cfg.bc_weight * max(0.0, 1.0 - frac / cfg.bc_fraction)
            self.logger.record("train/bc_weight", weight)
            if weight <= 0.0:
                return
            vn = _vecnorm_of(self.training_env)
            x = th.as_tensor(vn.normalize_obs(self.obs) if vn is not None else self.obs, dtype=th.float32)
            policy = self.model.policy
            policy.set_training_mode(True)
            rng = np.random.default_rng([cfg.seed, self.num_timesteps])  # (a resumed run draws the same batches)
            for _ in range(cfg.n_epochs * max(1, cfg.n_steps * cfg.num_envs // cfg.batch_size)):
                b = th.as_tensor(rng.integers(0, len(x), size=min(cfg.batch_size, len(x))))
                mean = policy.get_distribution(x[b]).distribution.mean
                loss = th.mean(self.weights[b] * (mean - self.act[b]) ** 2)
                policy.optimizer.zero_grad()
                (weight * loss).backward()
                th.nn.utils.clip_grad_norm_(policy.parameters(), cfg.max_grad_norm)
                policy.optimizer.step()
            policy.set_training_mode(False)
            self.logger.record("train/bc_loss", float(loss.detach()))

    evaluation = ScoredEvaluation()
    every = EveryNTimesteps(n_steps=cfg.eval_freq, callback=evaluation)
    every.last_time_trigger = state["last_eval"] or 0  # on resume: the schedule goes on from the checkpoint's
    # The evaluation runs before the checkpoint of the same step (written at the next rollout's start), so that its
    # progress.json records it.
    run = [RunCheckpoint(), Curriculum(), every, WallTimeLimit()]
    if demos is not None:
        run.insert(2, BehaviourCloningRegularizer())  # (after the curriculum's std cap, before the rollout)
    return CallbackList(run), evaluation


def _eval_line(row: dict[str, Any]) -> str:
    def f(k: str, fmt: str) -> str:
        v = row.get(k)
        return "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)

    return (f"[eval] step {row['step']:>9d}  success {f('success_rate', '.2f')} (nominal {f('nominal_success', '.0f')})"
            f"  T {f('T', '.2f')} s  fuel {f('fuel_g', '.1f')} g  gaps {f('time_gap', '+.3f')}/{f('fuel_gap', '+.3f')}"
            f"  errors rev {f('reversing_error_m', '+.3f')} end {f('final_position_error_m', '+.3f')} "
            f"H {f('final_height_error_m', '+.3f')}"
            f"  return {f('nominal_return', '.3f')}"
            + (f"  lateness {f('lateness_median', '.3f')} fuel gap over targets {f('fuel_gap_median', '+.3f')}"
               if "lateness_median" in row else ""))


def _append_eval_row(path: Path, row: dict[str, Any]) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(EVAL_FIELDS) + ["mean_time_gap", "mean_fuel_gap", "max_time_gap", "max_fuel_gap"],
                           extrasaction="ignore")
        if new:
            w.writeheader()
        w.writerow({k: ("" if v is None else v) for k, v in row.items()})
        f.flush()
        os.fsync(f.fileno())


def read_eval_csv(path: str | os.PathLike) -> list[dict[str, float]]:
    """The rows of a run's eval.csv as floats (NaN for empty cells); ValueError naming the file if a cell is no
    number or the file no text."""
    rows = []
    try:
        with open(path, newline="") as f:
            for r in csv.DictReader(f):
                rows.append({k: (float(v) if v not in ("", None) else math.nan) for k, v in r.items()})
    except (ValueError, TypeError, csv.Error) as exc:  # (a row longer than the header: a list under the key None)
        raise ValueError(f"{path} is not a readable evaluation log: {brief(exc, 200)}") from None
    return rows


def _eval_csv_up_to(path: Path, step: int) -> str | None:
    """On resume: eval.csv with the evaluations up to the checkpoint (later ones are redone; a line cut short by
    the interruption is dropped), or None if nothing is to be dropped; ValueError naming the file if it cannot be
    continued. (Read before anything is written; written once the checkpoint is restored.)"""
    if not path.exists():
        return None
    try:  # (a step that is no number, or a file that is no text: ValueError naming it, not a bare one)
        # (a regular file, bounded: a FIFO in its place hung the resume for good; its newlines read as read_text does)
        text = atomic_io.read_regular_file(path, MAX_EVAL_CSV_BYTES, "an evaluation log holds").decode()
        lines = text.replace("\r\n", "\n").replace("\r", "\n").splitlines(keepends=True)
        if not lines:
            return None
        n_cols = len(next(csv.reader(lines[:1])))

        def keep(line: str) -> bool:
            cells = next(csv.reader([line]), [])
            return line.endswith("\n") and len(cells) == n_cols and float(cells[0]) <= step

        kept = [line for line in lines[1:] if keep(line)]
    except (ValueError, OSError, csv.Error) as exc:
        raise ValueError(f"{path} cannot be continued: {brief(exc, 200)}") from None
    # (rewritten only to drop rows: its bytes are kept otherwise)
    return "".join(lines[:1] + kept) if len(kept) != len(lines) - 1 else None


def read_run_config(path: Path) -> tuple[PPOConfig, list[str]]:
    """A run's config.json, checked: its PPOConfig and the commands recorded (ValueError naming the file)."""
    try:
        meta = json.loads(atomic_io.read_regular_file(path, MAX_RUN_JSON_BYTES, "a run config holds"))  # (a FIFO: a hang)
        if not isinstance(meta, dict) or not isinstance(meta.get("config"), dict):
            raise ValueError('it holds no "config" object')
        commands = meta.get("commands", [])
        if not (isinstance(commands, list) and all(isinstance(c, str) for c in commands)):
            raise ValueError('"commands" must be a list of strings')
        return PPOConfig.from_dict(meta["config"]), list(commands)
    except (OSError, ValueError, TypeError, RecursionError) as exc:  # (JSON and config errors are ValueErrors)
        raise ValueError(f"{path} is not a readable run config: {brief(exc, 300)}") from None


def read_progress(folder: Path) -> tuple[dict[str, Any], int]:
    """A checkpoint's progress.json, checked, and its step count (CheckpointError naming the folder)."""
    try:
        progress = json.loads(atomic_io.read_regular_file(Path(folder) / "progress.json", MAX_RUN_JSON_BYTES,
                                                          "a checkpoint's progress.json holds"))  # (a FIFO: a hang)
        if not isinstance(progress, dict):
            raise ValueError("it holds no JSON object")
        step, wall = progress["num_timesteps"], progress["wall_time"]
        if type(step) is not int or not 0 <= step <= MAX_STEPS:  # (it may pass total_timesteps by the last rollout)
            raise ValueError(f"num_timesteps must be an integer in [0, {MAX_STEPS}], got {str(step)[:40]}")
        if type(wall) not in (int, float) or not (math.isfinite(wall) and wall >= 0):
            raise ValueError(f"wall_time must be a finite number of seconds >= 0, got {wall!r}")
        return progress, step
    except (OSError, ValueError, KeyError, TypeError, RecursionError, OverflowError) as exc:  # (10**400: OverflowError)
        raise CheckpointError(f"checkpoint {folder} cannot be resumed from: progress.json: {brief(exc, 300)}") from None


def check_env_settings(cfg: PPOConfig) -> None:
    """The run's env built once with its settings: ValueError (the env's, naming the setting) if it refuses them."""
    import warnings

    import gymnasium as gym

    with warnings.catch_warnings():  # (an older env's deprecation is said where the run builds its envs)
        warnings.simplefilter("ignore", DeprecationWarning)
        gym.make(cfg.env_id, **cfg.env_kwargs()).close()


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint folder of a run, or None."""
    root = Path(run_dir) / "checkpoints"

    def complete(folder: Path) -> bool:
        return all((folder / f).is_file() for f in CHECKPOINT_FILES)

    try:  # (the pointer is a shortcut: a pointer that is unreadable or names no checkpoint folder is passed over)
        # (a regular file, bounded: a FIFO in its place hung every resume for good)
        name = json.loads(atomic_io.read_regular_file(root / "latest.json", MAX_RUN_JSON_BYTES, "a pointer holds"))["checkpoint"]
        if isinstance(name, str) and CHECKPOINT_NAME.fullmatch(name) and complete(root / name):
            return root / name
    except (OSError, ValueError, KeyError, TypeError, RecursionError):  # (RecursionError: a deeply nested pointer)
        pass
    folders = sorted(p for p in root.glob("step_*") if CHECKPOINT_NAME.fullmatch(p.name) and complete(p))
    if not folders:
        old = sorted(p for p in root.glob("step_*") if (p / "model.zip").is_file())
        if old:  # (a stable-baselines3 zip: resuming from it would unpickle)
            raise CheckpointError(f"{old[-1]} is an older checkpoint (a stable-baselines3 zip, a pickle) that this "
                                  f"version does not resume from: train again from step 0 (remove {root})")
    return folders[-1] if folders else None


class BoundedMeanPolicy(ActorCriticPolicy):
    """SB3's ``MlpPolicy`` with the Gaussian's mean squashed to ``mean_bound * tanh(.)``.

    The env clips actions to [-1, 1]. An unbounded mean can drift far outside, where neither the clipped
    action nor the return depends on it and samples rarely come back inside: PPO then stops learning
    that action (e.g. a bucket held at full lift past its target, up to the end stop).
    """

    def __init__(self, *args: Any, mean_bound: float = 1.1, **kwargs: Any) -> None:
        self.mean_bound = mean_bound
        super().__init__(*args, **kwargs)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        return {**super()._get_constructor_parameters(), "mean_bound": self.mean_bound}

    def _get_action_dist_from_latent(self, latent_pi: th.Tensor) -> Distribution:
        if not isinstance(self.action_dist, DiagGaussianDistribution):
            return super()._get_action_dist_from_latent(latent_pi)
        mean = self.mean_bound * th.tanh(self.action_net(latent_pi))
        return self.action_dist.proba_distribution(mean, self.log_std)


def build_model(cfg: PPOConfig, env: Any, tb_dir: Path):
    from stable_baselines3 import PPO

    lr: Any = cfg.learning_rate
    if cfg.lr_schedule == "linear":
        lr0 = cfg.learning_rate

        def lr(progress_remaining: float) -> float:  # noqa: F811 - SB3 schedule: 1 -> 0 over training
            return lr0 * max(progress_remaining, 0.05)

    bounded = cfg.bounded_mean and not cfg.use_sde
    model = PPO(
        BoundedMeanPolicy if bounded else "MlpPolicy", env, learning_rate=lr, n_steps=cfg.n_steps, batch_size=cfg.batch_size, n_epochs=cfg.n_epochs,
        gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range, ent_coef=cfg.ent_coef,
        vf_coef=cfg.vf_coef, max_grad_norm=cfg.max_grad_norm, target_kl=cfg.target_kl,
        use_sde=cfg.use_sde, sde_sample_freq=cfg.sde_sample_freq,
        policy_kwargs={"net_arch": {"pi": list(cfg.net_arch), "vf": list(cfg.net_arch)},
                       "log_std_init": cfg.log_std_init},
        tensorboard_log=str(tb_dir), seed=cfg.seed, device="cpu", verbose=0,
    )
    # Initial action means. The shift is a threshold (action[3] > 0) on a continuous action: start by
    # holding the gear, or the untrained policy ends phases 1 and 3 within a step or two and never sees a
    # full leg. The fuel: above ~40 mg the governor caps a neutral engine at omega_max, so a policy that
    # starts around half injection sees no gain from less fuel (a flat region) and keeps racing the engine.
    def raw(mean: float) -> float:  # the bias giving this initial mean
        return math.atanh(max(-0.99, min(0.99, mean / 1.1))) if bounded else mean

    if cfg.env_id in PLAN_ENV_IDS:  # (a plan's numbers start mid-range: none is a threshold)
        return model
    with th.no_grad():
        model.policy.action_net.bias[0] = raw(cfg.fuel_bias_init)
        model.policy.action_net.bias[1] = raw(cfg.bucket_bias_init)
        if cfg.env_id in COAST_ENV_IDS:  # (their fourth action is the coasting fraction)
            model.policy.action_net.bias[3] = raw(cfg.coast_bias_init)
        elif model.policy.action_net.bias.shape[0] == 4:  # (WheelLoaderTarget-v2's assist shifts by itself)
            model.policy.action_net.bias[3] = raw(cfg.shift_bias_init)
    return model


def start_from(model: Any, env: Any, cfg: PPOConfig) -> None:
    """Fine-tuning: the weights and observation statistics of the pickle-free policy ``cfg.init_policy``
    (the same network as ``cfg``'s), with the exploration noise reset to ``cfg.log_std_init``."""
    stem = _safe_stem(Path(cfg.init_policy).expanduser())
    if stem is None:
        raise PolicyFileError(f"init_policy {cfg.init_policy}: not a pickle-free policy (STEM{WEIGHTS_SUFFIX} with "
                              f"its normalization and metadata)")
    network, normalization, _ = read_policy(stem)
    try:
        model.policy.load_state_dict(network.state_dict(), strict=True)
    except RuntimeError as exc:
        raise PolicyFileError(f"init_policy {stem}: its network does not fit the run's (net_arch {list(cfg.net_arch)}, "
                              f"{cfg.env_id}): {' '.join(str(exc).split())[:300]}") from None
    with th.no_grad():
        model.policy.log_std.fill_(cfg.log_std_init)
    vn = _vecnorm_of(env)
    if vn is not None and normalization is not None:
        vn.obs_rms.mean, vn.obs_rms.var = normalization.mean.copy(), normalization.var.copy()
        vn.obs_rms.count = 1e6  # held: statistics from many demonstrations, not from the first rollout alone


def train(cfg: PPOConfig, resume: bool = False, command: str | None = None, callbacks: list | None = None) -> dict[str, Any]:
    """Train (or, with ``resume``, continue) the run ``cfg.run_dir``; returns the run's summary.

    ``command`` (the command line) is recorded in config.json; ``callbacks`` are extra SB3 callbacks.

    Resuming reads the run's saved config (the given one only names the run), loads the newest
    checkpoint (model, optimizer, VecNormalize statistics, step count) and trains for the rest of the
    same ``total_timesteps``; TensorBoard events and ``eval.csv`` continue where the checkpoint was.
    """
    from stable_baselines3.common.utils import set_random_seed

    th.set_num_threads(max(1, cfg.torch_threads))
    run_dir = cfg.run_dir
    state: dict[str, Any] = {"wall_time": 0.0, "last_eval": None, "t0": time.time()}
    ckpt = latest_checkpoint(run_dir) if resume else None
    commands: list[str] = []
    if resume:
        saved = run_dir / "config.json"
        if not saved.exists():
            raise FileNotFoundError(f"nothing to resume: {saved} does not exist")
        given = cfg
        cfg, commands = read_run_config(saved)
        cfg.progress_bar = given.progress_bar
        if ckpt is None and (run_dir / "final").exists():
            # (it trained again from step 0 over the finished run's policy, eval.csv and tb/)
            raise FileExistsError(f"{run_dir} holds a finished run with no checkpoint to resume from (it ended before "
                                  f"its first --checkpoint-freq steps): its policy is {run_dir / 'final'}; train "
                                  "another run name to train again")
        if (run_dir / "final" / "summary.json").exists():
            # (it restored the last checkpoint, taken before the last rollout's update, and wrote it as final/: the
            # finished policy replaced by an older one, its last evaluation dropped from summary.json, exit 0)
            raise FileExistsError(f"{run_dir} holds a finished run: its policy is {run_dir / 'final'}, nothing is left "
                                  "to resume; train another run name to train again")
        if ckpt is None:
            log.info("resume: no checkpoint in %s, starting from step 0", run_dir)
    elif ((run_dir / "checkpoints").exists() and any((run_dir / "checkpoints").iterdir())) or (run_dir / "final").exists():
        # (a finished run shorter than --checkpoint-freq has no checkpoint: it was overwritten without a word)
        raise FileExistsError(f"{run_dir} already holds a run; pass resume=True (--resume) or another run name")
    demos = None
    if cfg.bc_demos:  # (read and checked before anything is built or written)
        from agents.imitation import demo_samples, read_demo_folder

        demos = demo_samples(read_demo_folder(cfg.bc_demos, cfg.env_id), cfg.env_id, cfg.braking)
    check_env_settings(cfg)  # (before config.json is written: a run is never saved with settings its env refuses)
    if ckpt is not None:  # (and its progress and eval.csv: a resume that fails on them changes nothing)
        progress, step = read_progress(ckpt)
        eval_csv = _eval_csv_up_to(run_dir / "eval.csv", step)
    run_dir.mkdir(parents=True, exist_ok=True)

    tb_dir = run_dir / "tb"
    if ckpt is not None:
        # Fresh episodes after the interruption; a different env seed so they are not a replay.
        env = make_env(cfg, seed=(cfg.seed + step) % 2**32)
        model = build_model(cfg, env, tb_dir)
        restore_checkpoint(model, _vecnorm_of(env), ckpt)  # (a bad checkpoint: refused before anything is written)
        if eval_csv is not None:
            write_atomic(run_dir / "eval.csv", eval_csv)
        set_random_seed((cfg.seed + step) % 2**32)  # (after the build, which seeds with cfg.seed)
        model.num_timesteps = step
        state.update(wall_time=float(progress["wall_time"]), last_eval=progress.get("last_eval"))
        log.info("resume: %s, %d of %d steps done", ckpt.name, step, cfg.total_timesteps)
    else:
        step = 0
        (run_dir / "eval.csv").unlink(missing_ok=True)
        shutil.rmtree(tb_dir, ignore_errors=True)
        env = make_env(cfg)
        model = build_model(cfg, env, tb_dir)
        if cfg.init_policy:
            start_from(model, env, cfg)
    if command:
        commands.append(command)
    write_json_atomic(run_dir / "config.json", {"config": cfg.to_dict(), "commands": commands})

    remaining = cfg.total_timesteps - step
    if remaining > 0:
        run_callbacks, evaluation = _callbacks(cfg, run_dir, state, demos)
        model.learn(total_timesteps=remaining, callback=[run_callbacks, *(callbacks or [])],
                    reset_num_timesteps=ckpt is None, tb_log_name="PPO", progress_bar=cfg.progress_bar)
        if state["last_eval"] != model.num_timesteps:
            evaluation.evaluate()  # the final policy is the learning curve's last point
    wall = state["wall_time"] + time.time() - state["t0"]
    final = save_model_files(model, _vecnorm_of(env), run_dir / "final", export=True, summary=True, extra={
        "num_timesteps": int(model.num_timesteps), "wall_time": wall, "braking": cfg.braking, "seed": cfg.seed,
        "config": cfg.to_dict(), "commands": commands, "last_eval": state.get("last_eval_row"),
        "stopped_by_time_limit": bool(state.get("timed_out")),
    })
    env.close()
    return json.loads((final / "summary.json").read_text())


# ---------------------------------------------------------------------------------------------- shipping
def export_policy(run_dir: str | os.PathLike, out_dir: str | os.PathLike, name: str, n_episodes: int = 100,
                  init_noise: float = 1.0, extra: dict[str, Any] | None = None, front: Any = None,
                  *, score: bool = True, trust_pickle: bool = False) -> dict[str, Any]:
    """Ship a run's final policy as the pickle-free ``out_dir/<name>.safetensors``, ``<name>_vecnormalize.npz``
    and ``<name>.json`` (network, config, commands, steps, wall time and a fresh deterministic evaluation,
    scored against ``front`` or else :func:`mpc.benchmark.pareto.pareto_front`; not scored if ``score`` is false).

    The policy is read from the run's ``final/policy.*`` (no pickle); a run from before those files has only
    ``final/model.zip``, read with ``trust_pickle=True``.
    """
    from agents.seeds import read_summary

    n_episodes = check_n_episodes(n_episodes)  # (before the front's solve: it failed after it)
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    final = run_dir / "final"
    summary = read_summary(final / "summary.json")  # (checked, bounded: a FIFO there hung, a bad one was a KeyError)
    if not isinstance(summary.get("config"), dict):
        raise ValueError(f"{final / 'summary.json'} is not a readable run summary: it holds no \"config\" object")
    cfg = PPOConfig.from_dict(summary["config"])
    source = final / "policy" if PolicyFiles.of(final / "policy").weights.exists() else final / "model.zip"
    policy = load_policy(source, trust_pickle=trust_pickle)
    if front is None and score:
        try:
            from mpc.benchmark.pareto import pareto_front

            front = pareto_front(cfg.braking)
        except Exception as e:  # noqa: BLE001
            log.warning("no Pareto front, the evaluation is not scored (%s)", e)
    ev = evaluate(policy.act, cfg.braking, n_episodes, init_noise, env_kwargs=cfg.env_kwargs(),
                  with_score=front is not None, front=front, env_id=cfg.env_id)
    if front is not None:
        ev["optimum"] = {"T_min": front.T_min, "fuel_at_T_g": front.fuel_at(ev["T"]) if front.T_min <= ev["T"]
                         < front.T_fuel_opt else None, "T_fuel_opt": front.T_fuel_opt, "fuel_min_g": front.fuel_min_g}
    meta = {
        "name": name, "braking": cfg.braking, "seed": cfg.seed, "num_timesteps": summary["num_timesteps"],
        "training_wall_time_s": round(float(summary["wall_time"]), 1), "commands": summary.get("commands", []),
        "config": summary["config"], "env_kwargs": cfg.env_kwargs(),
        "evaluation": {"deterministic": True, "episodes": n_episodes, "init_noise": init_noise,
                       "seed": 10_000, **ev},
        **(extra or {}),
    }
    files = write_policy(policy.network, policy.normalization, out_dir / name, meta)
    return json.loads(files.metadata.read_text())
