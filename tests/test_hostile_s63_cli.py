"""Stop 63's hostile-input round on the command line and the scripts: each test fails on the code before its fix
(docs/reliability.md lists the earlier rounds)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fakes import load_script

import wl.cli

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _script(name: str):
    return load_script(name, "s63_")


def test_a_deadline_under_a_microsecond_is_named_as_the_option(tmp_path, capsys, monkeypatch):
    """`wl mpc --deadline-ms 0.0001` passed the option's check, then MPCConfig refused it as "deadline_ms": the
    option and its range unnamed."""
    import mpc.controller.mpc

    def never(*args, **kwargs):
        raise AssertionError("the work was reached")

    monkeypatch.setattr(mpc.controller.mpc, "run_closed_loop", never)
    code = wl.cli.main(["mpc", "--deadline-ms", "0.0001", "--out", str(tmp_path / "m.json")])
    err = capsys.readouterr().err
    assert code == 2 and "argument --deadline-ms" in err and "(0, 100] ms" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "m.json").exists()


@pytest.mark.parametrize("argv, needle", [
    # (1e7 was refused as MPCConfig.rate_weight, after the sweep's cycles before it)
    (["--rate-sweep", "1e7"], "--rate-sweep weights must each be a number >= 0, at most 1e+06"),
    # (under the nominal T_min: refused after the minimum-time runs, naming MPCConfig.target_time)
    (["--targets", "5", "--braking", "tc"], "--targets 5 s lie below the nominal cycle's minimum cycle time with tc"),
    (["--quick", "--targets", "8", "11"], "--targets 8 s lie below"),
    # (longer than the control interval, or under a microsecond: refused by the controller, naming no option)
    (["--deadline-ms", "500"], "--deadline-ms must be a number > 0, in [0.001, 100] ms"),
    (["--deadline-ms", "1e-9"], "--deadline-ms must be a number > 0, in [0.001, 100] ms")])
def test_bench_mpc_checks_what_its_runs_would_refuse_before_any_run(argv, needle):
    r = subprocess.run([sys.executable, str(SCRIPTS / "bench_mpc.py"), *argv], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert "[default]" not in r.stderr  # (no run began)


def test_bench_mpc_rate_sweep_writes_its_json_and_takes_a_run_without_a_score(tmp_path, monkeypatch, capsys):
    """`bench_mpc.py --rate-sweep W --json P` checked P, then never wrote it (exit 0, no file); a cycle without a score
    or a verified optimum at its time (no smoothness) was a KeyError's traceback after the sweep's cycles."""
    bench = _script("bench_mpc.py")
    scored = {"T": 11.0, "fuel_g": 57.4, "fuel_gap": 0.001, "max_violation": 0.0,
              "smoothness": {"ratio_fuel_injection": 0.9, "ratio_bucket_acceleration": 0.2}}
    unscored = {"T": 40.0, "fuel_g": 90.0, "max_violation": 0.0}  # (not completed: no score, no smoothness)
    made = []

    def closed_loop(braking, config, solver, label, **kw):
        made.append(config.rate_weight)
        return dict(scored if len(made) == 1 else unscored)

    monkeypatch.setattr(bench, "closed_loop", closed_loop)
    out = tmp_path / "sweep.json"
    monkeypatch.setattr(sys, "argv", ["bench_mpc.py", "--rate-sweep", "0.1", "1", "--json", str(out)])
    bench.main()
    assert made == [(0.1, 0.1), (1.0, 1.0)]
    printed = capsys.readouterr().out
    assert "| 1 | 40.00 | 90.000 | n/a | n/a | n/a |" in printed
    rows = json.loads(out.read_text())["rate_sweep"]
    assert [r["rate_weight"] for r in rows] == [0.1, 1.0] and rows[0]["fuel_gap"] == 0.001


@pytest.mark.parametrize("argv, needle", [
    (["bench_far_starts.py", "--brakings", "tc", "tc"], "--brakings names a braking alternative twice"),
    (["bench_draws.py", "--modes", "1.15", "1.150"], "--modes names a mode twice"),
    (["bench_draws.py", "--modes", "time", "time"], "--modes names a mode twice"),
    (["bench_mpc.py", "--targets", "11", "11.0"], "--targets names a value twice"),
    (["bench_mpc.py", "--braking", "tc", "tc"], "--braking names a value twice"),
    (["bench_mpc.py", "--horizons", "10", "10"], "--horizons names a value twice"),
    (["bench_mpc.py", "--rate-sweep", "1", "1"], "--rate-sweep names a value twice")])
def test_a_benchmark_refuses_a_value_given_twice_before_any_run(argv, needle):
    """Each ran its cycles twice and counted them twice in its summary (the runs, successes and step times)."""
    r = subprocess.run([sys.executable, str(SCRIPTS / argv[0]), *argv[1:]], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("seeds", [(), (3, 4)])
def test_train_plan_policy_checks_each_seeds_stages_record_before_the_training(tmp_path, monkeypatch, seeds):
    """`<log-dir>/plan_<braking>_s<seed>_stages.json`, written after each seed's stages were trained (hours), was
    not checked first: a folder there failed after the training."""
    script = _script("train_plan_policy.py")
    seed = seeds[-1] if seeds else 0
    (tmp_path / f"plan_service_s{seed}_stages.json").mkdir()

    def never(o):
        raise AssertionError("the training began")

    monkeypatch.setattr(script, "train_stages", never)
    o = script.Options(log_dir=str(tmp_path), seeds=seeds, cycles=(16,), log_std_init=(-1.0,), log_std_final=(-2.0,),
                       num_envs=4, score=False)
    with pytest.raises(ValueError, match=f"stages record: .*plan_service_s{seed}_stages.json is a folder"):
        script.main(o)
