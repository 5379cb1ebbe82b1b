"""The MPC's one-step safety filter (mpc.controller.safety): a control within the limits passes unchanged, one
over them is eased by the right control (the brake, then the injection), an engine about to stall gets fuel,
and a plan applied open loop to a mismatched plant keeps the limits through it. The simulator's plant-estimate
input it predicts with is checked against the environment's own step."""

import math

import gymnasium as gym
import numpy as np
import pytest
from fakes import FailingSolver
from hypothesis import given, settings
from hypothesis import strategies as st

import wl_env  # noqa: F401  (registers the env)
from mpc.controller.mpc import MPCConfig, MPCController
from mpc.controller.safety import FILTER_TOL, STALL_MARGIN, SafetyFilter
from wl_env.params import DEFAULT_PARAMS as P
from wl_env.simulator import Simulator

NOMINAL_ESTIMATE = np.array([0.0, 1.0, 1.0])  # [accel offset, accel gain, lift gain]: the model as it is

states = st.tuples(st.floats(60.0, 230.0), st.floats(-3.0, 3.0), st.floats(0.5, 5.0), st.floats(0.0, 1.0))
controls = st.tuples(st.floats(0.0, 260.0), st.floats(-2.5, 2.5), st.floats(0.0, P.U_b_max))


@settings(max_examples=200, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4), state=states, u=controls)
def test_the_simulator_with_the_nominal_estimate_steps_as_without_one(braking, phase, state, u):
    """The estimate's path (unflattened) and the environment's (flattened) give the same step, its stop cut and
    its limits' excess; a lighter-looking plant (gain 1.25) moves the speed."""
    sim = Simulator(P, braking)
    y = (*state, -3.0, 0.0)
    ue = sim.effective_controls(y, phase, *u, 0.1)[:3]
    plain, est = sim.substep(y, phase, ue, 0.1), sim.substep(y, phase, ue, 0.1, est=NOMINAL_ESTIMATE)
    np.testing.assert_allclose(est[0], plain[0], rtol=1e-9, atol=1e-9)
    assert est[1] == plain[1]
    assert (math.isnan(est[2]) and math.isnan(plain[2])) or est[2] == pytest.approx(plain[2], abs=1e-9)
    for name in plain[3]:
        assert est[3][name] == pytest.approx(plain[3][name], abs=1e-9)


@settings(max_examples=150, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4), state=states, u=controls)
def test_the_filter_only_eases_and_only_where_it_helps(braking, phase, state, u):
    """Any state and control: the bucket untouched; brake and injection never raised but for a stall; a control
    the model keeps within the limits passes unchanged; an eased one is predicted further inside than before."""
    f = SafetyFilter(P, braking, 0.1)
    x, u = np.array([*state, -3.0]), np.array(u)
    out = f(x, phase, u, NOMINAL_ESTIMATE)
    assert out.control[1] == u[1]
    if out.eased == "":
        np.testing.assert_array_equal(out.control, u)
        assert out.excess_before <= FILTER_TOL or out.excess_after == out.excess_before
    elif "stall" in out.eased:
        assert out.control[0] > u[0] and out.control[2] == u[2]
    else:
        assert out.control[0] <= u[0] and out.control[2] <= u[2]
        assert out.excess_after <= out.excess_before


def test_the_filter_eases_the_injection_where_the_converter_would_brake_over_the_limit():
    """TC braking, phase 2 (forward gear, reversing at 1 m/s): at 85 rad/s the converter brakes at ~0.9 of the
    limit; a full injection speeds the engine up within the step and the drag with it, over the limit. The
    filter's injection keeps it, on the environment's own step."""
    f, sim = SafetyFilter(P, "tc", 0.1), Simulator(P, "tc")
    x, u = np.array([85.0, -1.0, 1.5, 0.3, -5.0]), np.array([200.0, 0.5, 0.0])
    out = f(x, 2, u, NOMINAL_ESTIMATE)
    assert out.eased == "U_mf" and out.excess_before > 0.02
    y = (*x, 0.0)
    assert sim.substep(y, 2, sim.effective_controls(y, 2, *u, 0.1)[:3], 0.1)[3]["deceleration"] > 0.02
    assert sim.substep(y, 2, sim.effective_controls(y, 2, *out.control, 0.1)[:3], 0.1)[3]["deceleration"] == 0.0
    assert 0.0 < out.control[0] < u[0]  # (eased, not cut: the largest injection that keeps the limit)


