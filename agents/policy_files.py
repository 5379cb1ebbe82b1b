"""Policy files that load without pickle: the shipped policies (``agents/policies/``) and every export.

A policy ``<stem>`` is three files::

    <stem>.safetensors            the policy network's weights (safetensors: tensors only, never code)
    <stem>_vecnormalize.npz       the observation normalization: mean, var, clip_obs, epsilon, norm_obs
                                  (read with ``np.load(allow_pickle=False)``)
    <stem>.json                   metadata: the network (class, net_arch, activation, mean bound...), the
                                  observation and action spaces, braking, the PPOConfig, the evaluation,
                                  and the sha256 of the two other files

Loading rebuilds the torch module from the metadata (only the classes and activations listed here) and
loads the weights into it: nothing in these files is executed. A stable-baselines3 zip (``model.zip`` +
``vecnormalize.pkl``) unpickles objects, which can run any code; it is loaded only with
``trust_pickle=True`` (``wl evaluate --trust-pickle``) and can be converted once to these files::

    python -m agents.policy_files IN.zip OUT_STEM --trust-pickle
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import math
import os
import stat
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from wl_env.params import is_finite

FORMAT = "wl-ppo-policy"
FORMAT_VERSION = 1
WEIGHTS_SUFFIX = ".safetensors"
NORMALIZATION_SUFFIX = "_vecnormalize.npz"
METADATA_SUFFIX = ".json"
PICKLE_SUFFIXES = (".zip", ".pkl")
NORMALIZATION_ENTRIES = ("mean", "var", "clip_obs", "epsilon", "norm_obs")

# The only torch classes a file can name (a name is looked up here, never imported).
ACTIVATIONS = ("Tanh", "ReLU", "ELU", "LeakyReLU", "SiLU", "GELU", "Sigmoid")
POLICY_CLASSES = ("ActorCriticPolicy", "BoundedMeanPolicy")
MAX_LAYER_WIDTH, MAX_LAYERS, MAX_DIM = 4096, 16, 1024
FLOAT32_MAX = float(np.finfo(np.float32).max)  # a space's bounds are float32 (a larger one turned inf, with a warning)


class PolicyFileError(ValueError):
    """A policy file that is missing, unreadable or inconsistent; the message names the file."""


def check_policy_output(path: str | Path, option: str) -> Path:
    """The path ``PATH`` of a policy to be written as PATH.safetensors, PATH_vecnormalize.npz and PATH.json, each
    checked before the work (:func:`wl_env.atomic_io.check_output_file`): a ValueError naming ``option`` if one is a
    folder, a pipe or a device, or their folder cannot be written in (a folder at PATH_vecnormalize.npz failed the
    export after the training)."""
    from wl_env.atomic_io import check_output_file

    if not str(path).strip():
        raise ValueError(f"{option} must name the policy's path (PATH.safetensors, ...), got an empty string")
    path = Path(path)
    for suffix in (WEIGHTS_SUFFIX, NORMALIZATION_SUFFIX, METADATA_SUFFIX):
        check_output_file(path.with_name(path.name + suffix), f"{option} {path}")
    return path


@dataclass(frozen=True)
class PolicyFiles:
    """The three files of a pickle-free policy."""

    weights: Path
    normalization: Path
    metadata: Path

    @classmethod
    def of(cls, stem: str | Path) -> PolicyFiles:
        stem = Path(stem)
        for suffix in (WEIGHTS_SUFFIX, METADATA_SUFFIX):  # the stem of any of its files
            if stem.name.endswith(suffix):
                stem = stem.with_name(stem.name[: -len(suffix)])
        if stem.name.endswith(NORMALIZATION_SUFFIX):
            stem = stem.with_name(stem.name[: -len(NORMALIZATION_SUFFIX)])
        return cls(stem.with_name(stem.name + WEIGHTS_SUFFIX), stem.with_name(stem.name + NORMALIZATION_SUFFIX),
                   stem.with_name(stem.name + METADATA_SUFFIX))

    def missing(self) -> list[Path]:
        """The files that do not exist (one that is there but no regular file, a FIFO say, is refused by name when
        read: it was called missing)."""
        return [p for p in (self.weights, self.normalization, self.metadata) if not p.exists()]


@dataclass(frozen=True)
class ObsNormalization:
    """VecNormalize's observation statistics: z = clip((obs - mean) / sqrt(var + epsilon), +-clip_obs)."""

    mean: np.ndarray
    var: np.ndarray
    clip_obs: float = 10.0
    epsilon: float = 1e-8

    def apply(self, obs: np.ndarray) -> np.ndarray:
        z = (np.asarray(obs, dtype=np.float32) - self.mean) / np.sqrt(self.var + self.epsilon)
        return np.clip(z, -self.clip_obs, self.clip_obs).astype(np.float32)

    @classmethod
    def of_vecnormalize(cls, vn: Any) -> ObsNormalization | None:
        """The statistics of a stable-baselines3 ``VecNormalize`` (None if it does not normalize obs)."""
        if vn is None or not getattr(vn, "norm_obs", True):
            return None
        return cls(np.array(vn.obs_rms.mean, dtype=np.float64), np.array(vn.obs_rms.var, dtype=np.float64),
                   float(vn.clip_obs), float(vn.epsilon))


