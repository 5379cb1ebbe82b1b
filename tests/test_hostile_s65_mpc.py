"""Stop 65's hostile-input round on the `mpc` package's API (the MPC, the benchmark, its cache and the workers): each
test's docstring says what the code before its fix did (docs/reliability.md lists the earlier rounds)."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from fakes import fake_solve

import mpc.benchmark.pareto as pareto
import mpc.benchmark.reference as reference
import mpc.workers as workers
from mpc.benchmark import store
from mpc.benchmark.ocp import check_cycle_time, solve_ocp
from mpc.benchmark.optima import optima_folder
from mpc.benchmark.verify import CHECK_VERSION, verify_result
from mpc.controller.solver import FallbackSolver, IpoptSolver, SqpRtiSolver
from wl_env.params import LoaderParams


@pytest.fixture
def fake(monkeypatch):
    """The expensive solve replaced by :func:`fakes.fake_solve` (the cache's load and write paths are the real ones)."""
    fake_solve.calls = []
    monkeypatch.setattr(pareto, "solve_ocp", fake_solve)
    monkeypatch.setattr(reference, "solve_ocp", fake_solve)
    return fake_solve


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_front_whose_scenario_fields_are_no_cycle_is_set_aside_not_a_keyerror(tmp_path, caplog):
    """A front entry's `scenario_fields` were not checked: {"x": 1} (checksum and all) in any front folder of the
    machine was a bare KeyError in `nearest_front`, so every other scenario's `pareto_front` failed before its first
    solve. It is a bad entry now: set aside with a warning, and refused at write."""
    shipped = reference.shipped_fronts()["service_" + LoaderParams().fingerprint()]
    bad = {**shipped.__dict__, "scenario_fields": {"x": 1.0}}
    folder = tmp_path / "pareto" / f"service_0123456789abcdef_n{len(shipped.T)}_{pareto.CACHE_VERSION}"
    store.write_entry(folder / "front.json", pareto.FRONT_KIND, bad, lambda d: None)  # (made by hand)
    with caplog.at_level(logging.WARNING):
        assert pareto.nearest_front("service", len(shipped.T), LoaderParams(M_load=3000.0), tmp_path) is None
    assert any("scenario_fields" in w and "front.json" in w for w in _warnings(caplog))
    assert list(folder.glob("front.json.bad-*"))
    with pytest.raises(ValueError, match="scenario_fields"):
        pareto.ParetoFront(**bad).save(tmp_path / "f.json")
    assert not pareto.check_front(store.as_read(shipped.__dict__))  # (a good one as before)


def test_a_cached_minimum_time_cycle_that_fails_its_re_simulation_is_solved_again(tmp_path, fake):
    """`direct_min_time` (so `min_time_of` and every score of a cycle without a known front) returned a cached
    minimum-time cycle that failed its re-simulation (success False) as the cycle's T_min. It is solved again."""
    p = LoaderParams(M_load=3000.0)
    failed = fake_solve("service", "time", params=p)
    failed.T, failed.success, failed.status = 6.0, False, "Solve_Succeeded (re-simulation check failed)"
    failed.verification = {"passed": False, "check_version": CHECK_VERSION, "fine_mesh_failed": True}
    pareto.save_result(failed, optima_folder("service", p, tmp_path) / "min_time.json")
    fake.calls = []
    r = reference.direct_min_time("service", p, tmp_path)
    assert r.success and r.T == 7.0 and fake.calls
    assert reference.min_time_of("service", p, tmp_path) == 7.0


def test_float32_cycle_times_and_weights_are_taken_as_the_numbers_they_print(monkeypatch):
    """`solve_ocp(T=np.float32(9.1))` solved for, and recorded, 9.1000003815 s (`w_fuel` float32 0.3 as
    0.30000001192); `check_cycle_time` and `optimal_fuel_at` took float32 times by their binary value too, where
    `score_run` takes the number written (stop 64)."""
    import mpc.benchmark.ocp as ocp

    seen = []
    monkeypatch.setattr(ocp, "_solve_on_mesh", lambda braking, objective, T, w_fuel, *rest: seen.append((T, w_fuel)))
    solve_ocp("service", "fuel_at_time", T=np.float32(9.1), verify=False)
    solve_ocp("service", "weighted", w_fuel=np.float32(0.3), verify=False)
    assert seen == [(9.1, None), (None, 0.3)]
    assert check_cycle_time(np.float32(9.1)) == 9.1
    front = reference.shipped_fronts()["service_" + LoaderParams().fingerprint()]
    assert pareto.optimal_fuel_at(np.float32(9.1), front=front) == pareto.optimal_fuel_at(9.1, front=front)


@pytest.mark.parametrize("where", ["front folder", "pareto folder", "optima folder"])
def test_a_file_in_place_of_a_cache_folder_is_set_aside_not_a_traceback_after_a_solve(tmp_path, fake, caplog, where):
    """A file where a front's folder (or the `pareto/` or optima folder above it) belongs was a FileExistsError's
    traceback at the first write, once the first optimum was solved (tens of seconds into a sweep). It is a bad
    entry: set aside with a warning naming it, and the folder made."""
    p = LoaderParams(M_load=3000.0)
    in_the_way = {"front folder": pareto.front_folder("service", 5, p, tmp_path),
                  "pareto folder": tmp_path / "pareto", "optima folder": optima_folder("service", p, tmp_path)}[where]
    in_the_way.parent.mkdir(parents=True, exist_ok=True)
    in_the_way.write_text("not a folder")
    with caplog.at_level(logging.WARNING):
        if where == "optima folder":
            assert reference.direct_min_time("service", p, tmp_path).success
        else:
            assert len(pareto.pareto_front("service", 5, p, tmp_path, progress=lambda m: None).T) >= 2
    assert any(str(in_the_way) in w and "no folder" in w for w in _warnings(caplog))
    assert in_the_way.is_dir() and list(in_the_way.parent.glob(in_the_way.name + ".bad-*"))


def test_pareto_fronts_checks_its_cache_before_any_worker(tmp_path, monkeypatch):
    """With more than one worker, `pareto_fronts(cache=5)` (or b"x") gave the workers str(cache): both fronts were
    solved into a folder "5" (or "b'x'") of the working folder; one worker refused it. Refused before any worker."""
    monkeypatch.setattr(workers, "run_in_workers", lambda *a, **k: pytest.fail("a worker started"))
    for bad in (5, b"x"):
        with pytest.raises(ValueError, match="cache must be a folder path"):
            pareto.pareto_fronts(cache=bad, workers=2)
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="cache must be a folder"):
        pareto.pareto_fronts(cache=tmp_path / "file", workers=2)


