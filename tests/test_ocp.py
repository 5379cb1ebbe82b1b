"""The optimal control benchmark: converges, reproduces in simulation, refines, fails clearly."""

import json

import numpy as np
import pytest

from mpc.benchmark.ocp import OCPError, OCPResult, OCPSettings, solve_ocp
from mpc.benchmark.pareto import ParetoFront, front_times, pchip
from mpc.benchmark.scoring import score_run
from wl_env.params import DEFAULT_PARAMS, resolve

BRAKINGS = ["service", "tc"]


@pytest.fixture(scope="module")
def optima():
    return {(b, obj): solve_ocp(b, obj) for b in BRAKINGS for obj in ("time", "fuel")}


@pytest.mark.parametrize("braking", BRAKINGS)
@pytest.mark.parametrize("objective", ["time", "fuel"])
def test_optimum_reproduces_in_simulation(optima, braking, objective):
    r = optima[(braking, objective)]
    v = r.verification
    assert r.success and v["passed"]
    assert abs(v["reversing_error_m"]) <= 0.05
    assert abs(v["final_position_error_m"]) <= 0.05
    assert abs(v["final_height_error_m"]) <= 0.02
    assert v["max_violation"] <= 0.01
    assert abs(v["fuel_rel_error"]) <= 0.01  # the simulated fuel is the optimizer's fuel


@pytest.mark.parametrize("braking", BRAKINGS)
def test_boundary_conditions_and_constraints_in_the_solution(optima, braking):
    r = optima[(braking, "time")]
    x = np.asarray(r.states)
    s = np.asarray(r.position)
    phase = np.asarray(r.phase)
    p = DEFAULT_PARAMS
    assert x[0] == pytest.approx([p.omega_0, 0.0, p.H_0, 0.0])
    assert x[-1][1] == pytest.approx(0.0, abs=1e-6) and x[-1][2] == pytest.approx(p.H_T, abs=1e-6)
    assert s[-1] == pytest.approx(0.0, abs=1e-6) and s.min() == pytest.approx(-p.reverse_distance, abs=1e-6)
    assert all(d >= 0.1 - 1e-9 for d in r.phase_durations) and sum(r.phase_durations) == pytest.approx(r.T)
    assert list(np.unique(phase)) == [1, 2, 3, 4] and (np.diff(phase) >= 0).all()
    assert len(r.controls) == len(r.t) - 1
    # IPOPT relaxes bounds by 1e-8 relative (bound_relax_factor)
    assert (x[:, 0] >= p.omega_min - 1e-5).all() and (x[:, 0] <= p.omega_max + 1e-5).all()
    assert (x[:, 3] >= -1e-7).all()  # the bucket is never lowered
    reversing = phase[:-1] <= 2
    assert (x[:-1][reversing, 1] <= 1e-7).all() and (x[:-1][~reversing, 1] >= -1e-7).all()


def test_minimum_time_is_faster_and_minimum_fuel_is_leaner(optima):
    for b in BRAKINGS:
        t_opt, f_opt = optima[(b, "time")], optima[(b, "fuel")]
        assert t_opt.T < f_opt.T and f_opt.fuel_g < t_opt.fuel_g
        assert 6.0 < t_opt.T < 12.0  # the short loading cycle takes seconds, not minutes


def test_tc_braking_costs_more_fuel_at_equal_cycle_time():
    service = solve_ocp("service", "fuel_at_time", T=10.0)
    tc = solve_ocp("tc", "fuel_at_time", T=10.0)
    assert service.T == pytest.approx(10.0) and tc.T == pytest.approx(10.0)
    assert tc.fuel_g > service.fuel_g


def test_tc_braking_is_slower_in_the_minimum_time_cycle(optima):
    assert optima[("tc", "time")].T > optima[("service", "time")].T


@pytest.mark.parametrize("braking", BRAKINGS)
def test_mesh_refinement_moves_the_objective_less_than_half_a_percent(optima, braking):
    base = optima[(braking, "time")]
    fine = solve_ocp(braking, "time", settings=OCPSettings(intervals=tuple(2 * n for n in base.mesh)),
                     warm_start=base, verify=False)
    assert fine.T == pytest.approx(base.T, rel=0.005)


def test_smoothing_homotopy_moves_the_objective_little(optima):
    for r in optima.values():
        first, last = r.smoothing[0]["objective"], r.smoothing[-1]["objective"]
        assert r.smoothing[-1]["k"] == 0.0
        assert abs(first - last) / last < 0.01


