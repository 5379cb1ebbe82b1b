"""The ``wl`` command line, in process: params, evaluate (built-in and user controllers), train, report,
one-line user errors and every subcommand's --help.

Scoring needs a Pareto front; solving one takes minutes, so the tests write a synthetic front where
:func:`mpc.benchmark.pareto.pareto_front` looks for it (``--cache tmp_path``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import wl.cli
import wl.report
import wl_env  # noqa: F401
from agents.evaluate import load_controller, summarize
from agents.operator import OperatorPolicy
from mpc.benchmark.ocp import OCPResult
from mpc.benchmark.pareto import ParetoFront, front_folder, save_result
from wl_env.controller import Controller
from wl_env.params import DEFAULT_PARAMS, resolve
from wl_env.rollout import run_episode

SUBCOMMANDS = ["params", "ocp", "pareto", "mpc", "evaluate", "train", "run", "report", "suite"]


# ------------------------------------------------------------------------------------------ helpers
def _front(braking: str) -> ParetoFront:
    """A made-up convex front around the operator's cycles (8-9 s), wide enough to score every episode: five
    verified points and six that failed, one record for each of the 11 points its cache folder (n11) is named for."""
    T = [7.0, 8.0, 10.0, 14.0, 20.0]
    fuel = [110.0, 95.0, 80.0, 70.0, 65.0] if braking == "service" else [100.0, 86.0, 72.0, 63.0, 60.0]
    points = ([{"T": t, "fuel_g": f, "verified": True} for t, f in zip(T, fuel, strict=True)]
              + [{"T": t, "fuel_g": None, "verified": False} for t in (7.5, 9.0, 12.0, 16.0, 18.0, 19.0)])
    return ParetoFront(braking, T, fuel, resolve(None).fingerprint(), T[0], T[-1], fuel[-1], [20, 12, 20, 12],
                       points=points)


@pytest.fixture
def cache(tmp_path: Path) -> Path:
    """A cache folder holding synthetic fronts and minimum-time cycles for both braking alternatives."""
    root = tmp_path / "cache"
    for b in ("service", "tc"):
        folder = front_folder(b, cache=root)
        _front(b).save(folder / "front.json")
        t = np.linspace(0.0, 7.0, 15)
        states = np.column_stack([np.full_like(t, 200.0), np.sin(t), 0.7 + 0.6 * t, np.full_like(t, 0.5)])
        r = OCPResult(b, "time", 7.0, 110.0, [2.0, 1.5, 2.0, 1.5], t.tolist(), states.tolist(),
                      [[0.0, 0.0, 0.0]] * 14, [1] * 15, t.tolist(), "Solve_Succeeded", True, 10, 0.1,
                      params_fingerprint=resolve(None).fingerprint(), mesh=[20, 12, 20, 12])
        save_result(r, folder / "min_time.json")  # a checked cache entry, as pareto_front writes it
    return root


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = wl.cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _check_scores(episodes: list[dict], braking: str) -> None:
    """The nominal starts against the cached (made-up) front; a perturbed start against its own optimum,
    solved directly (by the fake solver: T_min 7 s, fuel 47 + 63 ((21 - T) / 14)^2 g)."""
    front = _front(braking)
    for e in episodes:
        if e.get("init_noise", 0.0) == 0.0:
            T_min, fuel_opt, ref = front.T_min, front.fuel_at(e["T"]), "cached front"
        else:
            T_min, fuel_opt, ref = 7.0, 47.0 + 63.0 * ((21.0 - e["T"]) / 14.0) ** 2, "direct solve"
        assert e.get("reference", ref) == ref and e.get("T_min", T_min) == T_min
        assert e["time_gap"] == pytest.approx(e["T"] / T_min - 1.0, rel=1e-12)
        assert e["fuel_gap"] == pytest.approx(e["fuel_g"] / fuel_opt - 1.0, rel=1e-12)


@pytest.fixture(autouse=True)
def fake_direct_solves(monkeypatch):
    """A perturbed start's own optimum is solved directly: by the fake solver here (seconds saved per episode)."""
    from fakes import fake_solve

    import mpc.benchmark.optima
    import mpc.benchmark.reference

    for module in (mpc.benchmark.reference, mpc.benchmark.optima):
        monkeypatch.setattr(module, "solve_ocp", fake_solve)


# ------------------------------------------------------------------------------------------ params
def test_params_prints_every_parameter(capsys):
    code, out, _ = _run(capsys, "params", "--json")
    assert code == 0 and json.loads(out) == json.loads(json.dumps(resolve(None).to_dict()))
    code, out, _ = _run(capsys, "params")
    assert code == 0 and len(out.splitlines()) == len(resolve(None).to_dict())


# ------------------------------------------------------------------------------------------ evaluate
def test_evaluate_operator_nominal_then_perturbed_and_scored(tmp_path, cache, capsys):
    out = tmp_path / "eval.json"
    code, stdout, _ = _run(capsys, "evaluate", "--controller", "operator", "--braking", "service", "--episodes", 2,
                           "--seed", 5, "--cache", cache, "--out", out)
    assert code == 0
    assert len(stdout.strip().splitlines()) == 1 and stdout.strip().endswith(f"-> {out}")
    r = json.loads(out.read_text())
    eps = r["per_episode"]
    assert [(e["episode"], e["seed"], e["init_noise"]) for e in eps] == [(0, 5, 0.0), (1, 6, 1.0)]
    # episode 0 is the nominal cycle, episode 1 the perturbed start of seed 6: the same as rolled by hand
    for e, noise in zip(eps, (0.0, 1.0), strict=True):
        ref = run_episode(gym.make("WheelLoader-v1", braking="service", init_noise=noise), OperatorPolicy("service"),
                          seed=e["seed"])
        assert (e["T"], e["fuel_g"], e["completed"], e["success"]) == (ref.T, ref.fuel_g, ref.completed, ref.success)
    assert eps[0]["fuel_g"] != eps[1]["fuel_g"]  # the perturbation was applied
    assert all(e["completed"] for e in eps)
    _check_scores(eps, "service")
    s = r["summary"]
    assert s["success_rate"] == np.mean([e["success"] for e in eps])
    # issue #14's "aggregate": its keys, the summary's values
    assert r["aggregate"] == {k: s[k] for k in ("success_rate", "time_gap_median", "fuel_gap_median", "fuel_gap_p90",
                                                "lateness_median")}
    assert s["completion_rate"] == 1.0 and s["scored"] == 2
    assert s["fuel_gap"]["mean"] == pytest.approx(np.mean([e["fuel_gap"] for e in eps]))
    assert s["T"]["max"] == max(e["T"] for e in eps)
    assert s["nominal"]["fuel_g"] == eps[0]["fuel_g"]
    assert r["optimum"]["T_min"] == 7.0 and r["controller"] == "operator"
    # reproducible: the same command gives the same file
    code, _, _ = _run(capsys, "evaluate", "--controller", "operator", "--episodes", 2, "--seed", 5, "--cache", cache,
                      "--out", tmp_path / "again.json")
    assert code == 0 and json.loads((tmp_path / "again.json").read_text()) == r


USER_CONTROLLER = '''
import numpy as np

from agents.operator import OperatorPolicy

LOG = {log!r}


class GentleDriver:
    """The operator with at most 60 % fuel injection: a slower, different cycle."""

    def __init__(self, braking):
        self.braking = braking
        self.inner = OperatorPolicy(braking)
        self._write("init " + braking)

    def _write(self, line):
        with open(LOG, "a") as f:
            f.write(line + "\\n")

    def reset(self):
        self._write("reset")

    def act(self, obs):
        self._write("act")
        action = self.inner.act(obs).copy()
        action[0] = min(action[0], 0.2)
        return action


class NoBraking:
    def __init__(self):
        self.inner = OperatorPolicy("service")

    def act(self, obs):
        return self.inner.act(obs)
'''


@pytest.mark.parametrize("out", [[], ["--out", "-"]])
def test_evaluate_without_out_writes_only_the_json_to_stdout(tmp_path, cache, capfd, out):
    """Issue #14's command names no --out: the JSON is then all of stdout (file descriptor 1, where C code prints
    too), the summary line on stderr, and no file is written."""
    code = wl.cli.main(["evaluate", "--controller", "operator", "--episodes", "1", "--cache", str(cache), *out])
    stdout, stderr = capfd.readouterr()
    assert code == 0, stderr
    r = json.loads(stdout)
    assert set(r["aggregate"]) == {"success_rate", "time_gap_median", "fuel_gap_median", "fuel_gap_p90",
                                   "lateness_median"}
    assert r["controller"] == "operator" and r["per_episode"][0]["success"]
    assert "operator, service braking, 1 episode" in stderr and "->" not in stderr
    assert not list(Path.cwd().glob("-"))


def test_evaluate_user_controller_from_a_file(tmp_path, cache, capsys):
    log = tmp_path / "calls.log"
    module = tmp_path / "my_controllers.py"
    module.write_text(USER_CONTROLLER.format(log=str(log)))
    out = tmp_path / "eval.json"
    code, _, err = _run(capsys, "evaluate", "--controller", f"{module}:GentleDriver", "--braking", "tc",
                        "--episodes", 3, "--cache", cache, "--out", out)
    assert code == 0, err
    eps = json.loads(out.read_text())["per_episode"]
    calls = log.read_text().split()
    # constructed once with the braking, reset before each episode, one act per 0.1 s step
    assert calls[:2] == ["init", "tc"] and calls.count("reset") == 3
    assert calls.count("act") == sum(round(e["T"] / 0.1) for e in eps)
    # its actions drove the episodes: the nominal one equals a rollout of the class, not the operator's
    ctrl = load_controller(f"{module}:GentleDriver", "tc")
    ref = run_episode(gym.make("WheelLoader-v1", braking="tc"), ctrl, seed=0)
    op = run_episode(gym.make("WheelLoader-v1", braking="tc"), OperatorPolicy("tc"), seed=0)
    assert (eps[0]["T"], eps[0]["fuel_g"]) == (ref.T, ref.fuel_g)
    assert eps[0]["T"] > op.T and eps[0]["fuel_g"] != op.fuel_g
    _check_scores([e for e in eps if e["completed"]], "tc")
    # a class without a braking argument is made without arguments (and needs no reset); modules import by name
    plain = load_controller(f"{module}:NoBraking", "tc")
    assert type(plain).__name__ == "NoBraking" and plain.inner.braking == "service"
    assert load_controller("agents.operator:OperatorPolicy", "tc").braking == "tc"


def test_load_controller_builtins_follow_the_protocol():
    import gymnasium as gym

    obs, _ = gym.make("WheelLoader-v1", braking="tc").reset(seed=0)  # (a real observation: zeros have no phase)
    for spec in ("operator", "mpc", "ppo"):
        c = load_controller(spec, "tc")
        assert isinstance(c, Controller), spec
        if spec != "mpc":  # (its first act plans the cycle, 20-40 s: the MPC's own tests drive it through act)
            assert c.act(obs).shape == (4,)


def test_summary_aggregates_per_episode_values():
    def ep(success, completed, T, fuel, gap, viol):
        return {"success": success, "completed": completed, "T": T, "fuel_g": fuel, "max_violation": viol,
                "time_gap": gap, "fuel_gap": None if gap is None else 2 * gap}

    records = [ep(True, True, 9.0, 90.0, 0.1, 0.0), ep(False, True, 11.0, 80.0, 0.3, 0.02),
               ep(False, False, 40.0, 300.0, None, 0.5), ep(True, True, 10.0, 85.0, 0.2, 0.0)]
    s = summarize(records)
    assert s["success_rate"] == 0.5 and s["completion_rate"] == 0.75 and s["violation_rate"] == 0.5
    assert s["T"]["mean"] == pytest.approx(10.0) and s["T"]["max"] == 11.0  # only completed cycles
    # gaps over the successful cycles only (a completed cycle that missed its targets is no regret to average)
    assert s["fuel_gap"]["mean"] == pytest.approx(0.3) and s["scored"] == 2
    assert s["fuel_gap_median"] == pytest.approx(0.3) and s["time_gap_p90"] == pytest.approx(0.19)
    assert s["max_violation"] == 0.5 and s["nominal"]["T"] == 9.0