def brief(exc: BaseException, limit: int = 160) -> str:
    """An exception as one short line: its type and the start of its message."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:limit] + ' ...' if len(text) > limit else text}"


def sha256(path: Path) -> str:
    with open(path, "rb") as f:  # (streamed: a file is not read whole into memory to be hashed)
        return hashlib.file_digest(f, "sha256").hexdigest()


# ---------------------------------------------------------------------------------------------- describe
def _space(space: Any, what: str) -> dict[str, Any]:
    from gymnasium import spaces

    if not isinstance(space, spaces.Box) or space.dtype != np.float32:
        raise ValueError(f"cannot export a policy whose {what} space is {space} (only float32 Box spaces)")
    return {"shape": list(space.shape), "low": space.low.tolist(), "high": space.high.tolist(), "dtype": "float32"}


def describe_network(policy: Any) -> dict[str, Any]:
    """The constructor arguments of an SB3 ``ActorCriticPolicy`` (or ``BoundedMeanPolicy``) as JSON."""
    from stable_baselines3.common.torch_layers import FlattenExtractor

    cls = type(policy).__name__
    if cls not in POLICY_CLASSES:
        raise ValueError(f"cannot export a {cls}: only {', '.join(POLICY_CLASSES)}")
    c = policy._get_constructor_parameters()
    act = c["activation_fn"].__name__
    if act not in ACTIVATIONS or c["features_extractor_class"] is not FlattenExtractor or c["features_extractor_kwargs"]:
        raise ValueError(f"cannot export a policy with activation {act} and features extractor "
                         f"{c['features_extractor_class'].__name__} (supported: {', '.join(ACTIVATIONS)}; FlattenExtractor)")
    net_arch = c["net_arch"]
    return {
        "class": cls, "net_arch": dict(net_arch) if isinstance(net_arch, dict) else list(net_arch),
        "activation_fn": act, "ortho_init": bool(c["ortho_init"]), "use_sde": bool(c["use_sde"]),
        "log_std_init": float(c["log_std_init"]), "full_std": bool(c["full_std"] if c["full_std"] is not None else True),
        "use_expln": bool(c["use_expln"] or False), "squash_output": bool(c["squash_output"] or False),
        "share_features_extractor": bool(policy.share_features_extractor),
        "normalize_images": bool(c["normalize_images"]),
        "mean_bound": float(policy.mean_bound) if cls == "BoundedMeanPolicy" else None,
        "observation_space": _space(c["observation_space"], "observation"),
        "action_space": _space(c["action_space"], "action"),
    }


# ---------------------------------------------------------------------------------------------- write
def write_policy(policy: Any, normalization: ObsNormalization | None, stem: str | Path,
                 meta: dict[str, Any] | None = None) -> PolicyFiles:
    """Write ``policy`` (an SB3 ActorCriticPolicy) and its normalization as the three files of ``stem``.

    Each file is written atomically; the metadata last (it holds the others' checksums), so a reader
    never sees a metadata file whose weights are not complete.
    """
    import torch as th
    from safetensors.torch import save as save_tensors

    from wl_env.atomic_io import write_atomic, write_json_atomic

    files = PolicyFiles.of(stem)
    network = describe_network(policy)
    obs_dim = network["observation_space"]["shape"]
    norm = normalization or ObsNormalization(np.zeros(obs_dim), np.ones(obs_dim), math.inf, 0.0)
    buf = io.BytesIO()
    np.savez(buf, mean=np.asarray(norm.mean, np.float64), var=np.asarray(norm.var, np.float64),
             clip_obs=np.float64(norm.clip_obs), epsilon=np.float64(norm.epsilon),
             norm_obs=np.bool_(normalization is not None))
    out = {k: v for k, v in (meta or {}).items() if k not in ("format", "format_version", "network", "files",
                                                               "obs_normalization")}
    # What reading the policy refuses, refused before any file is written: a NaN mean, a negative variance or a
    # braking "x" was written (over a policy there too), and the policy no longer loaded.
    try:
        check_metadata_fields(out, files.metadata)
        env_id = (out.get("config") or {}).get("env_id")
        if env_id is not None:  # (a policy whose env takes other observations or actions was written, then not loaded)
            from agents.ppo import check_policy_env

            check_policy_env(policy, env_id)
        read_normalization(files.normalization, obs_dim[0], buf.getvalue())
    except PolicyFileError as exc:
        raise PolicyFileError(f"policy {files.weights.with_suffix('')} not written: {exc}") from None
    state = {k: v.detach().to("cpu", th.float32).contiguous() for k, v in policy.state_dict().items()}
    write_atomic(files.weights, save_tensors(state))
    write_atomic(files.normalization, buf.getvalue())
    out.update(format=FORMAT, format_version=FORMAT_VERSION, network=network, files={
        "weights": {"name": files.weights.name, "sha256": sha256(files.weights)},
        "normalization": {"name": files.normalization.name, "sha256": sha256(files.normalization)}})
    write_json_atomic(files.metadata, out, indent=2, nan_as_null=True)
    return files


# ---------------------------------------------------------------------------------------------- read
# The files' sizes at most (bytes): a few bytes of JSON padded to 400 MB took 1 GB to read, and were accepted
MAX_METADATA_BYTES, MAX_WEIGHTS_BYTES = 2**20, 2**30
MAX_TENSORS = 4 * MAX_LAYERS + 16  # (a million empty tensors in a 75 MB file took 22 s and 1.7 GB before any check)


def _read_file(path: Path, most: int, what: str) -> bytes:
    """The bytes of one of a policy's files, read once by :func:`wl_env.atomic_io.read_regular_file` (a regular file of
    at most ``most`` bytes, checked on the file opened): PolicyFileError naming it otherwise. (A FIFO was called
    missing, or blocked the hash of the weights for good; the size was checked, then the file read separately.)"""
    from wl_env.atomic_io import read_regular_file

    try:
        info = os.stat(path)
        if stat.S_ISREG(info.st_mode) and info.st_size > most:  # (said before any byte is read, as it always was)
            raise PolicyFileError(f"{what} {path} is {info.st_size} bytes; a policy's is at most {most}")
        return read_regular_file(path, most, f"a policy's {what}")
    except PolicyFileError:
        raise
    except FileNotFoundError:
        raise PolicyFileError(f"{what} {path} is missing") from None
    except (OSError, ValueError) as exc:  # not a regular file, a folder, no permission, a file that grew
        raise PolicyFileError(f"{what} {path} is unreadable: {' '.join(str(exc).split())}") from None


def read_metadata(files: PolicyFiles) -> dict[str, Any]:
    """The metadata, checked: format, network description, checksums of the weights and normalization."""
    return _read_checked(files)[0]


def _read_checked(files: PolicyFiles) -> tuple[dict[str, Any], bytes, bytes]:
    """(metadata, weights, normalization): the metadata checked, and the bytes of the other two, each read once and
    checked against its checksum there (what is loaded is what was checked)."""
    path = files.metadata
    raw = _read_file(path, MAX_METADATA_BYTES, "policy metadata")
    try:
        meta = json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError) as exc:  # (nested too deeply; an integer of 5000 digits; not UTF-8)
        raise PolicyFileError(f"policy metadata {path} is unreadable: {brief(exc)}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise PolicyFileError(f"{path} is not policy metadata (no \"format\": \"{FORMAT}\"); a pickle-free policy is "
                              f"written by `wl train --export` or `python -m agents.policy_files`")
    if meta.get("format_version") != FORMAT_VERSION:
        raise PolicyFileError(f"{path}: format_version {meta.get('format_version')!r}, this version reads {FORMAT_VERSION}")
    _check_network(meta.get("network"), path)
    check_metadata_fields(meta, path)
    recorded = meta.get("files")
    contents = []
    for key, file, most in (("weights", files.weights, MAX_WEIGHTS_BYTES),
                            ("normalization", files.normalization, MAX_NORMALIZATION_BYTES)):
        entry = recorded.get(key) if isinstance(recorded, dict) else None
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
            raise PolicyFileError(f"{path}: files.{key}.sha256 is missing")
        # (the size before the hash: a 1.2 GB file took 5 s and 1.4 GB of memory to be refused)
        data = _read_file(file, most, f"{key} file")
        if hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise PolicyFileError(f"{file} does not match its metadata {path.name} (sha256 differs): a corrupt or "
                                  f"mixed-up file")
        contents.append(data)
    return meta, contents[0], contents[1]


def check_metadata_fields(meta: dict[str, Any], path: Path) -> None:
    """The metadata's braking, config and env id, as the policy's reader takes them (PolicyFileError naming ``path``)."""
    if meta.get("braking") not in (None, "service", "tc"):
        raise PolicyFileError(f"{path}: braking must be \"service\" or \"tc\" (or absent), got {meta.get('braking')!r}")
    config = meta.get("config")
    if config is not None and not isinstance(config, dict):
        raise PolicyFileError(f"{path}: config must be an object (the training options), got {type(config).__name__}")
    env_id = (config or {}).get("env_id")
    if env_id is not None and not isinstance(env_id, str):
        raise PolicyFileError(f"{path}: config.env_id must be an env id string, got {env_id!r}")


def _check_network(net: Any, path: Path) -> None:
    def fail(what: str) -> None:
        raise PolicyFileError(f"{path}: network.{what}")

    if not isinstance(net, dict):
        fail("is missing")
    if net.get("class") not in POLICY_CLASSES:
        fail(f"class must be one of {POLICY_CLASSES}, got {net.get('class')!r}")
    if net.get("activation_fn") not in ACTIVATIONS:
        fail(f"activation_fn must be one of {ACTIVATIONS}, got {net.get('activation_fn')!r}")
    arch = net.get("net_arch")
    layers = list(arch.values()) if isinstance(arch, dict) and set(arch) <= {"pi", "vf"} else [arch]
    for widths in layers:
        if not (isinstance(widths, list) and len(widths) <= MAX_LAYERS
                and all(type(w) is int and 1 <= w <= MAX_LAYER_WIDTH for w in widths)):
            fail(f"net_arch must be a list (or {{pi, vf}} lists) of at most {MAX_LAYERS} widths in 1..{MAX_LAYER_WIDTH}, "
                 f"got {arch!r}")
    for key in ("ortho_init", "use_sde", "full_std", "use_expln", "squash_output", "share_features_extractor",
                "normalize_images"):
        if type(net.get(key)) is not bool:
            fail(f"{key} must be true or false, got {net.get(key)!r}")
    if not _finite_number(net.get("log_std_init")):
        fail(f"log_std_init must be a finite number, got {net.get('log_std_init')!r}")
    if net["squash_output"] and not net["use_sde"]:  # (stable-baselines3 asserts it)
        fail("squash_output must be false unless use_sde is true (stable-baselines3 squashes gSDE actions only)")
    if net["class"] == "BoundedMeanPolicy" and not (_finite_number(net.get("mean_bound")) and net["mean_bound"] > 0):
        fail(f"mean_bound must be a number > 0, got {net.get('mean_bound')!r}")
    for key in ("observation_space", "action_space"):
        space = net.get(key)
        shape = space.get("shape") if isinstance(space, dict) else None
        if not (isinstance(shape, list) and len(shape) == 1 and type(shape[0]) is int and 1 <= shape[0] <= MAX_DIM):
            fail(f"{key}.shape must be [n] with 1 <= n <= {MAX_DIM}, got {shape!r}")
        for bound in ("low", "high"):
            values = space.get(bound)
            if not (isinstance(values, list) and len(values) == shape[0]
                    and all(_finite_number(v) and abs(v) <= FLOAT32_MAX for v in values)):
                fail(f"{key}.{bound} must be {shape[0]} finite numbers (float32: within +-{FLOAT32_MAX:.4g})")


def _finite_number(v: Any) -> bool:
    return type(v) in (int, float) and is_finite(v)


def _least_parameters(net: dict[str, Any]) -> int:
    """How many numbers the (checked) network description's layers hold at least (its gSDE noise not counted)."""
    n_obs, n_act = net["observation_space"]["shape"][0], net["action_space"]["shape"][0]
    arch = net["net_arch"]
    pi, vf = (arch.get("pi", []), arch.get("vf", [])) if isinstance(arch, dict) else (arch, arch)

    def mlp(widths: list[int]) -> tuple[int, int]:  # (weights and biases, output width)
        n, prev = 0, n_obs
        for w in widths:
            n, prev = n + prev * w + w, w
        return n, prev

    (n_pi, last_pi), (n_vf, last_vf) = mlp(pi), mlp(vf)
    return n_pi + n_vf + last_pi * n_act + n_act + last_vf + 1 + (0 if net["use_sde"] else n_act)


