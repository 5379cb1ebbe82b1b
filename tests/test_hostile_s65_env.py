"""Hostile input, stop 65's round on ``wl_env`` and ``agents``: each test fails on the code before its fix (its
docstring says what that code did)."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import wl_env  # noqa: F401  (registers the envs)
from wl_env import rendering

POLICIES = Path(__file__).resolve().parents[1] / "agents" / "policies"


@pytest.mark.parametrize("frames, needle", [
    ([np.zeros((6, 8, 3), np.uint8), np.zeros((4, 8, 3), np.uint8)], r"one size: frames\[0\] is \(6, 8, 3\), frames\[1\] \(4, 8, 3\)"),
    ([np.full((6, 8, 3), 0.5)], r"frames\[0\] must be an RGB image.*dtype float64"),
    ([np.full((6, 8, 3), 300, np.int64)], r"frames\[0\] must be an RGB image"),
    ([np.zeros((6, 8), np.uint8)], r"frames\[0\] must be an RGB image, \(height, width, 3\) uint8"),
    ([np.zeros((1, 6, 8, 3), np.uint8)], r"frames\[0\] must be an RGB image"),
    ([np.zeros((0, 8, 3), np.uint8)], r"frames\[0\] must be an RGB image"),
    (["frame"], r"frames\[0\] must be an RGB image"),
])
def test_an_animation_refuses_frames_that_are_no_rgb_images_of_one_size(tmp_path, frames, needle):
    """``save_gif`` cast every frame to uint8 without a look: a float frame of values in [0, 1] became a black GIF, 300
    wrapped to 44, frames of two sizes went into one GIF; a 4-d frame was Pillow's "Cannot handle this data type", a
    string int()'s error."""
    for path in (tmp_path / "a.gif", tmp_path / "a.mp4"):
        with pytest.raises(ValueError, match=needle):
            rendering.save_animation(frames, str(path), fps=5)
    assert not list(tmp_path.iterdir())
    # frames of integers within [0, 255] are taken, as uint8 ones are
    assert rendering.save_gif([np.full((6, 8, 3), 200, np.int64)] * 2, str(tmp_path / "b.gif")) == 2


def test_a_reward_that_sets_w_fuel_beside_the_runs_own_is_refused():
    """``PPOConfig(reward={"w_fuel": 0.5})`` (``wl train --reward w_fuel=0.5``) trained with the run's w_fuel 2.0, the
    default, which the env applies over the reward's, while config.json recorded 0.5."""
    from agents.ppo import reward_config
    from agents.ppo_config import ConfigError, PPOConfig

    for bad in ({"w_fuel": 0.5}, {"w_time": 1.0, "failure": 3.0}):
        with pytest.raises(ConfigError, match=r"PPOConfig.reward must be without w_fuel and w_time.*--w-fuel"):
            PPOConfig(reward=bad)
    # the same value as the run's own is no contradiction; the curriculum's start values are its own (unchanged)
    assert reward_config(PPOConfig(w_fuel=0.5, reward={"w_fuel": 0.5})).w_fuel == 0.5
    assert PPOConfig(curriculum_start={"w_fuel": 0.5}).curriculum_start == {"w_fuel": 0.5}


def test_a_reward_key_given_twice_in_one_option_is_refused():
    """``wl train --reward failure=1 failure=2`` kept the last value without a word (an option given twice is refused
    since stop 61, a key given twice in one option was not)."""
    from agents.ppo_config import PPOConfig
    from agents.train_cli import add_dataclass_args, config_from_args

    parser = argparse.ArgumentParser()
    add_dataclass_args(parser, PPOConfig)
    for argv, needle in ((["--reward", "failure=1", "failure=2"], r"--reward gives failure twice \(1 and 2\)"),
                         (["--curriculum-start", "w_fuel=1", "w_fuel=3"], r"--curriculum-start gives w_fuel twice")):
        with pytest.raises(ValueError, match=needle):
            config_from_args(PPOConfig, parser.parse_args(argv))
    cfg, _ = config_from_args(PPOConfig, parser.parse_args(["--reward", "failure=1", "failure=1.0", "shaping=2"]))
    assert cfg.reward == {"failure": 1.0, "shaping": 2.0}


def test_run_episode_records_a_numpy_seed_as_the_int_it_holds():
    """``run_episode(env, c, seed=np.int64(3))`` recorded the numpy integer itself: ``json.dumps(result.to_dict())``
    was "Object of type int64 is not JSON serializable"."""
    from agents.operator import OperatorPolicy
    from wl_env.rollout import run_episode

    ep = run_episode(gym.make("WheelLoader-v2"), OperatorPolicy("service"), seed=np.int64(3), trajectory=False)
    assert type(ep.seed) is int and ep.seed == 3
    assert json.loads(json.dumps(ep.to_dict()))["seed"] == 3


def test_json_with_nan_as_null_writes_an_arrays_non_finite_numbers_as_null(tmp_path):
    """``json_text(..., nan_as_null=True)`` (policy metadata, progress.json) says it writes non-finite numbers as null
    and converts numpy arrays; an array holding NaN or inf was "Out of range float values are not JSON compliant"."""
    from wl_env.atomic_io import json_text, write_json_atomic

    obj = {"a": np.array([np.nan, 1.5]), "b": np.array(np.inf), "c": np.array([[2.0, -np.inf]], np.float32)}
    assert json.loads(json_text(obj, nan_as_null=True)) == {"a": [None, 1.5], "b": None, "c": [[2.0, None]]}
    path = write_json_atomic(tmp_path / "p.json", obj, nan_as_null=True)
    assert json.loads(path.read_text())["a"] == [None, 1.5]


