"""Follow-ups of the eleventh hostile round (stop 63) in the scripts, `wl report` and the benchmark's fronts: each
test fails on the code before its fix."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fakes import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"


def _script(name: str):
    return load_script(name, "s63f_")


def _refused(argv: list[str], needle: str, timeout: float = 90) -> None:
    r = subprocess.run([sys.executable, str(SCRIPTS / argv[0]), *argv[1:]], capture_output=True, text=True,
                       timeout=timeout, cwd=ROOT)
    assert r.returncode == 2 and needle in r.stderr and "Traceback" not in r.stderr, r.stderr


# ------------------------------------------------------------------------------- a value given twice in a list
@pytest.mark.parametrize("argv, needle", [
    (["bench_safety_stale.py", "--every", "3", "3"], "--every names a value twice: 3 and 3"),
    (["bench_safety_stale.py", "--braking", "tc", "tc"], "--braking names a braking alternative twice"),
    (["bench_estimator.py", "--braking", "tc", "tc"], "--braking names a braking alternative twice"),
    (["bench_mpc_memory.py", "--braking", "tc", "tc"], "--braking names a braking alternative twice"),
    (["bench_env.py", "--num-envs", "64", "64"], "--num-envs names a size twice"),
    (["bench_rti_qp.py", "--solvers", "osqp", "osqp"], "--solvers names a QP solver twice"),
    (["bench_mpc_derivatives_ab.py", "--variants", "mapped", "mapped"], "--variants names a variant twice"),
    (["bench_agents.py", "--suite", "test", "--runs", "agents/policies/plan_target_service",
      "agents/policies/../policies/plan_target_service"], "--runs names a run twice"),
    (["bench_plan_ceiling.py", "--ratios", "1.15", "1.150"], "--ratios names a ratio twice: 1.15 and 1.15"),
    (["bench_plan_ceiling.py", "--scenarios", "0", "1", "0"], "--scenarios names a scenario twice: 0 and 0")])
def test_a_script_refuses_a_value_given_twice_in_a_list_before_any_work(argv, needle):
    """Each ran that value's work twice and counted its rows twice in the summaries (bench_plan_ceiling searched a
    scenario twice, bench_safety_stale ran every cycle of an --every twice; bench_mpc_derivatives_ab dropped it
    without a word)."""
    _refused(argv, needle)


def test_the_tyro_scripts_refuse_a_value_given_twice_in_their_lists():
    """The same check in the scripts whose options are a dataclass (checked before any run), and the three copies
    it replaced (bench_mpc, bench_draws, bench_far_starts) and select_policy's say what they said."""
    cases = [
        ("bench_mumps_ordering.py", "check", {"brakings": ("tc", "tc")}, "--brakings names a braking alternative twice"),
        ("bench_replan_lag.py", "check", {"brakings": ("service", "service")}, "--brakings names a braking alternative"),
        ("bench_planning.py", "check", {"reference_starts": (0.3, 0.30)}, "--reference-starts names a start twice"),
        ("bench_draws.py", "check", {"modes": ("1.15", "time", "1.150")}, "--modes names a mode twice: 1.15 and 1.150"),
        ("bench_far_starts.py", "run", {"brakings": ("tc", "tc")}, "--brakings names a braking alternative twice"),
        ("select_policy.py", "check", {"policies": ["a.safetensors", "./a.safetensors"]}, "--policies names a policy twice"),
    ]
    for name, fn, options, needle in cases:
        script = _script(name)
        with pytest.raises(ValueError, match=needle.replace("(", r"\(")):
            getattr(script, fn)(script.Options(**options))
    from agents.train_cli import refuse_repeated_values

    refuse_repeated_values("--x", [1, 2, 3])  # (distinct values pass)
    refuse_repeated_values("--x", None)
    with pytest.raises(ValueError, match=r"--x names a value twice: 1 and 1.0; 2 and 2 \(give each once\)"):
        refuse_repeated_values("--x", [1, 2, 1.0, 2])


def test_bench_plan_ceiling_checks_its_lists_before_any_search(monkeypatch):
    script = _script("bench_plan_ceiling.py")

    def never(*args):
        raise AssertionError("a search began")

    monkeypatch.setattr(script, "search", never)
    for options in ({"ratios": (1.15, 1.5, 1.15)}, {"scenarios": (2, 2)}):
        with pytest.raises(ValueError, match="names a (ratio|scenario) twice"):
            script.main(script.Options(**options))
    script.check(script.Options(scenarios=(0, 1), ratios=(1.0, 1.15)))  # (distinct: as before)


# ------------------------------------------------------------------------------- bench_assist_cost's allocation
def test_bench_assist_cost_bounds_a_rounds_actions_by_name():
    """`--steps 1000000 --num-envs 16384` asked numpy for 131 GB of actions: a MemoryError's traceback."""
    _refused(["bench_assist_cost.py", "--steps", "1000000", "--num-envs", "16384"],
             "--steps x --num-envs must be at most 10,000,000 env-steps per round")
    _refused(["bench_assist_cost.py", "--steps", "700", "--num-envs", "16384"], "got 700 x 16384 = 11,468,800")