def build_network(net: dict[str, Any]) -> Any:
    """The torch module a (checked) network description names, with fresh weights."""
    from gymnasium import spaces
    from stable_baselines3.common.policies import ActorCriticPolicy
    from torch import nn

    from agents.ppo import BoundedMeanPolicy

    def box(d: dict[str, Any]) -> spaces.Box:
        return spaces.Box(np.array(d["low"], np.float32), np.array(d["high"], np.float32), dtype=np.float32)

    kwargs: dict[str, Any] = {k: net[k] for k in ("ortho_init", "use_sde", "full_std", "use_expln",
                                                 "squash_output", "share_features_extractor", "normalize_images")}
    kwargs["log_std_init"] = float(net["log_std_init"])  # (an int of 30 digits overflowed torch's int64)
    kwargs.update(net_arch=net["net_arch"], activation_fn=getattr(nn, net["activation_fn"]))
    if net["class"] == "BoundedMeanPolicy":
        cls, kwargs["mean_bound"] = BoundedMeanPolicy, float(net["mean_bound"])
    else:
        cls = ActorCriticPolicy
    policy = cls(box(net["observation_space"]), box(net["action_space"]), lambda _: 0.0, **kwargs)
    return policy.eval()


MAX_NORMALIZATION_VALUES = 4096  # per entry: the statistics are a few floats per observation
# the whole file: five entries of at most that many float64 values, with their zip and .npy headers
MAX_NORMALIZATION_BYTES = 5 * (8 * MAX_NORMALIZATION_VALUES + 1024)