# ------------------------------------------------------------------------------------------ train
def test_train_tiny_run_then_evaluate_its_policy(tmp_path, capsys):
    argv = ["train", "--total-timesteps", "2048", "--num-envs", "8", "--n-steps", "64", "--batch-size", "256",
            "--n-epochs", "2", "--eval-freq", "1024", "--eval-episodes", "2", "--checkpoint-freq", "1024",
            "--no-score", "--no-progress-bar", "--log-dir", str(tmp_path), "--run-name", "tiny",
            "--net-arch", "16", "16", "--reward", "target_distance=30"]
    code, out, err = _run(capsys, *argv)
    assert code == 0, err
    run = tmp_path / "tiny"
    assert "[eval] step" in err  # the evaluation lines (logging, on stderr); the run's summary as JSON on stdout
    assert json.loads(out)["num_timesteps"] >= 2048
    saved = json.loads((run / "config.json").read_text())
    assert saved["commands"] == ["wl " + " ".join(argv)]
    cfg = saved["config"]
    assert (cfg["num_envs"], cfg["net_arch"], cfg["score"], cfg["total_timesteps"]) == (8, [16, 16], False, 2048)
    assert cfg["reward"] == {"target_distance": 30.0, "target_height": 60.0, "failure": 100.0}  # one field overridden
    assert (run / "final" / "model.zip").exists()
    # the same run again is a user error; the trained policy evaluates through --model
    code, _, err = _run(capsys, *argv)
    assert code == 2 and err.startswith("wl: error:") and "already holds a run" in err
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--model", run / "final" / "model.zip",
                        "--trust-pickle", "--episodes", 1, "--no-score", "--out", tmp_path / "ppo.json")
    assert code == 0, err
    assert json.loads((tmp_path / "ppo.json").read_text())["model"] == str(run / "final" / "model.zip")