def test_the_filter_eases_the_service_brake_before_the_injection():
    f = SafetyFilter(P, "service", 0.1)
    x, u = np.array([100.0, 1.5, 4.0, 0.0, 10.0]), np.array([30.0, 0.0, P.U_b_max])
    out = f(x, 4, u, NOMINAL_ESTIMATE)
    assert out.eased == "U_b" and out.excess_before > 0.05 and out.excess_after <= FILTER_TOL
    assert out.control[0] == u[0] and 0.0 < out.control[2] < u[2]


def test_a_fresh_plans_hair_over_the_limit_is_eased_just_inside_it():
    """A plan's deceleration limit is elastic (its NLP traded 1.9e-5 over it at a TC stop against a centimetre of
    target miss): an excess under FILTER_TOL is eased too, to just inside the limit, the brake barely touched."""
    f = SafetyFilter(P, "service", 0.1)
    x = np.array([100.0, 1.5, 4.0, 0.0, 10.0])
    lo, hi = 0.0, P.U_b_max  # (the brake torque at which the step meets the limit: bisected)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f.excess(x, 4, np.array([30.0, 0.0, mid]), NOMINAL_ESTIMATE) <= 0.0 else (lo, mid)
    u = np.array([30.0, 0.0, hi * (1.0 + 2e-5)])
    out = f(x, 4, u, NOMINAL_ESTIMATE)
    assert 0.0 < out.excess_before <= FILTER_TOL
    assert out.eased == "U_b" and out.excess_after == 0.0
    assert u[2] * (1.0 - 1e-3) < out.control[2] < u[2]


def test_the_last_stop_at_the_limit_is_eased_by_what_the_predictions_missed():
    """A fresh plan's last stop brakes at the limit by the estimate's account. On a plant 0.5 % lighter than the
    estimate says, the filter's predictions miss; the stop the estimate puts exactly at the limit then breaks it on
    the plant, unless eased by that miss (the last stops of three draws within #13's ranges were 1e-5..1.6e-4 over,
    stop 57). A braking step that does not end the cycle is left to the plan."""
    f = SafetyFilter(P, "service", 0.1)
    plant = SafetyFilter(P, "service", 0.1)  # (the plant's step: the same machine, gain 0.5 % up)
    lighter = NOMINAL_ESTIMATE * np.array([1.0, 1.005, 1.0])

    def at_limit(x: np.ndarray) -> np.ndarray:  # the brake torque at which the step meets the limit by the estimate
        lo, hi = 0.0, P.U_b_max
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f.excess(x, 4, np.array([0.0, 0.0, mid]), NOMINAL_ESTIMATE) <= 0.0 else (lo, mid)
        return np.array([0.0, 0.0, lo])

    moving, stopping = np.array([100.0, 1.5, 4.0, 0.0, 10.0]), np.array([100.0, 0.15, 4.0, 0.0, 10.0])
    last = at_limit(stopping)
    assert f._step(stopping, 4, last, NOMINAL_ESTIMATE)[0][1] == 0.0  # (it ends standing)
    assert f(stopping, 4, last, NOMINAL_ESTIMATE).eased == ""  # (no prediction missed yet: it passes)
    assert plant.excess(stopping, 4, last, lighter) > 0.0  # (and breaks the limit on the plant)
    for _ in range(5):  # braking steps of the plant the filter has predicted
        u = 0.9 * at_limit(moving)
        f(moving, 4, u, NOMINAL_ESTIMATE)
        f.observe(np.array(plant._step(moving, 4, u, lighter)[0][:5]), 4)
    out = f(stopping, 4, last, NOMINAL_ESTIMATE)
    assert out.eased == "U_b" and out.control[2] < last[2] and out.control[0] == 0.0
    assert plant.excess(stopping, 4, out.control, lighter) == 0.0
    assert f(moving, 4, at_limit(moving), NOMINAL_ESTIMATE).eased == ""


