"""WheelLoaderTarget-v0: a target cycle time per episode, in the observation and the reward."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import wl_env  # noqa: F401  (registers the envs)
from wl_env.scenario import Scenario
from wl_env.suites.min_time import estimate_min_time


def test_the_target_env_passes_the_gymnasium_checks_and_observes_its_target():
    env = gym.make("WheelLoaderTarget-v0", braking="tc", scenario="train")
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=4)
    core = env.unwrapped
    assert obs.shape == (21,) and env.observation_space.contains(obs)
    T_min = estimate_min_time(core.episode_scenario)
    assert 1.0 * T_min <= info["target_time"] <= 2.5 * T_min  # drawn from the default range
    assert obs[19] == pytest.approx(info["target_time"] / 40.0, rel=1e-6)
    assert obs[20] == pytest.approx(info["target_time"] / T_min - 1.0, rel=1e-5)
    again, info2 = env.reset(seed=4)
    assert np.array_equal(obs, again) and info2["target_time"] == info["target_time"]  # same seed, same target


def test_the_reset_options_set_the_target_and_v2_refuses_them():
    env = gym.make("WheelLoaderTarget-v0", braking="service")
    _, info = env.reset(seed=0, options={"target_ratio": 1.5})
    assert info["target_time"] == pytest.approx(1.5 * estimate_min_time(Scenario.nominal("service")))
    _, info = env.reset(seed=0, options={"target_time": 12.0})
    assert info["target_time"] == 12.0
    for bad in ({"target_time": 0.0}, {"target_time": 45.0}, {"target_ratio": 0.5}, {"target_ratio": 1.2, "target_time": 9.0}):
        with pytest.raises(ValueError, match="target"):
            env.reset(seed=0, options=bad)
    with pytest.raises(ValueError, match="WheelLoaderTarget-v0"):
        gym.make("WheelLoader-v2").reset(seed=0, options={"target_time": 12.0})
    with pytest.raises(ValueError, match="ratio to T_min in \\[1, 3\\]"):
        gym.make("WheelLoaderTarget-v0", target=(2.0, 1.0))


def _run(env, ctrl, seed, options):
    from wl_env.rollout import reset_controller

    obs, _ = env.reset(seed=seed, options=options)
    reset_controller(ctrl)
    total, done = 0.0, False
    while not done:
        obs, r, term, trunc, info = env.step(ctrl.act(obs))
        total, done = total + r, term or trunc
    return total, info


def test_finishing_late_costs_the_lateness_times_its_weight():
    """The same cycle (the operator's) under a target it misses and one it meets: the returns differ by
    exactly RewardConfig.late times the lateness, and nothing else."""
    from agents.evaluate import load_controller

    env = gym.make("WheelLoaderTarget-v0", braking="tc")
    ctrl = load_controller("operator", "tc")
    r_met, info_met = _run(env, ctrl, 0, {"target_time": 30.0})
    r_late, info_late = _run(env, ctrl, 0, {"target_time": 6.0})
    assert info_met["completed"] and info_met["lateness"] == 0.0
    T = info_late["t"]
    assert info_late["lateness"] == pytest.approx((T - 6.0) / 6.0)
    assert r_met - r_late == pytest.approx(env.unwrapped.core.reward.late * (T - 6.0) / 6.0, rel=1e-9)


def test_the_vector_target_env_draws_targets_as_single_envs_do():
    n, seed = 3, 11
    venv = gym.make_vec("WheelLoaderTarget-v0", num_envs=n, vectorization_mode="vector_entry_point", braking="tc",
                        scenario="train", init_noise=0.5)
    envs = [gym.make("WheelLoaderTarget-v0", braking="tc", scenario="train", init_noise=0.5) for _ in range(n)]
    obs_v, _ = venv.reset(seed=seed)
    singles = [e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]
    np.testing.assert_array_equal(obs_v, np.stack(singles))
    rng = np.random.default_rng(0)
    for _ in range(40):
        a = rng.uniform(-1, 1, size=(n, 4)).astype(np.float32)
        a[:, 3] = -1.0
        obs_v, rew_v, *_ = venv.step(a)
        for i, e in enumerate(envs):
            o, r, *_ = e.step(a[i])
            np.testing.assert_allclose(obs_v[i], o, rtol=0, atol=1e-6)
            assert rew_v[i] == pytest.approx(r, rel=1e-9, abs=1e-12)


def test_evaluation_at_a_target_reaches_the_target_env_through_its_observation():
    """`evaluate_controller(..., target_time=)` on the target env: the env observes the target (a controller
    that reads it there needs no reset(target_time=)), and each episode records it and its lateness."""
    from agents.evaluate import evaluate_controller, load_controller

    r = evaluate_controller(load_controller("operator", "tc"), "tc", episodes=1, env_id="WheelLoaderTarget-v0",
                            target_time=6.0, score=False)
    e = r["per_episode"][0]
    assert e["target_time"] == 6.0 and e["completed"]
    assert e["lateness"] == pytest.approx((e["T"] - 6.0) / 6.0) and r["summary"]["lateness_median"] == e["lateness"]