def test_a_policy_that_reading_would_refuse_is_not_written(tmp_path):
    """``write_policy`` wrote a normalization of NaN means or negative variances, of another length, or metadata
    whose braking or config reading refuses: the policy (an export over a good one too) no longer loaded."""
    from agents.policy_files import ObsNormalization, PolicyFileError, write_policy
    from agents.ppo import load_policy

    stem = tmp_path / "p"
    for suffix in (".safetensors", "_vecnormalize.npz", ".json"):
        shutil.copy(POLICIES / f"ppo_service{suffix}", f"{stem}{suffix}")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    policy = load_policy(stem)
    n = policy.normalization
    for norm, meta, needle in [
        (ObsNormalization(np.full_like(n.mean, np.nan), n.var), policy.meta, "mean and var must be finite"),
        (ObsNormalization(n.mean, -n.var), policy.meta, "mean and var must be finite, var >= 0"),
        (ObsNormalization(n.mean[:3], n.var[:3]), policy.meta, "mean and var must be 12 floats"),
        (ObsNormalization(n.mean, n.var, 10.0, 0.0), policy.meta, "epsilon in"),
        (n, {**policy.meta, "braking": "x"}, 'braking must be "service" or "tc"'),
        (n, {**policy.meta, "config": [1]}, "config must be an object"),
        (n, {**policy.meta, "config": {"env_id": 5}}, "config.env_id must be an env id string"),
    ]:
        with pytest.raises(PolicyFileError, match=f"policy {stem} not written: .*{needle}"):
            write_policy(policy.network, norm, stem, meta)
        assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing written, no temporary left
    write_policy(policy.network, n, stem, policy.meta)  # what reading takes is written, as before
    obs, _ = gym.make("WheelLoader-v1").reset(seed=0)
    np.testing.assert_array_equal(load_policy(stem).act(obs), policy.act(obs))


def test_demo_settings_refuse_a_learner_that_is_no_path():
    """``DemoSettings(learner=5)`` (or True, None) was taken, and the collection failed inside its first episode with
    a bare TypeError ("expected str, bytes or os.PathLike object, not int")."""
    from agents.imitation import DemoSettings

    for bad in (5, True, None, ["p"]):
        with pytest.raises(ValueError, match=r"learner must be '' \(the expert drives\) or the path of a pickle-free policy"):
            DemoSettings("service", expert="operator", learner=bad)
    assert DemoSettings("service", expert="operator", learner=Path("runs/a/final/policy")).learner == "runs/a/final/policy"


def test_evaluate_controller_refuses_a_scenario_in_env_kwargs():
    """``evaluate_controller(c, env_kwargs={"scenario": {"payload": 6000, ...}})`` ran every episode on the paper's
    cycle (10 t, 6.6 m) without a word: each episode is reset with the evaluation's own scenario. The training-time
    evaluation, which passes the training env's arguments (its scenario source), evaluates as before."""
    from agents.evaluate import check_env_kwargs, evaluate_controller
    from agents.operator import OperatorPolicy
    from agents.ppo import evaluate
    from agents.ppo_config import PPOConfig

    for scenario in ({"payload": 6000}, "test"):
        with pytest.raises(ValueError, match="env_kwargs sets scenario, which the evaluation's own arguments set"):
            evaluate_controller(OperatorPolicy("service"), "service", episodes=1, score=False,
                                env_kwargs={"scenario": scenario})
    check_env_kwargs("WheelLoader-v2", {"max_time": 30.0}, "service")
    operator = OperatorPolicy("service")
    kwargs = PPOConfig(env_id="WheelLoader-v2", scenario="train").env_kwargs()
    assert kwargs["scenario"] == "train"
    row = evaluate(operator.act, "service", n_episodes=0, env_kwargs=kwargs, with_score=False, env_id="WheelLoader-v2")
    assert row["nominal_success"]


def test_the_evaluation_guard_refuses_a_masked_action_not_its_hidden_values():
    """A controller's action as a masked array with a masked entry drove ``wl evaluate`` with the value under the mask
    (the guard's ``np.asarray`` dropped the mask; the env refuses such an action since stop 62)."""
    from agents.evaluate import ControllerError, GuardedController
    from agents.operator import OperatorPolicy

    operator = OperatorPolicy("service")
    obs, _ = gym.make("WheelLoader-v1").reset(seed=0)

    class Masked:
        def act(self, o):
            return np.ma.masked_array(operator.act(o), mask=[False, False, True, False])

    guard = GuardedController(Masked(), "masked")
    guard.reset()
    with pytest.raises(ControllerError, match="controller masked: act.. returned a masked array with 1 masked entries"):
        guard.act(obs)

    class Unmasked:  # (nothing masked: its values, as before)
        def act(self, o):
            return np.ma.masked_array(operator.act(o), mask=False)

    np.testing.assert_array_equal(GuardedController(Unmasked(), "unmasked").act(obs), operator.act(obs))
