"""The learned controllers of scenarios and target cycle times (#14): training on WheelLoaderTarget-v0/v1, the
behaviour-cloning baseline, fine-tuning from it, and the shipped target-conditioned policies."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from fakes import tiny_ppo_config

from agents.imitation import DemoSettings, action_weights, clone, collect_demos, read_demo
from agents.policy_files import PolicyFileError
from agents.ppo import (
    PPOConfig,
    build_model,
    load_policy,
    make_env,
    start_from,
)
from agents.ppo_config import TARGET_ENV_ID
from wl_env import Scenario

POLICIES = Path(__file__).resolve().parents[1] / "agents" / "policies"


def _tiny(tmp_path: Path, **kw) -> PPOConfig:
    return tiny_ppo_config(tmp_path, **{"env_id": TARGET_ENV_ID, "scenario": "train", "init_noise": 0.0,
                                        "total_timesteps": 2048, "n_epochs": 1, "eval_episodes": 1, **kw})


# ---------------------------------------------------------------------------------------------- config
def test_the_config_names_the_env_the_suite_and_the_target_range():
    cfg = PPOConfig(env_id=TARGET_ENV_ID, scenario="train", target=(1.0, 2.0), w_time=3.0)
    kw = cfg.env_kwargs()
    assert kw["scenario"] == "train" and kw["target"] == (1.0, 2.0)
    assert kw["w_time"] == 0.0  # the lateness term replaces the time term
    assert "target_power" not in kw  # (the uniform draw: older runs' kwargs unchanged)
    assert PPOConfig(env_id=TARGET_ENV_ID, scenario="train", target_power=2).env_kwargs()["target_power"] == 2.0
    from agents.ppo import reward_config

    assert reward_config(cfg, 0).w_time == 0.0 and reward_config(cfg).w_time == 0.0
    for bad, field in ((dict(env_id="WheelLoader-v9"), "env_id"), (dict(scenario="moon"), "scenario"),
                       (dict(scenario="train"), "scenario"),  # v1 does not observe the scenario
                       (dict(env_id=TARGET_ENV_ID, target=(0.5, 2.0)), "target"),
                       (dict(env_id=TARGET_ENV_ID, target=(2.0, 1.5)), "target"),
                       (dict(env_id=TARGET_ENV_ID, target=(1.0,)), "target"),
                       (dict(env_id=TARGET_ENV_ID, target_power=0.1), "target_power")):
        with pytest.raises(ValueError, match=field):
            PPOConfig(**bad)


# ---------------------------------------------------------------------------------------------- imitation
def test_the_shift_label_is_a_ramp_crossing_zero_at_the_experts_shift():
    from agents.imitation import SHIFT_RAMP, shift_labels
    from wl_env.codec import N_TARGET_OBS

    obs = np.zeros((7, N_TARGET_OBS), np.float32)
    obs[:, 8:12] = np.eye(4)[[0, 0, 0, 0, 1, 2, 2]]  # phases 1 1 1 1 2 3 3
    actions = np.full((7, 4), -1.0, np.float32)
    actions[3, 3] = 1.0  # the shift of phase 1, at step 3; none in phase 3
    labels = shift_labels(obs, actions)
    np.testing.assert_allclose(labels[:4, 3], SHIFT_RAMP * (np.arange(4) - 3 + 0.5))
    assert (labels[:3, 3] < 0).all() and labels[3, 3] > 0  # the clone's threshold shifts at the expert's step
    assert labels[5:, 3].tolist() == [-1.0, -1.0]  # no shift in the phase: held
    np.testing.assert_array_equal(labels[:, :3], actions[:, :3])
    w = action_weights(obs, actions)
    assert w[:, :3].tolist() == np.ones((7, 3)).tolist() and w[:, 3].tolist() == [1, 1, 1, 1, 0, 1, 1]


def test_demonstrations_resume_and_reject_a_foreign_file(tmp_path):
    s = DemoSettings("service", seed=3, expert="operator")
    demos = collect_demos(s, 2, tmp_path)
    assert len(demos) == 2 and all(d["obs"].shape[1] == 21 and len(d["obs"]) == len(d["actions"]) for d in demos)
    assert demos[0]["scenario"] != demos[1]["scenario"]
    stamp = (tmp_path / "episode_00000.npz").stat().st_mtime_ns
    again = collect_demos(s, 3, tmp_path)  # resumed: the two on disk are read, one more is run
    assert (tmp_path / "episode_00000.npz").stat().st_mtime_ns == stamp and len(again) == 3
    np.testing.assert_array_equal(again[1]["actions"], demos[1]["actions"])
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        read_demo(tmp_path / "bad.npz")
    # a crafted meta: not an object, a field of the wrong type, an array name that would replace the checked array
    good = dict(np.load(tmp_path / "episode_00000.npz"))
    meta = json.loads(str(good["meta"]))
    for name, m, obs in (("list", [1], good["obs"]), ("env_id", {**meta, "env_id": ["x"]}, good["obs"]),
                         ("obs", {**meta, "obs": 1}, good["obs"]), ("float", meta, good["obs"].astype(str))):
        np.savez(tmp_path / f"{name}.npz", obs=obs, actions=good["actions"], meta=np.array(json.dumps(m)))
        with pytest.raises(ValueError, match=f"{name}.npz"):
            read_demo(tmp_path / f"{name}.npz")
    for bad in (dict(expert="oracle"), dict(target=(0.5, 1.0)), dict(fast_share=2.0), dict(seed=-1), dict(beta=1.5)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            DemoSettings("service", **bad)


def test_a_clone_acts_like_its_expert_and_ppo_fine_tuning_starts_from_it(tmp_path):
    demos = collect_demos(DemoSettings("service", seed=5, expert="operator", env_id=TARGET_ENV_ID), 6, tmp_path / "demos")
    cfg = _tiny(tmp_path, run_name="bc", net_arch=(64, 64))
    result = clone(demos, cfg, epochs=150)
    assert result.episodes + result.episodes_dropped == 6 and result.samples > 300
    obs = np.concatenate([d["obs"] for d in demos])
    acts = np.clip(np.concatenate([d["actions"] for d in demos]), -1, 1)
    constant = float(np.mean(action_weights(obs, acts) * (acts - acts.mean(0)) ** 2))  # the best constant action's
    assert result.train_loss < 0.2 * constant and result.validation_loss < 0.5 * constant, (result, constant)
    policy = load_policy(cfg.run_dir)
    d = demos[0]
    err = np.abs(policy.act(d["obs"])[:, :3] - np.clip(d["actions"][:, :3], -1, 1))
    assert np.median(err) < 0.1
    # PPO fine-tuning starts from the clone: the same deterministic actions before any update
    tune = _tiny(tmp_path, run_name="tune", net_arch=(64, 64), init_policy=str(cfg.run_dir / "final" / "policy"))
    env = make_env(tune, num_envs=1)
    model = build_model(tune, env, tmp_path / "tb")
    start_from(model, env, tune)
    z = env.normalize_obs(d["obs"])
    np.testing.assert_allclose(model.predict(z, deterministic=True)[0], policy.act(d["obs"]), atol=1e-5)
    # DAgger: the clone drives, the expert labels the states it visits
    (dagger,) = collect_demos(DemoSettings("service", seed=6, expert="operator", learner=str(cfg.run_dir / "final" / "policy"),
                                           env_id=TARGET_ENV_ID), 1, tmp_path / "dagger")
    assert dagger["learner"] and len(dagger["obs"]) > 10
    from agents.imitation import usable
    from agents.operator import OperatorPolicy

    assert usable({**dagger, "success": False})  # the learner's outcome; the labels are the expert's
    expert = OperatorPolicy("service", params=Scenario.from_dict(dagger["scenario"]).params())
    np.testing.assert_allclose(dagger["actions"], expert.act(dagger["obs"]), atol=1e-6)
    wrong = _tiny(tmp_path, run_name="wrong", init_policy=str(cfg.run_dir / "final" / "policy"))  # (16, 16)
    with pytest.raises(PolicyFileError, match="net_arch"):
        start_from(build_model(wrong, env, tmp_path / "tb2"), env, wrong)


def test_governed_demonstrations_replay_the_experts_cycle_and_clone_only_into_their_env(tmp_path):
    """WheelLoaderTarget-v1 demos (the default): the expert's injections labelled as engine-speed requests
    drive the same cycle as in v0, and a clone refuses demonstrations of another env."""
    runs = {env: collect_demos(DemoSettings("service", seed=3, expert="operator", env_id=env), 1, tmp_path / env)[0]
            for env in ("WheelLoaderTarget-v0", "WheelLoaderTarget-v1")}
    v0, v1 = runs.values()
    assert v1["env_id"] == "WheelLoaderTarget-v1" and v1["success"]
    assert v1["T"] == pytest.approx(v0["T"], abs=1e-9) and v1["fuel_g"] == pytest.approx(v0["fuel_g"], rel=1e-5)
    np.testing.assert_array_equal(v1["actions"][:, 1:], v0["actions"][:, 1:])
    assert not np.allclose(v1["actions"][:, 0], v0["actions"][:, 0])  # requests, not injections
    with pytest.raises(ValueError, match="WheelLoaderTarget-v1 episodes; WheelLoaderTarget-v0 needs WheelLoaderTarget-v0"):
        clone([v1, v1], _tiny(tmp_path, run_name="mixed"))
    cfg = _tiny(tmp_path, run_name="governed", env_id="WheelLoaderTarget-v1", net_arch=(64, 64))
    clone([v1, v1], cfg, epochs=5)
    policy = load_policy(cfg.run_dir)  # the same 21 observations as v0's: the env comes from its config
    assert policy.env_id == "WheelLoaderTarget-v1"
    with pytest.raises(ValueError, match="env_id"):
        DemoSettings("service", env_id="WheelLoader-v2")
    with pytest.raises(ValueError, match="is a WheelLoaderTarget-v0 episode; this collection is of WheelLoaderTarget-v1"):
        collect_demos(DemoSettings("service", seed=3, expert="operator"), 1, tmp_path / "WheelLoaderTarget-v0")


def _replay(env_id: str, braking: str, demo: dict, driver: np.ndarray) -> dict:
    """The labelled driver actions applied open loop through ``env_id``, each phase's from its own first step
    (the assist may end a leg a step off the expert's)."""
    import gymnasium as gym

    from wl_env.codec import Codec

    phases = Codec(observe_scenario=True).decode_observation(demo["obs"]).phase
    env = gym.make(env_id, braking=braking)
    env.reset(seed=0, options={"scenario": Scenario.from_dict(demo["scenario"]), "target_time": demo["target_time"]})
    done, phase, k, info = False, 1, 0, {}
    while not done:
        if env.unwrapped._phase != phase:
            phase, k = env.unwrapped._phase, 0
        steps = np.flatnonzero(phases == phase)
        _, _, term, trunc, info = env.step(driver[steps[min(k, len(steps) - 1)]])
        done, k = term or trunc, k + 1
    return info


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_driver_labels_replay_the_experts_cycle_through_the_assist(tmp_path, braking):
    """A WheelLoaderTarget-v1 expert episode labelled as the assisted driver's actions (v2, v3) and replayed
    open loop through the assist drives the expert's cycle: its marks met, the cycle time within 0.2 s, the
    fuel within 1 %. v3's coasting labels carry the expert's shift as a ramp."""
    from agents.imitation import driver_labels, labels

    (demo,) = collect_demos(DemoSettings(braking, seed=3, expert="operator"), 1, tmp_path)
    assert demo["success"]
    for env_id, coast in (("WheelLoaderTarget-v2", False), ("WheelLoaderTarget-v3", True)):
        driver, weights = driver_labels(demo["obs"], demo["actions"], demo["scenario"], braking, coast=coast)
        assert driver.shape == weights.shape == (len(demo["obs"]), 4 if coast else 3)
        assert (np.abs(driver) <= 1.0).all() and set(np.unique(weights)) <= {0.0, 1.0}
        np.testing.assert_array_equal(driver[:, :2], demo["actions"][:, :2])  # request and bucket: the expert's
        np.testing.assert_array_equal(labels(demo, env_id, braking)[0], driver)
        info = _replay(env_id, braking, demo, driver)
        assert info["is_success"] and info["violations"]["max_excess"] == 0.0, (env_id, info)
        assert info["t"] == pytest.approx(demo["T"], abs=0.2) and info["fuel_g"] == pytest.approx(demo["fuel_g"], rel=0.01)


# ---------------------------------------------------------------------------------------------- shipped
# the shipped target-conditioned policies (agents.evaluate.SHIPPED_POLICIES): PPO, and the imitation baseline (a clone
# of the MPC fine-tuned by PPO, docs/benchmarks.md section 7)
SHIPPED = [(k, b) for k in ("ppo-target", "plan", "bc") for b in ("service", "tc")]
SHIPPED_ENV = {"ppo-target": "WheelLoaderTarget-v6", "bc": "WheelLoaderTarget-v5",
               "plan": "WheelLoaderPlan-v1"}


@pytest.mark.parametrize("kind,braking", SHIPPED)
def test_the_shipped_target_policies_load_and_complete_a_test_scenario(kind, braking):
    """Each shipped target-conditioned policy loads pickle-free, drives its env (WheelLoaderTarget-v5: the coasting
    assist with its guards and the lift's engine floor; PPO v6: and with TC braking the lift-off's full load; the
    plan policy: WheelLoaderPlan-v1 (service) or -v0 (TC), one plan per cycle driven on v7 or v6)
    through a held-out cycle at a 1.5 T_min target with its marks met and no violation; its metadata records how it
    was made, stage by stage, the last stage's command the policy's own (PPO: one run from scratch on v6; the plan policy: PPO
    from scratch, then on from it; the imitation baseline: the MPC episodes, the clone, the v3, v4 and v5 fine-tunings)."""
    from agents.evaluate import default_policy_path, evaluate_controller
    from wl_env.suites import load_suite

    policy = load_policy(default_policy_path(braking, kind))
    env_id = SHIPPED_ENV[kind] if isinstance(SHIPPED_ENV[kind], str) else SHIPPED_ENV[kind][braking]
    assert policy.env_id == env_id and policy.braking == braking  # (its config says; the assist)
    assert policy.meta["commands"] and policy.meta["seed"] is not None
    stages = policy.meta["stages"]
    if kind == "plan":  # (scripts/train_plan_policy.py: every stage with its commands, the last the policy's own)
        assert len(stages) == 2 and all(stage["commands"] for stage in stages)
        assert stages[-1]["commands"] == policy.meta["commands"]
    else:  # (the stages before its own run, with commands)
        earlier = {"bc": 4}.get(kind, 0)
        assert [bool(stage.get("commands")) for stage in stages] == [True] * earlier + [False]
    scenario = load_suite("test").of(braking)[0]
    e = evaluate_controller(policy, braking, scenarios=[scenario], target_ratio=1.5, solve=False)["per_episode"][0]
    assert e["success"] and e["max_violation"] == 0.0, e


def _target_pairs(kind: str, braking: str) -> tuple[list[float], list[float], list[float]]:
    """Three held-out cycles at 1.0 and at 1.5 T_min: per cycle the change in cycle time, in target and in fuel."""
    from agents.evaluate import default_policy_path, evaluate_controller
    from wl_env.suites import load_suite

    policy = load_policy(default_policy_path(braking, kind))
    scenarios = list(load_suite("test").of(braking)[:3])
    fast, slow = (evaluate_controller(policy, braking, scenarios=scenarios, target_ratio=r, solve=False)["per_episode"]
                  for r in (1.0, 1.5))
    dT = [s["T"] - f["T"] for f, s in zip(fast, slow, strict=True)]
    d_target = [s["target_time"] - f["target_time"] for f, s in zip(fast, slow, strict=True)]
    d_fuel = [s["fuel_g"] - f["fuel_g"] for f, s in zip(fast, slow, strict=True)]
    return dT, d_target, d_fuel


@pytest.mark.parametrize("kind,braking", SHIPPED)
def test_a_later_target_gives_a_slower_leaner_cycle(kind, braking):
    """Target conditioning: the later target's cycles take longer and burn less fuel, in the median."""
    dT, d_target, d_fuel = _target_pairs(kind, braking)
    assert np.median(dT) > 0 and np.median(d_fuel) < 0, (dT, d_target, d_fuel)


@pytest.mark.parametrize("kind,braking", SHIPPED)
def test_a_later_target_slows_the_cycle_by_a_third_of_the_difference_at_least(kind, braking):
    dT, d_target, d_fuel = _target_pairs(kind, braking)
    assert np.median(dT) > np.median(d_target) / 3, (dT, d_target, d_fuel)


@pytest.mark.parametrize("args,message", [
    (["--env-id", "WheelLoaderTarget-v2", "--dagger-rounds", "1"], "dagger_rounds must be 0 with env_id WheelLoaderTarget-v2"),
    (["--env-id", "WheelLoaderTarget-v2", "--graft-base", "agents/policies/ppo_target_v2_tc"],
     "graft_base needs env_id WheelLoaderTarget-v3"),
    (["--braking", "tc", "--env-id", "WheelLoaderTarget-v6", "--clone-base", "agents/policies/ppo_target_service"],
     "drives service braking"),
    (["--env-id", "WheelLoaderTarget-v3", "--clone-base", "agents/policies/no_such_policy"], "no_such_policy"),
    (["--epochs", "0"], "--epochs must be an integer in [1, 100000]"),  # (was an untrained clone, exit 0)
    (["--beta", "2"], "--beta must be a number in [0, 1]")])  # (was refused after the demonstrations)
def test_train_bc_refuses_what_an_assisted_driver_cannot_take(tmp_path, args, message):
    """The assisted drivers' braking labels come from the expert's own cycle: DAgger (the clone drives) is
    refused by name; a graft is v3's only; a clone's base of another braking, or missing, is refused. Exit 2, no
    traceback, before any demonstration is collected."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "scripts" / "train_bc.py"
    r = subprocess.run([sys.executable, str(script), *args, "--log-dir", str(tmp_path)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and message in r.stderr
    assert "Traceback" not in r.stderr and not any(tmp_path.iterdir())


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_grafting_the_coasting_fraction_keeps_the_v2_policy(tmp_path, braking):
    """The graft (a WheelLoaderTarget-v3 policy from the v2 one) acts as v2 in its three actions and
    fits the fourth to the expert's shifts better than a constant; it refuses a base of another env."""
    from agents.imitation import graft_early_shift

    demos = collect_demos(DemoSettings(braking, seed=3, expert="operator"), 3, tmp_path / "demos")
    base = POLICIES / f"ppo_target_v2_{braking}"  # (the shipped policies' base)
    cfg = PPOConfig(braking=braking, env_id="WheelLoaderTarget-v3", scenario="train", init_noise=0.0,
                    log_dir=str(tmp_path), run_name="graft", progress_bar=False)
    result = graft_early_shift(base, demos, cfg)
    assert result.episodes == 3 and result.samples > 30 and result.loss < 0.5 * result.constant_loss, result
    graft, v2 = load_policy(cfg.run_dir), load_policy(base)
    assert graft.env_id == "WheelLoaderTarget-v3" and graft.meta["method"].startswith("PPO (WheelLoaderTarget-v2)")
    obs = np.concatenate([d["obs"] for d in demos])
    np.testing.assert_allclose(graft.act(obs)[:, :3], v2.act(obs), atol=1e-6)
    with pytest.raises(ValueError, match="must be a WheelLoaderTarget-v2 policy"):
        graft_early_shift(cfg.run_dir / "final" / "policy", demos, PPOConfig(**{**cfg.__dict__, "run_name": "again"}))
    with pytest.raises(ValueError, match="makes a WheelLoaderTarget-v3 policy"):
        graft_early_shift(base, demos, PPOConfig(**{**cfg.__dict__, "env_id": "WheelLoaderTarget-v2"}))


def test_a_clone_from_a_base_keeps_its_critic_and_statistics_and_fits_the_expert(tmp_path):
    """clone(base=...): the regression starts from the shipped v3 policy; its critic and observation
    statistics are kept as they are, its actor comes closer to the expert's labels than the base's; a base
    of another env is refused by name."""
    import torch as th

    from agents.imitation import clone, labels

    demos = collect_demos(DemoSettings("service", seed=3, expert="operator"), 3, tmp_path / "demos")
    base = POLICIES / "ppo_target_service"
    cfg = PPOConfig(braking="service", env_id="WheelLoaderTarget-v6", scenario="train", init_noise=0.0,
                    log_dir=str(tmp_path), run_name="clone", progress_bar=False)
    result = clone(demos, cfg, epochs=30, validation_share=0.34, base=base)
    cloned, shipped = load_policy(cfg.run_dir), load_policy(base)
    assert cloned.meta["base"] == str(base)
    np.testing.assert_array_equal(cloned.normalization.mean, shipped.normalization.mean)
    obs = np.concatenate([d["obs"] for d in demos])
    values = [p.network.predict_values(th.as_tensor(p.normalize(obs))).detach().numpy() for p in (cloned, shipped)]
    np.testing.assert_allclose(values[0], values[1], atol=1e-6)  # the critic untouched
    y, w = (np.concatenate(v) for v in zip(*(labels(d, cfg.env_id, "service") for d in demos), strict=True))
    loss = [float(np.mean(w * (p.network.get_distribution(th.as_tensor(p.normalize(obs))).distribution.mean
                                .detach().numpy() - y) ** 2)) for p in (cloned, shipped)]
    assert loss[0] < 0.5 * loss[1], (loss, result)
    with pytest.raises(ValueError, match="must be a WheelLoaderTarget-v6 policy"):
        clone(demos, PPOConfig(**{**cfg.__dict__, "run_name": "again"}), epochs=1, base=POLICIES / "ppo_target_v2_service")


def test_an_untrained_v3_policy_starts_without_early_coasting(tmp_path):
    """WheelLoaderTarget-v3's fourth action is the coasting fraction: PPO starts it at coast_bias_init (+1:
    95 % of the limit, so the untrained driver drives v2's cycles), not at the shift action's "hold" (-1,
    which here would coast from the first moment coasting reaches the mark)."""
    cfg = _tiny(tmp_path, env_id="WheelLoaderTarget-v3")
    env = make_env(cfg, num_envs=1)
    model = build_model(cfg, env, tmp_path / "tb")
    assert float(model.policy.action_net.bias[3]) == cfg.coast_bias_init == 1.0
    assert float(model.policy.action_net.bias[1]) == cfg.bucket_bias_init
    env.close()


def _demo_loss(policy, demos, env_id: str) -> float:
    import torch as th

    from agents.imitation import demo_samples

    obs, y, w = demo_samples(demos, env_id, "service")
    mean = policy.network.get_distribution(th.as_tensor(policy.normalize(obs))).distribution.mean.detach().numpy()
    return float(np.mean(w * (mean - y) ** 2))


def test_behaviour_cloning_regularization_pulls_the_actor_to_the_demonstrations(tmp_path):
    """--bc-demos: between PPO's updates the actor is fitted to the demonstrations' labels with a decaying
    weight (DAPG-style). The same run with the weight 0 is the control: same seed, same rollouts at first."""
    from agents.ppo import train

    demos = collect_demos(DemoSettings("service", seed=3, expert="operator"), 2, tmp_path / "demos")
    loss = {}
    for weight in (0.0, 5.0):
        cfg = _tiny(tmp_path, env_id="WheelLoaderTarget-v3", run_name=f"bc{weight:g}", learning_rate=3e-3, n_epochs=8,
                    bc_demos=str(tmp_path / "demos"), bc_weight=weight)
        train(cfg)
        loss[weight] = _demo_loss(load_policy(cfg.run_dir), demos, cfg.env_id)
    assert loss[5.0] < 0.5 * loss[0.0], loss


def test_behaviour_cloning_regularization_refuses_what_it_cannot_use(tmp_path):
    from agents.ppo import train
    from agents.ppo_config import ConfigError

    with pytest.raises(ConfigError, match="bc_demos"):
        PPOConfig(env_id="WheelLoader-v1", bc_demos=str(tmp_path))
    with pytest.raises(ConfigError, match="bc_fraction"):
        _tiny(tmp_path, bc_fraction=0.0)
    with pytest.raises(ValueError, match="no demonstration episodes"):
        train(_tiny(tmp_path, env_id="WheelLoaderTarget-v3", bc_demos=str(tmp_path / "none")))
    collect_demos(DemoSettings("service", seed=3, expert="operator", env_id=TARGET_ENV_ID), 1, tmp_path / "v0")
    with pytest.raises(ValueError, match="needs WheelLoaderTarget-v1 episodes"):
        train(_tiny(tmp_path, env_id="WheelLoaderTarget-v3", bc_demos=str(tmp_path / "v0")))
    assert not (tmp_path / "tiny").exists()  # refused before the run folder was written


def test_plan_labels_read_the_fractions_off_the_mpcs_plan():
    """A v3 driver's DAgger labels (agents.imitation.plan_labels): the coasting fraction whose braking point
    is the plan's shift, the braking fraction whose is its brakes' onset (TC, phase 1: its shift), the
    request and bucket as given; weight 0 where an action does nothing or the plan does not say."""
    from agents.imitation import plan_labels
    from wl_env.assist import COAST_FRACTION, fraction_action
    from wl_env.params import DEFAULT_PARAMS as P

    # reversing: 3 steps in gear, 2 rolling, brakes from the 6th; s from 0 towards -6.6 m
    phases = np.array([1, 1, 1, 2, 2, 2, 2])
    controls = np.zeros((7, 3))
    controls[5:, 2] = 20_000.0
    speed = np.array([1.0, 1.5, 2.0, 2.2, 2.1, 2.0, 1.2, 0.3])
    s = -np.concatenate([[3.0], 3.0 + np.cumsum(speed[1:] * 0.1)])
    states = np.column_stack([np.full(8, 150.0), -speed, np.full(8, 1.0), np.zeros(8), s])
    plan = {"phase": phases, "stop": np.zeros(7, bool), "controls": controls, "states": states}
    label, weight = plan_labels(plan, 1, 0.3, -0.2, P, "service", 0.1)
    to_go = s + P.reverse_distance
    assert label[:2].tolist() == pytest.approx([0.3, -0.2]) and weight.tolist() == [1, 1, 1, 1]
    assert label[3] == pytest.approx(fraction_action(speed[3], to_go[3], P, 0.1, COAST_FRACTION))  # the shift
    assert label[2] == pytest.approx(fraction_action(speed[5], to_go[5], P, 0.1))  # the brakes' onset
    label, weight = plan_labels(plan, 1, 0.3, -0.2, P, "tc", 0.1)  # TC: phase 1 is no coasting leg
    assert weight.tolist() == [1, 1, 1, 0] and label[2] == pytest.approx(fraction_action(speed[3], to_go[3], P, 0.1))
    assert plan_labels(plan, 2, 0.3, -0.2, P, "tc", 0.1)[1].tolist() == [0, 1, 0, 0]  # the assist meters phase 2
    assert plan_labels(None, 3, 0.3, -0.2, P, "service", 0.1)[1].tolist() == [1, 1, 0, 0]


def test_a_v3_dagger_collection_needs_a_learner_and_the_mpc():
    with pytest.raises(ValueError, match="with a learner and the MPC"):
        DemoSettings("service", env_id="WheelLoaderTarget-v3")
    with pytest.raises(ValueError, match="with a learner and the MPC"):
        DemoSettings("service", env_id="WheelLoaderTarget-v3", learner="x", expert="operator")


@pytest.mark.slow
def test_a_v3_dagger_episode_is_labelled_from_the_mpcs_plans(tmp_path):
    """The shipped v3 policy drives a train draw; the MPC labels every state it visits; the stored episode
    reads back with its labels and weights, and clones into v3 beside v1 demonstrations (~30-60 s)."""
    from agents.imitation import clone

    (d,) = collect_demos(DemoSettings("service", seed=7, learner=str(POLICIES / "ppo_target_service"),
                                      env_id="WheelLoaderTarget-v3"), 1, tmp_path / "dagger")
    assert d["env_id"] == "WheelLoaderTarget-v3" and d["weights"].shape == d["actions"].shape == (len(d["obs"]), 4)
    assert (np.abs(d["actions"]) <= 1.0).all() and d["weights"][:, 2:].sum() > 0  # fractions labelled somewhere
    (v1,) = collect_demos(DemoSettings("service", seed=3, expert="operator"), 1, tmp_path / "v1")
    cfg = PPOConfig(braking="service", env_id="WheelLoaderTarget-v3", scenario="train", init_noise=0.0,
                    log_dir=str(tmp_path), run_name="clone", progress_bar=False)
    result = clone([v1, d], cfg, epochs=2, validation_share=0.5)
    assert result.samples == len(v1["obs"]) + len(d["obs"])


def test_a_corrupt_demonstration_file_is_refused_by_name(tmp_path):
    """Truncated or empty files, a missing or foreign scenario (the drivers' labels read it), negative weights
    (a loss the fit maximizes) and an episode without steps: a ValueError naming the file, nothing unpickled."""
    collect_demos(DemoSettings("service", seed=3, expert="operator"), 1, tmp_path)
    src = tmp_path / "episode_00000.npz"
    good = dict(np.load(src))
    meta = json.loads(str(good["meta"]))
    (tmp_path / "truncated.npz").write_bytes(src.read_bytes()[:200])
    (tmp_path / "empty.npz").write_bytes(b"")
    cases = {"noscenario": {**good, "meta": np.array(json.dumps({k: v for k, v in meta.items() if k != "scenario"}))},
             "foreign": {**good, "meta": np.array(json.dumps({**meta, "scenario": {"payload": "x"}}))},
             "negative": {**good, "weights": -np.ones_like(good["actions"])},
             "nosteps": {**good, "obs": good["obs"][:0], "actions": good["actions"][:0]}}
    for name, arrays in cases.items():
        np.savez(tmp_path / f"{name}.npz", **arrays)
    for name in ("truncated", "empty", *cases):
        with pytest.raises(ValueError, match=f"{name}.npz"):
            read_demo(tmp_path / f"{name}.npz")


def test_train_bc_checks_its_output_paths_before_the_demonstrations(tmp_path):
    import subprocess
    import sys

    (tmp_path / "file").write_text("")
    script = Path(__file__).resolve().parents[1] / "scripts" / "train_bc.py"
    for flag in ("--export", "--demos"):
        r = subprocess.run([sys.executable, str(script), flag, str(tmp_path / "file" / "x"), "--log-dir",
                            str(tmp_path / "runs")], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and f"{flag} {tmp_path / 'file' / 'x'}" in r.stderr and "Traceback" not in r.stderr
        assert not list((tmp_path / "runs").glob("demos_*"))


def _select_policy(monkeypatch) -> tuple:
    """scripts/select_policy.py as a module, and the shipped target PPO's and imitation baseline's paths (service)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("select_policy", Path(__file__).resolve().parents[1] / "scripts" / "select_policy.py")
    select = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "select_policy", select)  # (its dataclass looks its module up there)
    spec.loader.exec_module(select)
    from agents.evaluate import default_policy_path

    return select, [str(default_policy_path("service", kind)) for kind in ("ppo-target", "bc")]


def test_select_policy_chooses_the_leaner_policy_on_train_draws(tmp_path, monkeypatch):
    """scripts/select_policy.py (the shipping rule of section 7): of the shipped target PPO and the imitation
    baseline, both within the limits on two `train` draws, it chooses the one with less fuel over the three
    targets, and writes what it measured."""
    select, paths = _select_policy(monkeypatch)
    out = select.run(select.Options(braking="service", policies=paths, draws=2, json=str(tmp_path / "sel.json")))
    recs = out["records"]
    assert [r["policy"] for r in recs] == paths and all(r["episodes"] == 6 and r["over_a_limit"] == 0 for r in recs)
    assert out["chosen"] == min(recs, key=lambda r: r["fuel_per_draw_g"])["policy"]
    assert json.loads((tmp_path / "sel.json").read_text())["chosen"] == out["chosen"]
    with pytest.raises(ValueError, match="--draws must be an integer in"):
        select.run(select.Options(braking="service", policies=paths, draws=0))
    with pytest.raises(ValueError, match="--policies needs at least one"):
        select.run(select.Options(braking="service"))
    with pytest.raises(ValueError, match="--by must be 'fuel' or 'gap'"):
        select.run(select.Options(braking="service", policies=paths, by="grams"))
    with pytest.raises(ValueError, match="--cache keeps the optima of --by gap"):
        select.run(select.Options(braking="service", policies=paths, cache=str(tmp_path / "c")))


@pytest.mark.slow  # (80 s: each draw's optima solved)
def test_select_policy_by_gap_scores_each_draw_against_its_own_optimum(tmp_path, monkeypatch):
    """--by gap: #14's figures on the draws, each episode against its own optimum (solved, kept in the cache)."""
    select, paths = _select_policy(monkeypatch)
    out = select.run(select.Options(braking="service", policies=paths, draws=1, by="gap", cache=str(tmp_path / "c")))
    recs = out["records"]
    for r in recs:
        assert sorted(r["per_target"]) == sorted(str(ratio) for ratio in select.RATIOS)
        gaps = [t["fuel_gap_median"] for t in r["per_target"].values()]
        assert all(0.0 < g < 1.0 for g in gaps)  # (above the optimum: a gap under it would be a scoring bug)
        late = [t["lateness_median"] for t in r["per_target"].values()]
        assert r["gap_score_pct"] == pytest.approx(100 * (sum(gaps) + sum(late)))
    assert out["by"] == "gap" and out["chosen"] == min(recs, key=lambda r: r["gap_score_pct"])["policy"]


# ---------------------------------------------------------------------------------------------- hostile-input review
# (agents/ and scripts/: each test fails on the code before its fix)
def test_a_demonstration_folder_of_other_settings_is_refused_when_resumed(tmp_path):
    """A collection resumed in a folder of another braking, seed, --target or --fast-share took its episodes as they
    were: a TC clone was fitted to service cycles, and the metadata named the settings given (train_bc.py's default
    folder names neither --target nor --fast-share)."""
    s = DemoSettings("service", seed=3, expert="operator")
    collect_demos(s, 2, tmp_path)
    assert len(collect_demos(s, 2, tmp_path)) == 2  # the same settings: read back
    d = read_demo(tmp_path / "episode_00000.npz")
    assert d["target_ratio"] > 0 and d["expert"] == "operator" and d["beta"] == 0.0
    for other, what in ((dict(braking="tc"), "scenario"), (dict(seed=4), "scenario"),
                        (dict(target=(2.0, 2.5)), "target"), (dict(fast_share=1.0), "speed")):
        stamp = (tmp_path / "episode_00000.npz").stat().st_mtime_ns
        with pytest.raises(ValueError, match=f"episode_0000.\\.npz is an episode of another collection .*{what}"):
            collect_demos(DemoSettings(**{"braking": "service", "seed": 3, "expert": "operator", **other}), 2, tmp_path)
        assert (tmp_path / "episode_00000.npz").stat().st_mtime_ns == stamp


def test_select_policy_refuses_a_policy_without_targets_before_any_episode(monkeypatch):
    """A policy of WheelLoader-v1 among --policies failed ("PPOPolicy.reset takes no target_time") only after the
    policies before it had driven every draw at the three targets; a policy named twice was one record."""
    import agents.evaluate

    select, paths = _select_policy(monkeypatch)

    def no_episode(*args, **kwargs):
        raise AssertionError("an episode ran before the policies were checked")

    monkeypatch.setattr(agents.evaluate, "evaluate_controller", no_episode)
    v1 = str(POLICIES / "ppo_service.safetensors")
    with pytest.raises(ValueError, match=f"--policies {v1} is a policy of WheelLoader-v1, which is given no target"):
        select.run(select.Options(braking="service", policies=[paths[0], v1], draws=1))
    with pytest.raises(ValueError, match="--policies names a policy twice"):
        select.run(select.Options(braking="service", policies=[paths[0], paths[0]], draws=1))


def test_a_clone_never_replaces_a_training_run_of_its_name(tmp_path):
    """`train_bc.py --run-name R` with R a PPO run: the clone's final/ and config.json replaced the run's (its trained
    policy lost, its checkpoints left under a config of another env), exit 0. A clone's own folder is fitted again."""
    demos = collect_demos(DemoSettings("service", seed=5, expert="operator", env_id=TARGET_ENV_ID), 3, tmp_path / "demos")
    ppo = _tiny(tmp_path, run_name="ppo")
    for folder in ("checkpoints/step_0000001024", "final"):
        (ppo.run_dir / folder).mkdir(parents=True)
    (ppo.run_dir / "final" / "summary.json").write_text(json.dumps({"num_timesteps": 1024}))
    (ppo.run_dir / "config.json").write_text("{}")
    with pytest.raises(ValueError, match=f"{ppo.run_dir} holds a training run, not a clone"):
        clone(demos, ppo, epochs=1)
    assert (ppo.run_dir / "config.json").read_text() == "{}" and sorted(p.name for p in (ppo.run_dir / "final").iterdir()) == ["summary.json"]
    import shutil

    shutil.rmtree(ppo.run_dir / "checkpoints")  # a finished run without checkpoints: refused as well
    with pytest.raises(ValueError, match="holds a training run, not a clone"):
        clone(demos, ppo, epochs=1)
    cfg = _tiny(tmp_path, run_name="bc")
    clone(demos, cfg, epochs=1)
    clone(demos, cfg, epochs=1)  # (a rerun fits its clone again)