def test_a_plant_far_from_the_model_keeps_the_margins_below_the_limits():
    """Predictions that miss by more than the limit itself (a plant far outside the model) give a margin of at most
    MAX_MARGIN, and the filter still checks a control against limits inside the machine's: the uncapped margin
    went over 1 and made the limits negative (`wl mpc --rolling-scale 10` ended on a V_max error)."""
    from mpc.controller.safety import MAX_MARGIN

    f = SafetyFilter(P, "service", 0.1)
    moving = np.array([100.0, 1.5, 4.0, 0.0, 10.0])
    for _ in range(10):
        f(moving, 4, np.array([0.0, 0.0, 0.5 * P.U_b_max]), NOMINAL_ESTIMATE)
        f.observe(np.array([100.0, 1.5 - 3.0 * P.decel_max * P.g * 0.1, 4.0, 0.0, 10.0]), 4)  # 3x the limit's change
    assert f.prediction_margin == MAX_MARGIN and f.stale_margin == MAX_MARGIN
    out = f(moving, 4, np.array([0.0, 0.0, P.U_b_max]), NOMINAL_ESTIMATE, stale=True)
    assert np.isfinite(out.control).all() and out.excess_after <= out.excess_before


def test_the_filter_fuels_an_engine_about_to_stall():
    """Reversing in gear on an idling engine with the lift drawing on it: the step would end near omega_min."""
    f = SafetyFilter(P, "tc", 0.1)
    x, u = np.array([62.0, -1.7, 1.5, 0.5, -5.0]), np.array([0.0, 2.0, 0.0])
    sim = f.sim
    y = (*x, 0.0)
    assert sim.substep(y, 1, sim.effective_controls(y, 1, *u, 0.1)[:3], 0.1)[0][0] < P.omega_min
    out = f(x, 1, u, NOMINAL_ESTIMATE)
    assert out.eased == "U_mf up (stall)"
    assert sim.substep(y, 1, sim.effective_controls(y, 1, *out.control, 0.1)[:3], 0.1)[0][0] >= P.omega_min + STALL_MARGIN - 1e-6


def test_a_plan_applied_open_loop_to_a_mismatched_plant_keeps_the_limits():
    """TC braking, the plant 20 % lighter and rolling 30 % harder than the model, every solve after the first
    plan failing: the plan's controls run open loop. Without the filter the cycle breaks the deceleration limit
    by 77 % (its shift meets the converter with the engine too fast; measured); with it, no violation."""
    plant = P.variant(payload_scale=0.8, rolling_scale=1.3)
    env = gym.make("WheelLoader-v2", braking="tc", params=plant)
    solver = FailingSolver(set(range(1, 400)))  # (step 0 plans the cycle; it runs open loop from then on)
    ctrl = MPCController("tc", config=MPCConfig(), solver=solver)
    obs, _ = env.reset(seed=0)
    for k in range(400):
        solver.step = k
        action = ctrl.act(obs)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    assert info["completed"] and not info["stalled"]
    assert ctrl.fallbacks > 50 and ctrl.safety_eased > 0
    assert info["violations"]["max_excess"] == 0.0, info["violations"]


def test_stale_plans_on_a_heavier_plant_keep_the_limit_at_the_shift():
    """TC braking, a plant 20 % heavier than the model, a solve only every 25th step (the others fail: plans up to
    24 steps old, as the real-time controller applies them). Until stop 44 the plant estimate settled the lift's
    load 2 % high: the engine ran 0.1-0.3 rad/s per step faster than predicted, and the shift met the converter
    2.1 % over the limit while the look-ahead predicted it within (measured; stop 43's engine-speed bias in the
    look-ahead kept it). The estimate is now the plant's, the engine predicted to the step: no bias to learn, and
    no violation."""
    plant = P.variant(payload_scale=1.2)
    env = gym.make("WheelLoader-v2", braking="tc", params=plant)
    solver = FailingSolver({k for k in range(1, 400) if k % 25})
    ctrl = MPCController("tc", config=MPCConfig(), solver=solver)
    obs, _ = env.reset(seed=0)
    bias = []
    for k in range(400):
        solver.step = k
        action = ctrl.act(obs)
        obs, _, terminated, truncated, info = env.step(action)
        bias.append(ctrl.safety.engine_speed_bias)
        if terminated or truncated:
            break
    assert info["completed"] and not info["stalled"]
    assert ctrl.estimator.lift_gain == pytest.approx(1.2, abs=0.005)
    assert max(bias[:30]) < 0.02  # rad/s per step: no engine faster than predicted (it learned 0.1-0.3 before)
    assert info["violations"]["max_excess"] == 0.0, info["violations"]


