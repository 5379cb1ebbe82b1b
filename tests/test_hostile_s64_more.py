"""The twelfth hostile-input round (stop 64), third pass: -0.0 in the machine's parameters, float32 numbers in the
scores, numpy arrays in MPCConfig, a --bc-demos path too long, malformed evaluation results, unbounded reads of run
files, and sweep values whose run names collide. Each test fails on the code before its fix (the old behaviour is
said in its docstring)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

import wl.cli

LONG = "a" * 300  # a file name longer than the system's 255 bytes (ENAMETOOLONG)


def _sparse(path: Path, size: int) -> Path:
    """A file of ``size`` bytes that takes no room (a read of it would still read them all)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.truncate(size)
    return path


# ------------------------------------------------------------------------------------------ the machine
@pytest.mark.parametrize("minus, plus", [
    ({"M_load": -0.0}, {"M_load": 0.0}),
    ({"c_r": -0.0}, {"c_r": 0.0}),
    ({"T_max_lines": ((8.0, 2.086), (2200.0, -0.0), (3855.0, -1.40))}, {}),  # (the default's 0.0)
])
def test_minus_zero_gives_the_fingerprint_of_zero(minus, plus):
    """LoaderParams(M_load=-0.0) compared equal to M_load=0.0 but had another fingerprint (json writes "-0.0"): the
    same machine was another cache key, and its shipped or cached optimum was missed."""
    from wl_env.params import LoaderParams

    a, b = LoaderParams(**minus), LoaderParams(**plus)
    assert a == b and a.fingerprint() == b.fingerprint()
    assert "-0.0" not in json.dumps(a.to_dict())


def test_the_fingerprints_of_the_shipped_optima_stay():
    """(The fix keeps every other fingerprint: the shipped optima are keyed by them.)"""
    from mpc.benchmark.reference import shipped_fronts
    from wl_env.params import LoaderParams

    assert LoaderParams().fingerprint() == "af90c889db5176fb"
    assert {"service_af90c889db5176fb", "tc_af90c889db5176fb"} <= set(shipped_fronts())


# ------------------------------------------------------------------------------------------ float32 numbers
def test_score_run_records_a_float32_as_the_number_written():
    """score_run(np.float32(9.1), np.float32(80.3), ...) recorded T 9.100000381469727 and fuel 80.30000305175781
    (and scored those)."""
    from mpc.benchmark.scoring import score_run

    s = score_run(np.float32(9.1), np.float32(80.3), "service", solve=False)
    assert s.T == 9.1 and s.fuel_g == 80.3
    assert s == score_run(9.1, 80.3, "service", solve=False)


def test_fuel_at_reads_a_float32_as_the_number_written():
    """ParetoFront.fuel_at(np.float32(9.1)) interpolated at 9.100000381469727 s, another fuel than at 9.1 s."""
    from mpc.benchmark.reference import shipped_fronts

    front = shipped_fronts()["service_af90c889db5176fb"]
    assert front.fuel_at(np.float32(9.1)) == front.fuel_at(9.1)


def test_an_evaluation_records_a_float32_target_as_the_number_written():
    """evaluate_controller(target_time=np.float32(9.1)) recorded the np.float32 itself (9.100000381469727 as a
    float; json.dumps refused it) as the episodes' target_time, and its lateness as a float32."""
    from agents.evaluate import evaluate_controller, load_controller

    r = evaluate_controller(load_controller("operator", "tc"), "tc", episodes=1, env_id="WheelLoaderTarget-v0",
                            target_time=np.float32(9.1), score=False)
    e = r["per_episode"][0]
    assert type(e["target_time"]) is float and e["target_time"] == 9.1
    assert type(e["lateness"]) is float
    json.dumps(r)


# ------------------------------------------------------------------------------------------ MPCConfig
@pytest.mark.parametrize("field", ["mode", "horizon_steps", "horizon_solver", "replan_lag_steps"])
def test_mpc_config_names_a_field_given_an_array(field):
    """MPCConfig(replan_lag_steps=np.array([1, 2])) (and mode, horizon_steps, horizon_solver) was numpy's "The truth
    value of an array with more than one element is ambiguous", naming no field."""
    from mpc.controller.mpc import MPCConfig

    with pytest.raises(ValueError, match=rf"^{field} must "):
        MPCConfig(**{field: np.array([1, 2])})


def test_mpc_config_takes_rate_weight_as_an_array():
    """rate_weight=np.array([0.1, 0.1]) was refused as "must be two weights" (a list or tuple was taken)."""
    from mpc.controller.mpc import MPCConfig

    assert MPCConfig(rate_weight=np.array([0.1, 0.1], np.float32)).rate_weight == (0.1, 0.1)


