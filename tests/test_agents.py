"""PPO agents: the SB3 adapter of the vector env, training, checkpoints, resume, save/load, shipped policies."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from fakes import tiny_ppo_config
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv

import wl_env  # noqa: F401
from agents.operator import OperatorPolicy, run_episode
from agents.ppo import (
    PPOConfig,
    build_model,
    export_policy,
    latest_checkpoint,
    load_policy,
    make_env,
    read_eval_csv,
    reward_config,
    save_model_files,
    train,
)
from agents.sb3_vec import make_sb3_vec_env
from wl_env.logs import cli_logging

ROOT = Path(__file__).resolve().parents[1]
POLICIES = ROOT / "agents" / "policies"


# ------------------------------------------------------------------------------------------ adapter
@pytest.mark.parametrize("braking,max_time", [("service", 40.0), ("tc", 40.0), ("service", 3.0)])
def test_adapter_matches_dummy_vec_env(braking, max_time):
    """Same observations, rewards, dones, terminal observations and infos as DummyVecEnv of single envs."""
    n, seed = 5, 7
    kw = dict(braking=braking, init_noise=1.0, max_time=max_time)
    ours = make_sb3_vec_env(n, seed=seed, **kw)
    ref = DummyVecEnv([lambda: gym.make("WheelLoader-v1", **kw) for _ in range(n)])
    ref.seed(seed)
    obs_a, obs_b = ours.reset(), ref.reset()
    np.testing.assert_array_equal(obs_a, obs_b)
    operator, rng = OperatorPolicy(braking), np.random.default_rng(0)
    ends = {"done": 0, "truncated": 0, "completed": 0}
    for _ in range(600):
        actions = operator.act(obs_a) + rng.normal(0.0, 0.3, (n, 4)).astype(np.float32)
        actions[0, 3] = rng.uniform(-1.0, 1.0)  # loader 0 shifts at random: short, failed episodes
        obs_a, rew_a, done_a, info_a = ours.step(actions)
        obs_b, rew_b, done_b, info_b = ref.step(actions)
        np.testing.assert_allclose(obs_a, obs_b, rtol=0, atol=1e-6)
        np.testing.assert_allclose(rew_a, rew_b, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(done_a, done_b)
        for a, b in zip(info_a, info_b, strict=True):
            assert a["TimeLimit.truncated"] == b["TimeLimit.truncated"]
            assert a["is_success"] == b["is_success"]
            assert a["phase"] == b["phase"]
            assert a["t"] == pytest.approx(b["t"])
            assert ("terminal_observation" in a) == ("terminal_observation" in b)
            if "terminal_observation" in a:
                np.testing.assert_allclose(a["terminal_observation"], b["terminal_observation"], atol=1e-6)
                ends["done"] += 1
                ends["truncated"] += a["TimeLimit.truncated"]
                ends["completed"] += b["completed"]
    assert ends["done"] > 10
    if max_time < 10:
        assert ends["truncated"] > 0
    else:
        assert ends["completed"] > 0


# ------------------------------------------------------------------------------------------ training
def _tiny(tmp_path: Path, **kw) -> PPOConfig:
    return tiny_ppo_config(tmp_path, **kw)


class _Interrupt(BaseCallback):
    """Stops training like Ctrl-C once ``at`` steps are done."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.at:
            raise KeyboardInterrupt
        return True


