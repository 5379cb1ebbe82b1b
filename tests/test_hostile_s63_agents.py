"""Hostile input, stop 63's round on ``agents``: each test fails on the code before its fix."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from fakes import in_thread

import wl_env  # noqa: F401  (registers the envs)
from agents.imitation import read_demo
from agents.operator import OperatorPolicy
from agents.policy_files import PolicyFileError
from agents.ppo import PPOConfig, latest_checkpoint, load_policy, read_run_config
from agents.seeds import read_summary

POLICIES = Path(__file__).resolve().parent.parent / "agents" / "policies"


def _not_real_numbers(obs: np.ndarray) -> list:
    """Observations of no real numbers (and a masked one), each of the shape of ``obs``."""
    return [obs.astype(bool), obs.astype(complex) + 1j, np.array([str(v) for v in obs]), {"a": 1},
            np.ma.masked_array(obs, mask=[True] + [False] * (len(obs) - 1))]


def test_the_operator_refuses_an_observation_of_no_real_numbers_by_name():
    """The operator cast its observation to float64 before the codec's check: a bool array (the engine at omega_max),
    digit strings and complex numbers (imaginary part dropped) were driven on without a word, a dict was float()'s
    bare TypeError."""
    obs, _ = gym.make("WheelLoader-v1").reset(seed=0)
    op = OperatorPolicy("service")
    for bad in _not_real_numbers(obs):
        with pytest.raises(ValueError, match=r"obs must be WheelLoader observations \(arrays of real numbers\)"):
            op.act(bad)
        if isinstance(bad, np.ndarray):
            with pytest.raises(ValueError, match=r"obs must be WheelLoader observations"):
                op.act(bad[None])  # (a batch the same)
    # real numbers of any width act as before
    expected = op.act(obs)
    np.testing.assert_array_equal(op.act(obs.astype(np.float64)), expected)
    np.testing.assert_array_equal(op.act(obs.tolist()), expected)
    np.testing.assert_array_equal(op.act(obs[None])[0], expected)


def test_a_learned_policy_refuses_an_observation_of_no_real_numbers_by_name():
    """``PPOPolicy.act`` cast to float64 first: a complex observation lost its imaginary part (a warning only), a bool
    one was read as 0/1, a masked entry as the value under its mask, and strings or ragged lists were numpy's bare
    errors, naming no observation."""
    policy = load_policy(POLICIES / "ppo_target_service")
    obs, _ = gym.make(policy.env_id).reset(seed=0)
    for bad in [*_not_real_numbers(obs)[:3], _not_real_numbers(obs)[4], ["a"] * len(obs), [[1.0, 2.0], [3.0]]]:
        with pytest.raises(ValueError, match=r"obs must be WheelLoader observations \(arrays of real numbers\)"):
            policy.act(bad)
    expected = policy.act(obs)
    np.testing.assert_array_equal(policy.act(obs.tolist()), expected)
    np.testing.assert_array_equal(policy.act(np.ma.masked_array(obs, mask=False)), expected)
    np.testing.assert_allclose(policy.act(np.stack([obs, obs]))[1], expected, atol=1e-6)  # (torch's batched sums)


def _tampered_normalization(tmp_path: Path, **changes) -> Path:
    """A copy of the shipped TC policy whose normalization file has ``changes`` (entry -> value), resealed."""
    for part in (".safetensors", "_vecnormalize.npz", ".json"):
        shutil.copy(POLICIES / f"ppo_tc{part}", tmp_path / f"ppo_tc{part}")
    npz = tmp_path / "ppo_tc_vecnormalize.npz"
    with np.load(npz) as f:
        data = {k: f[k] for k in f.files}
    for key, value in changes.items():
        if isinstance(value, dict):  # entries of an array
            data[key] = data[key].copy()
            for i, v in value.items():
                data[key][i] = v
        else:
            data[key] = np.float64(value)
    buf = io.BytesIO()
    np.savez(buf, **data)
    npz.write_bytes(buf.getvalue())
    meta_path = tmp_path / "ppo_tc.json"
    meta = json.loads(meta_path.read_text())
    meta["files"]["normalization"]["sha256"] = hashlib.sha256(buf.getvalue()).hexdigest()
    meta_path.write_text(json.dumps(meta))
    return tmp_path / "ppo_tc"


def test_a_normalization_whose_clip_lets_an_infinite_observation_through_is_refused(tmp_path):
    """clip_obs 1e308 (finite, > 0: accepted) with a mean of 1e308 over a var of 0: the normalized observation
    overflowed to -inf and was fed to the network, which acted on it. The normalized observations are float32: clip_obs
    lies within float32's range, so they stay finite."""
    stem = _tampered_normalization(tmp_path, clip_obs=1e308, epsilon=1e-12, mean={0: 1e308}, var={0: 0.0})
    with pytest.raises(PolicyFileError, match=r"ppo_tc_vecnormalize.npz: clip_obs must be a finite number > 0, at most 3.403e\+38"):
        load_policy(stem)
    # at float32's largest the same statistics give finite (if absurd) observations
    stem = _tampered_normalization(tmp_path, clip_obs=float(np.finfo(np.float32).max), epsilon=1e-12,
                                   mean={0: 1e308}, var={0: 0.0})
    policy = load_policy(stem)
    obs, _ = gym.make("WheelLoader-v1", braking="tc").reset(seed=0)
    assert np.isfinite(policy.normalize(obs)).all()


