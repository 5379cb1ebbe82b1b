"""Hostile input, stop 63's round on ``wl_env``: each test fails on the code before its fix."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import wl_env  # noqa: F401  (registers the envs)
from wl_env.codec import Codec
from wl_env.env import WheelLoaderEnv, make_reward_config
from wl_env.plan import PlanDriver
from wl_env.rollout import run_episode


def test_a_reward_dict_with_a_key_that_is_no_string_is_refused_by_name():
    """``reward={1: 2, "a": 3}`` failed in sorted() with a bare TypeError ('<' not supported between str and int)."""
    for bad in ({1: 2.0, "a": 3.0}, {None: 1.0, "w_fuel": 0.5}):
        with pytest.raises(ValueError, match=r"unknown reward field\(s\)"):
            make_reward_config(bad, None, None)
        with pytest.raises(ValueError, match=r"unknown reward field\(s\)"):
            WheelLoaderEnv(reward=bad)
    with pytest.raises(ValueError, match=r"unknown reward field\(s\) \['colour'\]"):  # (the message as it was)
        make_reward_config({"colour": 1.0}, None, None)
    assert make_reward_config({"w_fuel": 0.25}, None, None).w_fuel == 0.25


def test_an_observation_with_masked_entries_is_refused_not_read_as_its_filler():
    """A masked array's masked entry was read as the value under its mask by every reader of observations (the
    codec's decoders: the plan driver, the operator, the MPC), as the env's actions were before stop 62."""
    obs, _ = gym.make("WheelLoaderTarget-v7").reset(seed=0)
    masked = np.ma.masked_array(obs, mask=[True] + [False] * (len(obs) - 1))
    codec = Codec(observe_scenario=True)
    with pytest.raises(ValueError, match="obs must be WheelLoader observations .*masked array with 1 masked"):
        codec.decode_observation(masked)
    with pytest.raises(ValueError, match="masked array with 1 masked"):
        PlanDriver(np.zeros(14)).act(masked)
    # a masked array with nothing masked is its values, as before
    unmasked = np.ma.masked_array(obs, mask=False)
    assert codec.decode_observation(unmasked) == codec.decode_observation(obs)
    np.testing.assert_array_equal(PlanDriver(np.zeros(14)).act(unmasked), PlanDriver(np.zeros(14)).act(obs))


def test_run_episode_takes_only_a_bool_as_its_trajectory_switch():
    """``run_episode(trajectory="no")`` recorded the trajectory (any non-empty string is true)."""
    from agents.operator import OperatorPolicy

    env = gym.make("WheelLoader-v1")
    for bad in ("no", 0, None, np.array([False])):
        with pytest.raises(ValueError, match="trajectory must be True or False"):
            run_episode(env, OperatorPolicy("service"), seed=0, trajectory=bad)
    ep = run_episode(env, OperatorPolicy("service"), seed=0, trajectory=np.bool_(False))
    assert ep.trajectory is None and ep.success