def _check_entry_sizes(path: Path, data: bytes | None = None) -> None:
    """Each entry's shape, from its .npy header, before any array is read: a crafted header would have numpy
    allocate what it claims (2^45 floats: a MemoryError), a crafted entry be inflated whole. (``data``: the file's
    bytes, read already.)"""
    with zipfile.ZipFile(path if data is None else io.BytesIO(data)) as z:
        for info in z.infolist():
            with z.open(info) as f:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(f, max_header_size=1000)
            if Path(info.filename).stem not in NORMALIZATION_ENTRIES:  # (300 000 extra entries: 14 s, accepted)
                raise PolicyFileError(f"normalization file {path}: entry {info.filename[:80]!r} is none of "
                                      f"{', '.join(NORMALIZATION_ENTRIES)}")
            if math.prod(shape) > MAX_NORMALIZATION_VALUES or info.file_size > 64 * MAX_NORMALIZATION_VALUES:
                raise PolicyFileError(f"normalization file {path}: entry {info.filename!r} holds {shape} values "
                                      f"({info.file_size} bytes); the statistics are at most "
                                      f"{MAX_NORMALIZATION_VALUES} values each")


def read_normalization(path: Path, obs_dim: int, raw: bytes | None = None) -> ObsNormalization | None:
    """The statistics of a ``_vecnormalize.npz`` (no pickle), checked; None if the policy does not normalize.
    ``raw``: the file's bytes, read (and checked against the metadata's checksum) already; else the file is read
    (a regular file, bounded)."""
    try:
        if raw is None:
            raw = _read_file(path, MAX_NORMALIZATION_BYTES, "normalization file")
        _check_entry_sizes(path, raw)
        with np.load(io.BytesIO(raw), allow_pickle=False, max_header_size=1000) as f:
            absent = [k for k in NORMALIZATION_ENTRIES if k not in f.files]
            if absent:
                raise PolicyFileError(f"normalization file {path} has no entry {', '.join(map(repr, absent))} "
                                      f"(needs {', '.join(NORMALIZATION_ENTRIES)})")
            data = {k: f[k] for k in NORMALIZATION_ENTRIES}
    except PolicyFileError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, MemoryError) as exc:  # truncated, not an npz, object
        # arrays; a dtype of 2 GB per item ('|S2000000000') under the value cap: 7 TiB asked of numpy
        raise PolicyFileError(f"normalization file {path} is unreadable: {brief(exc)}") from None
    scalars = {k: data[k] for k in ("clip_obs", "epsilon", "norm_obs")}
    if any(v.shape != () for v in scalars.values()) or scalars["norm_obs"].dtype != np.bool_ or any(
            scalars[k].dtype.kind != "f" for k in ("clip_obs", "epsilon")):
        raise PolicyFileError(f"normalization file {path}: clip_obs and epsilon must be single floats, norm_obs a bool")
    if not data["norm_obs"]:
        return None
    mean, var = data["mean"], data["var"]
    if any(data[k].dtype.itemsize > 8 for k in ("mean", "var", "clip_obs", "epsilon")):  # (1e400 as a long double)
        raise PolicyFileError(f"normalization file {path}: mean, var, clip_obs and epsilon must be float16/32/64")
    return checked_normalization(mean, var, float(data["clip_obs"]), float(data["epsilon"]), obs_dim,
                                 f"normalization file {path}")


