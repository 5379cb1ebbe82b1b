"""Stop 63's hostile-input round on the MPC's and the benchmark's library API: each test fails on the code before
its fix (docs/reliability.md lists the earlier rounds)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

import mpc.benchmark.suite as suite_module
from mpc.benchmark.ocp import OCPError
from mpc.benchmark.reference import shipped_fronts
from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop
from mpc.controller.solver import IpoptSolver
from wl_env.rollout import EpisodeResult

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _fake_episode(env, controller, seed=None, trajectory=True, scenario=None, target_time=None) -> EpisodeResult:
    """A cycle not completed (nothing scored), without a step driven: what the run records is under test."""
    return EpisodeResult(seed, 40.0, 100.0, False, False, True, False, False, -1.0, None, 1.0, 1.0, 0.0)


def test_run_closed_loop_records_the_given_controllers_config_and_refuses_another(monkeypatch):
    """A given controller drove with its own config, but the result recorded MPCConfig() (mode "time", no target: a
    target-time run written down as a minimum-time one); a config or solver given beside it was dropped unsaid."""
    import wl_env.rollout

    monkeypatch.setattr(wl_env.rollout, "run_episode", _fake_episode)
    targeted = MPCConfig(mode="target_time", target_time=12.0)
    ctrl = MPCController("service", config=targeted)
    r = run_closed_loop(controller=ctrl, score=False)
    assert r.config == targeted
    d = r.to_dict()
    assert d["mode"] == "target_time" and d["target_time"] == 12.0
    assert run_closed_loop("service", targeted, controller=ctrl, score=False).config == targeted  # (the same: taken)
    with pytest.raises(ValueError, match="config .* is not the given controller's"):
        run_closed_loop("service", MPCConfig(mode="time"), controller=ctrl, score=False)
    with pytest.raises(ValueError, match="solver is the given controller's own"):
        run_closed_loop("service", controller=ctrl, solver=IpoptSolver(50), score=False)


def _entry_or_failure(scenario, cache, n_points):
    """A suite solve's job: the shipped entry, but the service cycles' first scenario fails as a solve can."""
    key = suite_module.entry_key(scenario)
    if scenario.braking == "service" and not _entry_or_failure.failed:
        _entry_or_failure.failed = True
        raise OCPError(f"no front: the minimum-time cycle fails its re-simulation (Restoration_Failed) [{key}]")
    return {**shipped_fronts()[key].__dict__, "scenario": scenario.to_dict(), "solve_s": 0.0}


_entry_or_failure.failed = False


def test_a_shipped_optimum_whose_fresh_solve_fails_is_no_agreement(tmp_path, monkeypatch):
    """`wl suite solve --check`: a scenario no fresh solve could do was left out of the rows, so 4 scenarios checked
    with one failure read "3 of 3 shipped optima agree", exit 0."""
    solve_suite = suite_module.solve_suite
    _entry_or_failure.failed = False
    monkeypatch.setattr(suite_module, "solve_suite", lambda *a, **k: solve_suite(
        *a, **{**k, "workers": 1, "job": f"{__name__}:_entry_or_failure"}))
    rows = suite_module.check_shipped("test", cache=str(tmp_path / "cache"), limit=2, workers=1)
    assert len(rows) == 4
    bad = [r for r in rows if not r["ok"]]
    assert len(bad) == 1 and bad[0]["key"].startswith("service_") and "Restoration_Failed" in bad[0]["problem"]


@pytest.mark.parametrize("out, needle", [
    ("{folder}", "is a folder"), ("", "must name a file"), (5, "out must be a file path or None, got 5"),
    ("/dev/null", "not a regular file"), ("{file}/x.json", "is not a folder")])
def test_a_suite_files_path_is_checked_before_any_solve(tmp_path, monkeypatch, out, needle):
    """solve_suite(out=...) wrote the suite's file only after every scenario was solved (hours): a folder, a device or
    a path under a file there failed then, and an out that is no path was a TypeError."""
    (tmp_path / "file").write_text("")

    def never(*args):
        raise AssertionError("a solve ran before the out check")

    monkeypatch.setattr(suite_module, "_never", never, raising=False)
    if isinstance(out, str):
        out = out.format(folder=tmp_path, file=tmp_path / "file")
    with pytest.raises(ValueError, match=needle):
        suite_module.solve_suite("test", cache=str(tmp_path / "cache"), out=out, limit=1, workers=1,
                                 job="mpc.benchmark.suite:_never")
    assert not os.path.exists(tmp_path / "cache" / "suites" / "test.json")


def test_a_minimum_time_cycle_that_fails_its_re_simulation_is_no_optimum(tmp_path, monkeypatch):
    """min_time_result (`wl run`'s "optimum (min time)" row and trajectory) returned a cycle that failed its
    re-simulation, solved there or cached by a sweep that then refused it as its front's end, without a word."""
    import dataclasses

    from fakes import fake_solve

    import mpc.benchmark.pareto as pareto
    from mpc.benchmark.verify import CHECK_VERSION

    failed = dataclasses.replace(fake_solve("tc"), success=False, status="Solve_Succeeded (re-simulation check failed)",
                                 verification={"passed": False, "check_version": CHECK_VERSION})
    monkeypatch.setattr(pareto, "solve_ocp", lambda *a, **k: dataclasses.replace(failed))
    with pytest.raises(OCPError, match=r"no verified tc minimum-time cycle: .*re-simulation check failed"):
        pareto.min_time_result("tc", cache=tmp_path)
    path = pareto.front_folder("tc", cache=tmp_path) / "min_time.json"
    assert not path.exists()  # (nothing cached of it)
    pareto.save_result(failed, path)  # as a sweep caches its end before refusing it
    with pytest.raises(OCPError, match="no verified tc minimum-time cycle"):
        pareto.min_time_result("tc", cache=tmp_path)
    good = fake_solve("tc")
    monkeypatch.setattr(pareto, "solve_ocp", lambda *a, **k: good)
    assert pareto.min_time_result("tc", cache=tmp_path).success  # (solved again, and cached so)
    assert pareto.cached_result(path, objective="time", braking="tc").success