def test_the_look_ahead_counts_a_faster_engine_against_the_shift():
    """The same plan to the shift, an engine measured faster than predicted: the shift's predicted excess grows
    with that bias (a faster engine brakes harder through the converter); a slower one is not credited."""
    f = SafetyFilter(P, "tc", 0.1)
    x = np.array([150.0, -2.0, 2.0, 0.3, -4.5])
    plan = np.tile([0.0, 0.0, 0.0], (6, 1))
    shift = np.array([0.0, 0.0, 0.0])
    excess = []
    for bias in (-2.0, 0.0, 2.0, 4.0):
        f.engine_speed_bias = bias
        excess.append(f.shift_excess(x, 1, plan, shift, NOMINAL_ESTIMATE))
    assert excess[0] == excess[1]
    assert excess[1] < excess[2] < excess[3], excess


def test_where_no_fuel_cut_is_enough_the_filter_lifts_the_bucket_to_load_the_engine():
    """TC braking, phase 1, 4 steps before a shift the plan takes unfuelled, the engine at 120 rad/s and the bucket
    rising slowly: even no injection meets the shift over the limit (0.6 of it). A lift at full acceleration loads
    the engine down to a shift within the limit; near the dump height the lift is only what stops the bucket there."""
    from wl_env.assist import bucket_command

    f = SafetyFilter(P, "tc", 0.1)
    x, u = np.array([120.0, -1.9, 2.0, 0.1, -5.0]), np.array([20.0, 0.0, 0.0])
    ahead = (np.zeros((4, 3)), np.zeros(3))
    cut_only = f.shift_excess(x, 1, np.vstack([[0.0, 0.0, 0.0], ahead[0]]), ahead[1], NOMINAL_ESTIMATE)
    out = f(x, 1, u, NOMINAL_ESTIMATE, ahead=ahead)
    assert cut_only > 0.5
    assert out.eased == "U_mf+U_ab up (the shift ahead)" and out.control[0] == 0.0 and out.control[1] > 2.0
    assert f.shift_excess(x, 1, np.vstack([out.control, ahead[0]]), ahead[1], NOMINAL_ESTIMATE) <= FILTER_TOL
    top = np.array([120.0, -1.9, P.H_T - 0.02, 0.1, -5.0])
    near = f(top, 1, u, NOMINAL_ESTIMATE, ahead=ahead)
    assert near.control[1] <= bucket_command(top[2], top[3], P.U_ab_bounds[1], P, 0.1) + 1e-12


def test_the_filter_is_a_flag_of_the_config():
    with pytest.raises(ValueError, match="safety_filter must be True or False"):
        MPCConfig(safety_filter="yes")


def test_a_filter_out_of_time_keeps_the_safe_side():
    """Past its deadline the filter skips its bisections: the brake eased all the way (the safe end of the
    bisection), not left over the limit, and no time spent searching."""
    import time

    f = SafetyFilter(P, "service", 0.1)
    x, u = np.array([100.0, 1.5, 4.0, 0.0, 10.0]), np.array([30.0, 0.0, P.U_b_max])
    timed = f(x, 4, u, NOMINAL_ESTIMATE)
    t0 = time.perf_counter()
    late = f(x, 4, u, NOMINAL_ESTIMATE, until=t0 - 1.0)
    assert late.eased == "U_b" and late.control[2] == 0.0 < timed.control[2]
    assert late.excess_after <= FILTER_TOL and time.perf_counter() - t0 < 0.05
