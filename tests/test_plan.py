"""WheelLoaderPlan-v0 and -v1 (wl_env.plan): one decision per cycle, a phase-parametric plan driven on
WheelLoaderTarget-v6 (v0) or -v7 (v1)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st

import wl_env  # noqa: F401  (registers the envs)
from wl_env.plan import MAX_HOLD_TIME, N_PLAN_ACTIONS, PlanDriver, driven_on
from wl_env.rollout import run_episode


def plan(drive=1.0, coast=1.0, brake=1.0, hold=-1.0, lift=1.0, stop_request=-1.0, stop_lift=1.0) -> np.ndarray:
    """The same numbers for both legs (the module's table, per leg)."""
    return np.array([drive, coast, brake, hold, lift, stop_request, stop_lift] * 2, dtype=np.float32)


def test_the_plan_env_passes_the_gymnasium_checks_and_ends_in_one_step():
    env = gym.make("WheelLoaderPlan-v0", braking="tc", scenario="train")
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=5)
    assert obs.shape == (21,) and env.action_space.shape == (N_PLAN_ACTIONS,)
    v6 = gym.make("WheelLoaderTarget-v6", braking="tc", scenario="train")
    obs6, info6 = v6.reset(seed=5)
    assert np.array_equal(obs, obs6) and info["target_time"] == info6["target_time"]  # v6's start, seen once
    _, reward, terminated, truncated, info = env.step(plan())
    assert terminated and not truncated and info["is_success"] and info["steps"] == round(info["t"] / 0.1)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(plan())


@pytest.mark.parametrize("plan_id", ["WheelLoaderPlan-v0", "WheelLoaderPlan-v1"])
@pytest.mark.parametrize("braking", ["service", "tc"])
def test_the_plan_env_is_the_plan_driver_on_its_target_env_step_for_step(braking, plan_id):
    """The env and the same driver run as a controller of the per-step env it drives (v6 under v0, v7 under v1;
    as an evaluation could) drive the same cycle."""
    x = np.random.default_rng(3).uniform(-1, 1, N_PLAN_ACTIONS)
    env = gym.make(plan_id, braking=braking, scenario="test")
    env.reset(seed=2)
    _, reward, *_, info = env.step(x)
    target = gym.make(driven_on(plan_id), braking=braking, scenario="test")
    ep = run_episode(target, PlanDriver(x), seed=2, trajectory=False)
    assert (ep.T, ep.fuel_g, ep.success) == (info["t"], info["fuel_g"], info["is_success"])
    assert ep.episode_return == pytest.approx(reward, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("plan_id", ["WheelLoaderPlan-v0", "WheelLoaderPlan-v1"])
def test_the_vector_env_runs_each_loader_as_the_single_env_does(plan_id):
    n, rng = 6, np.random.default_rng(11)
    plans = rng.uniform(-1, 1, (n, N_PLAN_ACTIONS))
    venv = gym.make_vec(plan_id, num_envs=n, vectorization_mode="vector_entry_point", braking="service",
                        scenario="train")
    obs, _ = venv.reset(seed=40)
    _, rewards, terminated, truncated, infos = venv.step(plans)
    env = gym.make(plan_id, braking="service", scenario="train")
    for i in range(n):
        o, _ = env.reset(seed=40 + i)
        assert np.array_equal(o, obs[i])
        _, r, te, tr, info = env.step(plans[i])
        assert (info["t"], info["fuel_g"], te, tr) == pytest.approx(
            (infos["t"][i], infos["fuel_g"][i], terminated[i], truncated[i]))
        assert r == pytest.approx(rewards[i], rel=1e-6) and info["steps"] == infos["steps"][i]
        assert info["violations"]["max_excess"] == pytest.approx(infos["violation"][i])
    # next-step autoreset: the following step starts new cycles and ignores its plans
    new_obs, rewards, terminated, *_ = venv.step(plans)
    assert not terminated.any() and not rewards.any() and not np.array_equal(new_obs, obs)


def test_the_bucket_is_held_for_the_hold_time_and_then_lifts():
    hold = 1.5  # s
    x = plan(hold=2.0 * hold / MAX_HOLD_TIME - 1.0)
    v6 = gym.make("WheelLoaderTarget-v6", braking="service")
    ep = run_episode(v6, PlanDriver(x), seed=0)
    t = np.asarray(ep.trajectory.t)
    H = np.asarray(ep.trajectory.states)[:, 2]
    assert np.ptp(H[t <= hold + 1e-9]) < 1e-9  # still while held
    assert H[t <= hold + 1.0][-1] > H[0] + 0.05  # lifting right after
    assert ep.success and ep.max_violation == 0.0


def test_a_higher_drive_request_drives_a_faster_and_heavier_cycle():
    env = gym.make("WheelLoaderPlan-v0", braking="service")
    results = []
    for drive in (-0.2, 0.4, 1.0):
        env.reset(seed=0)
        *_, info = env.step(plan(drive=drive))
        assert info["is_success"]
        results.append((info["t"], info["fuel_g"]))
    times, fuels = zip(*results, strict=True)
    assert times[0] > times[1] > times[2] and fuels[0] < fuels[1] < fuels[2]


def test_bad_plans_and_arguments_are_refused_by_name():
    env = gym.make("WheelLoaderPlan-v0", braking="service")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must have shape \(14,\)"):
        env.step(np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.full(N_PLAN_ACTIONS, np.nan))
    with pytest.raises(ValueError, match="plan must have shape"):
        PlanDriver(np.zeros(3))
    with pytest.raises(ValueError, match="coast cannot be changed"):
        gym.make("WheelLoaderPlan-v0", coast=False)
    with pytest.raises(ValueError, match=r"takes no argument\(s\) \['colour'\]"):
        gym.make("WheelLoaderPlan-v0", colour="red")
    with pytest.raises(ValueError, match="WheelLoaderPlan-v1 drives WheelLoaderTarget-v7: step_braking cannot be changed"):
        gym.make("WheelLoaderPlan-v1", step_braking=False)
    with pytest.raises(ValueError, match="plan_id must be a plan env, one of WheelLoaderPlan-v0, WheelLoaderPlan-v1"):
        driven_on("WheelLoaderPlan-v9")
    venv = gym.make_vec("WheelLoaderPlan-v0", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 14\)"):
        venv.step(np.zeros((2, 4)))


@settings(max_examples=15, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=N_PLAN_ACTIONS, max_size=N_PLAN_ACTIONS), st.integers(0, 10_000),
       st.sampled_from(["service", "tc"]))
