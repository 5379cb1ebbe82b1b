"""Hostile input, stop 63's round on loading (``agents``, ``wl_env``): each test fails on the code before its fix."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from fakes import in_thread

import wl_env  # noqa: F401  (registers the envs)
from agents.policy_files import PolicyFileError
from agents.ppo_config import PPOConfig
from wl_env.episode import IntegrationDiverged

POLICIES = Path(__file__).resolve().parent.parent / "agents" / "policies"
SHIPPED = sorted(p.name[: -len(".json")] for p in POLICIES.glob("*.json"))


def _release(fifos) -> None:
    """Open each FIFO's other end: a thread left blocked on one returns."""
    for fifo in fifos:
        try:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            pass


def _copy(name: str, folder: Path) -> Path:
    for part in (".safetensors", "_vecnormalize.npz", ".json"):
        shutil.copy(POLICIES / f"{name}{part}", folder / f"{name}{part}")
    return folder / name


# ------------------------------------------------------------------------------------------ 1: observation bounds
@pytest.mark.parametrize("name, entry, bound, value", [
    ("ppo_tc", 7, "high", 1.0),  # narrower: the env's fuel entry reaches 5
    ("plan_target_tc", 20, "low", 0.0),  # narrower: the target's ratio entry starts at -1
    ("ppo_target_tc", 0, "high", 3.0),  # wider: another observation layout (another scaling of the engine speed)
])
def test_a_policy_whose_observation_bounds_differ_from_its_envs_is_refused_at_loading(tmp_path, name, entry, bound,
                                                                                      value):
    """The metadata's observation space was never compared with the env's: narrower bounds loaded and refused the env's
    own observations at the first act() (``obs[7] must lie in [0, 1]``), naming the controller, not the file."""
    stem = _copy(name, tmp_path)
    meta_path = stem.with_name(f"{name}.json")
    meta = json.loads(meta_path.read_text())
    meta["network"]["observation_space"][bound][entry] = value
    meta_path.write_text(json.dumps(meta))
    from agents.ppo import load_policy

    with pytest.raises(PolicyFileError, match=rf"{name}\.json.*observation space differs from its env .*entry {entry}"):
        load_policy(stem)


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_policy_loads_and_acts_on_its_envs_observations(name):
    """The check refuses none of the shipped policies: each loads and acts on its env's observations."""
    from agents.ppo import load_policy

    policy = load_policy(POLICIES / name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make(policy.env_id, braking=policy.braking or "service")
    obs, _ = env.reset(seed=0)
    assert policy.act(obs).shape == env.action_space.shape
    space = env.observation_space
    batch = np.random.default_rng(0).uniform(space.low, space.high, (16, *space.shape)).astype(np.float32)
    assert np.isfinite(policy.act(batch)).all()


# ------------------------------------------------------------------------------------------ 2: a FIFO is no policy file
@pytest.mark.parametrize("part", [".json", ".safetensors", "_vecnormalize.npz"])
def test_a_fifo_in_place_of_a_policy_file_is_not_a_regular_file_not_missing(tmp_path, part):
    """A FIFO in place of a policy's file was reported as missing (``is incomplete: missing ...``), which it is not;
    each file is read once, as a regular file of bounded size, and the error says what it is."""
    from agents.ppo import load_policy

    stem = _copy("ppo_tc", tmp_path)
    fifo = tmp_path / f"ppo_tc{part}"
    fifo.unlink()
    os.mkfifo(fifo)
    try:
        with pytest.raises(PolicyFileError) as info:
            in_thread(lambda: load_policy(stem))
    finally:
        _release([fifo])
    message = str(info.value)
    assert str(fifo) in message and "not a regular file" in message and "missing" not in message


def test_a_policy_file_that_is_missing_or_a_folder_is_said_so(tmp_path):
    from agents.ppo import load_policy

    stem = _copy("ppo_tc", tmp_path)
    (tmp_path / "ppo_tc_vecnormalize.npz").unlink()
    with pytest.raises(PolicyFileError, match=r"incomplete: missing .*ppo_tc_vecnormalize\.npz"):
        load_policy(stem)
    (tmp_path / "ppo_tc_vecnormalize.npz").mkdir()
    with pytest.raises(PolicyFileError, match=r"ppo_tc_vecnormalize\.npz is unreadable: a folder"):
        load_policy(stem)


# ------------------------------------------------------------------------------------------ 3: a checkpoint's files
def test_a_fifo_in_place_of_a_checkpoints_files_is_refused_not_a_hang(tmp_path):
    """``restore_checkpoint`` read training.json (and optimizer.safetensors), ``read_progress`` progress.json and the
    resume's eval.csv with plain reads: a FIFO in their place hung the resume for good. Each is a bounded regular file
    now, an error naming it; the checkpoint itself restores as before."""
    from agents.ppo import (
        CheckpointError,
        _eval_csv_up_to,
        build_model,
        make_env,
        read_progress,
        restore_checkpoint,
        save_checkpoint,
    )

    cfg = PPOConfig(num_envs=2, n_steps=16, batch_size=32, net_arch=(8, 8), log_dir=str(tmp_path), progress_bar=False,
                    score=False)
    env = make_env(cfg)
    model = build_model(cfg, env, tmp_path / "tb")
    folder = save_checkpoint(model, env, tmp_path / "step_0000000000", {"num_timesteps": 0, "wall_time": 0.0})
    restore_checkpoint(model, env, folder)  # (as before)
    assert read_progress(folder)[1] == 0
    csv_path = tmp_path / "eval.csv"
    csv_path.write_bytes(b"step,x\r\n10,1\r\n20,2\r\n")
    assert _eval_csv_up_to(csv_path, 10) == "step,x\n10,1\n"  # (newlines read as read_text read them)
    for name in ("training.json", "optimizer.safetensors", "progress.json"):
        (folder / name).rename(tmp_path / name)
    fifos = [folder / "training.json", folder / "optimizer.safetensors", folder / "progress.json", tmp_path / "fifo.csv"]
    for fifo in fifos:
        os.mkfifo(fifo)
    try:
        with pytest.raises(CheckpointError, match="training.json: not a regular file|not a regular file"):
            in_thread(lambda: restore_checkpoint(model, env, folder))
        os.unlink(folder / "training.json")
        shutil.copy(tmp_path / "training.json", folder / "training.json")
        with pytest.raises(CheckpointError, match="not a regular file"):
            in_thread(lambda: restore_checkpoint(model, env, folder))  # the optimizer's FIFO
        with pytest.raises(CheckpointError, match="progress.json: .*not a regular file"):
            in_thread(lambda: read_progress(folder))
        with pytest.raises(ValueError, match="fifo.csv cannot be continued: .*not a regular file"):
            in_thread(lambda: _eval_csv_up_to(tmp_path / "fifo.csv", 10))
    finally:
        _release(fifos)
    env.close()


def test_a_checkpoints_progress_that_is_no_object_is_refused_by_name(tmp_path):
    from agents.ppo import CheckpointError, read_progress

    (tmp_path / "progress.json").write_text("[1, 2]")
    with pytest.raises(CheckpointError, match="progress.json: .*no JSON object"):
        read_progress(tmp_path)


# ------------------------------------------------------------------------------------------ 4: arrays as arguments
@pytest.mark.parametrize("plan_id", ["WheelLoaderPlan-v0", "WheelLoaderPlan-v1"])
@pytest.mark.parametrize("vector", [False, True])
@pytest.mark.parametrize("name", ["w_time", "assist", "observe_target", "fuel_action", "braking", "step_braking"])
def test_an_array_argument_to_a_plan_env_is_an_error_naming_it(plan_id, vector, name):
    """An array given for one of the per-step env's settings (or braking, fuel_action) was numpy's "The truth value of
    an array with more than one element is ambiguous", naming no argument."""
    value = np.array([True, False]) if name in ("assist", "observe_target", "step_braking") else (
        np.array(["tc", "service"]) if name in ("braking", "fuel_action") else np.array([0.0, 1.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        with pytest.raises(ValueError) as info:
            if vector:
                gym.make_vec(plan_id, 2, vectorization_mode="vector_entry_point", **{name: value})
            else:
                gym.make(plan_id, **{name: value})
    assert name in str(info.value) and "ambiguous" not in str(info.value)


def test_a_plan_envs_settings_given_as_they_are_still_pass():
    """The per-step env's settings given as their own values (numpy's too) are accepted, as before; another value is
    refused by name."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = gym.make("WheelLoaderPlan-v1", w_time=0.0, assist=np.bool_(True), fuel_action="engine_speed",
                       observe_target=True, braking=np.str_("tc"))
        assert env.unwrapped.assist is True and env.unwrapped.braking == "tc"
        with pytest.raises(ValueError, match="assist cannot be changed"):
            gym.make("WheelLoaderPlan-v1", assist=False)
        with pytest.raises(ValueError, match="w_time cannot be changed"):
            gym.make("WheelLoaderPlan-v0", w_time=np.float64(1.0))


def test_array_arguments_to_the_per_step_envs_are_errors_naming_them():
    from wl_env.env import WheelLoaderEnv
    from wl_env.plan import WheelLoaderPlanEnv

    for cls in (WheelLoaderEnv, WheelLoaderPlanEnv):
        for name, value in (("braking", np.array(["tc", "tc"])), ("render_mode", np.array(["human", "x"])),
                            ("fuel_action", np.array(["engine_speed"] * 2))):
            with pytest.raises(ValueError, match=name):
                cls(**{name: value})


# ------------------------------------------------------------------------------------------ 5: the vector plan env
def test_a_finished_loaders_discarded_step_does_not_fail_the_batch():
    """The vector plan env steps every loader until the last has ended; a loader that had ended (here: its engine
    stalled at 2.9 s) was stepped on from its end state and that step diverged (560 rad/s), raising
    IntegrationDiverged for the whole batch, where each single env ends its cycle. The discarded step is not checked
    now: the batch gives each loader's own cycle."""
    params = {"omega_min": 69.24987802505565, "eta_lift": 0.17026805870560918}  # (each within its range)
    plans = np.array([
        [0.0853, 0.4701, -0.8997, -0.4723, -1.1622, 1.2909, -0.1980, 0.4641, -0.5583, -0.9302, -0.7968, -1.2605, 0.4895, 1.2732],
        [-1.0618, -0.8704, 0.7844, 0.3546, 1.1643, -0.3517, -0.1870, -0.5554, 0.7914, -0.8125, -0.3125, 0.4144, 1.0748, 0.8134],
    ], dtype=np.float32)
    singles = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for i in range(2):
            env = gym.make("WheelLoaderPlan-v0", params=params, braking="service")
            env.reset(seed=5 + i)
            singles.append(env.step(plans[i]))
        venv = gym.make_vec("WheelLoaderPlan-v0", 2, vectorization_mode="vector_entry_point", params=params,
                            braking="service")
    assert singles[1][4]["stalled"] and singles[0][4]["t"] > singles[1][4]["t"] + 1.0  # (it ends first)
    venv.reset(seed=5)
    obs, reward, terminated, truncated, info = venv.step(plans)
    for i, (o, r, te, tr, inf) in enumerate(singles):
        np.testing.assert_allclose(obs[i], o, rtol=0, atol=1e-6)
        assert reward[i] == pytest.approx(r, abs=1e-9) and terminated[i] == te and truncated[i] == tr
        assert info["t"][i] == pytest.approx(inf["t"]) and info["steps"][i] == inf["steps"]


def test_a_running_loaders_divergence_still_fails_the_batch():
    """A loader that diverges while running still raises (the exemption is the ended loaders' only), its message
    naming the running loaders' numbers."""
    from wl_env.vector_env import WheelLoaderVectorEnv

    venv = WheelLoaderVectorEnv(2)
    venv.reset(seed=0)
    venv._y = (np.array([1e9, venv._y[0][1]]), *venv._y[1:])  # (loader 0: far past what the engine reaches)
    with pytest.raises(IntegrationDiverged):
        venv._advance(np.zeros((2, 4)), ignore=np.array([False, True]))
    venv.reset(seed=0)
    venv._y = (np.array([1e9, venv._y[0][1]]), *venv._y[1:])
    venv._advance(np.zeros((2, 4)), ignore=np.array([True, False]))  # (loader 0's step is discarded)


# ------------------------------------------------------------------------------------------ 6: numpy integers
def test_ppo_config_takes_numpys_integers_as_ints():
    """``PPOConfig(seed=np.int64(3))`` was refused ("must be an integer"); numpy's integers are taken as Python's ints
    (and numpy's bools as bools for the flags), while bools and floats stay refused as counts."""
    cfg = PPOConfig(seed=np.int64(3), num_envs=np.int32(4), n_steps=np.uint16(64), total_timesteps=np.int64(10**6),
                    net_arch=(np.int64(32), 32), progress_bar=np.bool_(False), log_dir="runs")
    assert (cfg.seed, cfg.num_envs, cfg.n_steps, cfg.total_timesteps, cfg.net_arch) == (3, 4, 64, 10**6, (32, 32))
    assert all(type(v) is int for v in (cfg.seed, cfg.num_envs, cfg.n_steps, cfg.total_timesteps, *cfg.net_arch))
    assert cfg.progress_bar is False
    assert json.loads(json.dumps(cfg.to_dict()))["seed"] == 3
    assert PPOConfig(seed=3, num_envs=4) == PPOConfig(seed=np.int64(3), num_envs=np.int8(4))
    for bad in ({"seed": np.bool_(True)}, {"seed": True}, {"seed": np.float64(3.0)}, {"num_envs": np.float32(4)},
                {"seed": np.int64(-1)}, {"net_arch": (np.bool_(True),)}, {"progress_bar": np.int64(1)}):
        with pytest.raises(ValueError, match=f"PPOConfig.{next(iter(bad))}"):
            PPOConfig(**bad)
