"""The simulator: stiction, the reversing point, machine saturations, integration accuracy."""

import math

import numpy as np
import pytest

from wl_env.params import DEFAULT_PARAMS as P
from wl_env.physics import lift
from wl_env.simulator import Simulator


def run(sim, y, phase, u_cmd, t_end, h):
    s_rev = math.nan
    for _ in range(round(t_end / h)):
        u = sim.effective_controls(y, phase, *u_cmd, h)
        y, phase, sr, _ = sim.substep(y, phase, u[:3], h)
        if sr == sr:
            s_rev = sr
    return y, phase, s_rev


def test_stiction_holds_a_braked_standing_machine():
    sim = Simulator(P, "service")
    y = (P.omega_0, 0.0, 2.0, 0.0, -3.0, 0.0)
    y1, phase, _ = run(sim, y, 4, (50.0, 0.0, P.U_b_max), 2.0, 0.05)
    assert y1[1] == 0.0 and y1[4] == -3.0 and phase == 4


def test_standing_in_neutral_without_brake_does_not_roll_backwards():
    sim = Simulator(P, "service")
    y1, _, _ = run(sim, (P.omega_0, 0.0, 2.0, 0.0, 0.0, 0.0), 4, (50.0, 0.0, 0.0), 1.0, 0.05)
    assert y1[1] == 0.0 and y1[4] == 0.0


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_reversing_point_is_cut_without_overshoot(braking):
    sim = Simulator(P, braking)
    y = (200.0, -2.0, 2.0, 0.0, -4.0, 0.0)
    u_cmd = (60.0, 0.0, 0.6 * P.U_b_max)
    s_rev, phase = math.nan, 2
    for _ in range(100):
        u = sim.effective_controls(y, phase, *u_cmd, 0.1)
        y_new, phase, sr, _ = sim.substep(y, phase, u[:3], 0.1)
        if sr == sr:
            s_rev = sr
            # position never goes past the stopping point: s_rev is the most negative position reached
            assert y_new[4] >= sr - 1e-12 and y[4] >= sr
            break
        y = y_new
    assert phase == 3 and not math.isnan(s_rev)
    # the stopping point matches a fine-step reference to a millimetre
    fine = Simulator(P, braking)
    yf, ph, s_fine = run(fine, (200.0, -2.0, 2.0, 0.0, -4.0, 0.0), 2, u_cmd, 4.0, 0.001)
    assert s_rev == pytest.approx(s_fine, abs=2e-3)


def test_the_machine_saturates_what_it_cannot_do():
    sim = Simulator(P, "service")
    y = (P.omega_max, 0.0, 3.0, 0.0, 0.0, 0.0)
    u_mf, u_ab, u_b, u_mf_torque, u_ab_pressure = sim.effective_controls(y, 3, 1e9, 1e9, 1e9, 0.1)
    assert u_mf <= u_mf_torque <= P.U_mf_max and u_ab <= P.U_ab_bounds[1] and u_b == 0.0  # no brake in phase 3
    # pump flow: the bucket speed never exceeds V_lift,max, and the bucket is never lowered
    y = (120.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    for _ in range(60):
        u = sim.effective_controls(y, 3, 200.0, 2.5, 0.0, 0.05)
        y, _, _, _ = sim.substep(y, 3, u[:3], 0.05)
        assert 0.0 <= y[3] <= lift.max_lift_speed(y[2], max(y[0], 0.0), P) * 1.05 + 1e-9
    for _ in range(20):
        u = sim.effective_controls(y, 3, 200.0, -2.5, 0.0, 0.05)
        y, _, _, _ = sim.substep(y, 3, u[:3], 0.05)
        assert y[3] >= 0.0
    assert y[3] == 0.0


def test_governor_keeps_the_engine_below_omega_max():
    sim = Simulator(P, "service")
    y, ph = (P.omega_0, 0.0, 1.0, 0.0, 0.0, 0.0), 4
    for _ in range(100):
        u = sim.effective_controls(y, ph, P.U_mf_max, 0.0, P.U_b_max, 0.1)
        y, ph, _, _ = sim.substep(y, ph, u[:3], 0.1)
        assert y[0] <= P.omega_max + 0.5


@pytest.mark.parametrize("h", [0.1, 0.05])
def test_rk4_converges_to_a_fine_reference(h):
    sim = Simulator(P, "service")
    y0 = (P.omega_0, 0.0, P.H_0, 0.0, 0.0, 0.0)
    cmd = (180.0, 0.8, 0.0)
    coarse, _, _ = run(sim, y0, 1, cmd, 3.0, h)
    fine, _, _ = run(sim, y0, 1, cmd, 3.0, 0.005)
    assert coarse[4] == pytest.approx(fine[4], abs=0.02)  # position within 2 cm after 3 s
    assert coarse[5] == pytest.approx(fine[5], rel=0.01)  # fuel within 1 %


def test_batch_equals_single_loaders():
    sim = Simulator(P, "tc")
    rng = np.random.default_rng(0)
    n = 16
    ys = [(float(rng.uniform(120, 220)), float(-rng.uniform(0.0, 2.5)), float(rng.uniform(0.7, 4.5)), 0.3, -3.0, 0.0) for _ in range(n)]
    phases = [int(rng.integers(1, 3)) for _ in range(n)]
    cmd = [(float(rng.uniform(0, 260)), float(rng.uniform(-2.5, 2.5)), float(rng.uniform(0, 57800))) for _ in range(n)]
    yb = tuple(np.array(col) for col in zip(*ys, strict=True))
    pb = np.array(phases)
    cb = tuple(np.array(col) for col in zip(*cmd, strict=True))
    for _ in range(40):
        ub = sim.effective_controls(yb, pb, *cb, 0.1)
        yb, pb, _, _ = sim.substep(yb, pb, ub[:3], 0.1)
        for i in range(n):
            u = sim.effective_controls(ys[i], phases[i], *cmd[i], 0.1)
            ys[i], phases[i], _, _ = sim.substep(ys[i], phases[i], u[:3], 0.1)
    for i in range(n):
        assert tuple(a[i] for a in yb) == ys[i] and pb[i] == phases[i]