def _npy(array: np.ndarray, shape: tuple[int, ...] | None = None) -> bytes:
    """``array`` as .npy bytes, its header claiming ``shape`` (default: its own)."""
    buf = io.BytesIO()
    np.save(buf, array)
    raw = buf.getvalue()
    if shape is None:
        return raw
    n = int.from_bytes(raw[8:10], "little")
    header = raw[10:10 + n].decode("latin1").replace(str(array.shape), str(shape)).rstrip()
    header = header + " " * (n - len(header) - 1) + "\n"
    assert len(header) == n
    return raw[:10] + header.encode("latin1") + raw[10 + n:]


def test_a_demonstration_whose_header_claims_a_huge_array_is_one_error_naming_the_file(tmp_path):
    """A demonstration file (``--bc-demos``) whose obs header claims 2^45 values was numpy's MemoryError, a
    traceback (the policy files' normalization was fixed for this at stop 38)."""
    meta = {"env_id": "WheelLoaderTarget-v6", "success": True, "max_violation": 0.0, "scenario": {}}
    path = tmp_path / "episode_00000.npz"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("obs.npy", _npy(np.zeros((3, 21)), (2**22, 2**23)))
        z.writestr("actions.npy", _npy(np.zeros((3, 4))))
        z.writestr("meta.npy", _npy(np.array(json.dumps(meta))))
    with pytest.raises(ValueError, match="episode_00000.npz is not a demonstration file"):
        read_demo(path)


def test_a_fifo_in_place_of_a_run_folders_json_is_refused_not_a_hang(tmp_path):
    """A FIFO as a run's ``checkpoints/latest.json`` (read on every ``--resume`` and by ``--seeds``' read-back),
    ``config.json`` or ``final/summary.json`` blocked the read for good: each is read as a regular file of bounded
    size (the pointer is passed over, as an unreadable one was; the others are an error naming the file)."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "final").mkdir()
    fifos = [run / "checkpoints" / "latest.json", run / "config.json", run / "final" / "summary.json"]
    for fifo in fifos:
        os.mkfifo(fifo)
    try:
        assert in_thread(lambda: latest_checkpoint(run)) is None
        with pytest.raises(ValueError, match="config.json is not a readable run config: .*not a regular file"):
            in_thread(lambda: read_run_config(run / "config.json"))
        with pytest.raises(ValueError, match="summary.json is not a readable run summary: not a regular file"):
            in_thread(lambda: read_summary(run / "final" / "summary.json"))
    finally:
        for fifo in fifos:  # (a thread left blocked on one is released by opening its other end)
            try:
                fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
                os.close(fd)
            except OSError:
                pass
    # the same files as regular ones are read as before
    for fifo in fifos:
        fifo.unlink()
    cfg = PPOConfig(log_dir=str(tmp_path), run_name="run", num_envs=2, n_steps=8, batch_size=16)
    (run / "config.json").write_text(json.dumps({"config": cfg.to_dict(), "commands": ["wl train"]}))
    assert read_run_config(run / "config.json")[0].to_dict() == cfg.to_dict()
    (run / "final" / "summary.json").write_text(json.dumps({"num_timesteps": 5, "wall_time": 1.0, "last_eval": None}))
    assert read_summary(run / "final" / "summary.json")["num_timesteps"] == 5


def test_export_refuses_a_run_summary_that_is_a_fifo_or_has_no_config(tmp_path):
    """export_policy read final/summary.json with a plain read: a FIFO there hung for good, a summary without its
    config was a bare KeyError."""
    from agents.ppo import export_policy

    final = tmp_path / "run" / "final"
    final.mkdir(parents=True)
    os.mkfifo(final / "summary.json")
    try:
        with pytest.raises(ValueError, match="summary.json is not a readable run summary"):
            in_thread(lambda: export_policy(tmp_path / "run", tmp_path / "out", "p"))
    finally:
        (final / "summary.json").unlink()
    (final / "summary.json").write_text(json.dumps({"num_timesteps": 10, "wall_time": 1.0, "last_eval": None}))
    with pytest.raises(ValueError, match='holds no "config" object'):
        export_policy(tmp_path / "run", tmp_path / "out", "p")