# ------------------------------------------------------------------------------- resolve_unverified_points --suite
def test_resolve_unverified_points_reads_and_writes_only_a_shipped_suite_file(tmp_path, monkeypatch):
    """`--suite ../../x --write` read mpc/x.json (any path, by ../) and rewrote it when a point was spliced in."""
    from mpc.benchmark.reference import REFERENCE_DIR

    script = _script("resolve_unverified_points.py")
    outside = tmp_path / "suite.json"
    outside.write_bytes((REFERENCE_DIR / "nominal.json").read_bytes())  # (no unverified point: nothing to solve)
    before = outside.read_bytes()
    relative = os.path.relpath(outside.with_suffix(""), REFERENCE_DIR)
    assert (REFERENCE_DIR / f"{relative}.json").resolve() == outside.resolve()

    def never(*args, **kwargs):
        raise AssertionError("a point was solved")

    monkeypatch.setattr(script, "solve_ocp", never)
    for suite in (relative, "train", "", "nominal/../test", str(outside.with_suffix(""))):
        with pytest.raises(ValueError, match=r"--suite must name a suite with a shipped file \(nominal, test\)"):
            script.run(script.Options(suite=suite, write=True))
    assert outside.read_bytes() == before
    assert script.shipped_suite_file("test") == REFERENCE_DIR / "test.json"


# ------------------------------------------------------------------------------- wl report: names in the table
def _cells(line: str) -> int:
    """The cells of a markdown table row (a ``|`` escaped by a backslash, or a backslash escaped, splits none)."""
    n, i = 0, 0
    while i < len(line):
        if line[i] == "\\":
            i += 2
            continue
        n += line[i] == "|"
        i += 1
    return n - 1


def test_a_controller_name_with_a_newline_or_a_bar_stays_in_its_cell_of_the_leaderboard():
    """A name with a newline ended its row (the rest a line of its own), a `|` split its cell: every column after
    it shifted. Each is shown in its cell; a name without them is written as before."""
    from wl.report import suite_table

    row = {"braking": "tc", "target": "1.15 | T_min\n", "scenarios": 2, "success_rate": 1.0, "time_gap_median": 0.1,
           "time_gap_p90": 0.2, "fuel_gap_median": 0.01, "fuel_gap_p90": 0.02, "lateness_median": 0.0,
           "max_violation": 0.0}
    suite = {"suite": "test\n## injected", "version": 1, "full": True, "scenarios_per_braking": 2, "sample": None,
             "rows": [{**row, "controller": "evil | name\nnext line \\|"}, {**row, "controller": "ppo (plan)",
                                                                            "target": "fastest"}]}
    lines = suite_table(suite)
    table = [line for line in lines if line.startswith("|")]
    assert len(table) == 4 and {_cells(line) for line in table} == {11}
    assert "| evil \\| name next line \\\\\\| | tc | 1.15 \\| T_min  | 2 |" in lines[-2]
    assert lines[-1].startswith("| ppo (plan) | tc | fastest | 2 | 100 % |")  # (as before)
    assert not any(line.startswith("## injected") for line in lines)


def test_the_run_leaderboard_keeps_a_hostile_controller_name_in_its_cell(tmp_path, monkeypatch):
    """`wl report` of a results.json whose row's controller is 'a|b\\nc': the table's rows keep 8 cells each."""
    import wl.report

    captured = {}
    real = wl.report.write_atomic

    def keep(path, text, *args, **kwargs):
        if Path(path).name == "leaderboard.md":
            captured["text"] = text
        return real(path, text, *args, **kwargs)

    monkeypatch.setattr(wl.report, "write_atomic", keep)
    results = _results()
    results["rows"][0]["controller"] = "a|b\nc"
    wl.report.render(results, tmp_path / "out")
    table = [line for line in captured["text"].splitlines() if line.startswith("|")]
    assert {_cells(line) for line in table} == {8} and any(line.startswith("| a\\|b c | service |") for line in table)


def _results() -> dict:
    """A minimal results.json of `wl run` (one braking, one controller), as render takes it."""
    from mpc.benchmark.reference import shipped_fronts
    from wl.report import RESULTS_FORMAT
    from wl_env.params import DEFAULT_PARAMS

    front = shipped_fronts()["service_" + DEFAULT_PARAMS.fingerprint()]
    t = np.linspace(0.0, 8.0, 9).tolist()
    states = [[200.0, 0.0, 0.7, 0.0]] * 9
    return {"format": RESULTS_FORMAT, "brakings": ["service"], "fronts": {"service": dict(front.__dict__)},
            "optima": {"service": {"t": t, "states": states}}, "wall_time_s": 1.0,
            "rows": [{"controller": "operator", "braking": "service", "T": 9.0, "fuel_g": 70.0, "time_gap": 0.1,
                      "fuel_gap": 0.05, "max_violation": 0.0, "success": True, "completed": True}],
            "trajectories": [{"controller": "operator", "braking": "service", "t": t, "states": states}]}