def checked_normalization(mean: np.ndarray, var: np.ndarray, clip_obs: float, eps: float, obs_dim: int,
                          where: str) -> ObsNormalization:
    """The statistics of a policy of ``obs_dim`` observations as an :class:`ObsNormalization`, checked (PolicyFileError
    naming ``where``, the file they came from): ``obs_dim`` finite means and variances >= 0, clip_obs and epsilon in
    range. (A stable-baselines3 policy's, from its pickle or its metadata's JSON copy, were taken unchecked: a 1-entry
    mean was broadcast over 12 observations without a word, a NaN one failed in torch at the first act.)"""
    if mean.shape != (obs_dim,) or var.shape != (obs_dim,) or mean.dtype.kind != "f" or var.dtype.kind != "f":
        raise PolicyFileError(f"{where}: mean and var must be {obs_dim} floats, got shapes {mean.shape} and {var.shape}")
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
        raise PolicyFileError(f"{where}: mean and var must be finite, var >= 0")
    # (clip_obs within float32's range: 1e308 let a mean of 1e308 over a var of 0 reach the network as -inf)
    if not (math.isfinite(clip_obs) and 0 < clip_obs <= FLOAT32_MAX and 1e-12 <= eps <= 1.0):
        raise PolicyFileError(f"{where}: clip_obs must be a finite number > 0, at most "
                              f"{FLOAT32_MAX:.4g} (the normalized observations are float32), and epsilon in [1e-12, 1], "
                              f"got {clip_obs}, {eps}")
    return ObsNormalization(mean.astype(np.float64), var.astype(np.float64), clip_obs, eps)