def test_impossible_cycle_time_raises_with_solver_status():
    with pytest.raises(OCPError, match="Infeasible"):
        solve_ocp("service", "fuel_at_time", T=4.0, verify=False)


@pytest.mark.parametrize("T", [1e-4, 5e-324, 0.39, 10**400, np.float64(61.0)])
def test_a_cycle_time_the_nlp_cannot_hold_is_refused_before_the_solve(T):
    """Each of the 4 phases lasts at least 0.1 s: T = 1e-4 s passed (0, 60] and failed in the start guess
    ("zero-size array to reduction operation minimum"); 10**400 was an OverflowError."""
    with pytest.raises(ValueError, match=r"T must be a finite cycle time in \[0.4, 60\] s"):
        solve_ocp("service", "fuel_at_time", T=T, verify=False)


def test_height_out_of_reach_is_rejected():
    with pytest.raises(ValueError, match="H_T"):
        solve_ocp("service", "time", params={"H_T": 5.3})


def test_bad_requests_raise():
    with pytest.raises(ValueError, match="objective"):
        solve_ocp("service", "speed")
    with pytest.raises(ValueError, match="braking"):
        solve_ocp("engine", "time")
    with pytest.raises(ValueError, match="w_fuel"):
        solve_ocp("service", "weighted", w_fuel=1.5)


def test_weighted_objective_lies_between_the_extremes(optima):
    r = solve_ocp("service", "weighted", w_fuel=0.5, warm_start=optima[("service", "time")])
    assert optima[("service", "time")].T <= r.T <= optima[("service", "fuel")].T + 1e-6


def test_result_json_round_trip(optima, tmp_path):
    r = optima[("service", "time")]
    path = r.save(tmp_path / "r.json")
    data = json.loads(path.read_text())
    for key in ("braking", "objective", "T", "fuel_g", "phase_durations", "t", "states", "controls", "phase"):
        assert key in data
    back = OCPResult.load(path)
    assert back.T == r.T and back.states == r.states and back.phase == r.phase
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(ValueError, match="missing fields"):
        OCPResult.load(tmp_path / "bad.json")


def test_the_front_is_interpolated_where_it_is_straight():
    """Near T_min the fuel falls like sqrt(T - T_min): on the front's points (front_times) the interpolation
    in u = sqrt(T - T_min) follows such a front within 0.05 %, where interpolating in T misses by far more."""
    T_min, T_end = 8.0, 21.0

    def true_fuel(T):
        x = T - T_min
        return 85.0 - 30.0 * np.sqrt(x) + 1.2 * x - 0.035 * x * x

    times = front_times(T_min, T_end, 10)
    front = ParetoFront("service", times.tolist(), [float(true_fuel(t)) for t in times], "f", T_min, T_end,
                        float(true_fuel(T_end)), [20, 12, 20, 12])
    probe = T_min * (1 + np.array([0.002, 0.004, 0.01, 0.02, 0.05, 0.1, 0.3, 0.6, 1.0]))
    err_u = max(abs(front.fuel_at(t) / true_fuel(t) - 1) for t in probe)
    err_T = max(abs(pchip(times, np.array(front.fuel_g), t) / true_fuel(t) - 1) for t in probe)
    assert err_u < 5e-4 < 3 * err_u < err_T
    assert times[0] == pytest.approx(1.001 * T_min) and times[-1] == pytest.approx(T_end)


def test_front_interpolation_and_scoring():
    T = [8.0, 9.0, 11.0, 15.0, 21.0]
    fuel = [95.0, 70.0, 55.0, 49.0, 47.5]
    front = ParetoFront("service", T, fuel, resolve(None).fingerprint(), 8.0, 21.0, 47.5, [20, 12, 20, 12])
    assert front.fuel_at(9.0) == pytest.approx(70.0)
    mid = front.fuel_at(10.0)
    assert 55.0 < mid < 70.0
    with pytest.raises(ValueError, match="own optimum"):  # a front of other parameters scores nothing
        score_run(10.0, 60.0, "service", front=ParetoFront("service", T, fuel, "x", 8.0, 21.0, 47.5, [20, 12, 20, 12]))
    with pytest.raises(ValueError, match="impossible"):
        front.fuel_at(7.0)
    s = score_run(10.0, mid * 1.1, "service", front=front)
    assert s.time_gap == pytest.approx(10.0 / 8.0 - 1) and s.fuel_gap == pytest.approx(0.1)
    with pytest.raises(ValueError, match="fuel_g"):
        score_run(10.0, float("nan"), "service", front=front)