@pytest.mark.parametrize("call, match", [
    (lambda: workers.run_in_workers({"a": ("math:sqrt", (4.0,))}, log_level="bogus"), "log_level"),
    (lambda: workers.run_in_workers({"a": ("math:sqrt", (4.0,))}, grace=math.inf), "grace"),
    (lambda: workers.run_in_workers({"a": ("math:sqrt", (4.0,))}, grace=math.nan), "grace"),
    (lambda: workers.run_in_workers({"a": ("math:sqrt", (4.0,))}, grace=-1), "grace"),
    (lambda: workers.run_in_workers([("math:sqrt", (4.0,))]), "jobs must be a dict"),
    (lambda: workers.run_in_workers({"a": ("math.sqrt", (4.0,))}), "job 'a' must be"),
    (lambda: workers.run_in_workers({"a": ("math:sqrt", 4.0)}), "job 'a' must be"),
    (lambda: workers.check_workers(10**5000), r"workers must be an integer in \[1, \d+\]"),
])
def test_the_workers_helpers_refuse_their_arguments_by_name(call, match, monkeypatch):
    """`run_in_workers(log_level="bogus")` killed each worker at its start ("the worker process died", a traceback on
    stderr); `grace=inf` was an OverflowError while the other workers were being stopped, NaN or -1 no grace; jobs
    that are no mapping (an AttributeError) or name no module:function failed in the workers; `check_workers(10**5000)`
    was repr()'s "Exceeds the limit (4300 digits)", naming no parameter."""
    monkeypatch.setattr(workers, "_child", lambda *a: pytest.fail("a worker started"))
    with pytest.raises(ValueError, match=match):
        call()
    long = "x" * 10**6
    for check in (workers.check_workers, workers.check_ray_address):  # (the value quoted, not all of it)
        with pytest.raises(ValueError) as err:
            check(long)
        assert len(str(err.value)) < 300