def read_policy(stem: str | Path) -> tuple[Any, ObsNormalization | None, dict[str, Any]]:
    """(network, normalization, metadata) of a pickle-free policy; errors name the missing or bad file."""
    import torch
    from safetensors import SafetensorError
    from safetensors.torch import load as load_tensors

    files = PolicyFiles.of(stem)
    missing = files.missing()
    if missing:
        raise PolicyFileError(f"policy {files.weights.with_suffix('')} is incomplete: missing "
                              f"{', '.join(str(p) for p in missing)} (a policy needs its weights, its normalization "
                              f"and its metadata; without the normalization it acts on wrongly scaled observations)")
    meta, weights, normalization_bytes = _read_checked(files)
    net = meta["network"]
    try:
        _check_tensor_header(weights)
        state = load_tensors(weights)
    except (SafetensorError, OSError, ValueError, MemoryError, RecursionError) as exc:  # (a header nested 100 000 deep)
        raise PolicyFileError(f"weights file {files.weights} is unreadable: {brief(exc)}") from None
    if not all(t.dtype == torch.float32 and bool(t.isfinite().all()) for t in state.values()):
        # (float8 weights failed in isfinite, or loaded and drove another cycle; the exporter writes float32)
        raise PolicyFileError(f"weights file {files.weights}: every weight must be a finite float32")
    held, least = sum(t.numel() for t in state.values()), _least_parameters(net)
    if held < least:  # (before building it: a few bytes of metadata could ask for gigabytes of layers)
        raise PolicyFileError(f"weights file {files.weights} holds {held} numbers; the network of {files.metadata.name} "
                              f"has at least {least}")
    try:
        network = build_network(net)
    except (ValueError, AssertionError) as exc:  # (a space with low > high: gymnasium's error, naming no file)
        raise PolicyFileError(f"policy metadata {files.metadata}: its network cannot be built: {brief(exc)}") from None
    try:
        network.load_state_dict(state, strict=True)
    except RuntimeError as exc:  # missing or unexpected tensors, wrong shapes
        raise PolicyFileError(f"weights file {files.weights} does not fit the network of {files.metadata.name}: "
                              f"{' '.join(str(exc).split())}") from None
    normalization = read_normalization(files.normalization, net["observation_space"]["shape"][0], normalization_bytes)
    return network, normalization, meta