def test_short_training_checkpoints_and_saves(tmp_path, capsys):
    cfg = _tiny(tmp_path)
    with cli_logging():  # as the command line shows the progress: logging on stderr, nothing on stdout
        summary = train(cfg, command="pytest")
    out, err = capsys.readouterr()
    assert out == "" and err.count("[eval] step") == 5 and err.splitlines()[0].startswith("[eval] step         0")
    run = cfg.run_dir
    assert summary["num_timesteps"] >= cfg.total_timesteps
    for f in ("final/model.zip", "final/vecnormalize.pkl", "final/summary.json", "config.json", "eval.csv",
              "final/policy.safetensors", "final/policy_vecnormalize.npz", "final/policy.json"):
        assert (run / f).exists(), f
    assert list((run / "tb").glob("PPO_1/events.*"))
    ckpt = latest_checkpoint(run)
    assert ckpt is not None and json.loads((ckpt / "progress.json").read_text())["num_timesteps"] >= 4096
    assert len(list((run / "checkpoints").glob("step_*"))) == cfg.keep_checkpoints
    rows = read_eval_csv(run / "eval.csv")
    assert rows[0]["step"] == 0 and rows[-1]["step"] == summary["num_timesteps"]
    assert json.loads((run / "config.json").read_text())["commands"] == ["pytest"]
    with pytest.raises(FileExistsError):
        train(cfg)  # an existing run is only continued with resume


def test_resume_continues_from_checkpoint(tmp_path):
    cfg = _tiny(tmp_path, total_timesteps=6144)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, callbacks=[_Interrupt(3500)])
    ckpt = latest_checkpoint(cfg.run_dir)
    done = json.loads((ckpt / "progress.json").read_text())["num_timesteps"]
    assert 1024 <= done < 3500
    assert not (cfg.run_dir / "final").exists()
    # the given config only names the run: the saved one (6144 steps) is used
    summary = train(PPOConfig(log_dir=cfg.log_dir, run_name="tiny", progress_bar=False), resume=True, command="again")
    assert cfg.total_timesteps <= summary["num_timesteps"] < cfg.total_timesteps + 8 * 64
    steps = [r["step"] for r in read_eval_csv(cfg.run_dir / "eval.csv")]
    assert steps == sorted(set(steps)) and steps[0] == 0 and steps[-1] == summary["num_timesteps"]
    assert [p.name for p in (cfg.run_dir / "tb").iterdir()] == ["PPO_1"]  # logs appended to the same folder
    assert summary["commands"] == ["again"] or summary["commands"][-1] == "again"


