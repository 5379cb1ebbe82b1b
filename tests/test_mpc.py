"""The MPC drives the environment through the cycle, within the constraints, and survives failures."""

import numpy as np
import pytest

from mpc.mpc import MPCConfig, MPCController, run_closed_loop
from mpc.ocp import solve_ocp
from wl_env.params import DEFAULT_PARAMS


@pytest.mark.parametrize(
    "braking, mode",
    [
        ("service", "time"),
        ("service", "target_time"),
        ("tc", "target_time"),
        ("tc", "time"),
    ],
)
def test_closed_loop_cycle(braking, mode):
    config = MPCConfig(mode=mode, target_time=11.0 if mode == "target_time" else None)
    r = run_closed_loop(braking, config, score=False)
    if mode == "time":  # near the OCP minimum (measured +4.1 % service, +3.8 % tc; the env steps 0.1 s)
        assert r["T"] <= 1.05 * solve_ocp(braking, "time", verify=False).T
    assert r["completed"] and r["success"]
    assert abs(r["reversing_error_m"]) <= 0.05 and abs(r["final_position_error_m"]) <= 0.05
    assert abs(r["final_height_error_m"]) <= 0.02
    assert r["max_violation"] == 0.0  # deceleration and speed limits held at every step
    states = np.asarray(r["states"])
    assert (states[:, 0] > DEFAULT_PARAMS.omega_min).all()
    assert r["T"] < (10.0 if mode == "time" else 11.0 + 0.15)  # near the 8.2-8.4 s optimum / on time
    assert r["solve_time"]["median_s"] < 0.1  # faster than the control interval


def test_target_time_mode_saves_fuel():
    fast = run_closed_loop("service", MPCConfig(mode="time"), score=False)
    slow = run_closed_loop("service", MPCConfig(mode="target_time", target_time=11.0), score=False)
    assert slow["fuel_g"] < 0.7 * fast["fuel_g"]


def test_fallback_applies_the_shifted_plan_on_a_forced_failure():
    import gymnasium as gym

    import wl_env  # noqa: F401

    env = gym.make("WheelLoader-v0", braking="service")
    ctrl = MPCController("service")
    obs, _ = env.reset(seed=0)
    flagged = 0
    for k in range(200):
        if k in (10, 11, 12, 30):
            ctrl._force_failure = True
        a = ctrl.act(obs)
        assert np.isfinite(a).all() and a.shape == (4,)
        if ctrl.last_info["fallback"]:
            flagged += 1
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    assert flagged >= 4 and ctrl.fallbacks >= 4
    assert info["completed"] and info["is_success"]


@pytest.mark.parametrize("payload, rolling", [(0.8, 1.3), (1.2, 0.7)])
def test_model_mismatch_case_completes(payload, rolling):
    plant = DEFAULT_PARAMS.variant(payload_scale=payload, rolling_scale=rolling)
    ctrl = MPCController("service")  # the nominal model
    r = run_closed_loop("service", MPCConfig(mode="time"), plant_params=plant, score=False, controller=ctrl)
    assert r["completed"] and r["success"]
    # the first braking step starts from a model-error estimate a few percent short of the truth:
    # measured up to 0.5 % over the 0.18 g limit there, none after
    assert r["max_violation"] < 0.01
    # the estimate: gain = model mass / plant mass, offset = the rolling-resistance error (m/s^2)
    gain, offset = ctrl._theta
    assert gain == pytest.approx(DEFAULT_PARAMS.M_tot / plant.M_tot, abs=0.01)
    assert offset == pytest.approx((DEFAULT_PARAMS.F_roll - plant.F_roll) / plant.M_tot, abs=0.03)


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="mode"):
        MPCConfig(mode="fast")
    with pytest.raises(ValueError, match="target_time"):
        MPCConfig(mode="target_time")
    with pytest.raises(ValueError, match="braking"):
        MPCController("engine")