def test_any_plan_ends_its_cycle_in_one_step_with_a_finite_return(x, seed, braking):
    """Out-of-range numbers are clipped as v6 clips its actions; every plan ends (completed, failed or timed out)."""
    env = gym.make("WheelLoaderPlan-v0", braking=braking, scenario="train")
    env.reset(seed=seed)
    _, reward, terminated, truncated, info = env.step(np.asarray(x))
    assert terminated or truncated
    assert np.isfinite(reward) and 0.0 < info["t"] <= 40.0 + 1e-9 and info["fuel_g"] > 0.0
    assert info["steps"] == round(info["t"] / 0.1)


def test_ppo_trains_on_the_plan_env_and_its_policy_is_evaluated_as_any_target_policy(tmp_path):
    """The PPO pipeline on the native vector env (each step a cycle), the pickle-free export, and
    `wl evaluate`'s path: the loaded policy runs the plan env, each episode at its target."""
    from fakes import tiny_ppo_config

    from agents.evaluate import evaluate_controller, load_controller
    from agents.ppo import train
    from wl_env.suites import load_suite

    cfg = tiny_ppo_config(tmp_path, env_id="WheelLoaderPlan-v0", braking="tc", scenario="train", init_noise=0.0,
                          total_timesteps=64, num_envs=8, n_steps=4, batch_size=16, n_epochs=1, eval_freq=32,
                          eval_episodes=1, checkpoint_freq=32)
    summary = train(cfg)
    assert summary["num_timesteps"] >= 64
    policy = load_controller("ppo", "tc", model=str(cfg.run_dir / "final"))
    assert policy.env_id == "WheelLoaderPlan-v0"
    scenario = next(s for s in load_suite("test").scenarios if s.braking == "tc")
    res = evaluate_controller(policy, "tc", scenarios=[scenario], score=False, env_id=policy.env_id, target_ratio=1.5,
                              min_time="estimate")
    (episode,) = res["per_episode"]
    assert episode["completed"] and episode["target_time"] > 0 and episode["T"] > 1.0


@pytest.mark.parametrize("dt", [0.0, float("nan"), -0.1, "0.1", 5.0])
def test_the_plan_driver_refuses_a_control_interval_by_name(dt):
    """dt 0 or NaN held the bucket by a NaN action, which v6 blamed on the action; a string was numpy's TypeError;
    a negative interval ran a plan with no hold."""
    with pytest.raises(ValueError, match=r"dt \(the control interval\) must lie in \[0.001, 1\] s"):
        PlanDriver(plan(), dt=dt)


def test_the_vector_plan_env_gives_the_same_info_keys_at_its_autoreset_step():
    """The step that starts the new cycles returned {} as its infos: infos["is_success"] was a KeyError every other step."""
    venv = gym.make_vec("WheelLoaderPlan-v0", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    *_, ended = venv.step(np.stack([plan(), plan()]))
    obs, rewards, terminated, truncated, started = venv.step(np.stack([plan(), plan()]))
    assert sorted(started) == sorted(ended)
    assert not started["is_success"].any() and not started["steps"].any() and not started["t"].any()
    assert not (rewards.any() or terminated.any() or truncated.any())
    assert np.array_equal(started["target_time"], venv.unwrapped.target_time) and np.isfinite(started["target_time"]).all()