def test_an_injected_solver_of_no_solvers_or_unbounded_steps_is_refused_by_name():
    """`FallbackSolver(5, IpoptSolver())` was taken and failed at the controller's first plan with an
    AttributeError ("'int' object has no attribute 'prepare'"); `short_only="no"` gave the RTI the full plans;
    `SqpRtiSolver(extra_steps=10**9)` was taken (a plan whose rows stay unmet would take SQP steps for hours)."""
    with pytest.raises(ValueError, match="primary must be a GridSolver"):
        FallbackSolver(5, IpoptSolver())
    with pytest.raises(ValueError, match="fallback must be a GridSolver"):
        FallbackSolver(IpoptSolver(), None)
    for name in ("short_only", "lazy_fallback"):
        with pytest.raises(ValueError, match=f"{name} must be True or False"):
            FallbackSolver(IpoptSolver(), IpoptSolver(), **{name: "no"})
    with pytest.raises(ValueError, match="extra_steps must be at most 100"):
        SqpRtiSolver("hpipm", extra_steps=10**9)
    assert SqpRtiSolver("hpipm", extra_steps=np.int64(100)).extra_steps == 100
    assert FallbackSolver(IpoptSolver(), IpoptSolver(), short_only=np.bool_(True)).short_only is True


@pytest.mark.parametrize("bad", [0.0, math.nan, -1.0, True, "0.01", 5e-5])
def test_the_re_simulation_refuses_a_substep_by_name(bad):
    """`verify_result(r, max_substep=0)` divided by zero, NaN was int()'s error, -1 and True re-simulated one step
    per interval without a word (and recorded the number), 1e-9 would have taken days (0.0005 takes ~0.6 s; 5e-5, 6 s)."""
    r = fake_solve("service", "time")
    with pytest.raises(ValueError, match=r"max_substep must lie in \[0.0001, 0.1\] s"):
        verify_result(r, max_substep=bad)


def test_solve_ocp_refuses_more_starts_than_it_can_run_before_any_solve(monkeypatch):
    """`solve_ocp(starts=[(5.0, 0.7)] * 100000)` was taken: 100000 solves of seconds each."""
    import mpc.benchmark.ocp as ocp

    monkeypatch.setattr(ocp, "get_ocp", lambda *a: pytest.fail("an NLP was built"))
    with pytest.raises(ValueError, match="starts must be at most 100 pairs"):
        solve_ocp("service", starts=[(5.0, 0.7)] * 100_000)


def test_a_bad_entrys_warning_quotes_the_bad_value_not_all_of_it(tmp_path, caplog):
    """A front entry with a 5 MB `params_fingerprint` (or schema) was reported with all of it: one warning line of 5 MB
    in the log, for every lookup."""
    shipped = reference.shipped_fronts()["service_" + LoaderParams().fingerprint()]
    path = pareto.front_folder("service", params=None, cache=tmp_path) / "front.json"
    store.write_entry(path, pareto.FRONT_KIND, {**shipped.__dict__, "params_fingerprint": "f" * 5_000_000},
                      lambda d: None)
    with caplog.at_level(logging.WARNING):
        assert reference.known_front("service", LoaderParams(), tmp_path)[1] == "shipped"
    (warning,) = _warnings(caplog)
    assert str(path) in warning and len(warning) < 1000