def _check_tensor_header(data: bytes) -> None:
    """The safetensors header alone (its length, then JSON): at most MAX_TENSORS tensors, each float32, before the
    tensors are parsed."""
    n = int.from_bytes(data[:8], "little")
    if not 2 <= n <= 2**20 or len(data) < 8 + n:
        raise ValueError(f"a header of {n} bytes" + (f" in a file of {len(data)}" if 2 <= n <= 2**20 else ""))
    header = json.loads(data[8:8 + n])
    if not isinstance(header, dict):
        raise ValueError("its header is no JSON object")
    tensors = {k: v for k, v in header.items() if k != "__metadata__"}
    if len(tensors) > MAX_TENSORS:
        raise ValueError(f"{len(tensors)} tensors; a policy network has at most {MAX_TENSORS}")
    dtypes = {str(v.get("dtype"))[:40] if isinstance(v, dict) else type(v).__name__ for v in tensors.values()}
    if dtypes - {"F32"}:  # (a dtype of ["F32"] failed as unhashable)
        raise ValueError(f"tensors of dtype {sorted(dtypes - {'F32'})}; the weights are float32 (F32)")


# ---------------------------------------------------------------------------------------------- convert
def convert_sb3_policy(zip_path: str | Path, stem: str | Path, *, trust_pickle: bool = False) -> PolicyFiles:
    """Convert a stable-baselines3 zip (and its VecNormalize pickle and JSON metadata beside it) into the
    pickle-free files of ``stem``. Reading the zip unpickles: only for files you trust."""
    from agents.ppo import load_policy

    policy = load_policy(zip_path, trust_pickle=trust_pickle)
    return write_policy(policy.network, policy.normalization, stem, policy.meta)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agents.policy_files", description=convert_sb3_policy.__doc__)
    parser.add_argument("zip", help="the stable-baselines3 model zip (e.g. runs/NAME/final/model.zip)")
    parser.add_argument("out", help="output stem: writes OUT.safetensors, OUT_vecnormalize.npz, OUT.json")
    parser.add_argument("--trust-pickle", action="store_true", required=True,
                        help="required: the zip and its .pkl are unpickled, which can run code (trusted files only)")
    args = parser.parse_args(argv)
    try:
        files = convert_sb3_policy(args.zip, args.out, trust_pickle=args.trust_pickle)
    except (ValueError, OSError) as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    print(f"{args.zip} -> {files.weights}, {files.normalization}, {files.metadata}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
