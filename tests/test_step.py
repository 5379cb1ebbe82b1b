"""The one control step (wl_env.step) and the one set of limits (wl_env.limits): known values, the
saturations' constraint form against the saturations themselves, and the same step on every number kind."""

import math

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wl_env import limits, step
from wl_env.params import DEFAULT_PARAMS as P
from wl_env.physics import engine, lift


def test_limit_residuals_are_zero_on_the_limit_and_relative_beyond():
    a_max = P.decel_max * P.g
    assert limits.deceleration(-a_max, 1.0, P) == [pytest.approx(0.0)]  # forward, braking at 0.18 g
    assert limits.deceleration(1.1 * a_max, -1.0, P) == [pytest.approx(0.1)]  # reversing, 10 % over
    assert limits.speed(-P.V_max, -1.0, P) == [pytest.approx(0.0)]
    omega = 150.0
    line = min(engine.torque_limit_lines(omega, P))
    u_on_curve = (line + engine.friction_torque(omega, P)) / P.T_ig_per_mg
    assert max(limits.torque(omega, u_on_curve, P)) == pytest.approx(0.0, abs=1e-12)
    v = lift.max_lift_speed(2.0, omega, P)
    assert max(limits.lift_speed(2.0, omega, 1.05 * v, P)) == pytest.approx(0.05, rel=1e-9)
    assert limits.excess([-0.3, 0.02, -1.0]) == 0.02 and limits.excess([-0.3, -0.2]) == 0.0
    res = limits.residuals((omega, -1.0, 2.0, 0.3), (100.0, 0.5, 0.0), -0.5, -1.0, P)
    assert set(res) == set(limits.NAMES)


states = st.tuples(st.floats(60.0, 230.0), st.floats(-2.5, 2.5), st.floats(0.7, 5.0), st.floats(0.0, 1.2))
controls = st.tuples(st.floats(0.0, 260.0), st.floats(-2.5, 2.5), st.floats(0.0, 57800.0))


@settings(max_examples=300, deadline=None)
@given(states, controls, st.sampled_from([1, 2, 3, 4]), st.sampled_from([0.1, 0.05]))
def test_saturation_residuals_say_when_the_machine_changes_the_control(x, u, phase, h):
    """The constraint form a planner uses: every residual <= 0 exactly when effective_controls passes the
    control unchanged (within rounding), for any state and control in range."""
    from wl_env.cycle import phase_tables

    gear_t, dir_t, brake_t = phase_tables("tc", P)
    gear, d = float(gear_t[phase]), float(dir_t[phase])
    y = (*x, 0.0, 0.0)
    u = (u[0], u[1], u[2] if brake_t[phase] else 0.0)
    applied = step.effective_controls(y, gear, float(brake_t[phase]), *u, h, P)[:3]
    omega_rate = step.rhs(y, applied, gear, d, P, saturate=False)[0]
    rows = step.saturation_residuals(y, applied, omega_rate, h, P)
    worst = max(r for group in rows.values() for r in group)
    if u[1] + x[3] / h >= 0.0 and worst < -1e-9:  # inside every saturation (and not lowering the bucket)
        assert np.allclose(applied, u, rtol=1e-12, atol=1e-9)
    if not np.allclose(applied, u, rtol=1e-9, atol=1e-6):  # the machine changed it: a row says so
        changed_by_lowering = u[1] < -x[3] / h
        assert worst > -1e-6 or changed_by_lowering
    # what the machine applies never lies beyond a saturation row
    assert worst <= 1e-9


def test_the_step_is_the_same_on_floats_numpy_and_casadi():
    y = (180.0, -1.2, 1.5, 0.3, -1.0, 0.0)
    u = (120.0, 0.5, 0.0)
    gear, d = -P.gear_ratio, -1.0
    floats, _, _ = step.rk4(y, u, gear, d, 0.1, P)
    arrays, _, _ = step.rk4(tuple(np.full(3, v) for v in y), tuple(np.full(3, v) for v in u), gear, d, 0.1, P)
    x, uu = ca.SX.sym("x", 6), ca.SX.sym("u", 3)
    sym, _, _ = step.rk4(tuple(x[i] for i in range(6)), tuple(uu[i] for i in range(3)), gear, d, 0.1, P, held=0.0)
    f = ca.Function("f", [x, uu], [ca.vertcat(*sym)])
    casadi_out = np.array(f(np.array(y), np.array(u))).ravel()
    for i in range(6):
        assert arrays[i].tolist() == [floats[i]] * 3  # numpy: bit-identical to floats
        assert casadi_out[i] == pytest.approx(floats[i], rel=1e-12, abs=1e-12)
    assert not math.isnan(floats[0])