def test_train_script_is_the_same_command_line(capsys):
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "scripts" / "train_ppo.py"
    spec = importlib.util.spec_from_file_location("train_ppo_script", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    with pytest.raises(SystemExit) as exc:
        script.main(["--help"])
    assert exc.value.code == 0
    script_help = capsys.readouterr().out
    code, cli_help, _ = _run(capsys, "train", "--help")
    assert code == 0

    def flags(text):  # the flags of the options section (the script's description has examples)
        return {w.strip("[],") for w in text.split("options:")[1].split() if w.startswith("--")}

    assert flags(script_help) == flags(cli_help) and "--total-timesteps" in flags(cli_help)


@pytest.mark.parametrize("argv, needle", [
    (["--batch-size", "1"], "--batch-size must be an integer >= 2"),  # (SB3's AssertionError, a traceback)
    (["--n-steps", "1", "--num-envs", "1"], "--n-steps must be such that n_steps * num_envs lies in [2, "),
    (["--n-steps", "100000000", "--num-envs", "1024"], "--n-steps must be such")])  # (a MemoryError allocating 4 TiB)
def test_train_refuses_a_rollout_ppo_cannot_take(tmp_path, capsys, argv, needle):
    """Checked with the other fields, in both `wl train` and scripts/train_ppo.py (whose bad options were a
    traceback and exit 1), before torch or the envs."""
    import importlib.util

    code, _, err = _run(capsys, "train", *argv, "--log-dir", tmp_path)
    assert code == 2 and needle in err and not any(tmp_path.iterdir())
    path = Path(__file__).resolve().parents[1] / "scripts" / "train_ppo.py"
    spec = importlib.util.spec_from_file_location("train_ppo_script", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main([*argv, "--log-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("train_ppo: error:") and needle in err and "Traceback" not in err


def test_benchmarks_check_their_json_before_the_work(tmp_path):
    import subprocess
    import sys

    (tmp_path / "file").write_text("")
    scripts = Path(__file__).resolve().parents[1] / "scripts"
    bad = str(tmp_path / "file" / "x.json")
    for argv in (["bench_agents.py", "--json", bad], ["bench_env.py", "--quick", "--json", bad],
                 ["bench_suite.py", "--out", bad], ["bench_corners.py", "--out", bad], ["bench_estimator.py", "--json", bad],
                 ["bench_planning.py", "--out", bad], ["bench_far_starts.py", "--out", bad],
                 ["bench_mumps_ordering.py", "--out", bad], ["bench_draws.py", "--out", bad], ["bench_modes.py", "--out", bad],
                 ["bench_replan_lag.py", "--out", bad]):
        r = subprocess.run([sys.executable, str(scripts / argv[0]), *argv[1:]], capture_output=True, text=True,
                           timeout=60)
        err = " ".join(r.stderr.replace("│", " ").split())  # (tyro boxes and wraps its message)
        assert r.returncode == 2 and "is not a folder" in err and "Traceback" not in err, argv


@pytest.mark.parametrize("argv, needle", [
    (["bench_mpc_memory.py", "--target-time", "nan"], "--target-time must lie in [1, 40) s"),  # (a child's traceback)
    (["bench_mpc_memory.py", "--horizon-steps", "1"], "--horizon-steps must be an integer in [2, 1000]"),
    (["bench_rti_qp.py", "--solves", "0"], "--solves must be an integer in [1, 1000]"),  # (after a whole cycle, exit 1)
    (["bench_rti_qp.py", "--target", "inf"], "--target must lie in [1, 40) s"),
    (["bench_safety_stale.py", "--every", "0"], "--every must be integers in [1, 100]"),
    (["bench_mpc.py", "--min-time-only", "--corners"], "--min-time-only runs no corner"),
    (["bench_mpc.py", "--targets", "11", "100"], "--targets must lie in [1, 40) s"),  # (a traceback after the runs)
    (["bench_mpc.py", "--targets", "nan"], "--targets must lie in [1, 40) s"),
    (["bench_mpc.py", "--suite-sample", "-1"], "--suite-sample must be an integer in [0, 100000]"),
    (["bench_mpc.py", "--deadline-ms", "-5"], "--deadline-ms must be a number > 0"),
    (["bench_mpc.py", "--terminal-weight", "nan"], "--terminal-weight must be a number in [0, 1e+06]"),
    (["bench_mpc.py", "--rate-sweep", "0.1", "nan"], "--rate-sweep weights must each be a number >= 0"),
    (["bench_memory.py", "--period", "nan"], "--period must be a number of seconds in [0.01, 60]"),  # (wl run orphaned)
    (["bench_rti_qp.py", "--solvers", "nope"], "invalid choice: 'nope'"),
    (["bench_ocp.py", "--repeats", "0"], "--repeats must be an integer in [1, 1000]"),
    (["bench_ocp.py", "--pareto-repeats", "-3"], "--pareto-repeats must be an integer in [1, 1000]"),
    (["bench_env.py", "--single-steps", "100000000000"], "--single-steps must be an integer in [1, 10000000]"),  # (745 GiB)
    (["bench_env.py", "--repeats", "-1", "--quick"], "--repeats must be an integer in [1, 1000]"),
    (["bench_grid_min_time.py", "tc", "1000"], "R (reach) must be an integer in [1, 8]"),
    (["bench_grid_min_time.py", "tc", "--suite", "test"], "--suite and --scenario go together"),
    (["bench_grid_min_time.py", "tc", "--suite", "test", "--scenario", "50"], "--scenario must be an integer in [0, 49]"),
    (["select_policy.py", "--policies", "/nonexistent"], "/nonexistent: expected"),  # (a FileNotFoundError's traceback)
    (["bench_agents.py", "--suite", "test", "--runs", "/nonexistent"], "/nonexistent: expected"),
    (["bench_agents.py", "--suite", "test", "--runs", "agents/policies/plan_target_service", "--json",
      "agents/policies/plan_target_service.json"], "is the input file"),  # (written over after the work)
    (["distill_plans.py", "--policy", "agents/policies/plan_target_tc", "--out", ""], "--out must name the policy's file stem"),
    (["bench_planning.py", "--target-ratio", "0.5"], "--target-ratio must be 0 (minimum time) or lie in [1, 3]"),
    (["bench_planning.py", "--reference-starts", "0.3", "0"], "--reference-starts must each lie in (0, 1]"),
    (["bench_far_starts.py", "--brakings", "moon"], "braking must be one of"),
    (["bench_far_starts.py", "--brakings"], "--brakings needs at least one of service, tc"),  # (numpy's concatenate error)
    (["bench_mpc.py", "--horizons", "0"], "--horizons must be integers in [2, 1000]"),  # (a traceback after the runs)
    (["bench_ocp.py", "--skip-pareto", "--pareto-only"], "not allowed with argument"),  # (nothing timed, exit 0)
    (["bench_rti_qp.py", "--target", "1"], "target_time 1 s is impossible"),  # (a traceback)
    (["bench_mumps_ordering.py", "--orders", "2", "3"], "--orders must be two or more distinct values of [0, 2, 4, 5, 6, 7]"),
    (["bench_mumps_ordering.py", "--orders", "2"], "--orders must be two or more distinct values"),
    (["bench_mumps_ordering.py", "--scenarios", "0"], "nothing to run: --scenarios 0 without --corners"),
    (["bench_draws.py", "--modes", "time", "0.9"], "--modes must each be 'time', 'mismatch' or a target ratio in [1, 3]"),
    (["bench_draws.py", "--modes", "fast"], "--modes must each be 'time', 'mismatch' or a target ratio in [1, 3]"),
    (["bench_draws.py", "--draws", "0"], "--draws must be an integer in [1, 1000]"),
    (["bench_modes.py", "--settings", "fast"], "--settings must each be one of"),
    (["bench_modes.py", "--settings", "deadline", "deadline"], "--settings names a setting twice"),
    (["bench_modes.py", "--modes", "0.9"], "--modes must each be 'time', 'mismatch' or a target ratio in [1, 3]"),
    (["bench_modes.py", "--first", "49", "--count", "2"], "the test suite has 50 tc cycles"),  # (an IndexError at the end)
    (["bench_replan_lag.py", "--lags", "5", "0"], "--lags must be distinct integers in [1, 100]"),
    (["bench_replan_lag.py", "--brakings", "moon"], "braking must be one of"),
    (["bench_plan_ceiling.py", "--scenarios", "50"], "--scenarios must be indices in [0, 49]"),  # (an IndexError)
    (["bench_plan_ceiling.py", "--ratios", "0.5"], "--ratios must be target ratios to T_min in [1, 3]"),
    (["bench_plan_env.py", "--num-envs", "0"], "--num-envs must be integers in [1, 16384]"),
    (["bench_plan_env.py", "--rounds", "0"], "--rounds must be an integer in [1, 100]"),
    (["train_plan_policy.py", "--cycles", "16"], "--cycles, --log-std-init and --log-std-final must give one value per stage"),
    (["train_plan_policy.py", "--braking", "moon"], "braking must be one of"),
    (["train_plan_policy.py", "--cycles", "0", "0"], "--cycles must be integers in [1, 1000000000]"),
    (["train_bc.py", "--demo-seed", "-1"], "--demo-seed must be an integer in [0, 1048576]"),
    # an option given twice with another value: argparse and tyro kept the last without a word
    (["train_bc.py", "--epochs", "1", "--epochs", "100000"], "argument --epochs: given twice with different values"),
    (["train_bc.py", "--braking", "tc", "--braking=service"], "argument --braking: given twice with different values"),
    (["train_plan_policy.py", "--cycles", "16", "16", "--cycles", "8", "8"], "argument --cycles: given twice"),
    (["train_plan_policy.py", "--score", "--no-score"], "argument --score: given twice with different values"),
    (["bench_draws.py", "--draws", "1", "--draws", "3"], "argument --draws: given twice with different values"),
    (["distill_plans.py", "--policy", "a", "--out", "b", "--seed", "1", "--seed", "2"], "argument --seed: given twice"),
    (["render_cycle.py", "--fps", "5", "--fps", "10"], "argument --fps: given twice with different values"),
    (["bench_ocp.py", "--repeats", "1", "--repeats", "2"], "argument --repeats: given twice with different values"),
    (["reproduce_paper.py", "--points", "3", "--points", "4"], "argument --points: given twice with different values"),
    # a PPOConfig field said as the option typed, not as PPOConfig.num_envs
    (["train_plan_policy.py", "--num-envs", "0"], "error: --num-envs must be an integer in [1, 16384], got 0"),
    (["train_bc.py", "--net-arch", "0"], "error: --net-arch must be one or more layer widths")])
def test_mpc_benchmarks_check_their_options_before_the_work(argv, needle):
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "scripts" / argv[0]
    r = subprocess.run([sys.executable, str(script), *argv[1:]], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("argv, needle", [
    (["run", "--cache", "{file}"], "--cache"),
    (["evaluate", "--controller", "operator", "--scenario", '{{"x": 1}}'], "--scenario"),
    (["evaluate", "--controller", "operator", "--cache", "{file}"], "--cache"),
    (["mpc", "--realtime", "--deadline-ms", "50"], "--realtime and --deadline-ms"),
    (["mpc", "--mismatch"], "--mismatch")])
def test_a_refused_option_leaves_no_output_folder(tmp_path, capsys, argv, needle):
    """Every option is checked before the --out check creates the output's folder: a bad --cache or --scenario
    left an empty folder behind (wl run, wl evaluate)."""
    (tmp_path / "file").write_text("")
    out = tmp_path / "new" / ("results" if argv[0] == "run" else "r.json")
    code, _, err = _run(capsys, *[a.format(file=tmp_path / "file") for a in argv], "--out", out)
    assert code == 2 and needle in err
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("files, needle", [
    ({"eval.csv": b"step,a\nabc,1\n"}, "eval.csv is not a readable evaluation log"),
    ({"eval.csv": b"\xff\xfe,a\n"}, "eval.csv is not a readable evaluation log"),
    ({"eval.csv": b"step,a\n1,2\n", "config.json": b'{"config": '}, "config.json is not a readable run config"),
    ({"eval.csv": b"step,a\n1,2\n", "config.json": b"[1]"}, "config.json is not a readable run config")])
def test_plot_learning_curve_names_a_corrupt_run_file(tmp_path, files, needle):
    import subprocess
    import sys

    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    script = Path(__file__).resolve().parents[1] / "scripts" / "plot_learning_curve.py"
    r = subprocess.run([sys.executable, str(script), str(tmp_path), "--out", str(tmp_path / "c.png"), "--no-front"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not (tmp_path / "c.png").exists()


@pytest.mark.parametrize("front", ["other braking", "corrupt"])
def test_plot_learning_curve_refuses_a_front_not_of_its_cycle(tmp_path, front):
    """A service front on a TC curve was drawn without a word (or a traceback with rows to score); a corrupt
    --front was only a warning (stop 59)."""
    import subprocess
    import sys

    from mpc.benchmark.reference import shipped_fronts

    (tmp_path / "eval.csv").write_bytes(b"step,a\n1,2\n")
    path = tmp_path / "front.json"
    shipped_fronts()["service_" + DEFAULT_PARAMS.fingerprint()].save(path)
    if front == "corrupt":
        path.write_text(path.read_text()[:100])
    script = Path(__file__).resolve().parents[1] / "scripts" / "plot_learning_curve.py"
    r = subprocess.run([sys.executable, str(script), str(tmp_path), "--out", str(tmp_path / "c.png"), "--front", str(path),
                        "--braking", "tc" if front == "other braking" else "service"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "--front" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert ("'service' braking's, the cycle's is 'tc'" in r.stderr) == (front == "other braking")
    assert not (tmp_path / "c.png").exists()


def test_scripts_take_what_ctrl_c_became_inside_a_library_as_an_interrupt():
    """A SystemError out of CasADi's DM.__array__ ended train_bc.py with a traceback; the scripts had no handler
    setting the interrupt flag, so an interrupt a solve swallowed was lost (stop 59)."""
    from wl_env.logs import run_script

    def casadi_like():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("returned a result with an exception set") from None

    with pytest.raises(SystemExit) as exc:
        run_script("script", casadi_like)
    assert exc.value.code == 130

    def a_bug():
        raise SystemError("a bug of its own")

    with pytest.raises(SystemError, match="a bug of its own"):
        run_script("script", a_bug)


def test_a_missing_optimum_under_no_solve_is_one_line(tmp_path, capsys):
    """--no-solve with a perturbed start, whose optimum no file holds: a LookupError's traceback, exit 1, before."""
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--episodes", "2", "--no-solve",
                        "--cache", tmp_path / "cache", "--out", tmp_path / "e.json")
    assert code == 2 and "wl: error: no shipped or cached optimum" in err and "Traceback" not in err
    assert not (tmp_path / "e.json").exists()


@pytest.mark.parametrize("name, value, needle", [
    ("WL_CACHE_DIR", "{file}", "$WL_CACHE_DIR: {file} is not a folder"),  # (failed after an episode, naming no variable)
    ("WL_CODEGEN_DIR", "{file}", "$WL_CODEGEN_DIR: {file} is not a folder"),
    ("WL_NLP_CACHE_SIZE", "abc", "$WL_NLP_CACHE_SIZE must be an integer in [1, 1000]")])
def test_a_bad_environment_variable_is_one_line_before_any_work(tmp_path, capsys, monkeypatch, name, value, needle):
    (tmp_path / "file").write_text("")
    monkeypatch.setenv(name, value.format(file=tmp_path / "file"))
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--episodes", "1", "--out", tmp_path / "e.json")
    assert code == 2 and err.startswith("wl: error: " + needle.format(file=tmp_path / "file")) and len(err.splitlines()) == 1


# ------------------------------------------------------------------------------------------ report
def test_report_rebuilds_the_run_report_from_results_json(tmp_path, cache, capsys):
    out = tmp_path / "results"
    results = wl.report.collect(out, cache=str(cache),
                                controllers=lambda b: [("operator", lambda: OperatorPolicy(b))],
                                suite_controllers=lambda b: [("operator", lambda: OperatorPolicy(b))], suite_sample=2)
    wl.report.render(results, out)
    first = (out / "leaderboard.md").read_text()
    suite = results["suite"]
    # the operator's 2 cycles per braking, and the shipped target-conditioned policies' (PPO per step, PPO of one
    # plan per cycle and the imitation baseline) at the three targets
    assert suite["suite"] == "test" and not suite["full"] and len(suite["episodes"]) == 4 + 3 * 2 * 2 * 3
    targeted = [r for r in suite["rows"] if r["target"] is not None]
    assert sorted({r["target"] for r in targeted}) == ["1.15 T_min", "1.5 T_min", "fastest"]
    assert all(r["lateness_median"] is None or r["lateness_median"] >= 0 for r in targeted)
    assert "| ppo (target-conditioned) | tc | 1.15 T_min | 2 |" in first
    assert "| bc (imitation) | service | fastest | 2 |" in first
    assert "| ppo (plan) | service | 1.5 T_min | 2 |" in first
    assert "## The `test` suite" in first and "a fixed sample of 2 of its 50 scenarios" in first
    # each episode scored against its own scenario's optimum (shipped)
    from mpc.benchmark.reference import shipped_fronts
    from wl_env.scenario import Scenario

    for e in suite["episodes"]:
        if e["success"]:
            s = Scenario.from_dict(e["scenario"])
            assert e["T_min"] == shipped_fronts()[f"{s.braking}_{s.params().fingerprint()}"].T_min
    assert (out / "suite_gaps.png").stat().st_size > 10_000
    rows = {(r["controller"], r["braking"]): r for r in results["rows"]}
    assert rows[("optimum (min time)", "tc")]["T"] == 7.0
    for b in ("service", "tc"):
        _check_scores([rows[("operator", b)]], b)
    for f in ("leaderboard.md", "pareto.png", "trajectories_service.png", "trajectories_tc.png"):
        (out / f).unlink()
    code, stdout, err = _run(capsys, "report", "--results", out)
    assert code == 0, err
    assert (out / "leaderboard.md").read_text() == first
    for f in ("pareto.png", "trajectories_service.png", "trajectories_tc.png"):
        assert (out / f).stat().st_size > 10_000, f
    assert "leaderboard.md" in stdout
    code, _, _ = _run(capsys, "report", "--results", out, "--out", tmp_path / "elsewhere")
    assert code == 0 and (tmp_path / "elsewhere" / "leaderboard.md").read_text() == first


def test_isolated_evaluation_is_the_in_process_one(tmp_path):
    """`wl run` runs each controller's episodes in a worker process of its own (its memory goes back to the
    OS when it ends) and scores them after (deferred): the same episodes and scores as in this process, and
    an error comes back as itself."""
    from wl_env.suites import load_suite

    scenarios = list(load_suite("test").spread("service", 2))  # (their optima are shipped: nothing is solved)
    kwargs = {"scenarios": scenarios, "cache": str(tmp_path / "cache"), "name": "operator"}
    here = wl.report.evaluation(wl.report.suite_controllers, "service", "operator", **kwargs)
    there = wl.report.evaluation(wl.report.suite_controllers, "service", "operator", isolate=True, **kwargs)
    assert [e["success"] for e in here["per_episode"]] == [True, True]
    assert json.dumps(there["per_episode"], sort_keys=True) == json.dumps(here["per_episode"], sort_keys=True)
    assert there["summary"] == here["summary"] and there["optimum"] == here["optimum"] is not None
    with pytest.raises(ValueError, match="controller must be one of .*'operator'.*, got 'no such controller'"):
        wl.report.evaluation(wl.report.suite_controllers, "service", "no such controller", isolate=True, **kwargs)
    with pytest.raises(ValueError, match="module-level function"):
        wl.report.evaluation(lambda b: [("operator", lambda: OperatorPolicy(b))], "service", "operator", isolate=True,
                             **kwargs)


def _broken(results: dict, what: str) -> dict:
    results = json.loads(json.dumps(results))
    if what == "trajectories":
        del results["trajectories"]
    elif what == "states":
        results["trajectories"][0]["states"] = results["trajectories"][0]["states"][:-1]
    elif what == "row":
        results["rows"][1]["T"] = "fast"
    elif what == "old":
        results = {"rows": results["rows"], "wall_time_s": 1.0}
    # each of these was drawn as nonsense or failed in the drawing with a traceback or an unnamed error
    elif what == "nan":
        results["rows"][1]["T"] = math.nan
    elif what == "huge":
        results["rows"][1]["fuel_g"] = 10**400
    elif what == "controller":
        results["rows"][1]["controller"] = ["operator"]
    elif what == "times":
        results["optima"]["service"]["t"] = "abc"
    elif what == "front":
        results["fronts"]["service"]["T"] = results["fronts"]["service"]["T"][::-1]
    elif what == "string states":  # (passed as numbers, then the figure failed with half the report written)
        results["optima"]["service"]["states"] = [[str(v) for v in row] for row in results["optima"]["service"]["states"]]
    elif what == "empty trajectory":  # (passed, then "too many indices" after three files, naming nothing; stop 59)
        results["trajectories"][0]["t"], results["trajectories"][0]["states"] = [], []
    elif what == "brakings twice":  # (passed, then a staging file was missing, naming an internal path; stop 60)
        results["brakings"] = ["service", "service"]
    elif what == "front of the other braking":  # (drawn as the service front without a word; stop 61)
        results["fronts"]["service"]["braking"] = "tc"
    elif what == "fuel_min_g off its point":  # (drawn; stop 61)
        results["fronts"]["service"]["fuel_min_g"] = results["fronts"]["service"]["fuel_g"][-1] - 1.0
    return results


@pytest.mark.parametrize("what", ["missing", "garbled", "trajectories", "states", "row", "old", "nan", "huge", "brakings twice",
                                  "controller", "times", "front", "string states", "empty trajectory",
                                  "front of the other braking", "fuel_min_g off its point"])
def test_report_errors_are_one_line(tmp_path, cache, capsys, what):
    out = tmp_path / "results"
    if what != "missing":
        results = wl.report.collect(out, cache=str(cache), brakings=("service",), suite_controllers=None,
                                    controllers=lambda b: [("operator", lambda: OperatorPolicy(b))])
        text = "{\"rows\": [" if what == "garbled" else json.dumps(_broken(results, what))
        (out / "results.json").write_text(text)
        capsys.readouterr()  # collect's progress lines
    code, _, err = _run(capsys, "report", "--results", out)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("wl: error:") and "results.json" in err
    assert not (out / "leaderboard.md").exists()


def test_report_checks_its_files_before_writing_any(tmp_path, cache, capsys):
    """A folder where a figure goes is refused before any file is written (it failed after the leaderboard)."""
    out = tmp_path / "results"
    wl.report.collect(out, cache=str(cache), brakings=("service",), suite_controllers=None,
                      controllers=lambda b: [("operator", lambda: OperatorPolicy(b))])
    capsys.readouterr()
    (out / "leaderboard.md").unlink(missing_ok=True)
    (out / "pareto.png").unlink(missing_ok=True)
    (out / "pareto.png").mkdir()
    code, _, err = _run(capsys, "report", "--results", out)
    assert code == 2 and "pareto.png is a folder" in err
    assert not (out / "leaderboard.md").exists()


def test_an_interrupted_report_leaves_the_report_as_it_was(tmp_path, cache, capsys, monkeypatch):
    """Ctrl-C while drawing left 4 of the 5 new files beside the old fifth (stop 59): the files are drawn in a
    staging folder and moved into --out together."""
    out = tmp_path / "results"
    wl.report.collect(out, cache=str(cache), brakings=("service",), suite_controllers=None,
                      controllers=lambda b: [("operator", lambda: OperatorPolicy(b))])
    capsys.readouterr()
    before = {f.name: f.read_bytes() for f in out.iterdir() if f.is_file()}
    calls = []

    def interrupted(fig, path, **kwargs):
        calls.append(path)
        raise KeyboardInterrupt

    monkeypatch.setattr(wl.report, "save_figure", interrupted)
    code, _, err = _run(capsys, "report", "--results", out)
    assert code == 130 and calls
    assert {f.name: f.read_bytes() for f in out.iterdir() if f.is_file()} == before
    assert [f.name for f in out.iterdir() if f.name.startswith(".report-")] == []
    code, _, err = _run(capsys, "report", "--results", out, "--out", "")
    assert code == 2 and "--out must name a folder" in err


@pytest.mark.parametrize("argv, needle", [
    (["mpc", "--target-time", "1", "--no-score"], "--target-time 1 s lies below the minimum cycle time"),
    (["mpc", "--target-time", "7.9", "--braking", "tc", "--no-score"], "--target-time 7.9 s lies below"),
    (["evaluate", "--controller", "mpc", "--target-time", "7"], "--target-time 7 s lies below"),
    (["evaluate", "--controller", "operator", "--suite", "test", "--sample", "3", "--target-time", "8"],
     "--target-time 8 s lies below the minimum cycle time of the"),
])
def test_a_target_time_under_the_minimum_is_refused_before_any_work(tmp_path, capsys, argv, needle):
    """The MPC found it out after ~5 s of planning, naming MPCConfig.target_time; `wl evaluate` blamed the
    controller's act() (stop 59)."""
    t0 = time.perf_counter()
    code, _, err = _run(capsys, *argv, "--out", tmp_path / "x" / "out.json")
    assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert time.perf_counter() - t0 < 3.0 and not (tmp_path / "x").exists()


def test_an_interrupt_that_a_library_turned_into_another_error_exits_130(monkeypatch, capsys):
    """Ctrl-C inside CasADi's DM.__array__ came out as a SystemError (exit 1, a traceback), inside numpy's import
    at start-up as an ImportError (stop 59)."""
    from mpc import interrupt

    def casadi_like(args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise SystemError("<function DM.__array__> returned a result with an exception set") from None

    class Parser:
        def parse_args(self, argv):
            return argparse.Namespace(func=casadi_like, command="params", verbose=False, version=False)

    monkeypatch.setattr(wl.cli, "build_parser", Parser)
    code, _, err = _run(capsys, "params")
    assert code == 130 and err.strip() == "wl: interrupted"

    def import_interrupted():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError('PyCapsule_Import could not import module "datetime"')  # noqa: B904

    monkeypatch.setattr(wl.cli, "build_parser", import_interrupted)
    code, _, err = _run(capsys, "params")
    assert code == 130 and err.strip() == "wl: interrupted"
    assert not interrupt.caused_by_interrupt(SystemError("a bug of its own"))


# ------------------------------------------------------------------------------------------ errors, help
@pytest.mark.parametrize("argv,needle", [
    (["evaluate", "--controller", "operator", "--braking", "hydraulic"], "--braking"),
    (["evaluate", "--controller", "operator", "--episodes", "0"], "--episodes"),
    (["evaluate", "--controller", "operator", "--init-noise", "1.5"], "--init-noise"),
    (["evaluate", "--controller", "ppo", "--model", "{tmp}/no_policy.zip"], "no_policy.zip"),
    (["evaluate", "--controller", "not_a_controller"], "not_a_controller"),
    (["evaluate", "--controller", "{tmp}/nothing.py:Driver"], "nothing.py"),
    (["evaluate", "--controller", "agents.operator:NoSuchClass"], "NoSuchClass"),
    (["train", "--braking", "hydraulic", "--log-dir", "{tmp}"], "braking"),
    (["train", "--num-envs", "many"], "--num-envs"),
    (["train", "--num-envs", "1000000000", "--log-dir", "{tmp}"], "[1, 16384]"),
    (["train", "--seeds", "99999999999", "--log-dir", "{tmp}"], "--seeds"),  # (was named PPOConfig.seed)
    (["train", "--seeds", "0", "--sweep", "learning_rate=nan", "--log-dir", "{tmp}"], "--sweep learning_rate=nan"),
    (["train", "--reward", "bogus=1", "--log-dir", "{tmp}"], "--reward"),
    (["ocp", "--objective", "speed", "--out", "{tmp}/x.json"], "--objective"),
    (["report"], "--results"),
    (["evaluate", "--controller", "operator", "--scenario", ""], "--scenario is empty"),
    (["ocp", "--out", "{tmp}/x.json", "--params", " "], "--params is empty"),
    (["ocp", "--out", "{tmp}/x.json", "--params", '{"M_veh": 1' + "0" * 5000 + "}"], "--params is not valid JSON"),
    (["evaluate", "--controller", "ppo", "--model", "{tmp}/evil_vecnormalize.pkl"], "no policy at {tmp}/evil_vecnormalize.pkl"),
    (["params", "--set", '{"omega_min": 200, "omega_max": 50}'], "omega_min must be below omega_max"),
    (["params", "--set", ""], "--set is empty"),  # (printed the defaults)
    (["params", "--set", "[1]"], "--set must be a JSON object"),
    (["train", "--log-dir", "{tmp}", "--seed", "99999999999999999999"], "--seed must be an integer in [0, 2**31 - 1]"),
    (["train", "--log-dir", "{tmp}", "--max-time", "0.1"], "--max-time must be a number of seconds in [0.5, 3600]"),
    # stop 59: each failed after the env's build (torch's message, or init_policy's), or named no flag
    (["train", "--log-dir", "{tmp}", "--log-std-init", "1e308"], "--log-std-init must be a number in [-20, 5]"),
    (["train", "--log-dir", "{tmp}", "--max-grad-norm", "1e308"], "--max-grad-norm must be a number in (0, 1e6]"),
    (["train", "--log-dir", "{tmp}", "--init-policy", "{tmp}/nothing"], "--init-policy {tmp}/nothing: not a pickle-free"),
    (["train", "--log-dir", "{tmp}", "--run-name", "x" * 300], "--run-name must be a name of at most 200 characters"),
    (["mpc", "--params", '{"M_load": -1}', "--out", "{tmp}/m.json"], "--params: LoaderParams.M_load must"),
    (["evaluate", "--controller", "operator", "--scenario", "{tmp}"], "is a folder"),
])
def test_user_errors_are_one_line(tmp_path, capsys, argv, needle):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    needle = needle.replace("{tmp}", str(tmp_path))
    if argv[0] == "evaluate":
        argv += ["--out", str(tmp_path / "eval.json")]
    code, _, err = _run(capsys, *argv)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("wl: error:") and needle in lines[0], err
    assert not (tmp_path / "eval.json").exists()
    assert not list(tmp_path.glob("*/config.json"))  # (a refused run leaves no config behind)


def test_a_scenario_file_named_with_spaces_around_it(tmp_path, capsys):
    path = tmp_path / "s.json"
    path.write_text('{"payload": 6000}')
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--braking", "tc", "--scenario", f" {path} ",
                        "--no-score", "--out", str(tmp_path / "e.json"))
    assert code == 0, err
    assert json.loads((tmp_path / "e.json").read_text())["per_episode"][0]["scenario"]["payload"] == 6000


@pytest.mark.parametrize("controller,stem", [("ppo", "ppo_tc"), ("plan", "plan_target_tc")])
def test_missing_shipped_policy_names_the_path(tmp_path, capsys, monkeypatch, controller, stem):
    monkeypatch.setattr("agents.evaluate.POLICY_DIR", tmp_path)
    code, _, err = _run(capsys, "evaluate", "--controller", controller, "--braking", "tc", "--out", tmp_path / "e.json")
    assert code == 2 and err.count("\n") == 1 and str(tmp_path / f"{stem}.safetensors") in err


@pytest.mark.parametrize("command", SUBCOMMANDS + [None])
def test_help_of_every_subcommand(capsys, command):
    code, out, err = _run(capsys, *([command] if command else []), "--help")
    assert code == 0 and err == ""
    assert out.startswith(f"usage: wl {command}" if command else "usage: wl")


def test_every_subcommand_is_tested():
    sub = next(a for a in wl.cli.build_parser()._actions if a.dest == "command")
    assert sorted(sub.choices) == sorted(SUBCOMMANDS)


# ------------------------------------------------------------------------------------------ validation before work
class Reached(Exception):
    """Raised by the fakes of the expensive work: the command line got past its checks."""


@pytest.fixture
def no_work(monkeypatch):
    """Every subcommand's expensive work replaced by a fake that records its arguments and raises Reached."""
    import agents.evaluate
    import agents.ppo
    import mpc.benchmark.ocp
    import mpc.benchmark.pareto
    import mpc.controller.mpc

    calls: list[tuple[str, tuple, dict]] = []

    def fake(name):
        def work(*args, **kwargs):
            calls.append((name, args, kwargs))
            raise Reached(name)
        return work

    for module, name, label in [(mpc.benchmark.ocp, "solve_ocp", "ocp"), (mpc.benchmark.pareto, "pareto_fronts", "pareto"),
                                (mpc.controller.mpc, "run_closed_loop", "mpc"),
                                (agents.evaluate, "evaluate_controller", "evaluate"), (agents.ppo, "train", "train"),
                                (wl.report, "run_all", "run")]:
        monkeypatch.setattr(module, name, fake(label))
    return calls


def _attempt(capsys, argv: list[str]) -> tuple[int | None, str]:
    """(exit code, stderr) of ``wl ARGV``; exit code None if it reached the (fake) work."""
    try:
        code = wl.cli.main(argv)
    except Reached:
        code = None
    return code, capsys.readouterr().err


BAD_INPUT = [  # (argv, the option, the allowed range as the message says it)
    (["ocp", "--objective", "fuel", "--time", "0"], "--time", "[0.4, 60]"),
    (["ocp", "--objective", "fuel", "--time=-5"], "--time", "[0.4, 60]"),
    (["ocp", "--objective", "fuel", "--time", "nan"], "--time", "[0.4, 60]"),
    (["ocp", "--objective", "fuel", "--time", "inf"], "--time", "[0.4, 60]"),
    (["ocp", "--objective", "fuel", "--time", "100"], "--time", "30 s"),
    (["ocp", "--objective", "time", "--w-fuel", "0.5"], "--w-fuel", "--objective weighted"),
    (["ocp", "--objective", "weighted", "--w-fuel", "1.5"], "--w-fuel", "[0, 1]"),
    (["ocp", "--params", "{not json"], "--params", "JSON"),
    (["mpc", "--deadline-ms", "150", "--out", "x.json"], "--deadline-ms", "(0, 100] ms"),
    (["evaluate", "--controller", "mpc", "--target-ratio", "0.5", "--out", "x.json"], "--target-ratio", "[1, 3]"),
    (["evaluate", "--controller", "mpc", "--target-time", "50", "--out", "x.json"], "--target-time", "[1, 40) s"),
    (["mpc", "--deadline-ms", "0", "--out", "x.json"], "--deadline-ms", "(0, 100] ms"),
    (["mpc", "--rate-weight", "0.1", "-1", "--out", "x.json"], "--rate-weight", "[0, 1e+06]"),
    (["train", "--n-epochs", "0"], "--n-epochs", ">= 1"),
    (["train", "--total-timesteps", "-5"], "--total-timesteps", ">= 1"),
    (["train", "--gamma", "2"], "--gamma", "(0, 1]"),
    (["train", "--net-arch", "0"], "--net-arch", "[1, 4096]"),
    (["train", "--eval-episodes", "-1"], "--eval-episodes", ">= 0"),
    (["train", "--curriculum-fraction", "nan"], "--curriculum-fraction", "[0, 1]"),
    (["train", "--learning-rate", "inf"], "--learning-rate", "(0, 1]"),
    (["train", "--export-episodes", "-3"], "--export-episodes", ">= 0"),
    # (accepted, then after the whole training a target env's evaluation drew 10**9 scenarios: a hang)
    (["train", "--export-episodes", "1000000000"], "--export-episodes", "at most 99999"),
    (["train", "--eval-episodes", "1000000000"], "--eval-episodes", "at most 99999"),
    (["mpc", "--target-time", "nan"], "--target-time", "[1, 40)"),
    (["mpc", "--target-time=-1"], "--target-time", "[1, 40)"),
    (["evaluate", "--controller", "mpc", "--target-time", "5e-324", "--out", "x.json"], "--target-time", "[1, 40) s"),
    (["mpc", "--w-fuel", "2"], "--w-fuel", "[0, 1]"),
    (["mpc", "--payload-scale", "inf"], "--payload-scale", "[0, 10]"),
    (["mpc", "--params", '{"M_load": 150000}', "--payload-scale", "10"], "--payload-scale", "[0, 200000] kg"),
    (["pareto", "--points", "2"], "--points", "[3, 100]"),
    (["evaluate", "--controller", "operator", "--seed=-1"], "--seed", "in [0, 2147483647], got -1"),
    (["evaluate", "--controller", "operator", "--episodes", "99999999999999999999"], "--episodes", "[1, 100000]"),
    (["evaluate", "--controller", "operator", "--act-timeout", "1e308"], "--act-timeout", "(0, 86400]"),
    (["evaluate", "--controller", "operator", "--scenario", "[1, 2]"], "--scenario", "JSON object"),
    (["ocp", "--scenario", '{"payload": 1}'], "Scenario.payload", "[6000, 13000] kg"),
    (["pareto", "--scenario", '{"dump_height": 5.5}'], "Scenario.dump_height", "[3.5, 5.1] m"),
    (["mpc", "--scenario", '{"start_engine_speed": 3000}'], "Scenario.start_engine_speed", "[800, 2000] rpm"),
    (["evaluate", "--controller", "operator", "--scenario", '{"reverse_distance": 3}'], "Scenario.reverse_distance",
     "[4, 10] m"),
    (["evaluate", "--controller", "operator", "--scenario", '{"payloda": 9000}'], "--scenario", "unknown Scenario field"),
    (["evaluate", "--controller", "operator", "--scenario", '{"braking": "tc"}', "--braking", "service"], "--braking",
     "contradicts"),
    (["evaluate", "--controller", "operator", "--sample", "3"], "--sample", "--suite"),
    # (a sampler suite drew 10**11 scenarios before any check: minutes and gigabytes, then SIGTERM)
    (["evaluate", "--controller", "operator", "--suite", "train", "--sample", "100000000000"], "--sample",
     "[1, 100000]"),
    # (each scenario of a suite runs once from its own start: these were ignored without a word)
    (["evaluate", "--controller", "operator", "--suite", "test", "--episodes", "5"], "--episodes", "--suite"),
    (["evaluate", "--controller", "operator", "--suite", "test", "--init-noise", "0.5"], "--init-noise", "--suite"),
    (["mpc", "--mismatch"], "--mismatch", "--scenario"),
    (["mpc", "--realtime", "--deadline-ms", "50"], "--realtime", "--deadline-ms"),
    (["mpc", "--horizon-steps", "1"], "--horizon-steps", "[2, 1000]"),
    (["mpc", "--horizon-steps", "10", "--realtime"], "--horizon-steps", "--realtime"),
    (["mpc", "--full-horizon", "--horizon-solver", "sqp-rti"], "--horizon-solver", "--full-horizon"),
    (["mpc", "--realtime", "--replan-lag-steps", "10"], "--replan-lag-steps", "--realtime"),
    (["mpc", "--full-horizon", "--replan-in-step"], "--replan-in-step", "--full-horizon"),
    (["mpc", "--replan-in-step", "--replan-lag-steps", "5"], "--replan-lag-steps", "--replan-in-step"),
    (["mpc", "--full-horizon", "--horizon-steps", "10"], "--horizon-steps", "--full-horizon"),
    (["mpc", "--horizon-steps", "10", "--replan-lag-steps", "0"], "--replan-lag-steps", "[1, 100]"),
    (["mpc", "--horizon-steps", "10", "--horizon-solver", "fatrop"], "--horizon-solver", "sqp-rti"),
    (["train", "--env-id", "WheelLoader-v7"], "--env-id", "WheelLoaderTarget-v0"),
    (["train", "--scenario", "train"], "--scenario", "WheelLoader-v1"),
    (["train", "--env-id", "WheelLoaderTarget-v0", "--target", "0.5", "2"], "--target", "[1, 3]"),
    (["train", "--ray"], "--ray", "--seeds"),
    (["train", "--seeds", "0", "0"], "seeds", "repeat"),
    (["train", "--seeds", "0", "--sweep", "gamma=high"], "--sweep gamma", "float"),
    (["train", "--seeds", "0", "--workers", "0"], "--workers", "an integer in [1, "),
    (["train", "--seeds", "0", "1", "--workers", "100000000"], "--workers", "per CPU"),  # (a process per run)
    (["suite", "solve", "--suite", "test", "--workers", "100000000"], "--workers", "an integer in [1, "),
    (["train", "--torch-threads", "100000"], "--torch-threads", "[1, 1024]"),  # (segfaulted)
    (["train", "--reward", "target_distance=1e308"], "target_distance", "[0, 1e+06]"),  # (a reward of -inf)
    (["train", "--export", ""], "--export", "empty"),
    (["pareto", "--cache", ""], "--cache", "empty"),  # (the working folder, unasked)
    (["evaluate", "--controller", "operator", "--out", ""], "--out", "empty"),
    (["evaluate", "--controller", "ppo", "--model", ""], "--model", "empty"),  # (searched the working folder)
    (["ocp", "--params", "null"], "--params", "JSON object"),  # (taken as no overrides)
    # (passed (0, 60], then failed in the start guess: "zero-size array to reduction operation minimum")
    (["ocp", "--objective", "fuel", "--time", "0.0001"], "--time", "[0.4, 60]"),
    (["report", "--results", ""], "--results", "empty"),  # (searched the working folder)
    (["train", "--reward", "w_fuel=abc"], "--reward", "w_fuel: expected a number"),  # ("invalid _key_value value")
    # (Ray's "Invalid address format:" after the suite's setup; ray:// without a port hung)
    (["train", "--seeds", "0", "1", "--ray", "ray://"], "--ray", "[ray://]HOST:PORT"),
]


def test_a_kept_evaluation_is_keyed_by_the_shipped_data_not_the_version_alone(tmp_path, monkeypatch):
    """`wl run` reuses an interrupted run's kept evaluations by their key. Keyed by the version alone, a policy shipped
    anew without a version bump (stop 64) would have had the old policy's rows reused: the key holds the shipped
    policies', suites' and optima's content."""
    import wl.report as report

    assert all(any(folder.glob("*.json")) for folder in report.SHIPPED_DATA)  # (the folders are where the data lies)
    policies = tmp_path / "policies"
    policies.mkdir()
    (policies / "p.safetensors").write_bytes(b"weights")
    monkeypatch.setattr(report, "SHIPPED_DATA", (policies,))

    def key() -> str:
        report.shipped_data_digest.cache_clear()
        return report._evaluation_key(report.suite_controllers, "service", "ppo", {"seed": 0})

    first = key()
    assert key() == first  # (the same files: the same key, so a kept evaluation is found again)
    (policies / "p.safetensors").write_bytes(b"weight2")
    assert key() != first
    (policies / "p.safetensors").write_bytes(b"weights")
    (policies / "q.json").write_text("{}")
    assert key() != first


@pytest.mark.parametrize("argv,option,allowed", BAD_INPUT, ids=[" ".join(a[0]) for a in BAD_INPUT])
def test_bad_input_is_one_line_naming_the_option_and_range(tmp_path, capsys, no_work, argv, option, allowed):
    out = "--out" in argv or argv[0] == "train"
    argv = argv + ([] if out else ["--out", str(tmp_path / ("o" if argv[0] == "pareto" else "o.json"))])
    if argv[0] == "train":
        argv += ["--log-dir", str(tmp_path / "runs")]
    code, err = _attempt(capsys, argv)
    assert code == 2 and not no_work
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("wl: error:"), err
    assert option in lines[0] and allowed in lines[0], lines[0]


@pytest.mark.parametrize("argv, option, allowed", [
    (["--ray", ""], "--ray", "[ray://]HOST:PORT with PORT in [1, 65535]"),
    (["--ray", "foo"], "--ray", "[ray://]HOST:PORT"),
    (["--ray", "head:0"], "--ray", "PORT in [1, 65535]"),
    (["--out", ""], "--out", "empty"),  # (an empty --out was the default file: the solve started)
    (["--check", "--out", "x.json"], "--out", "--check"),  # (ignored without a word)
])
def test_suite_solve_options_fail_before_the_solve(monkeypatch, capsys, argv, option, allowed):
    import mpc.benchmark.suite

    def work(*args, **kwargs):
        raise Reached("suite")

    monkeypatch.setattr(mpc.benchmark.suite, "solve_suite", work)
    monkeypatch.setattr(mpc.benchmark.suite, "check_shipped", work)
    code, err = _attempt(capsys, ["suite", "solve", "--suite", "corners", *argv])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and option in lines[0] and allowed in lines[0], err


def test_ray_addresses():
    from mpc.workers import check_ray_address, is_ray_address

    for ok in ("local", "auto", "10.0.0.1:6379", "ray://head:10001", "[::1]:10001", "anyscale://cluster"):
        assert is_ray_address(ok) and check_ray_address(ok) == ok
    for bad in ("", " ", "ray://", "ray://head", "head", "head:", ":10001", "head:70000", "head:x", None, 6379):
        assert not is_ray_address(bad)
        with pytest.raises(ValueError, match="--ray must be local, auto or"):
            check_ray_address(bad)


def test_huge_input_is_one_short_line_and_the_limits_are_the_apis(tmp_path, capsys, no_work):
    """A 10 MB value or deeply nested JSON gives one readable line (were a 10 MB line, or a RecursionError
    naming no option); the evaluation's limits are agents.evaluate's."""
    from agents.evaluate import MAX_ACT_TIMEOUT, MAX_EPISODES

    out = ["--out", str(tmp_path / "o.json")]
    for argv, needle in [(["ocp", "--params", '{"a": ' + "[" * 100_000 + "]" * 100_000 + "}", *out], "--params"),
                         (["evaluate", "--controller", "operator", *out, "--scenario",
                           '{"payload": "' + "x" * 10_000_000 + '"}'], "Scenario.payload"),
                         (["params", "--set", '{"M_' + "x" * 10_000_000 + '": 1}'], "unknown LoaderParams")]:
        code, err = _attempt(capsys, argv)
        assert code == 2 and not no_work and len(err) < 3000 and needle in err, err[:300]
        assert len(err.strip().splitlines()) == 1 and err.startswith("wl: error:")
    code, _ = _attempt(capsys, ["evaluate", "--controller", "operator", *out, "--episodes", str(MAX_EPISODES),
                                "--act-timeout", f"{MAX_ACT_TIMEOUT:g}"])
    assert code is None and no_work[-1][2]["episodes"] == MAX_EPISODES


def _unwritable(tmp_path: Path) -> Path:
    """A folder no file can be created in (root writes through permission bits: /proc then)."""
    if os.geteuid() == 0:
        return Path("/proc")
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o500)
    return folder


OUTPUTS = {  # how each command names its output, and whether that is a file or a folder
    "ocp": (["ocp"], "--out", "file"), "mpc": (["mpc", "--no-score"], "--out", "file"),
    "evaluate": (["evaluate", "--controller", "operator"], "--out", "file"),
    "train": (["train", "--log-dir", "{tmp}/runs"], "--export", "file"),
    "pareto": (["pareto"], "--out", "folder"), "run": (["run"], "--out", "folder"),
}


@pytest.mark.parametrize("problem", ["wrong-kind", "under-a-file", "unwritable"])
@pytest.mark.parametrize("command", sorted(OUTPUTS))
def test_output_paths_are_checked_before_the_work(tmp_path, capsys, no_work, command, problem):
    argv, option, kind = OUTPUTS[command]
    a_file, a_folder = tmp_path / "a_file", tmp_path / "a_folder"
    a_file.write_text("x")
    a_folder.mkdir()
    path = {"wrong-kind": a_folder if kind == "file" else a_file, "under-a-file": a_file / "sub" / "out.json",
            "unwritable": _unwritable(tmp_path) / "out.json"}[problem]
    if command == "train" and problem == "wrong-kind":
        (tmp_path / "policy.safetensors").mkdir()  # where the export would write its weights
        path = tmp_path / "policy"
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv] + [option, str(path)]
    code, err = _attempt(capsys, argv)
    assert code == 2 and not no_work, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("wl: error:") and option in lines[0] and str(path) in lines[0], err


@pytest.mark.parametrize("flags, horizon, solver", [
    ([], 10, "sqp-rti"),  # the default: #13's best candidate
    (["--full-horizon"], None, None),
    (["--realtime"], None, None), (["--deadline-ms", "80"], None, None),  # (they act on the full horizon's solves)
    (["--horizon-steps", "20", "--horizon-solver", "ipopt"], 20, "ipopt"),
    (["--horizon-solver", "ipopt"], 10, "ipopt"),
])
def test_mpc_horizon_flags_make_the_config_they_say(tmp_path, capsys, no_work, flags, horizon, solver):
    code, err = _attempt(capsys, ["mpc", "--braking", "tc", *flags, "--out", str(tmp_path / "o.json")])
    assert code is None, err
    config = no_work[-1][1][1]  # run_closed_loop(braking, config, ...)
    assert (config.horizon, config.short_horizon_solver) == (horizon, solver)


def test_mpc_and_train_take_the_pareto_cache(tmp_path, capsys, no_work):
    cache = tmp_path / "my_cache"
    code, err = _attempt(capsys, ["mpc", "--cache", str(cache), "--out", str(tmp_path / "m.json")])
    assert code is None and no_work[-1][2]["cache"] == str(cache), err
    code, err = _attempt(capsys, ["train", "--cache", str(cache), "--log-dir", str(tmp_path / "runs")])
    assert code is None and no_work[-1][0] == "train", err


def test_mpc_safety_filter_is_on_unless_turned_off(tmp_path, capsys, no_work):
    for extra, on in (([], True), (["--no-safety-filter"], False)):
        code, err = _attempt(capsys, ["mpc", "--realtime", *extra, "--out", str(tmp_path / "m.json")])
        config = no_work[-1][1][1]  # run_closed_loop(braking, config, ...)
        assert code is None and config.safety_filter is on and config.realtime, err


def test_train_solves_the_front_in_its_cache_with_progress(tmp_path, capsys, monkeypatch):
    """Scoring on: the trainer's front comes from --cache, and solving it shows progress lines."""
    from fakes import fake_solve

    import mpc.benchmark.pareto

    monkeypatch.setattr(mpc.benchmark.pareto, "solve_ocp", fake_solve)
    cache = tmp_path / "cache"
    code, out, err = _run(capsys, "train", "--total-timesteps", "512", "--num-envs", "4", "--n-steps", "32",
                          "--batch-size", "128", "--n-epochs", "1", "--eval-freq", "100000", "--eval-episodes", "1",
                          "--checkpoint-freq", "100000", "--no-progress-bar", "--log-dir", tmp_path / "runs",
                          "--run-name", "scored", "--net-arch", "8", "--cache", cache)
    assert code == 0, err
    assert "[service] solving the Pareto front" in err and "[service] minimum time" in err
    assert (front_folder("service", cache=cache) / "front.json").exists()
    assert os.environ.get("WL_CACHE_DIR") != str(cache)  # restored after the run


# ------------------------------------------------------------------------------------------ fuzz
NUMERIC_OPTIONS = [  # (command before the option, option, the value as it reached the work)
    (["ocp", "--objective", "fuel"], "--time", lambda args, kw: kw["T"]),
    (["ocp", "--objective", "weighted"], "--w-fuel", lambda args, kw: kw["w_fuel"]),
    (["evaluate", "--controller", "operator"], "--episodes", lambda args, kw: kw["episodes"]),
    (["evaluate", "--controller", "operator"], "--init-noise", lambda args, kw: kw["init_noise"]),
    (["evaluate", "--controller", "operator"], "--seed", lambda args, kw: kw["seed"]),
    (["mpc"], "--target-time", lambda args, kw: args[1].target_time),
    (["mpc"], "--w-fuel", lambda args, kw: args[1].w_fuel),
    (["mpc"], "--payload-scale", lambda args, kw: (kw["plant_params"] or resolve(None)).M_load),  # None: scale 1
    (["mpc"], "--rolling-scale", lambda args, kw: (kw["plant_params"] or resolve(None)).c_r),
    (["pareto"], "--points", lambda args, kw: kw["n_points"]),
    *[(["train"], "--" + name.replace("_", "-"), lambda args, kw, name=name: getattr(args[0], name))
      for name in ("total_timesteps", "num_envs", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda",
                   "learning_rate", "clip_range", "ent_coef", "net_arch", "eval_episodes", "eval_freq",
                   "curriculum_fraction", "init_noise", "max_time", "time_limit", "w_fuel", "seed")],
]

NUMBER_TEXT = st.one_of(
    st.integers(-1000, 1000).map(str),
    st.integers().map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-2.0, 120.0).map(lambda x: f"{x:g}"),
    st.sampled_from(["--", "-", "nan", "-nan", "inf", "-inf", "1e309", "-1e309", "-0", "0", "1", "0.5", "", " ", "abc", "1,5",
                     "0x10", "1_000", "True", "none", "5e-324", "1e-320"]),
    st.text(alphabet="0123456789.-+eEinfa ", max_size=6),
)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=st.sampled_from(NUMERIC_OPTIONS), text=NUMBER_TEXT)
def test_fuzz_numeric_options_are_accepted_finite_or_rejected_in_one_line(tmp_path, capsys, no_work, case, text):
    """Any text for a numeric option either reaches the work as a finite value or is a one-line error that
    names the option (exit code 2); nothing else (no traceback, no other exit code)."""
    command, option, reached = case
    outs = {"train": ["--log-dir", str(tmp_path / "runs")], "pareto": ["--out", str(tmp_path / "fronts")]}
    argv = [*command, f"{option}={text}", *outs.get(command[0], ["--out", str(tmp_path / "o.json")])]
    no_work.clear()
    code, err = _attempt(capsys, argv)
    event(f"{option} {'accepted' if code is None else 'rejected'}")  # --hypothesis-show-statistics: both happen
    if code is None:  # accepted
        value = reached(*no_work[-1][1:])
        assert all(math.isfinite(v) for v in (value if isinstance(value, tuple) else (value,))), (argv, value)
    else:
        lines = err.strip().splitlines()
        assert code == 2 and not no_work, (argv, code, err)
        assert len(lines) == 1 and lines[0].startswith("wl: error:") and option in lines[0], (argv, err)


# ------------------------------------------------------------------------------------------ suite
def test_suite_solve_writes_each_scenario_resumes_and_assembles(tmp_path, capsys, monkeypatch):
    """`wl suite solve` (solver faked): one checked file per scenario, a rerun solves nothing, a lost entry
    is rebuilt from its cached points (nothing solved twice), and the suite's file holds every entry."""
    from fakes import fake_solve

    import mpc.benchmark.pareto as pareto

    fake_solve.calls = []
    monkeypatch.setattr(pareto, "solve_ocp", fake_solve)
    cache, out = tmp_path / "cache", tmp_path / "nominal.json"
    argv = ["suite", "solve", "--suite", "nominal", "--workers", "1", "--cache", str(cache), "--out", str(out)]
    assert wl.cli.main(argv) == 0, capsys.readouterr().err
    data = json.loads(out.read_text())
    assert sorted(data["entries"]) == sorted(f"{b}_{DEFAULT_PARAMS.fingerprint()}" for b in ("service", "tc"))
    assert all(e["scenario"]["braking"] in ("service", "tc") for e in data["entries"].values())
    parts = sorted((cache / "suites").glob("nominal_*/*.json"))
    assert len(parts) == 2
    n = len(fake_solve.calls)
    assert wl.cli.main(argv) == 0 and len(fake_solve.calls) == n  # resumed: nothing solved again
    parts[0].unlink()
    for f in (cache / "pareto").glob("*/front.json"):  # a sweep killed before its fronts were written
        f.unlink()
    assert wl.cli.main(argv) == 0
    assert len(fake_solve.calls) == n and len(sorted((cache / "suites").glob("nominal_*/*.json"))) == 2
    assert "2 scenarios" in capsys.readouterr().out
    service, tc = sorted((cache / "suites").glob("nominal_*/*.json"))
    tc.write_bytes(service.read_bytes())  # an entry under another scenario's name: set aside and rebuilt, not counted
    assert wl.cli.main(argv) == 0, capsys.readouterr().err
    assert "braking 'service', expected 'tc'" in capsys.readouterr().err and list(tc.parent.glob(f"{tc.name}.bad-*"))
    assert json.loads(out.read_text())["entries"][tc.stem]["braking"] == "tc"


def test_the_horizon_solver_flag_offers_exactly_the_configs_solvers():
    """(The parser names them itself, so that building it imports no CasADi.)"""
    from mpc.controller.mpc import HORIZON_SOLVERS
    from wl.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    flag = next(a for a in sub.choices["mpc"]._actions if "--horizon-solver" in a.option_strings)
    assert tuple(flag.choices) == HORIZON_SOLVERS


def test_the_nominal_ppo_on_another_scenario_warns(capsys, tmp_path):
    """The shipped ppo_<braking> was trained on the paper's cycle alone: asked for another, the CLI says so."""
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--scenario", '{"payload": 7000}', "--episodes", 1,
                        "--no-score", "--out", tmp_path / "other.json")
    assert code == 0 and "nominal cycle only" in err and "--target-ratio" in err
    code, _, err = _run(capsys, "evaluate", "--controller", "ppo", "--episodes", 1, "--no-score",
                        "--out", tmp_path / "nominal.json")
    assert code == 0 and "nominal cycle only" not in err


def test_version_is_the_package_metadata(capsys):
    """`wl --version` and pyproject.toml say the same (they had drifted: 0.2.0 against 0.1.0)."""
    import tomllib

    code, out, _ = _run(capsys, "--version")
    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    assert code == 0 and out.strip() == project["version"]


def test_ctrl_c_while_wl_starts_exits_130_without_a_traceback(monkeypatch, capsys):
    """Ctrl-C in the 0.3-1 s build_parser spends importing the packages printed a traceback (exit -2)."""
    def interrupted() -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(wl.cli, "build_parser", interrupted)
    assert wl.cli.main(["ocp", "--out", "x.json"]) == 130
    assert capsys.readouterr().err.strip() == "wl: interrupted"


def test_a_bad_codegen_mode_is_one_line_before_any_work(tmp_path, capsys, monkeypatch, no_work):
    """$WL_CODEGEN is read where the first NLP is built: `wl` checks it first, naming it and its values."""
    monkeypatch.setenv("WL_CODEGEN", "fast")
    code, err = _attempt(capsys, ["mpc", "--braking", "tc", "--no-score", "--out", str(tmp_path / "o.json")])
    assert code == 2 and not no_work
    assert err.strip() == "wl: error: $WL_CODEGEN must be one of auto, on, off; got 'fast'"


def test_a_dollar_in_a_controllers_name_is_drawn_as_it_is(tmp_path, cache, capsys):
    """A `$` in a controller's name started matplotlib's mathtext: a parse error naming neither file nor field."""
    out = tmp_path / "results"
    results = wl.report.collect(out, cache=str(cache), brakings=("service",), suite_controllers=None,
                                controllers=lambda b: [("operator", lambda: OperatorPolicy(b))])
    results = json.loads(json.dumps(results))
    for r in results["rows"]:
        r["controller"] = "$\\frac{$ " + r["controller"]
    for tr in results["trajectories"]:
        tr["controller"] = "$\\frac{$"
    (out / "results.json").write_text(json.dumps(results))
    capsys.readouterr()
    code, _, err = _run(capsys, "report", "--results", out)
    assert code == 0, err
    assert "$\\frac{$" in (out / "leaderboard.md").read_text()


def test_outputs_and_options_are_checked_before_the_work(tmp_path, capsys):
    """Stop 60's command-line round: `--out newdir/` became a file named newdir; `wl pareto` found a folder in the way
    of its second front's file after solving both, the first written; a 4300-digit --seed failed after the episodes;
    --params naming a field twice kept the last."""
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--episodes", "1", "--no-score",
                        "--out", f"{tmp_path}/newdir/")
    assert code == 2 and "names a folder (its trailing /)" in err and not (tmp_path / "newdir").exists()
    out = tmp_path / "p"
    (out / "pareto_tc.json").mkdir(parents=True)
    (out / "pareto_service.json").write_text('{"old": 1}')
    code, _, err = _run(capsys, "pareto", "--cache", tmp_path / "c", "--out", out)
    assert code == 2 and "pareto_tc.json is a folder" in err
    assert (out / "pareto_service.json").read_text() == '{"old": 1}'
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--episodes", "1", "--no-score",
                        "--seed", "9" * 4000, "--out", tmp_path / "e.json")
    assert code == 2 and "--seed: must be an integer in [0, 2147483647]" in err
    code, _, err = _run(capsys, "mpc", "--params", '{"M_load": 9000, "M_load": 9500}', "--out", tmp_path / "m.json")
    assert code == 2 and "--params: the field 'M_load' is given twice" in err


def test_plot_learning_curve_refuses_a_csv_that_is_no_evaluation_log(tmp_path):
    """A CSV without the evaluation's columns drew an empty plot, exit 0 (stop 60)."""
    import subprocess
    import sys

    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    script = Path(__file__).resolve().parents[1] / "scripts" / "plot_learning_curve.py"
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "x.csv"), "--no-front", "--out", str(tmp_path / "x.png")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "is no evaluation log: it has no step, T, fuel_g column" in r.stderr
    assert not (tmp_path / "x.png").exists()