@pytest.fixture(scope="module")
def highest_truck():
    """A scenario at the ranges' corner (6 t, 4 m legs, a 5.1 m truck) and its minimum fuel at 1.15 T_min."""
    from wl_env.scenario import Scenario

    sc = Scenario(payload=6000, reverse_distance=4, forward_distance=4, rolling_resistance=0.015, dump_height=5.1,
                  start_engine_speed=800, start_bucket_height=0.5)
    return sc, solve_ocp(scenario=sc, objective="fuel_at_time", T=6.977, refine=False, starts=((3.4885, 0.7),))


def test_a_plan_riding_the_pump_limit_up_to_the_highest_truck_reproduces(highest_truck):
    """The simulator caps the bucket speed at the pump flow of the substep's start, the OCP at the same
    instant: where the optimum rides the limit while the engine runs up (the shift into phase 3) an
    open-loop replay falls behind in bucket speed and stays behind. The replay's lift loop makes it up
    (this cycle failed the check at every mesh from 20 to 160 intervals per leg)."""
    _, r = highest_truck
    v = r.verification
    assert v["open_loop"]["final_height_error_m"] < -0.02  # what the check failed on
    assert r.success and v["passed"], r.status
    assert abs(v["final_height_error_m"]) <= 0.005 and abs(v["fuel_rel_error"]) <= 0.005


def test_a_cached_optimum_that_failed_an_older_check_is_checked_again(highest_truck, tmp_path):
    """A cache written before the lift loop holds such a cycle as failed: read, it is checked by the current
    check and saved so (else `wl evaluate` kept answering "no verified optimum" for good)."""
    from dataclasses import replace as dc_replace

    from mpc.benchmark.optima import _cached
    from mpc.benchmark.pareto import cached_result, save_result

    sc, r = highest_truck
    p = sc.params()
    old_check = {k: v for k, v in r.verification.items() if k not in ("check_version", "lift_gains")}
    old_check.update(passed=False, final_height_error_m=-0.043)
    stale = dc_replace(r, success=False, status=r.status + " (re-simulation check failed)", verification=old_check)
    path = tmp_path / "fuel_at_T6.9770.json"
    save_result(stale, path)
    got = _cached(path, "service", p, T=r.T)
    assert got.success and got.verification["passed"] and got.status == r.status
    assert cached_result(path).verification["check_version"] == 2  # saved so: not checked a third time
    failed_now = dc_replace(stale, verification={**r.verification, "passed": False})  # failed the current check
    save_result(failed_now, path)
    assert not _cached(path, "service", p, T=r.T).success


def test_the_optimum_a_step_over_the_minimum_time_is_found_from_the_cycles_own_fastest(tmp_path):
    """The smoothness yardstick near T_min: TC's minimum-fuel cycle at 8.4 s (0.25 % over its 8.38 s) failed
    from the templates alone with no other front cached, and #13's bench lost that run's total variation."""
    from mpc.benchmark.reference import direct_fuel_at

    r = direct_fuel_at("tc", 8.4, DEFAULT_PARAMS, tmp_path)
    assert r.success and abs(r.T - 8.4) < 1e-9
    # leaner than the minimum-time cycle, and not below the shipped front at 8.4 s (82.17 g interpolated)
    assert 82.0 < r.fuel_g < solve_ocp("tc", "time").fuel_g


@pytest.mark.parametrize("kwargs, needle", [
    ({"settings": "x"}, "settings must be an OCPSettings"),  # (a TypeError from dataclasses.replace)
    ({"warm_start": "x"}, "warm_start must be an OCPResult"),  # (an AttributeError)
    ({"starts": [(float("nan"), 0.5)]}, "starts must be"),  # (numpy's "arange: cannot compute length")
    ({"starts": "ab"}, "starts must be"),
    ({"T": -3.0}, "objective 'time' takes none"),  # (ignored without a word)
    ({"max_interval": 0}, "max_interval must lie in"),
    ({"max_interval": float("nan")}, "max_interval must lie in"),
    ({"max_refinements": -1}, "max_refinements must be an integer"),
    ({"objective": "speed"}, "objective must be one of")])
def test_solve_ocp_refuses_bad_arguments_by_name_before_any_solve(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        solve_ocp("service", **{"objective": "time", **kwargs})
