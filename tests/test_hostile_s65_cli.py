"""The gaps the thirteenth hostile round (stop 65, the `wl` command line and the scripts) found: two outputs of one
command at one path, an output over the policy a run starts from, a searches file that hung its read, a target under
the minimum time refused only in a later cycle's process, and options taken without a word where they do nothing.
Each test fails on the code before its fix."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest
from fakes import load_script

import wl.cli
from wl_env import atomic_io

ROOT = Path(__file__).resolve().parents[1]
POLICIES = ROOT / "agents" / "policies"  # (read only: copied where a test needs a writable one)


def _script(name: str):
    return load_script(name, "s65_")


def _never(*args, **kwargs):
    raise AssertionError("the work was reached")


# ------------------------------------------------------------------------------- two outputs at one path
def test_refuse_one_path_twice_sees_one_path_by_any_spelling(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "link").symlink_to(tmp_path / "a.json")
    for other in ("a.json", "./a.json", str(tmp_path / "a.json"), "link"):
        with pytest.raises(ValueError, match=r"--json .* is the same path as --cache a\.json"):
            atomic_io.refuse_one_path_twice([("--cache", "a.json"), ("--json", other)])
    atomic_io.refuse_one_path_twice([("--cache", "a.json"), ("--json", "b.json")])  # (two paths: no error)


def test_fit_min_time_refuses_its_cache_as_its_out_before_any_solve(tmp_path, monkeypatch):
    """`--cache X --out X` solved every draw (minutes: 160 OCPs by default), then failed "X is a folder"."""
    script = _script("fit_min_time.py")
    monkeypatch.setattr("mpc.workers.run_in_workers", _never)
    x = str(tmp_path / "X")
    with pytest.raises(ValueError, match="--out .* is the same path as --cache"):
        script.main(script.Options(draws=72, cache=x, out=x))
    assert not os.path.lexists(x)


def test_select_policy_refuses_its_cache_as_its_json_before_any_episode(tmp_path):
    """`--by gap --cache X --json X` drove every draw at every target, then failed "X is a folder"."""
    script = _script("select_policy.py")
    x = str(tmp_path / "X")
    with pytest.raises(ValueError, match="--json .* is the same path as --cache"):
        script.check(script.Options(policies=[str(POLICIES / "ppo_target_service")], by="gap", cache=x, json=x))
    assert not os.path.lexists(x)


def test_train_plan_policy_refuses_an_export_or_curve_on_its_own_files_before_the_training(tmp_path, monkeypatch):
    """`--export <log-dir>/plan_service_s0_stages` wrote the stages record over the shipped policy's metadata after the
    training; `--curve <stage run>/eval` wrote the curve over the eval.csv it is drawn from."""
    script = _script("train_plan_policy.py")
    monkeypatch.setattr(script, "train_stages", _never)
    runs = tmp_path / "runs"
    with pytest.raises(ValueError, match="--export .*_stages.json is the same path as --log-dir's stages record"):
        script.main(script.Options(log_dir=str(runs), export=str(runs / "plan_service_s0_stages")))
    with pytest.raises(ValueError, match="--curve .*eval.csv is the same path as a stage's eval.csv"):
        script.main(script.Options(log_dir=str(runs), curve=str(runs / "plan_service_s0_stage1" / "eval")))


def test_distill_plans_checks_its_default_searches_file_and_keeps_it_off_the_policy(tmp_path):
    """A FIFO at the default `OUT_searches.npz` hung the resume's read for good (only a given --demos was checked);
    `--demos OUT.json` had the distilled policy written over the searches."""
    script = _script("distill_plans.py")
    policy = str(POLICIES / "plan_target_service")
    os.mkfifo(tmp_path / "d_searches.npz")
    with pytest.raises(ValueError, match=r"--demos \(default OUT_searches.npz\): .*d_searches.npz is not a regular file"):
        script.check(script.Options(policy=policy, out=tmp_path / "d"))
    with pytest.raises(ValueError, match="--demos .*e.json is the same path as --out"):
        script.check(script.Options(policy=policy, out=tmp_path / "e", demos=tmp_path / "e.json"))
    script.check(script.Options(policy=policy, out=tmp_path / "e"))  # (the default searches file, free: as before)


# ------------------------------------------------------------------------------- an output over an input
def test_train_bc_refuses_an_export_over_its_clone_base_before_the_demonstrations(tmp_path, monkeypatch):
    """`--clone-base P --export P` collected the demonstrations and fitted, then wrote the clone over the policy it
    started from."""
    script = _script("train_bc.py")
    for suffix in (".safetensors", "_vecnormalize.npz", ".json"):
        shutil.copyfile(POLICIES / f"bc_target_service{suffix}", tmp_path / f"base{suffix}")
    monkeypatch.setattr("agents.imitation.collect_demos", _never)
    base = str(tmp_path / "base")
    with pytest.raises(ValueError, match="--export .*base.safetensors is the input file"):
        script.main(script.Options(log_dir=str(tmp_path / "runs"), env_id="WheelLoaderTarget-v5", clone_base=base,
                                   export=base), "train_bc.py")


# ------------------------------------------------------------------------------- checked before the work
def test_bench_mpc_memory_refuses_a_target_under_the_minimum_time_before_any_cycle(monkeypatch, capsys):
    """`--braking service tc --target-time 8` ran the service cycles (~30 s), then the tc cycle's process failed,
    naming MPCConfig.target_time."""
    script = _script("bench_mpc_memory.py")
    monkeypatch.setattr(script.subprocess, "run", _never)
    monkeypatch.setattr(sys, "argv", ["bench_mpc_memory.py", "--braking", "service", "tc", "--target-time", "8"])
    with pytest.raises(SystemExit) as info:
        script.main()
    assert info.value.code == 2
    assert "--target-time 8 s lies below the nominal cycle's minimum cycle time with tc braking" in capsys.readouterr().err


def test_wl_suite_solve_refuses_workers_beside_ray(monkeypatch, capsys):
    """`wl suite solve --ray --workers 2` took --workers without a word: the Ray tasks never read it."""
    monkeypatch.setattr("mpc.benchmark.suite.solve_suite", _never)
    monkeypatch.setattr("mpc.benchmark.suite.check_shipped", _never)
    for argv in (["suite", "solve", "--suite", "test", "--ray", "--workers", "2"],
                 ["suite", "solve", "--suite", "test", "--check", "--workers", "2", "--ray", "ray://h:10001"]):
        assert wl.cli.main(argv) == 2
        assert "--workers sets the local processes; with --ray" in capsys.readouterr().err


def test_wl_train_refuses_workers_beside_ray(tmp_path, monkeypatch, capsys):
    """`wl train --seeds 0 1 --ray --workers 2` took --workers without a word: the Ray tasks never read it."""
    monkeypatch.setattr("agents.seeds.train_runs", _never)
    argv = ["train", "--seeds", "0", "1", "--ray", "--workers", "2", "--log-dir", str(tmp_path / "runs")]
    assert wl.cli.main(argv) == 2
    assert "--workers sets the local processes; with --ray the cluster runs the trainings" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("argv, needle", [
    (["--suite", "test", "--episodes", "5"], "not with --suite (each scenario runs once from its own start): --episodes"),
    (["--suite", "test", "--seed", "3", "--init-noise", "0"], "--init-noise, --seed"),
    (["--mpc-sample", "3"], "--mpc-sample sets the MPC's scenarios of --suite without --runs"),
    (["--suite", "test", "--runs", "r", "--mpc-sample", "3"], "--mpc-sample sets the MPC's scenarios")])
def test_bench_agents_refuses_options_it_would_ignore(argv, needle, monkeypatch, capsys):
    """`--suite test --episodes 5` (or --seed, --init-noise) and `--mpc-sample` without the suite's MPC were taken and
    ignored without a word."""
    script = _script("bench_agents.py")
    for name in ("suite_mode", "runs_mode", "pareto_fronts"):
        monkeypatch.setattr(script, name, _never)
    monkeypatch.setattr(sys, "argv", ["bench_agents.py", *argv])
    with pytest.raises(SystemExit) as info:
        script.main()
    assert info.value.code == 2
    assert needle in capsys.readouterr().err


# ------------------------------------------------------------------------------- wl report: a file that draws for hours
def _results() -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from test_hostile_s63_followups import _results as minimal

    return minimal()


@pytest.mark.parametrize("what", ["trajectories", "suite labels"])
def test_wl_report_refuses_more_curves_than_a_run_writes_before_drawing(tmp_path, capsys, what):
    """A 0.6 MB results.json of 5000 trajectories took 44 s to draw (one curve each, on 4 axes); the 64 MiB the reader
    takes would have drawn for hours. `wl run` writes one per controller and braking; the suite figure one per
    controller and target."""
    import json

    from wl.report import MAX_CURVES

    results = _results()
    t, states = [0.0, 8.0], [[200.0, 0.0, 0.7, 0.0]] * 2
    n = MAX_CURVES + 1
    if what == "trajectories":
        results["trajectories"] = [{"controller": f"c{i}", "braking": "service", "t": t, "states": states} for i in range(n)]
        needle = f"{n} trajectories, more than the {MAX_CURVES}"
    else:
        results["suite"] = {"suite": "test", "version": 1, "sample": 10, "full": False, "scenarios_per_braking": 10,
                            "rows": [], "episodes": [{"controller": f"c{i}", "braking": "service", "success": True,
                                                      "fuel_gap": 0.1, "scenario": None} for i in range(n)]}
        needle = f"the suite's episodes name {n} controllers and targets, more than the {MAX_CURVES}"
    (tmp_path / "results.json").write_text(json.dumps(results))
    assert wl.cli.main(["report", "--results", str(tmp_path)]) == 2
    assert needle in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]  # (nothing drawn)