def test_an_output_that_is_one_of_the_inputs_is_refused_before_the_work(tmp_path, capsys, no_work):
    """`wl evaluate --model P --out P.json` wrote the evaluation over the policy's metadata (the policy was lost, exit
    0); `wl ocp/mpc --scenario s.json --out s.json` over the scenario; a symbolic link to the input too."""
    import shutil

    from agents.evaluate import default_policy_path

    shipped = default_policy_path("service")
    for f in shipped.parent.glob(f"{shipped.stem}*"):
        shutil.copy(f, tmp_path / f.name)
    policy = tmp_path / shipped.stem
    before = (tmp_path / f"{shipped.stem}.json").read_bytes()
    (tmp_path / "link.json").symlink_to(tmp_path / f"{shipped.stem}.json")
    for model, out in ((policy, f"{shipped.stem}.json"), (f"{policy}.safetensors", f"{shipped.stem}_vecnormalize.npz"),
                       (policy, "link.json")):
        code, err = _attempt(capsys, ["evaluate", "--controller", "ppo", "--model", str(model), "--episodes", "1",
                                      "--no-score", "--out", str(tmp_path / out)])
        assert code == 2 and "is the input file" in err and len(err.strip().splitlines()) == 1, err
    assert (tmp_path / f"{shipped.stem}.json").read_bytes() == before
    scenario = tmp_path / "s.json"
    scenario.write_text('{"payload": 12000}')
    for argv in (["ocp"], ["mpc", "--no-score"], ["evaluate", "--controller", "operator"]):
        code, err = _attempt(capsys, [*argv, "--scenario", str(scenario), "--out", str(scenario)])
        assert code == 2 and f"--out {scenario} is the input file" in err, err
    assert scenario.read_text() == '{"payload": 12000}' and not no_work
    code, err = _attempt(capsys, ["ocp", "--scenario", str(scenario), "--out", str(tmp_path / "o.json")])
    assert code is None, err  # (another file is fine)