def test_resume_after_sigkill_continues_from_the_last_complete_checkpoint(tmp_path):
    """A training process killed with SIGKILL (no cleanup) resumes from its newest complete checkpoint; a
    half-written checkpoint (the staging folder a kill leaves) is never used."""
    cfg = _tiny(tmp_path, total_timesteps=16384, eval_freq=4096)
    script = ("import json, sys\nfrom agents.ppo import PPOConfig, train\n"
              f"train(PPOConfig.from_dict(json.loads({json.dumps(json.dumps(cfg.to_dict()))})))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while latest_checkpoint(cfg.run_dir) is None:
            assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
            assert time.monotonic() < deadline, "no checkpoint within 120 s"
            time.sleep(0.05)
    finally:
        proc.kill()  # SIGKILL: no handler, no atexit, files as they are
        proc.wait()
    assert not (cfg.run_dir / "final").exists()
    done = json.loads((latest_checkpoint(cfg.run_dir) / "progress.json").read_text())["num_timesteps"]
    # what a kill in the middle of a save leaves: a staging folder, and a folder without its progress.json
    root = cfg.run_dir / "checkpoints"
    for half in (root / ".step_9999999999.tmp", root / "step_9999999999"):
        half.mkdir(exist_ok=True)
        (half / "model.zip").write_bytes(b"PK\x03\x04 cut short")
    # (the kill may land between a checkpoint folder's rename and the pointer's write: then there is none to remove)
    (root / "latest.json").unlink(missing_ok=True)
    assert latest_checkpoint(cfg.run_dir).name == f"step_{done:010d}"
    summary = train(PPOConfig(log_dir=cfg.log_dir, run_name="tiny", progress_bar=False), resume=True)
    assert cfg.total_timesteps <= summary["num_timesteps"] < cfg.total_timesteps + 8 * 64
    steps = [r["step"] for r in read_eval_csv(cfg.run_dir / "eval.csv")]
    assert steps == sorted(set(steps)) and steps[0] == 0 and steps[-1] == summary["num_timesteps"]
    left = sorted(p.name for p in root.iterdir())  # the leftovers were cleared with the old checkpoints
    assert left == ["latest.json", *[f"step_{n:010d}" for n in (15360, 16384)]], left


def test_save_load_round_trip_gives_identical_actions(tmp_path):
    cfg = _tiny(tmp_path)
    env = make_env(cfg)
    model = build_model(cfg, env, tmp_path / "tb")
    model.learn(1024)
    obs = env.get_original_obs()
    space = env.observation_space  # (random observations within it: the policy refuses others)
    obs = np.concatenate([obs, np.random.default_rng(1).uniform(space.low, space.high, obs.shape).astype(np.float32)])
    expected = model.predict(env.normalize_obs(obs), deterministic=True)[0]
    folder = save_model_files(model, env, tmp_path / "saved", {"braking": cfg.braking}, export=True)
    policy = load_policy(folder)  # the pickle-free policy.* in the folder
    assert policy.braking == cfg.braking
    np.testing.assert_array_equal(policy.act(obs), expected)
    single = model.predict(env.normalize_obs(obs[:1])[0], deterministic=True)[0]
    np.testing.assert_array_equal(policy.act(obs[0]), single)  # one observation, shape (12,)
    np.testing.assert_array_equal(load_policy(folder / "model.zip", trust_pickle=True).act(obs), expected)


def test_export_is_pickle_free_and_acts_like_the_run(tmp_path):
    cfg = _tiny(tmp_path, total_timesteps=1024, eval_freq=10**6, checkpoint_freq=10**6)
    train(cfg)
    meta = export_policy(cfg.run_dir, tmp_path / "shipped", "mine", n_episodes=1, score=False)
    assert sorted(p.name for p in (tmp_path / "shipped").iterdir()) == [
        "mine.json", "mine.safetensors", "mine_vecnormalize.npz"]
    assert meta["format"] == "wl-ppo-policy" and meta["network"]["net_arch"] == {"pi": [16, 16], "vf": [16, 16]}
    assert meta["braking"] == "service" and meta["config"]["total_timesteps"] == 1024
    obs = np.random.default_rng(3).uniform(0.0, 1.0, (32, 12)).astype(np.float32)
    run = load_policy(cfg.run_dir / "final" / "model.zip", trust_pickle=True)
    np.testing.assert_array_equal(load_policy(tmp_path / "shipped" / "mine").act(obs), run.act(obs))
    np.testing.assert_array_equal(load_policy(cfg.run_dir).act(obs), run.act(obs))  # a run dir: its final/policy.*


def test_bounded_mean_policy_is_rebuilt_from_its_metadata(tmp_path):
    cfg = _tiny(tmp_path, bounded_mean=True)
    env = make_env(cfg)
    env.reset()
    model = build_model(cfg, env, tmp_path / "tb")
    folder = save_model_files(model, env, tmp_path / "saved", {"braking": "service"}, export=True)
    policy = load_policy(folder)
    assert type(policy.network).__name__ == "BoundedMeanPolicy" and policy.network.mean_bound == 1.1
    obs = np.random.default_rng(2).uniform(0.0, 1.0, (32, 12)).astype(np.float32)
    np.testing.assert_array_equal(policy.act(obs), model.predict(env.normalize_obs(obs), deterministic=True)[0])


def test_reward_curriculum_ramps_to_the_run_values():
    cfg = PPOConfig(total_timesteps=1000, curriculum_fraction=0.5, w_time=3.0,
                    reward={"target_distance": 60.0}, curriculum_start={"target_distance": 2.0, "w_time": 1.0})
    assert (reward_config(cfg, 0).target_distance, reward_config(cfg, 0).w_time) == (2.0, 1.0)
    assert reward_config(cfg, 250).target_distance == pytest.approx(31.0)
    assert reward_config(cfg, 500) == reward_config(cfg, 10_000) == reward_config(cfg)
    assert reward_config(cfg).target_distance == 60.0 and reward_config(cfg).w_time == 3.0
    with pytest.raises(ValueError, match="unknown"):
        PPOConfig(reward={"no_such_weight": 1.0})


# ------------------------------------------------------------------------------------------ shipped
@pytest.mark.parametrize("braking", ["service", "tc"])
def test_shipped_policy_completes_the_cycle(braking):
    path = POLICIES / f"ppo_{braking}.safetensors"
    assert path.exists() and path.stat().st_size < 2_000_000
    assert (POLICIES / f"ppo_{braking}_vecnormalize.npz").exists()
    assert not list(POLICIES.glob("*.zip")) and not list(POLICIES.glob("*.pkl"))  # nothing shipped unpickles
    meta = json.loads((POLICIES / f"ppo_{braking}.json").read_text())
    assert meta["braking"] == braking
    policy = load_policy(path)
    env = gym.make("WheelLoader-v1", braking=braking)
    result = run_episode(env, policy)
    assert result.completed and result.success, result
    env = gym.make("WheelLoader-v1", braking=braking, init_noise=1.0)
    assert run_episode(env, policy, seed=123).completed


@pytest.mark.parametrize("braking", ["tc"])  # (the service policy was retrained on v1, exported pickle-free)
def test_shipped_policy_acts_as_before_its_conversion(braking):
    """The pickle-free shipped policy gives the actions the stable-baselines3 zip gave before the conversion
    (recorded with the old loader on 100 uniform and 100 on-trajectory observations), to float32 rounding:
    torch's CPU kernels differ between processors in the last bits (seen: 3.6e-7 on an AMD EPYC)."""
    ref = np.load(Path(__file__).parent / "data" / "shipped_policy_actions.npz", allow_pickle=False)
    obs, expected = ref[f"obs_{braking}"], ref[f"actions_{braking}"]
    assert obs.shape == (200, 12) and 0.2 < np.mean(np.abs(expected) < 1.0)  # not only saturated actions
    np.testing.assert_allclose(load_policy(POLICIES / f"ppo_{braking}").act(obs), expected, rtol=0, atol=1e-5)


def test_a_target_ratio_sets_each_episodes_target_from_its_own_minimum_time():
    """`--target-ratio 1.15` on a test-suite scenario: the MPC is told 1.15 x that scenario's T_min (from
    the shipped optima), finishes by it (lateness 0) and the aggregate carries the issue's keys."""
    from agents.evaluate import evaluate_controller, load_controller
    from mpc.benchmark.reference import min_time_of
    from wl_env.suites import load_suite

    sc = load_suite("test").spread("tc", 1)[0]
    r = evaluate_controller(load_controller("mpc", "tc"), scenarios=[sc], target_ratio=1.15, solve=False)
    e, s = r["per_episode"][0], r["summary"]
    assert e["target_time"] == pytest.approx(1.15 * min_time_of("tc", sc.params(), solve=False))
    assert e["success"] and e["T"] <= e["target_time"] + 1e-9 and e["lateness"] == 0.0
    assert e["T"] > e["T_min"] * 1.05  # not the minimum-time cycle: it spends the time on fuel
    for key in ("success_rate", "time_gap_median", "fuel_gap_median", "fuel_gap_p90", "lateness_median"):
        assert key in s
    assert s["lateness_median"] == 0.0 and s["fuel_gap_median"] < 0.01


def test_a_controller_that_takes_no_target_is_refused_by_name():
    from agents.evaluate import evaluate_controller, load_controller

    with pytest.raises(ValueError, match="OperatorPolicy.reset takes no target_time"):
        evaluate_controller(load_controller("operator", "service"), "service", episodes=1, target_time=12.0)
    for bad in ({"target_time": 0.0}, {"target_time": 45.0}, {"target_ratio": 0.9}, {"target_ratio": float("nan")},
                {"target_time": 10.0, "target_ratio": 1.2}):
        with pytest.raises(ValueError, match="target"):
            evaluate_controller(load_controller("operator", "service"), "service", episodes=1, **bad)


def test_evaluate_and_load_controller_refuse_bad_arguments_by_name(tmp_path):
    """Each a ValueError naming the argument before any episode (were AttributeErrors and TypeErrors, a cache that is
    a file failed after the episodes, a scenario dict was refused by load_controller that evaluate_controller takes)."""
    from agents.evaluate import evaluate_controller, load_controller

    op = load_controller("operator", "service")
    (tmp_path / "file").write_text("")
    for call, needle in [(lambda: evaluate_controller(None, "service", episodes=1), "act\\(obs\\) method"),
                         (lambda: evaluate_controller("operator", "service", episodes=1), "act\\(obs\\) method"),
                         (lambda: evaluate_controller(op, "service", episodes=1, front="x"), "front must be"),
                         (lambda: evaluate_controller(op, "service", episodes=1, cache=123), "cache must be"),
                         (lambda: evaluate_controller(op, "service", episodes=1, cache=tmp_path / "file"), "not a folder"),
                         (lambda: evaluate_controller(op, "service", episodes=1, progress=lambda: None), "progress must be"),
                         (lambda: load_controller(None, "service"), "must be named by a string"),
                         (lambda: load_controller("ppo", "service", model=5), "model must be"),
                         (lambda: load_controller("mpc", "service", scenario="junk"), "scenario takes JSON")]:
        with pytest.raises(ValueError, match=needle):
            call()
    assert load_controller("operator", "service", scenario={"payload": 9000.0}).params.M_load == pytest.approx(9000.0)


def test_a_learned_policy_refuses_an_observation_outside_its_space():
    """A 1-number obs was given an action, an obs of 1e30 too, NaN was torch's error: each a ValueError by name."""
    from agents.evaluate import load_controller

    for spec in ("ppo", "plan"):
        c = load_controller(spec, "service")
        n = c.network.observation_space.shape[0]
        for obs, needle in [(np.zeros(1), f"obs must be {n} finite numbers"), (0.5, "got float"),
                            (np.full(n, np.nan), "non-finite"), (np.full(n, 1e30), "obs\\[0\\] must lie in")]:
            with pytest.raises(ValueError, match=needle):
                c.act(obs)


def test_a_per_step_policy_is_refused_as_the_plan_controller():
    """`wl evaluate --controller plan --model agents/policies/ppo_service` ran the per-step policy and reported it as
    the plan policy. (--controller ppo runs any policy, a plan env's too: tests/test_plan.py.)"""
    from agents.evaluate import load_controller

    with pytest.raises(ValueError, match="is a policy of WheelLoader-v1, not of a plan env: --controller ppo runs it"):
        load_controller("plan", "service", "agents/policies/ppo_service")
    assert load_controller("plan", "service", "agents/policies/plan_target_service", targeted=True) is not None


def test_a_target_policy_evaluated_without_a_target_records_the_target_its_env_drew():
    """`wl evaluate --controller plan` (or bc) without a target: the env draws each episode's target in 1-2.5 T_min and
    the policy drives to it; the record said target_time None, lateness None (T 15.7, 14.0, 11.2 s on the nominal
    cycle read as untargeted time gaps of +37..+92 %)."""
    from agents.evaluate import evaluate_controller, load_controller

    c = load_controller("plan", "service")
    r = evaluate_controller(c, "service", episodes=2, init_noise=0.0, score=False)
    env = gym.make(c.env_id, braking="service")
    for i, e in enumerate(r["per_episode"]):
        env.reset(seed=i)
        assert e["target_time"] == env.unwrapped.target_time
        assert e["lateness"] == max(e["T"] - e["target_time"], 0.0) / e["target_time"]
    assert r["summary"]["lateness_median"] is not None
    op = evaluate_controller(load_controller("operator", "service"), "service", episodes=1, score=False)
    assert op["per_episode"][0]["target_time"] is None  # an env without targets records none


# ---------------------------------------------------------------------------------------------- hostile-input review
# (agents/ and scripts/: each test fails on the code before its fix)
def test_resuming_a_finished_run_is_refused_and_keeps_its_policy(tmp_path):
    """`wl train --resume` of a finished run restored its last checkpoint (taken before the last rollout's update)
    and wrote it as final/: the finished policy replaced by an older one, summary.json's last evaluation dropped,
    exit 0."""
    cfg = _tiny(tmp_path, total_timesteps=3000)  # (ends at 3072, a checkpoint step: its checkpoint is on disk)
    summary = train(cfg, command="first")
    assert latest_checkpoint(cfg.run_dir) is not None and summary["last_eval"] is not None
    final = cfg.run_dir / "final"
    before = {p.name: p.read_bytes() for p in final.iterdir()}
    with pytest.raises(FileExistsError, match="holds a finished run: its policy is"):
        train(PPOConfig(log_dir=cfg.log_dir, run_name="tiny", progress_bar=False), resume=True, command="again")
    assert {p.name: p.read_bytes() for p in final.iterdir()} == before
    assert json.loads((cfg.run_dir / "config.json").read_text())["commands"] == ["first"]


def test_a_checkpoint_holds_the_policy_updated_on_the_rollouts_its_step_count_includes(tmp_path):
    """A checkpoint was written during the last step of a rollout, before PPO's update on that rollout: its step count
    included the rollout, its weights did not, so a resumed run never learned from it (one update lost per resume).
    The checkpoint of a run's last step is its final policy; its update count is every rollout's."""
    from safetensors.numpy import load_file

    cfg = _tiny(tmp_path, total_timesteps=3000)  # (6 rollouts of 512 steps; checkpoints due at 1024, 2048, 3072)
    summary = train(cfg)
    ckpt = latest_checkpoint(cfg.run_dir)
    assert ckpt.name == f"step_{summary['num_timesteps']:010d}"
    ours, final = load_file(ckpt / "policy.safetensors"), load_file(cfg.run_dir / "final" / "policy.safetensors")
    assert ours.keys() == final.keys() and all(np.array_equal(ours[k], final[k]) for k in ours)
    updates = json.loads((ckpt / "training.json").read_text())["n_updates"]
    assert updates == 6 * cfg.n_epochs  # (6 rollouts, n_epochs each: was 5 rollouts' worth)


# ---------------------------------------------------------------------------------------------------------------------
# Eleventh review round (agents/evaluate.py): each test fails on the code before its fix.
# ---------------------------------------------------------------------------------------------------------------------
def test_evaluate_controller_refuses_switches_that_are_no_bools_before_any_episode():
    """`solve="no"` failed at the first score, after the episode had run; `score="no"` scored (a non-empty string is
    true). Each switch is True or False (numpy's too), else a ValueError naming it before any episode."""
    from agents.evaluate import evaluate_controller

    class Counting(OperatorPolicy):
        acts = 0

        def act(self, obs):
            Counting.acts += 1
            return super().act(obs)

    for kw in ({"solve": "no"}, {"score": "no"}, {"score": False, "solve": 0}, {"trajectories": 1},
               {"deferred": None}):
        name = next(k for k, v in kw.items() if not isinstance(v, bool))
        with pytest.raises(ValueError, match=f"^{name} must be True or False"):
            evaluate_controller(Counting("service"), "service", episodes=1, **kw)
    assert Counting.acts == 0
    r = evaluate_controller(Counting("service"), "service", episodes=1, score=np.bool_(False), solve=np.bool_(False))
    assert Counting.acts > 0 and r["per_episode"][0]["time_gap"] is None
