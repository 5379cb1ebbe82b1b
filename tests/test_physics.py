"""The model: known values of the specification, physical invariants, one model for numpy and CasADi."""

import casadi as ca
import numpy as np
import pytest

from wl_env import model
from wl_env.params import DEFAULT_PARAMS as P
from wl_env.physics import engine, lift
from wl_env.physics import torque_converter as tc
from wl_env.simulator import Simulator

RPM = np.pi / 30.0


def test_numpy_and_casadi_dynamics_agree():
    rng = np.random.default_rng(0)
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 3)
    for gear, d in [(-60, -1), (0, -1), (60, -1), (60, 1), (0, 1)]:
        f = ca.Function("f", [x, u], [model.dynamics(x, u, gear, d)])
        m = ca.Function("m", [x, u], [model.fuel_rate(x, u)])
        for _ in range(50):
            xs = np.array([rng.uniform(60, 230), d * rng.uniform(0, 2.7), rng.uniform(0.7, 5.0), rng.uniform(0, 0.9)])
            xs[1] *= 1.0 if gear * d >= 0 else 1.0
            us = np.array([rng.uniform(0, 260), rng.uniform(-2.5, 2.5), rng.uniform(0, 57800)])
            ref = model.dynamics(xs, us, gear, d)
            np.testing.assert_allclose(np.array(f(xs, us)).ravel(), ref, rtol=1e-9, atol=1e-9)
            assert float(m(xs, us)) == pytest.approx(float(model.fuel_rate(xs, us)), rel=1e-12)


def test_float_and_numpy_paths_are_bit_identical():
    xs = (180.0, -1.7, 2.2, 0.6)
    us = (150.0, 0.7, 0.0)
    scalar = model.derivatives(*xs, *us, -60.0, -1.0, P)
    vector = model.derivatives(*(np.array([v]) for v in xs), *(np.array([v]) for v in us), -60.0, -1.0, P)
    assert [float(a) for a in scalar] == [float(b[0]) for b in vector]


def test_peak_power_near_278_kw_at_1380_rpm():
    w = np.linspace(60, 230, 5000)
    power = engine.max_engine_torque(w, P) * w
    i = int(np.argmax(power))
    assert power[i] / 1e3 == pytest.approx(278, abs=3)
    assert w[i] / RPM == pytest.approx(1380, abs=30)


def test_converter_stall_speed_and_tractive_force():
    # stall: the engine at its torque limit holds the converter at phi = 0 (no lift)
    w = np.linspace(100, 230, 20000)
    gap = engine.max_engine_torque(w, P) - tc.pump_torque(0.0, w, P)
    w_stall = w[np.argmin(np.abs(gap))]
    assert w_stall / RPM == pytest.approx(1800, abs=40)
    force = tc.turbine_torque(0.0, w_stall, P) * P.eta_gb * P.gear_ratio / P.r_w
    assert force / 1e3 == pytest.approx(170, abs=8)


def test_top_speed_in_mode_two():
    # full throttle forward, no lift: the speed settles where traction meets rolling resistance
    sim = Simulator(P, "service")
    y, phase = (P.omega_0, 0.0, P.H_0, 0.0, 0.0, 0.0), 3
    for _ in range(600):
        u = sim.effective_controls(y, phase, P.U_mf_max, 0.0, 0.0, 0.05)
        y, phase, _, _ = sim.substep(y, phase, u[:3], 0.05)
    phi = tc.speed_ratio(y[1], y[0], 60.0, P)
    assert y[1] == pytest.approx(2.7, abs=0.2)
    assert 0.0 < phi <= 1.0  # mode II


def test_k_range_and_lift_time():
    H = np.linspace(P.H_0, P.H_T, 400)
    k = lift.k_factor(H, P)
    assert 2.5 < k.min() and k.max() < 3.4
    v_max = lift.max_lift_speed(H, P.pump_speed_sat, P)
    lift_time = np.trapezoid(1.0 / v_max, H)
    assert 5.0 <= lift_time <= 6.0


