"""scripts/train_plan_policy.py: the plan policy's staged PPO recipe as one resumable job, shipped with its stages."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import train_plan_policy as tp  # noqa: E402

from agents.ppo import load_policy, read_eval_csv  # noqa: E402


def tiny(log_dir: Path, **kw) -> tp.Options:
    return tp.Options(**{"braking": "tc", "seed": 3, "log_dir": str(log_dir), "cycles": (16, 16), "log_std_init": (-1.0, -3.0),
                         "log_std_final": (-3.5, -4.0), "num_envs": 8, "eval_freq": 16, "eval_episodes": 1,
                         "checkpoint_freq": 8, "score": False, **kw})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("plan_stages")
    out = tp.main(tiny(root, cycles=(16,), log_std_init=(-1.0,), log_std_final=(-3.5,)))  # stage 1 alone first
    return root, out


def test_a_second_stage_starts_from_the_first_which_is_kept(trained):
    root, first = trained
    stage1 = root / "plan_tc_s3_stage1" / "final" / "summary.json"
    before = stage1.read_text()
    out = tp.main(tiny(root, curve=str(root / "curve"), export=str(root / "policy"), export_episodes=2))[3]
    assert stage1.read_text() == before  # (not trained again)
    assert [s["num_timesteps"] for s in out["stages"]] == [16, 16]
    cfg2 = json.loads((root / "plan_tc_s3_stage2" / "config.json").read_text())["config"]
    assert Path(cfg2["init_policy"]) == root / "plan_tc_s3_stage1" and cfg2["log_std_init"] == -3.0
    # the curve runs on over the stages: stage 2's start (stage 1's end) is not repeated
    steps = [r["step"] for r in read_eval_csv(root / "curve.csv")]
    assert steps == [0, 16, 32] and (root / "curve.png").stat().st_size > 0
    meta = json.loads((root / "policy.json").read_text())
    assert meta["num_timesteps"] == 32 and [s["log_std"] for s in meta["stages"]] == [[-1.0, -3.5], [-3.0, -4.0]]
    assert all("train_plan_policy.py" in s["commands"][0] for s in meta["stages"])
    assert load_policy(root / "policy").act is not None


def test_an_interrupted_stage_resumes_from_its_checkpoint(tmp_path, caplog):
    one = dict(cycles=(16,), log_std_init=(-1.0,), log_std_final=(-3.5,))  # (its own run: the module's stays whole)
    tp.main(tiny(tmp_path, **one))
    shutil.rmtree(tmp_path / "plan_tc_s3_stage1" / "final")  # (killed after its last checkpoint, before its end)
    with caplog.at_level("INFO", logger="train_plan_policy"):
        out = tp.main(tiny(tmp_path, **one))[3]
    assert "(resuming)" in caplog.text and out["stages"][0]["num_timesteps"] == 16
    assert (tmp_path / "plan_tc_s3_stage1" / "final" / "summary.json").exists()


def test_a_kept_stage_of_other_settings_is_refused(trained):
    root, _ = trained
    with pytest.raises(ValueError, match=r"plan_tc_s3_stage1 holds a run made with other settings \(total_timesteps\)"):
        tp.main(tiny(root, cycles=(24,), log_std_init=(-1.0,), log_std_final=(-3.5,)))


@pytest.mark.parametrize("kw, match", [
    ({"cycles": (16,)}, "one value per stage"),
    ({"cycles": ()}, "one value per stage"),
    ({"num_envs": 0}, "--num-envs must be an integer in"),  # (said as the flag, not PPOConfig.num_envs)
    ({"cycles": (16, 0)}, r"--cycles must be integers in \[1, 1000000000\]"),  # (was PPOConfig.total_timesteps's error)
    ({"export": " "}, "--export must name a path"),
    ({"seeds": (1, 2), "export": "p"}, "--export and --curve ship one seed's policy"),
    ({"seeds": (1, 1)}, "--seeds must be distinct integers"),
    ({"ray": "nowhere"}, "--ray")])
def test_bad_options_are_refused_by_name_before_any_work(tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        tp.main(tiny(tmp_path / "runs", **kw))
    assert not (tmp_path / "runs").exists()


def test_seeds_train_on_a_local_ray_instance_as_they_would_here(tmp_path):
    """--seeds --ray local: each seed's stages as one Ray task, in the same folders as without Ray (the first
    seed trained here beforehand is read back, not trained again)."""
    pytest.importorskip("ray")
    one = dict(cycles=(16,), log_std_init=(-1.0,), log_std_final=(-3.5,))
    here = tp.main(tiny(tmp_path, seed=5, **one))[5]
    out = tp.main(tiny(tmp_path, seeds=(5, 6), ray="local", **one))
    assert out[5] == here and out[6]["stages"][0]["num_timesteps"] == 16
    cfg6 = json.loads((tmp_path / "plan_tc_s6_stage1" / "final" / "summary.json").read_text())
    assert cfg6["seed"] == 6 and (tmp_path / "plan_tc_s6_stages.json").exists()