# ------------------------------------------------------------------------------------------ wl train --bc-demos
def test_wl_train_names_bc_demos_for_a_path_too_long(tmp_path, capsys):
    """`wl train --bc-demos <300 characters>` was "[Errno 36] File name too long", naming no option."""
    code = wl.cli.main(["train", "--log-dir", str(tmp_path), "--env-id", "WheelLoaderTarget-v0",
                        "--bc-demos", str(tmp_path / LONG)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("wl: error: --bc-demos ") and "File name too long" in err, err


def test_read_demo_folder_names_bc_demos_for_a_path_too_long(tmp_path):
    """read_demo_folder (PPOConfig.bc_demos, in the library) raised the OSError itself."""
    from agents.imitation import read_demo_folder

    with pytest.raises(ValueError, match=r"^bc_demos .*: cannot use the path \(File name too long\)"):
        read_demo_folder(tmp_path / LONG, "WheelLoaderTarget-v0")


# ------------------------------------------------------------------------------------------ evaluation results
@pytest.mark.parametrize("call, needle", [
    (lambda e: e.aggregate({}), "result has no 'summary'"),
    (lambda e: e.aggregate({"summary": {"success_rate": 1.0}}), "result['summary'] has no 'time_gap_median'"),
    (lambda e: e.aggregate([]), "result must be a dict"),
    (lambda e: e.score_evaluation({}), "result has no 'braking', 'per_episode'"),
    (lambda e: e.score_evaluation({"braking": "tc", "per_episode": []}), "result['per_episode'] must be a non-empty"),
    (lambda e: e.score_evaluation({"braking": "tc", "per_episode": [{}]}), "result['per_episode'][0] has no 'completed'"),
    (lambda e: e.summarize([{"completed": True}]), "records[0] has no 'success'"),
    (lambda e: e.summary_line({}, "x"), "result has no 'braking', 'summary'"),
])
def test_malformed_evaluation_results_name_what_they_lack(call, needle):
    """aggregate({}), score_evaluation({}), summarize([{}]) and summary_line({}) raised a bare KeyError (a list or
    None a TypeError, an empty per_episode an IndexError)."""
    import agents.evaluate as e

    with pytest.raises(ValueError) as info:
        call(e)
    assert needle in str(info.value)


# ------------------------------------------------------------------------------------------ bounded reads
def test_check_run_folder_refuses_an_oversized_summary_by_name(tmp_path):
    """check_run_folder read final/summary.json whole (a file of any size), and a file it could not parse was "holds
    a training run, not a clone", naming no file."""
    from agents.imitation import check_run_folder
    from agents.ppo_config import MAX_RUN_JSON_BYTES, PPOConfig

    cfg = PPOConfig(log_dir=str(tmp_path), run_name="clone")
    summary = _sparse(cfg.run_dir / "final" / "summary.json", MAX_RUN_JSON_BYTES + 1)
    with pytest.raises(ValueError) as info:
        check_run_folder(cfg)
    assert str(summary) in str(info.value) and f"{MAX_RUN_JSON_BYTES + 1} bytes, more than" in str(info.value)


def test_check_run_folder_still_takes_a_clone(tmp_path):
    """(A clone's run, its summary read bounded, is still one a rerun fits again.)"""
    from agents.imitation import METHOD, check_run_folder
    from agents.ppo_config import PPOConfig

    cfg = PPOConfig(log_dir=str(tmp_path), run_name="clone")
    (cfg.run_dir / "final").mkdir(parents=True)
    (cfg.run_dir / "final" / "summary.json").write_text(json.dumps({"method": METHOD}))
    check_run_folder(cfg)


def test_a_kept_evaluation_is_read_bounded(tmp_path, caplog):
    """_read_kept read a kept evaluation whole (a file of any size); an oversized one is now refused by name, unread,
    and run again."""
    from wl.report import MAX_RESULTS_BYTES, _read_kept

    path = _sparse(tmp_path / "k.json", MAX_RESULTS_BYTES + 1)
    with caplog.at_level(logging.WARNING, logger="wl.report"):
        assert _read_kept(path, "sha256:x") is None
    assert f"{path}: not a kept evaluation ({MAX_RESULTS_BYTES + 1} bytes, more than" in caplog.text


# ------------------------------------------------------------------------------------------ sweeps
def test_sweep_values_whose_run_names_collide_are_named():
    """--sweep learning_rate=1.0000001e-4,1.0000002e-4 gave both points the run name ..._learning_rate0.0001_s0
    ({:g}), and train_runs refused "two runs share a name", naming no --sweep value."""
    from agents.ppo_config import PPOConfig
    from agents.seeds import expand, parse_sweep

    sweep = parse_sweep(["learning_rate=1.0000001e-4,1.0000002e-4"])
    with pytest.raises(ValueError, match=r"^--sweep learning_rate=0\.00010000001 and learning_rate=0\.00010000002 "
                                         r"would share the run name ppo_service_learning_rate0\.0001_s<seed>.*"
                                         r"6 significant digits"):
        expand(PPOConfig(), [0, 1], sweep)


def test_sweep_run_names_stay():
    """(The names of runs already trained stay: they resume under them.)"""
    from agents.ppo_config import PPOConfig
    from agents.seeds import expand, parse_sweep

    cfgs = expand(PPOConfig(), [3], parse_sweep(["learning_rate=1e-4,3e-4", "n_epochs=5"]))
    assert [c.name for c in cfgs] == ["ppo_service_learning_rate0.0001_n_epochs5_s3",
                                      "ppo_service_learning_rate0.0003_n_epochs5_s3"]