def test_k_is_the_derivative_of_height_by_cylinder_length():
    H = np.linspace(0.8, 4.9, 20)
    dh = 1e-6
    dL = lift.cylinder_length_and_arm(H + dh, P)[0] - lift.cylinder_length_and_arm(H - dh, P)[0]
    np.testing.assert_allclose(2 * dh / dL, lift.k_factor(H, P), rtol=1e-5)


def test_pressure_limit_is_consistent():
    H = np.linspace(0.7, 5.0, 30)
    u_max = lift.max_bucket_acceleration_for_pressure(H, P)
    np.testing.assert_allclose(lift.cylinder_pressure(H, u_max, P), P.P_cyl_max, rtol=1e-12)
    # a heavier payload raises the static pressure
    assert (lift.cylinder_pressure(H, 0.0, P.variant(payload_scale=1.5)) > lift.cylinder_pressure(H, 0.0, P)).all()


def test_converter_never_creates_power_in_mode_two():
    phi = np.linspace(0.0, 1.0, 1001)
    w = 180.0
    pump_power = tc.pump_torque(phi, w, P) * w
    turbine_power = tc.turbine_torque(phi, w, P) * phi * w  # T_gb * omega_gb
    assert (turbine_power <= pump_power + 1e-9).all()


def test_converter_passes_power_to_the_engine_in_mode_three():
    phi = np.linspace(1.1, 2.5, 50)
    assert (tc.xi(phi, P) < 0).all()  # pump torque negative: P_trac = T_p omega < 0 feeds the engine
    assert (tc.kappa(phi, P) < 0).all()  # the turbine brakes the wheels


def test_characteristics_are_c1_at_the_extension_points():
    for f in (tc.xi, tc.kappa):
        for x0 in (0.0, P.tc_phi_hi):
            e = 1e-7
            left, mid, right = f(np.array([x0 - e, x0, x0 + e]), P)
            assert left == pytest.approx(mid, abs=1e-4) and right == pytest.approx(mid, abs=1e-4)
            slope_l, slope_r = (mid - left) / e, (right - mid) / e
            assert slope_l == pytest.approx(slope_r, rel=1e-3, abs=1e-2)


def test_neutral_decouples_the_driveline():
    x = np.array([200.0, 1.5, 2.0, 0.5])
    u = np.array([100.0, 0.0, 0.0])
    out = model.outputs(x, u, 0.0, 1.0)
    assert out["P_trac"] == 0.0 and out["T_wheel"] == 0.0 and out["tc_mode"] == 0
    # dV/dt is rolling resistance only
    assert model.dynamics(x, u, 0.0, 1.0)[1] == pytest.approx(-P.F_roll / P.M_tot)


def test_tc_braking_decelerates_a_reversing_machine():
    x = np.array([150.0, -2.0, 2.0, 0.0])
    out = model.outputs(x, np.array([50.0, 0.0, 0.0]), 60.0, -1.0)
    assert out["phi"] < 0 and out["tc_mode"] == 1
    assert out["T_wheel"] > 0 and out["dVdt"] > 0  # pushes forward: slows the reversing machine
    assert out["P_trac"] > 0  # and loads the engine


def test_fuel_rate_known_value():
    # eq. (8): 1e-6/(4 pi) * U_mf * omega * n_cyl
    assert float(model.fuel_rate(np.array([200.0, 0, 1, 0]), np.array([100.0, 0, 0]))) == pytest.approx(
        1e-6 / (4 * np.pi) * 100 * 200 * 6
    )


def test_bad_gear_or_direction_raises():
    with pytest.raises(ValueError, match="gear"):
        model.dynamics(np.zeros(4) + 1, np.zeros(3), 30, 1)
    with pytest.raises(ValueError, match="direction"):
        model.dynamics(np.ones(4), np.zeros(3), 60, 0)