# ------------------------------------------------------------------------------- train_plan_policy --curve
def test_a_failed_learning_curve_plot_is_one_error_naming_the_kept_runs(tmp_path):
    """The plot's subprocess failing after the training was a CalledProcessError's traceback, saying neither why
    nor where the trained stages were."""
    script = _script("train_plan_policy.py")
    o = script.Options(braking="tc", seed=3, log_dir=str(tmp_path), cycles=(16, 16), log_std_init=(-1.0, -3.0),
                       log_std_final=(-3.5, -4.0), num_envs=8, eval_freq=16, eval_episodes=1, checkpoint_freq=8,
                       score=False, curve=str(tmp_path / "curve"))
    runs = [cfg.run_dir for cfg in script.stage_configs(o)]
    for run in runs:
        run.mkdir(parents=True)
        (run / "eval.csv").write_text("step,wall_time,T,fuel_g\n0,0.5,12.0,60.0\n16,1.5,11.0,58.0\n")
    (tmp_path / "curve.png").mkdir()  # (in the plot's way: plot_learning_curve.py refuses it, exit 2)
    summaries = [{"num_timesteps": 16, "wall_time": 1.5}] * 2
    with pytest.raises(ValueError) as caught:
        script.write_curve(o, summaries, Path(o.curve))
    message = str(caught.value)
    assert "plotting the learning curve failed (plot_learning_curve.py exit 2" in message and "--out" in message
    assert all(str(run) in message for run in runs) and str(tmp_path / "curve.csv") in message
    from agents.ppo import read_eval_csv

    assert [r["step"] for r in read_eval_csv(tmp_path / "curve.csv")] == [0, 16, 32]  # (the rows are kept)


# ------------------------------------------------------------------------------- bench_mpc_memory's child processes
def test_bench_mpc_memory_says_a_failed_cycle_process_in_one_error(monkeypatch, tmp_path):
    """A cycle's process that failed was a CalledProcessError's traceback; its own error was not shown."""
    script = _script("bench_mpc_memory.py")
    ran = []

    def child(cmd, check=False, **kwargs):
        ran.append(cmd)
        done = subprocess.CompletedProcess(cmd, 2, "", "bench_mpc_memory: error: the solver ran out of memory\n")
        if check:
            done.check_returncode()
        return done

    monkeypatch.setattr(script.subprocess, "run", child)
    monkeypatch.setattr(sys, "argv", ["bench_mpc_memory.py", "--braking", "tc", "--json", str(tmp_path / "m.json")])
    with pytest.raises(ValueError, match=r"the tc cycle's process \(full horizon\) failed \(nothing written\): exit 2: "
                                         r"bench_mpc_memory: error: the solver ran out of memory"):
        script.main()
    assert len(ran) == 1 and not (tmp_path / "m.json").exists()


# ------------------------------------------------------------------------------- a front without its parameters
def test_a_front_kept_in_a_file_must_name_its_parameters(tmp_path):
    """check_front_of matches a front with an empty params_fingerprint to any cycle (for fronts built in memory):
    such a front saved and loaded again scored another scenario's cycle (10 s, 60 g of the heavy, rough scenario
    against the nominal front). A file's front must name its parameters: saving, loading, caching or shipping
    one without them is refused by name; a front built in memory is still matched by its braking only."""
    from mpc.benchmark import store
    from mpc.benchmark.pareto import FRONT_KIND, ParetoFront, check_front_of
    from mpc.benchmark.reference import check_suite_file, shipped_fronts
    from mpc.benchmark.scoring import score_run
    from wl_env.params import DEFAULT_PARAMS

    nominal = shipped_fronts()["service_" + DEFAULT_PARAMS.fingerprint()]
    blank = ParetoFront(**{**nominal.__dict__, "params_fingerprint": ""})
    other = DEFAULT_PARAMS.variant(payload_scale=1.2, rolling_scale=1.3)
    with pytest.raises(ValueError, match="field 'params_fingerprint' is empty"):
        blank.save(tmp_path / "front.json")
    assert not (tmp_path / "front.json").exists()
    store.write_entry(tmp_path / "front.json", FRONT_KIND, dict(blank.__dict__), lambda d: None)  # (made by hand)
    with pytest.raises(store.BadEntry, match=r"front.json: field 'params_fingerprint' is empty"):
        ParetoFront.load(tmp_path / "front.json")
    entry = {**nominal.__dict__, "params_fingerprint": ""}
    assert "params_fingerprint' is empty" in check_suite_file(
        {"suite": "x", "suite_version": 1, "cache_version": 1, "n_points": 10, "entries": {"service_": entry}})
    # built in memory: matched by its braking only, as before; a front of named other parameters is refused
    check_front_of(blank, "service", other)
    assert score_run(10.0, 60.0, "service", params=other, front=blank, solve=False).reference == "given front"
    with pytest.raises(ValueError, match="a cycle is scored against its own optimum only"):
        check_front_of(nominal, "service", other)
    loaded = ParetoFront.load(nominal.save(tmp_path / "nominal.json"))  # (a front that names them: as before)
    assert loaded == nominal
    check_front_of(loaded, "service", DEFAULT_PARAMS)