def test_an_option_given_twice_with_another_value_is_refused(tmp_path, capsys, no_work):
    """argparse kept the last value without a word: `--episodes 1 ... --episodes 100` ran 100 episodes, `--reward
    failure=1 --reward shaping=2` dropped failure, `--score --no-score` did not score."""
    import importlib.util

    for argv, option in ((["evaluate", "--controller", "operator", "--episodes", "1", "--episodes", "100"], "--episodes"),
                         (["evaluate", "--controller", "operator", "--epi", "1", "--episodes", "2"], "--episodes"),
                         (["train", "--reward", "failure=1", "--reward", "shaping=2"], "--reward"),
                         (["train", "--score", "--no-score"], "--score/--no-score"),
                         (["mpc", "--rate-weight", "1", "2", "--rate-weight", "1", "3"], "--rate-weight")):
        code, err = _attempt(capsys, [*argv, "--out" if argv[0] != "train" else "--log-dir", str(tmp_path / "o")])
        assert code == 2 and f"argument {option}: given twice with different values" in err, err
        assert len(err.strip().splitlines()) == 1
    assert not no_work
    # the same value twice is what was meant
    code, err = _attempt(capsys, ["-v", "-v", "evaluate", "--controller", "operator", "--episodes", "2", "--episodes", "2",
                                  "--out", str(tmp_path / "e.json")])
    assert code is None and no_work[-1][2]["episodes"] == 2, err
    path = Path(__file__).resolve().parents[1] / "scripts" / "train_ppo.py"
    spec = importlib.util.spec_from_file_location("train_ppo_script", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    with pytest.raises(SystemExit):
        script.main(["--seed", "1", "--seed", "2", "--log-dir", str(tmp_path)])
    assert "argument --seed: given twice with different values" in capsys.readouterr().err


def test_pareto_takes_the_scenarios_braking_and_refuses_both_beside_it(tmp_path, capsys, no_work):
    """A --scenario naming tc braking: `wl pareto` solved both fronts (and with --braking both said nothing), where
    every other command takes the scenario's braking."""
    code, err = _attempt(capsys, ["pareto", "--scenario", '{"braking": "tc"}', "--braking", "both", "--out", str(tmp_path)])
    assert code == 2 and "--braking both contradicts the --scenario's braking 'tc'" in err and not no_work
    code, err = _attempt(capsys, ["pareto", "--scenario", '{"braking": "tc"}', "--out", str(tmp_path)])
    assert code is None and tuple(no_work[-1][1][0]) == ("tc",), err
    code, err = _attempt(capsys, ["pareto", "--scenario", '{"payload": 9000}', "--out", str(tmp_path)])
    assert code is None and tuple(no_work[-1][1][0]) == ("service", "tc"), err


def test_a_policy_export_or_curve_file_in_the_way_is_refused_before_the_training(tmp_path, capsys, monkeypatch,
                                                                                   no_work):
    """Only the folder of `--export PATH` (and train_plan_policy.py's `--curve`) was checked: a folder at
    PATH.safetensors or CURVE.csv, or a pipe at PATH.json (`wl train`), failed after the whole training."""
    import agents.imitation

    (tmp_path / "e.safetensors").mkdir()
    (tmp_path / "c.csv").mkdir()
    os.mkfifo(tmp_path / "p.json")
    code, err = _attempt(capsys, ["train", "--log-dir", str(tmp_path / "runs"), "--export", str(tmp_path / "p")])
    assert code == 2 and f"--export {tmp_path / 'p'}: {tmp_path / 'p.json'} is not a regular file" in err
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import train_bc
    import train_plan_policy

    monkeypatch.setattr(agents.imitation, "collect_demos", lambda *a, **k: pytest.fail("reached the demonstrations"))
    with pytest.raises(ValueError, match="e.safetensors is a folder"):
        train_bc.main(train_bc.Options(log_dir=str(tmp_path / "runs"), export=str(tmp_path / "e")), "train_bc.py")
    monkeypatch.setattr(train_plan_policy, "train_stages", lambda o: pytest.fail("reached the training"))
    for kw, needle in (({"curve": str(tmp_path / "c")}, "c.csv is a folder"),
                       ({"export": str(tmp_path / "e")}, "e.safetensors is a folder")):
        with pytest.raises(ValueError, match=needle):
            train_plan_policy.main(train_plan_policy.Options(log_dir=str(tmp_path / "runs"), **kw))


@pytest.mark.parametrize("argv, needle", [
    (["bench_draws.py", "--draws", "abc"], "bench_draws: error: Error parsing --draws: invalid literal for int()"),
    (["train_bc.py", "--epochs"], "train_bc: error: "),
    (["train_plan_policy.py", "--cycle", "3"], "train_plan_policy: error: Unrecognized options: --cycle, 3"),
    (["distill_plans.py", "--out", "x"], "distill_plans: error: Missing from"),
    (["select_policy.py", "--by", "gap", "--by", "fuel"], "select_policy: error: argument --by: given twice")])
def test_tyro_scripts_say_a_bad_option_in_one_line(argv, needle):
    """tyro drew its errors as a box of 5-10 lines; each is one line `name: error: ...`, exit 2."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "scripts" / argv[0]
    r = subprocess.run([sys.executable, str(script), *argv[1:]], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "COLUMNS": "40"})
    assert r.returncode == 2 and r.stderr.startswith(needle) and len(r.stderr.splitlines()) == 1, r.stderr


@pytest.mark.parametrize("script, out", [("distill_plans.py", "{stem}"), ("distill_plans.py", "{dir}/link"),
                                         ("select_policy.py", "{stem}.json")])
def test_a_script_refuses_an_output_that_is_its_input_policy(tmp_path, script, out):
    """`distill_plans.py --policy P --out P` distilled for minutes, then wrote over the policy it distils (by any path:
    a link to its metadata too); `select_policy.py --policies P --json P.json` wrote its records over P's metadata."""
    import shutil
    import subprocess
    import sys

    from agents.evaluate import default_policy_path

    shipped = default_policy_path("tc").with_name("plan_target_tc")
    for f in shipped.parent.glob(f"{shipped.name}*"):
        shutil.copy(f, tmp_path / f.name)
    stem = tmp_path / shipped.name
    (tmp_path / "link.json").symlink_to(f"{stem}.json")
    before = {f.name: f.read_bytes() for f in tmp_path.glob(f"{shipped.name}*")}
    out = out.format(stem=stem, dir=tmp_path)
    argv = (["--policy", f"{stem}.safetensors", "--out", out] if script == "distill_plans.py"
            else ["--policies", f"{stem}.safetensors", "--json", out, "--draws", "1"])
    r = subprocess.run([sys.executable, str(Path(__file__).resolve().parents[1] / "scripts" / script), *argv],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "is the input file" in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr
    assert {f.name: f.read_bytes() for f in tmp_path.glob(f"{shipped.name}*")} == before


# ------------------------------------------------------------------------------------------ hostile-input round (wl, report)
def _run_report_results(tmp_path: Path, cache: Path, capsys) -> Path:
    """A results.json of `wl run` (one braking, the operator only), in tmp_path/results."""
    out = tmp_path / "results"
    wl.report.collect(out, cache=str(cache), brakings=("service",), suite_controllers=None,
                      controllers=lambda b: [("operator", lambda: OperatorPolicy(b))])
    capsys.readouterr()
    return out


def test_a_report_file_that_is_the_results_json_by_a_link_is_refused(tmp_path, cache, capsys):
    """`wl report` wrote its leaderboard over results.json through a link named leaderboard.md (exit 0: the run's
    results were gone), and with --out over another folder's results.json through a link named pareto.png."""
    out = _run_report_results(tmp_path, cache, capsys)
    before = (out / "results.json").read_bytes()
    (out / "leaderboard.md").symlink_to("results.json")
    code, _, err = _run(capsys, "report", "--results", out)
    assert code == 2 and "leaderboard.md is the input file" in err and len(err.strip().splitlines()) == 1
    assert (out / "results.json").read_bytes() == before
    (out / "leaderboard.md").unlink()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "pareto.png").symlink_to(out / "results.json")
    code, _, err = _run(capsys, "report", "--results", out, "--out", elsewhere)
    assert code == 2 and "pareto.png is the input file" in err
    assert (out / "results.json").read_bytes() == before and not (elsewhere / "leaderboard.md").exists()
    (elsewhere / "pareto.png").unlink()
    (elsewhere / "results.json").write_text("another run's")  # (--out's own results.json is no report file either)
    (elsewhere / "trajectories_service.png").symlink_to("results.json")
    code, _, err = _run(capsys, "report", "--results", out, "--out", elsewhere)
    assert code == 2 and (elsewhere / "results.json").read_text() == "another run's"


def test_a_huge_or_irregular_results_json_is_refused_before_it_is_read(tmp_path, capsys):
    """A 2 GB results.json was read whole (4 GB, 10 s) before "not valid JSON"; a pipe there was "no results.json"."""
    folder = tmp_path / "r"
    folder.mkdir()
    with open(folder / "results.json", "wb") as fh:  # (sparse: no disk, no time)
        fh.truncate(wl.report.MAX_RESULTS_BYTES + 1 if hasattr(wl.report, "MAX_RESULTS_BYTES") else 64 * 2**20 + 1)
    t0 = time.perf_counter()
    code, _, err = _run(capsys, "report", "--results", folder)
    assert code == 2 and "bytes, more than a results.json" in err and time.perf_counter() - t0 < 1.0
    (folder / "results.json").unlink()
    os.mkfifo(folder / "results.json")
    code, _, err = _run(capsys, "report", "--results", folder)
    assert code == 2 and "results.json is not a regular file" in err


def test_an_interrupt_while_the_report_is_put_in_place_leaves_it_whole(tmp_path, cache, capsys, monkeypatch):
    """Ctrl-C between two of the report's files as they were moved into --out left the new leaderboard beside the old
    figures: the interrupt is taken once every file is in place (exit 130)."""
    import signal

    out = _run_report_results(tmp_path, cache, capsys)
    names = ["leaderboard.md", "pareto.png", "trajectories_service.png"]
    for name in names:
        (out / name).write_text("old")
    real = os.path.realpath
    seen = []

    def realpath(path, *args, **kwargs):  # the second look at pareto.png: where it is put in place
        if str(path) == str(out / "pareto.png"):
            seen.append(path)
            if len(seen) == 2:
                os.kill(os.getpid(), signal.SIGINT)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(os.path, "realpath", realpath)
    code, _, err = _run(capsys, "report", "--results", out)
    monkeypatch.undo()
    assert code == 130 and len(seen) >= 2
    old = [name for name in names if (out / name).read_bytes() == b"old"]
    assert old in ([], names), old  # all new or all old, never a mix
    assert [f.name for f in out.iterdir() if f.name.startswith(".")] == []


def test_a_scenario_file_larger_than_any_scenario_is_refused_by_its_size(tmp_path, capsys, no_work):
    """A 3 GB --scenario file was read whole (6 GB, 20 s); 2 MiB of spaces around {} was taken as the nominal cycle."""
    big = tmp_path / "big.json"
    big.write_text(" " * (2 * 2**20) + "{}")
    for argv in (["ocp"], ["mpc"], ["evaluate", "--controller", "operator"], ["pareto"]):
        code, err = _attempt(capsys, [*argv, "--scenario", str(big), "--out", str(tmp_path / "o")])
        assert code == 2 and "--scenario file" in err and "bytes, more than a scenario" in err, (argv, err)
    small = tmp_path / "small.json"
    small.write_text(' {"payload": 12000} ')
    code, _ = _attempt(capsys, ["ocp", "--scenario", str(small), "--out", str(tmp_path / "o.json")])
    assert code is None


def test_a_sampler_suite_without_sample_names_the_option(tmp_path, capsys, no_work):
    """`wl evaluate --suite train` said "suite 'train' is a sampler: say how many scenarios to draw", naming no option."""
    code, err = _attempt(capsys, ["evaluate", "--controller", "operator", "--suite", "train", "--out",
                                  str(tmp_path / "e.json")])
    assert code == 2 and "--sample N" in err and "--suite train" in err
    code, _ = _attempt(capsys, ["evaluate", "--controller", "operator", "--suite", "train", "--sample", "2",
                                "--out", str(tmp_path / "e.json")])
    assert code is None


def test_no_solve_with_perturbed_episodes_is_refused_before_any_episode(tmp_path, capsys, no_work):
    """--no-solve with perturbed starts (the default --episodes 10 --init-noise 1) ran episode 0 and then failed on
    episode 1's optimum, which no shipped or cached front holds."""
    base = ["evaluate", "--controller", "operator", "--no-solve", "--out", str(tmp_path / "e.json")]
    for extra in ([], ["--episodes", "3"]):
        code, err = _attempt(capsys, base + extra)
        assert code == 2 and "--no-solve" in err and "--init-noise" in err, err
    for extra in (["--episodes", "1"], ["--episodes", "3", "--init-noise", "0"], ["--episodes", "3", "--no-score"],
                  ["--suite", "test", "--sample", "2"]):
        code, err = _attempt(capsys, base + extra)
        assert code is None, (extra, err)


TARGET_CONTROLLER = '''
from agents.operator import OperatorPolicy


class Targeted(OperatorPolicy):
    def reset(self, scenario=None, target_time=None):
        super().reset(scenario)
'''


def test_the_evaluation_file_records_its_sample_and_target(tmp_path, capsys):
    """A file of `wl evaluate --target-ratio 1.2` did not say it was run at a target ratio (nor --sample, nor
    --target-time): only each episode's target time in seconds."""
    module = tmp_path / "targeted.py"
    module.write_text(TARGET_CONTROLLER)
    out = tmp_path / "e.json"
    code, _, err = _run(capsys, "evaluate", "--controller", f"{module}:Targeted", "--episodes", "1", "--no-score",
                        "--target-ratio", "1.2", "--out", out)
    assert code == 0, err
    r = json.loads(out.read_text())
    assert (r["target_ratio"], r["target_time"], r["sample"]) == (1.2, None, None)
    assert r["per_episode"][0]["target_time"] > 1.2 * 7  # (1.2 times the nominal cycle's T_min, 8.17 s)
    code, _, err = _run(capsys, "evaluate", "--controller", "operator", "--suite", "test", "--sample", "1",
                        "--no-score", "--out", out)
    assert code == 0, err
    r = json.loads(out.read_text())
    assert (r["suite"], r["sample"], r["target_ratio"], r["target_time"]) == ("test", 1, None, None)


@pytest.mark.parametrize("in_the_way", ["results.json", "pareto.png", "suite_gaps.png", "link"])
def test_wl_run_checks_every_file_it_writes_before_the_work(tmp_path, capsys, no_work, in_the_way):
    """`wl run --out R` with a folder at R/results.json or R/pareto.png ran every controller (5-10 min), then failed;
    a link R/leaderboard.md -> results.json had the leaderboard written over the results."""
    out = tmp_path / "R"
    out.mkdir()
    if in_the_way == "link":
        (out / "leaderboard.md").symlink_to("results.json")
    else:
        (out / in_the_way).mkdir()
    code, err = _attempt(capsys, ["run", "--out", str(out)])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert ("leaderboard.md is the input file" if in_the_way == "link" else f"{in_the_way} is a folder") in err
    code, _ = _attempt(capsys, ["run", "--out", str(tmp_path / "fresh")])
    assert code is None


# ---------------------------------------------------------------------------------------------------------------------
# Eleventh review round (`wl train --seeds/--sweep --export`): each test fails on the code before its fix.
# ---------------------------------------------------------------------------------------------------------------------
def test_the_export_files_of_several_runs_are_checked_before_the_training(tmp_path, capsys, no_work):
    """`wl train --seeds 0 1 --export P` writes P_<run name>.* per run, but only P.* was checked: a folder in the way
    of P_ppo_service_s1.safetensors failed after every run had trained. Each run's files are checked first."""
    (tmp_path / "P_ppo_service_s1.safetensors").mkdir()
    (tmp_path / "Q_ppo_tc_n_epochs3_s0.json").mkdir()
    runs = str(tmp_path / "runs")
    code, err = _attempt(capsys, ["train", "--seeds", "0", "1", "--log-dir", runs, "--export", str(tmp_path / "P")])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"--export {tmp_path / 'P_ppo_service_s1'}: {tmp_path / 'P_ppo_service_s1.safetensors'} is a folder" in err
    code, err = _attempt(capsys, ["train", "--braking", "tc", "--sweep", "n_epochs=2,3", "--log-dir", runs,
                                  "--export", str(tmp_path / "Q")])
    assert code == 2 and "Q_ppo_tc_n_epochs3_s0.json is a folder" in err, err
    assert not no_work
    code, _ = _attempt(capsys, ["train", "--seeds", "0", "1", "--log-dir", runs, "--export", str(tmp_path / "R")])
    assert code is None and [c[0] for c in no_work] == ["train"]  # (the rest reaches the training)


def test_a_controller_file_that_is_a_folder_is_named_a_folder(tmp_path, capsys, no_work):
    """`wl evaluate --controller /tmp:X` said "no controller file /tmp" of a folder that is there: it says it is a
    folder (one line, exit 2); a missing file is still "no controller file"."""
    out = str(tmp_path / "x.json")
    code, err = _attempt(capsys, ["evaluate", "--controller", f"{tmp_path}:X", "--out", out])
    assert code == 2 and err.strip() == (f"wl: error: controller file {tmp_path} is a folder, not a Python file (from "
                                         f"--controller {tmp_path}:X)"), err
    code, err = _attempt(capsys, ["evaluate", "--controller", f"{tmp_path}/c.py:X", "--out", out])
    assert code == 2 and f"no controller file {tmp_path}/c.py" in err
    assert not no_work
