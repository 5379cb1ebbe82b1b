"""Several PPO runs (agents.seeds): seeds and sweeps with one run directory each, locally and on a local Ray
instance with the same layout; a finished run is not trained again, an interrupted one resumes."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from fakes import tiny_ppo_config

from agents.ppo import PPOConfig, latest_checkpoint, load_policy, read_eval_csv, train
from agents.ppo_config import TARGET_ENV_ID
from agents.seeds import SUMMARY_FILE, expand, parse_sweep, train_runs


def _tiny(tmp_path: Path, **kw) -> PPOConfig:
    return tiny_ppo_config(tmp_path, **{"total_timesteps": 2048, "n_epochs": 1, "eval_episodes": 1,
                                        "net_arch": (8, 8), **kw})


def test_sweep_and_seeds_expand_to_one_named_run_each(tmp_path):
    cfgs = expand(_tiny(tmp_path), [0, 3], parse_sweep(["learning_rate=1e-4,3e-4", "n_epochs=2"]))
    assert [c.name for c in cfgs] == ["tiny_learning_rate0.0001_n_epochs2_s0", "tiny_learning_rate0.0001_n_epochs2_s3",
                                      "tiny_learning_rate0.0003_n_epochs2_s0", "tiny_learning_rate0.0003_n_epochs2_s3"]
    assert [(c.learning_rate, c.n_epochs, c.seed) for c in cfgs][1] == (1e-4, 2, 3)
    for bad, word in ((["learning_rate"], "FIELD=V1"), (["nope=1"], "nope"), (["n_epochs=two"], "two"),
                      (["reward=1"], "single value"), (["seed=1,2"], "seed"),
                      (["n_epochs=1", "n_epochs=2"], "given twice"), (["n_epochs=1,1"], "a value repeats")):
        with pytest.raises(ValueError, match=word):
            parse_sweep(bad)
    with pytest.raises(ValueError, match="repeat"):
        expand(_tiny(tmp_path), [1, 1])
    with pytest.raises(Exception, match="n_epochs"):
        expand(_tiny(tmp_path), [0], parse_sweep(["n_epochs=0"]))  # each point validated as a PPOConfig


def test_seeds_train_locally_report_their_spread_and_are_not_trained_twice(tmp_path):
    cfgs = expand(_tiny(tmp_path), [0, 1])
    results = train_runs(cfgs)
    assert set(results) == {"tiny_s0", "tiny_s1"}
    for c in cfgs:
        assert (c.run_dir / "final" / "policy.safetensors").exists()
    summary = json.loads((tmp_path / SUMMARY_FILE).read_text())
    point = summary["points"]["tiny"]
    assert point["seeds"] == [0, 1] and point["mean_return"]["n"] == 2
    assert point["mean_return"]["q25"] <= point["mean_return"]["median"] <= point["mean_return"]["q75"]
    # different seeds, different runs
    r0, r1 = (summary["runs"][n]["last_eval"]["mean_return"] for n in ("tiny_s0", "tiny_s1"))
    assert r0 != r1
    stamp = (cfgs[0].run_dir / "final" / "summary.json").stat().st_mtime_ns
    assert train_runs(cfgs) == results  # finished: read back, not trained again
    assert (cfgs[0].run_dir / "final" / "summary.json").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="holds a run made with other settings \\(gamma\\)"):  # (was read back as it)
        train_runs(expand(dataclasses.replace(_tiny(tmp_path), gamma=0.5), [0]))


def test_an_interrupted_target_run_of_a_sweep_resumes_its_step_count(tmp_path):
    """A WheelLoaderTarget-v0 run on train draws, killed by Ctrl-C after its first checkpoint: the same
    command (train_runs) resumes it from there with its saved config and ends on the step budget."""
    (cfg,) = expand(_tiny(tmp_path, total_timesteps=4096, env_id=TARGET_ENV_ID, scenario="train", init_noise=0.0), [0])
    from stable_baselines3.common.callbacks import BaseCallback

    class Stop(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps >= 2500:
                raise KeyboardInterrupt
            return True

    with pytest.raises(KeyboardInterrupt):
        train(cfg, callbacks=[Stop()])
    done = json.loads((latest_checkpoint(cfg.run_dir) / "progress.json").read_text())["num_timesteps"]
    assert 1024 <= done < 2500
    summary = train_runs([cfg])[cfg.name]
    assert 4096 <= summary["num_timesteps"] < 4096 + 64 * 8
    steps = [r["step"] for r in read_eval_csv(cfg.run_dir / "eval.csv")]
    assert steps == sorted(set(steps)) and steps[-1] == summary["num_timesteps"]
    assert summary["config"]["env_id"] == TARGET_ENV_ID
    assert load_policy(cfg.run_dir).env_id == TARGET_ENV_ID  # a 21-entry policy


def test_seeds_train_on_a_local_ray_instance_with_the_local_layout(tmp_path):
    pytest.importorskip("ray")
    cfgs = expand(_tiny(tmp_path, total_timesteps=1024, eval_freq=512), [0, 1])
    results = train_runs(cfgs, ray_address="local")
    assert set(results) == {"tiny_s0", "tiny_s1"}
    for c in cfgs:
        for f in ("config.json", "eval.csv", "final/summary.json", "final/policy.safetensors"):
            assert (c.run_dir / f).exists(), f
        assert json.loads((c.run_dir / "final" / "summary.json").read_text())["seed"] == c.seed
    assert json.loads((tmp_path / SUMMARY_FILE).read_text())["points"]["tiny"]["seeds"] == [0, 1]


def test_a_wheelloader_v2_run_trains_and_a_finished_run_is_not_overwritten(tmp_path):
    """A run on WheelLoader-v2 (19 observations) was evaluated on v1 (12) and failed at its first evaluation, blaming
    "controller policy"; a finished run shorter than a checkpoint was overwritten by another `wl train` without a word;
    the same --log-dir spelled with a trailing slash was "other settings" to its read-back (stop 59)."""
    from agents.seeds import train_one

    cfg = tiny_ppo_config(tmp_path, env_id="WheelLoader-v2", total_timesteps=1024, eval_freq=512, eval_episodes=1,
                          checkpoint_freq=10**6)
    summary = train(cfg)
    assert summary["num_timesteps"] >= 1024 and summary["last_eval"] is not None
    assert latest_checkpoint(cfg.run_dir) is None
    with pytest.raises(FileExistsError, match="already holds a run"):
        train(dataclasses.replace(cfg, seed=1, learning_rate=1e-3))
    # (--resume trained it again from step 0 over its policy, eval.csv and tb/: stop 60)
    eval_csv = (cfg.run_dir / "eval.csv").read_text()
    with pytest.raises(FileExistsError, match="holds a finished run with no checkpoint to resume from"):
        train(cfg, resume=True)
    assert (cfg.run_dir / "eval.csv").read_text() == eval_csv
    again = train_one(dataclasses.replace(cfg, log_dir=cfg.log_dir + "/").to_dict())
    assert again["num_timesteps"] == summary["num_timesteps"]


def test_a_run_that_fails_on_ray_is_its_own_error(monkeypatch):
    """Ray's RayTaskError reached the command line as its coloured traceback in one line (stop 59): the run's own
    error is raised, and the other tasks are cancelled."""
    import contextlib
    import types

    import ray.exceptions

    import agents.seeds as seeds
    import mpc.workers

    cancelled = []

    def get(ref):
        raise ray.exceptions.RayTaskError("train_one", "Traceback ...", ValueError("a bad run"))

    fake = types.SimpleNamespace(remote=lambda **kw: (lambda fn: types.SimpleNamespace(remote=lambda *a: object())),
                                 wait=lambda pending, num_returns: (pending[:1], pending[1:]), get=get,
                                 cancel=lambda ref, force: cancelled.append(ref), exceptions=ray.exceptions)
    monkeypatch.setattr(mpc.workers, "ray_session", lambda address: contextlib.nullcontext(fake))
    with pytest.raises(ValueError, match="^a bad run$") as exc:
        seeds.on_ray({"a": (print, ()), "b": (print, ())}, "local")
    assert "RayTaskError" not in type(exc.value).__name__ and "\x1b[" not in str(exc.value) and len(cancelled) == 1
