"""WheelLoaderTarget-v0/v1: a target cycle time per episode, in the observation and the reward; v1's governor."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st

import wl_env  # noqa: F401  (registers the envs)
from wl_env.scenario import Scenario
from wl_env.suites.min_time import estimate_min_time


def test_the_target_env_passes_the_gymnasium_checks_and_observes_its_target():
    env = gym.make("WheelLoaderTarget-v0", braking="tc", scenario="train")
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=4)
    core = env.unwrapped
    assert obs.shape == (21,) and env.observation_space.contains(obs)
    T_min = estimate_min_time(core.episode_scenario)
    assert 1.0 * T_min <= info["target_time"] <= 2.5 * T_min  # drawn from the default range
    assert obs[19] == pytest.approx(info["target_time"] / 40.0, rel=1e-6)
    assert obs[20] == pytest.approx(info["target_time"] / T_min - 1.0, rel=1e-5)
    again, info2 = env.reset(seed=4)
    assert np.array_equal(obs, again) and info2["target_time"] == info["target_time"]  # same seed, same target


def test_the_reset_options_set_the_target_and_v2_refuses_them():
    env = gym.make("WheelLoaderTarget-v0", braking="service")
    _, info = env.reset(seed=0, options={"target_ratio": 1.5})
    assert info["target_time"] == pytest.approx(1.5 * estimate_min_time(Scenario.nominal("service")))
    _, info = env.reset(seed=0, options={"target_time": 12.0})
    assert info["target_time"] == 12.0
    for bad in ({"target_time": 0.0}, {"target_time": 45.0}, {"target_ratio": 0.5}, {"target_ratio": 1.2, "target_time": 9.0}):
        with pytest.raises(ValueError, match="target"):
            env.reset(seed=0, options=bad)
    with pytest.raises(ValueError, match="WheelLoaderTarget-v0"):
        gym.make("WheelLoader-v2").reset(seed=0, options={"target_time": 12.0})
    with pytest.raises(ValueError, match="ratio to T_min in \\[1, 3\\]"):
        gym.make("WheelLoaderTarget-v0", target=(2.0, 1.0))
    # numpy numbers are the numbers they hold (np.float32 was refused)
    assert gym.make("WheelLoaderTarget-v0", target=np.float32(1.5)).unwrapped.target_ratios == (1.5, 1.5)
    assert gym.make("WheelLoaderTarget-v0", target=[np.float64(1.2), 2]).unwrapped.target_ratios == (1.2, 2.0)


def test_the_target_power_favours_fast_targets_in_the_same_range_and_one_is_the_uniform_draw():
    def ratios(**kw):
        env = gym.make("WheelLoaderTarget-v6", braking="service", scenario="train", target=(1.0, 2.5), **kw).unwrapped
        return np.array([info["target_time"] / env.min_time_estimate for info in
                         (env.reset(seed=k)[1] for k in range(120))])

    uniform, one, skewed = ratios(), ratios(target_power=1.0), ratios(target_power=3.0)
    np.testing.assert_array_equal(one, uniform)  # the default's numbers, unchanged
    assert skewed.min() >= 1.0 - 1e-12 and skewed.max() <= 2.5 + 1e-12
    # ratio < 1.15 where u**3 < 0.1: P = 0.1**(1/3) = 0.46, against 0.1 for the uniform draw
    assert np.mean(skewed < 1.15) > 0.3 > 0.2 > np.mean(uniform < 1.15)
    for bad in (0.0, 5.0, float("nan"), True, "2"):
        with pytest.raises(ValueError, match="target_power must be a number in \\[0.25, 4\\]"):
            gym.make("WheelLoaderTarget-v6", target_power=bad)


@settings(max_examples=200, deadline=None)
@given(power=st.floats(0.25, 4.0), lo=st.floats(1.0, 3.0), width=st.floats(0.0, 2.0), seed=st.integers(0, 2**32 - 1))
def test_every_target_draw_lies_in_its_range(power, lo, width, seed):
    from wl_env.env import episode_target

    hi = min(lo + width, 3.0)
    T_min, target = episode_target(Scenario.nominal("tc"), (lo, hi), np.random.default_rng(seed), power=power)
    assert lo * T_min * (1 - 1e-12) <= target <= hi * T_min * (1 + 1e-12)


def _run(env, ctrl, seed, options):
    from wl_env.rollout import reset_controller

    obs, _ = env.reset(seed=seed, options=options)
    reset_controller(ctrl)
    total, done = 0.0, False
    while not done:
        obs, r, term, trunc, info = env.step(ctrl.act(obs))
        total, done = total + r, term or trunc
    return total, info


def test_finishing_late_costs_the_lateness_times_its_weight():
    """The same cycle (the operator's) under a target it misses and one it meets: the returns differ by
    exactly RewardConfig.late times the lateness, and nothing else."""
    from agents.evaluate import load_controller

    env = gym.make("WheelLoaderTarget-v0", braking="tc")
    ctrl = load_controller("operator", "tc")
    r_met, info_met = _run(env, ctrl, 0, {"target_time": 30.0})
    r_late, info_late = _run(env, ctrl, 0, {"target_time": 6.0})
    assert info_met["completed"] and info_met["lateness"] == 0.0
    T = info_late["t"]
    assert info_late["lateness"] == pytest.approx((T - 6.0) / 6.0)
    assert r_met - r_late == pytest.approx(env.unwrapped.core.reward.late * (T - 6.0) / 6.0, rel=1e-9)


@pytest.mark.parametrize("env_id,braking,init_noise,seed", [("WheelLoaderTarget-v0", "tc", 0.5, 11),
                                                          ("WheelLoaderTarget-v1", "service", 0.0, 5),
                                                          ("WheelLoaderTarget-v2", "tc", 0.0, 3),
                                                          ("WheelLoaderTarget-v3", "service", 0.0, 7),
                                                          ("WheelLoaderTarget-v4", "tc", 0.0, 9),
                                                          ("WheelLoaderTarget-v5", "service", 0.0, 13),
                                                          ("WheelLoaderTarget-v6", "tc", 0.0, 17)])
def test_the_vector_target_env_draws_targets_and_steps_as_single_envs_do(env_id, braking, init_noise, seed):
    n = 3
    power = 2.0 if env_id.endswith("v6") else 1.0  # (the skewed draw too)
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", braking=braking,
                        scenario="train", init_noise=init_noise, target_power=power)
    envs = [gym.make(env_id, braking=braking, scenario="train", init_noise=init_noise, target_power=power)
            for _ in range(n)]
    obs_v, _ = venv.reset(seed=seed)
    singles = [e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]
    np.testing.assert_array_equal(obs_v, np.stack(singles))
    rng = np.random.default_rng(0)
    n_act = venv.single_action_space.shape[0]
    for _ in range(40):
        a = rng.uniform(-1, 1, size=(n, n_act)).astype(np.float32)
        if n_act == 4:
            a[:, 3] = -1.0  # (hold the gear: a full leg; v3: coast from the lowest fraction's braking point)
        else:
            a[:, 1] = 0.6  # (lift: the assist stops the bucket; v2 shifts by itself)
        obs_v, rew_v, *_ = venv.step(a)
        for i, e in enumerate(envs):
            o, r, *_ = e.step(a[i])
            np.testing.assert_allclose(obs_v[i], o, rtol=0, atol=1e-6)
            assert rew_v[i] == pytest.approx(r, rel=1e-9, abs=1e-12)


def test_evaluation_at_a_target_reaches_the_target_env_through_its_observation():
    """`evaluate_controller(..., target_time=)` on the target env: the env observes the target (a controller
    that reads it there needs no reset(target_time=)), and each episode records it and its lateness."""
    from agents.evaluate import evaluate_controller, load_controller

    r = evaluate_controller(load_controller("operator", "tc"), "tc", episodes=1, env_id="WheelLoaderTarget-v0",
                            target_time=6.0, score=False)
    e = r["per_episode"][0]
    assert e["target_time"] == 6.0 and e["completed"]
    assert e["lateness"] == pytest.approx((e["T"] - 6.0) / 6.0) and r["summary"]["lateness_median"] == e["lateness"]


# ---------------------------------------------------------------- WheelLoaderTarget-v1: the engine-speed governor
@settings(max_examples=60, deadline=None)
@given(omega=st.floats(60.0, 230.0), V=st.floats(-2.0, 2.0), H=st.floats(0.7, 4.0), V_b=st.floats(0.0, 0.8),
       request=st.floats(60.0, 230.0), U_ab=st.floats(-2.5, 2.5), gear=st.sampled_from((-60.0, 0.0, 60.0)),
       tau=st.floats(0.02, 1.0))
def test_the_governor_inverts_the_engine_model(omega, V, H, V_b, request, U_ab, gear, tau):
    """The injection the governor commands gives d omega/dt = (request - omega) / tau, exactly, at the state
    it sees (eq. (1) is affine in U_mf)."""
    from wl_env.model import derivatives, governed_injection
    from wl_env.params import DEFAULT_PARAMS as p

    d = 1.0 if V >= 0 else -1.0
    u_mf = governed_injection(omega, V, H, V_b, request, U_ab, gear, d, p, tau)
    d_omega = derivatives(omega, V, H, V_b, u_mf, U_ab, 0.0, gear, d, p)[0]
    assert d_omega == pytest.approx((request - omega) / tau, rel=1e-9, abs=1e-7)


def test_the_governed_target_env_tracks_its_engine_speed_request():
    """WheelLoaderTarget-v1: action 0 maps [-1, 1] onto [omega_min + margin, omega_max]; under a held request
    the engine settles within 3 rad/s of it (the load moves within the interval the governor holds its
    injection over), and the injection applied is what the governor commanded, clipped by the machine."""
    from wl_env.codec import GOVERNOR_FLOOR_MARGIN

    env = gym.make("WheelLoaderTarget-v1", braking="tc")
    check_env(env.unwrapped, skip_render_check=True)
    core = env.unwrapped
    p = core.params
    assert core.codec.decode_speed_request(-1.0) == pytest.approx(p.omega_min + GOVERNOR_FLOOR_MARGIN)
    assert core.codec.decode_speed_request(1.0) == pytest.approx(p.omega_max)
    env.reset(seed=0, options={"target_ratio": 1.2})
    for request in (100.0, 160.0, 80.0):
        a0 = float(2.0 * (request - p.omega_min - GOVERNOR_FLOOR_MARGIN) / (p.omega_max - p.omega_min - GOVERNOR_FLOOR_MARGIN) - 1.0)
        for _ in range(6):  # reverse slowly while lifting (phase 1)
            _, _, term, trunc, info = env.step(np.array([a0, 0.3, -1.0, -1.0], np.float32))
            assert not (term or trunc)
            assert 0.0 <= info["controls"][0] <= p.U_mf_max
        assert abs(core._y[0] - request) < 3.0
    # the same actions in v0 are injections: another engine speed
    v0 = gym.make("WheelLoaderTarget-v0", braking="tc")
    v0.reset(seed=0, options={"target_ratio": 1.2})
    for _ in range(6):
        v0.step(np.array([-0.3, 0.3, -1.0, -1.0], np.float32))
    assert abs(v0.unwrapped._y[0] - 100.0) > 3.0


def test_a_fuel_action_other_than_the_two_is_refused():
    with pytest.raises(ValueError, match="fuel_action must be one of"):
        gym.make("WheelLoaderTarget-v0", fuel_action="throttle")


def test_an_injection_expert_drives_the_governed_env_as_it_drives_v0():
    """translate_fuel_action: the operator's injection actions, translated into requests, drive
    WheelLoaderTarget-v1 through the same cycle as v0 (the governor injects what the operator asked,
    within the request's range), and a request translates back into the injection the governor made."""
    from agents.evaluate import load_controller

    runs = {}
    for env_id in ("WheelLoaderTarget-v0", "WheelLoaderTarget-v1"):
        env = gym.make(env_id, braking="service")
        obs, _ = env.reset(seed=0, options={"target_ratio": 1.3})
        ctrl = load_controller("operator", "service")
        core, done, fuel = env.unwrapped, False, []
        while not done:
            a = ctrl.act(obs)
            if env_id.endswith("v1"):
                a0 = a[0]
                a[0] = core.core.translate_fuel_action(core.state, core.phase, a, to="engine_speed")
                back = core.core.translate_fuel_action(core.state, core.phase, a, to="injection")
                if -0.999 < a[0] < 0.999:  # (a request at its range's end is clipped: another injection)
                    assert back == pytest.approx(float(a0), abs=1e-6)
            obs, _, term, trunc, info = env.step(a)
            fuel.append(info["controls"][0])
            done = term or trunc
        runs[env_id] = (info, np.array(fuel))
    (i0, f0), (i1, f1) = runs.values()
    assert i0["completed"] and i1["completed"]
    assert i1["t"] == pytest.approx(i0["t"], abs=1e-9) and i1["fuel_g"] == pytest.approx(i0["fuel_g"], rel=1e-5)


# ---------------------------------------------------------------- WheelLoaderTarget-v2: the stopping assist
def _drive(env, driver, seed=0, options=None):
    obs, info = env.reset(seed=seed, options=options)
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(np.asarray(driver, dtype=np.float32))
        done = term or trunc
    return info


@pytest.mark.parametrize("env_id,braking,names", [
    ("WheelLoaderTarget-v2", "tc", "engine-speed request, bucket, braking fraction"),
    ("WheelLoaderTarget-v3", "service", "engine-speed request, bucket, braking fraction, coasting fraction")])
def test_the_assisted_envs_pass_check_env_and_refuse_another_action_count(env_id, braking, names):
    env = gym.make(env_id, braking=braking, scenario="train")
    check_env(env.unwrapped, skip_render_check=True)
    n = len(names.split(", "))
    assert env.action_space.shape == (n,)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=rf"shape \({n},\) \[{names}\]"):
        env.step(np.zeros(7 - n, dtype=np.float32))
    with pytest.raises(ValueError, match="assist=True needs fuel_action='engine_speed'"):
        gym.make(env_id, fuel_action="injection")
    with pytest.raises(ValueError, match="coast=True needs assist=True"):
        gym.make("WheelLoaderTarget-v1", coast=True)
    with pytest.raises(ValueError, match="coast must be True or False"):
        gym.make("WheelLoaderTarget-v3", coast="yes")


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_the_assist_stops_on_the_marks_and_the_request_trades_time_for_fuel(braking):
    """Held driver actions on held-out cycles: the assist meets the marks (5 cm, 2 cm) at every engine-speed
    request, and a lower request gives a slower, leaner cycle. With service brakes no violation; the
    converter's braking follows the engine speed, which falls no faster than an unfuelled engine does, so a
    held request can overshoot the limit slightly at the end of TC braking (measured: 2.2 % once in these 6
    cycles; a policy learns the request from which the engine comes down in time)."""
    from wl_env.suites import load_suite

    env = gym.make("WheelLoaderTarget-v2", braking=braking)
    for scenario in load_suite("test").of(braking)[:2]:
        runs = [_drive(env, (request, 0.6, 0.5), options={"scenario": scenario}) for request in (1.0, 0.0, -0.6)]
        for info in runs:
            assert info["is_success"] and info["violations"]["max_excess"] <= (0.0 if braking == "service" else 0.05), info
        T, fuel = [i["t"] for i in runs], [i["fuel_g"] for i in runs]
        assert T[0] < T[1] < T[2] and fuel[0] > fuel[1] > fuel[2], (T, fuel)


def test_the_operator_drives_with_the_assists_laws():
    """The operator's stopping laws are the assist's (one implementation): the assisted env driven at the full
    request with the operator's lift and braking fraction drives the operator's service cycle (the same
    cycle time; the fuel within 1 %: the operator injects, the assist requests an engine speed)."""
    from agents.evaluate import load_controller
    from wl_env.assist import BRAKING_FRACTION

    op = load_controller("operator", "service")
    lo, hi = BRAKING_FRACTION
    fraction = 2.0 * (0.85 - lo) / (hi - lo) - 1.0  # the operator's decel_margin
    ab_lo, ab_hi = -2.5, 2.5
    bucket = (op.lift_accel - 0.5 * (ab_lo + ab_hi)) / (0.5 * (ab_hi - ab_lo))
    assisted = _drive(gym.make("WheelLoaderTarget-v2", braking="service"), (1.0, bucket, fraction))
    operated = _run(gym.make("WheelLoader-v2", braking="service"), op, 0, None)[1]
    assert assisted["is_success"] and operated["is_success"]
    assert assisted["t"] == pytest.approx(operated["t"]) and assisted["fuel_g"] == pytest.approx(operated["fuel_g"], rel=0.01)


@settings(max_examples=200, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4),
       state=st.tuples(st.floats(57.0, 240.0), st.floats(-3.0, 3.0), st.floats(0.0, 6.0), st.floats(-0.5, 1.5)),
       to_go=st.floats(-1.0, 12.0), driver=st.tuples(*[st.floats(-3.0, 3.0)] * 3))
def test_the_assist_gives_a_machine_action_in_range_at_any_state(braking, phase, state, to_go, driver):
    """Any state and driver action (outside [-1, 1] too): a finite machine action in [-1, 1]; the brake only
    where the phase lets it act; a shift only out of phases 1 and 3; the bucket never asked past the curve
    that stops it at the dump height."""
    from wl_env.assist import assisted_action, bucket_command
    from wl_env.params import DEFAULT_PARAMS as p

    y = (*state, 0.0, 0.0)
    action = np.array([float(v) for v in assisted_action(y, phase, to_go, driver, p, braking, 0.1)])
    assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0 + 1e-12), action
    shifted = action[3] > 0
    assert not shifted or phase in (1, 3)
    interval_phase = phase + 1 if shifted else phase
    if interval_phase in (1, 3) or (interval_phase == 2 and braking == "tc"):
        assert action[2] == -1.0  # no service brake where it does not act
    asked = 2.5 * float(np.clip(driver[1], -1, 1))
    assert 2.5 * action[1] <= float(bucket_command(state[2], state[3], 2.5, p, 0.1)) + 1e-9
    assert 2.5 * action[1] <= max(asked, -2.5) + 1e-9


# ---------------------------------------------------------------- WheelLoaderTarget-v3: the coasting assist
@pytest.mark.parametrize("braking", ["service", "tc"])
def test_coasting_off_is_v2_and_coasting_saves_fuel_on_the_marks(braking):
    """v3 with the coasting fraction at the braking fraction drives v2's cycle exactly. At its lowest (15 %
    of the limit) the legs the service brakes end end early to coast: on held-out cycles the marks are met
    with no violation and the cycle is slower and leaner (the machine rolls instead of driving on)."""
    from wl_env.suites import load_suite

    v2, v3 = gym.make("WheelLoaderTarget-v2", braking=braking), gym.make("WheelLoaderTarget-v3", braking=braking)
    for scenario in load_suite("test").of(braking)[:2]:
        opts = {"scenario": scenario, "target_ratio": 1.3}
        driver = (0.3, 0.6, 1.0)
        plain = _drive(v2, driver, options=opts)
        held = _drive(v3, (*driver, 1.0), options=opts)
        assert held["t"] == plain["t"] and held["fuel_g"] == plain["fuel_g"]
        coasting = _drive(v3, (*driver, -1.0), options=opts)
        assert coasting["is_success"] and coasting["violations"]["max_excess"] == 0.0, coasting
        assert coasting["fuel_g"] < plain["fuel_g"] - 1.0 and coasting["t"] > plain["t"], (coasting, plain)


def test_a_leg_ends_early_only_at_the_coasting_braking_point_and_where_coasting_reaches_the_mark():
    from wl_env.assist import COAST_FRACTION, coasting_deceleration, early_shift, stopping_distance
    from wl_env.params import DEFAULT_PARAMS as p

    speed, dt = 1.2, 0.1
    reach = stopping_distance(speed, coasting_deceleration(p))  # ~2.9 m: rolling resistance alone
    coast_point = stopping_distance(speed, COAST_FRACTION[0] * p.decel_max * p.g) + speed * dt  # at 15 % of the limit
    reach_limit = reach - speed * dt  # the farthest mark coasting from here carries the machine a step past
    assert 2.0 < reach_limit < coast_point < reach_limit + 0.1  # at 1.2 m/s the two limits lie close
    short = reach_limit - 0.05  # within both
    for phase, braking, to_go, coast, ends in ((3, "service", short, -1.0, True),
                                               (3, "service", coast_point + 0.3, -1.0, False),  # before its braking point
                                               (3, "service", short, 1.0, False),  # at 95 %: its braking point is later
                                               (1, "service", short, -1.0, True),
                                               (1, "tc", short, -1.0, False),  # the converter brakes phase 2
                                               (3, "tc", short, -1.0, True),
                                               (2, "service", 0.5, -1.0, False), (4, "service", 0.5, -1.0, False)):
        assert bool(early_shift(phase, speed, to_go, coast, p, braking, dt)) is ends, (phase, braking, to_go, coast)
    # past 15 %'s braking point but beyond coasting's reach: refused until coasting reaches
    assert early_shift(3, speed, 0.5 * (reach_limit + coast_point) - 0.2, -1.0, p, "service", dt)
    assert not early_shift(3, speed, 0.5 * (reach_limit + coast_point), -1.0, p, "service", dt)
    assert COAST_FRACTION[0] > p.F_roll / p.M_tot / (p.decel_max * p.g)  # above coasting's own (~14 %)
    assert not early_shift(3, 0.01, 0.0, -1.0, p, "service", dt)  # standing: the leg has not begun


@settings(max_examples=200, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4),
       state=st.tuples(st.floats(57.0, 240.0), st.floats(-3.0, 3.0), st.floats(0.0, 6.0), st.floats(-0.5, 1.5)),
       to_go=st.floats(-1.0, 12.0), driver=st.tuples(*[st.floats(-3.0, 3.0)] * 4))
def test_the_coasting_assist_brakes_only_from_the_braking_point(braking, phase, state, to_go, driver):
    """Any state and driver action: a machine action in [-1, 1]; in a braking phase the service brakes act
    only where braking at the driver's fraction from the next step would no longer stop short of the mark,
    and with the coasting fraction at or above the braking fraction the action is v2's."""
    from wl_env.assist import BRAKING_FRACTION, COAST_FRACTION, assisted_action, stopping_distance
    from wl_env.params import DEFAULT_PARAMS as p

    y = (*state, 0.0, 0.0)
    action = np.array([float(v) for v in assisted_action(y, phase, to_go, driver, p, braking, 0.1, coast=True)])
    assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0 + 1e-12), action
    interval_phase = phase + 1 if action[3] > 0 and phase in (1, 3) else phase
    fraction = [lo + 0.5 * (float(np.clip(a, -1, 1)) + 1.0) * (hi - lo)
                for a, (lo, hi) in ((driver[2], BRAKING_FRACTION), (driver[3], COAST_FRACTION))]
    speed = abs(state[1])
    if interval_phase in (2, 4) and action[2] > -1.0:
        assert stopping_distance(speed, fraction[0] * p.decel_max * p.g) >= to_go - speed * 0.1 - 1e-9
    if fraction[1] >= fraction[0]:
        v2 = np.array([float(v) for v in assisted_action(y, phase, to_go, driver[:3], p, braking, 0.1)])
        if interval_phase in (1, 3) or action[2] > -1.0:
            np.testing.assert_array_equal(action, v2)


def test_an_all_out_driver_of_the_assist_finishes_within_a_few_percent_of_t_min(tmp_path, monkeypatch):
    """scripts/bench_assist_floor.py's scheduled driver (top engine speed, strongest braking, the bucket held
    while the engine runs up): on service `test` cycles the assist's laws leave it a few percent over each cycle's
    T_min (measured: 2.73 % median over 20, 1.6-9.7 % each), on its marks and within the limits. A change to the braking point
    or the stopping laws that costs time shows here."""
    import importlib.util
    import json
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "bench_assist_floor.py"
    spec = importlib.util.spec_from_file_location("bench_assist_floor", path)
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, bench)  # (its dataclass looks its module up there)
    spec.loader.exec_module(bench)
    out = tmp_path / "floor.json"
    summary = bench.run(bench.Options(braking="service", scenarios=4, out=str(out)))
    assert summary["success_rate"] == 1.0 and summary["max_violation"] == 0.0
    late = [r["lateness"] for r in json.loads(out.read_text())["records"]]
    # (never under T_min, the optimum's; short legs with a high dump height are the slowest, the bucket's lift
    # held back while the engine runs up: 8.8-9.7 % measured)
    assert all(0.0 < x < 0.12 for x in late) and np.median(late) < 0.04, late
    with pytest.raises(ValueError, match="--engine-fraction"):
        bench.run(bench.Options(engine_fraction=1.5))


# ---------------------------------------------------------------- WheelLoaderTarget-v4: the assist's guards
def test_the_tc_lift_guard_keeps_the_deceleration_limit_at_the_corners_where_v3_breaks_it():
    """A driver that lifts at once and brakes hardest: in v3 its bucket reaches the dump height early, the shift
    into forward gear meets an engine the wheels hold up and the converter brakes over the limit at 52 of the 128
    corners of the scenario ranges (by up to 40 %, measured; 68 corners, up to 189 %, with a full request). v4's
    assist holds the lift for the braking: no corner over the limit, every mark met."""
    driver = (0.0, 1.0, 1.0, 1.0)
    from wl_env.suites import corner_scenarios

    corners = corner_scenarios("tc")
    runs = {}
    for env_id in ("WheelLoaderTarget-v3", "WheelLoaderTarget-v4"):
        env = gym.make(env_id, braking="tc")
        runs[env_id] = [_drive(env, driver, options={"scenario": c, "target_ratio": 1.0}) for c in corners]
    over = {k: sum(i["violations"]["max_excess"] > 0 for i in v) for k, v in runs.items()}
    assert over["WheelLoaderTarget-v3"] >= 40 and over["WheelLoaderTarget-v4"] == 0, over
    assert all(i["is_success"] for i in runs["WheelLoaderTarget-v4"])


@settings(max_examples=300, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4),
       state=st.tuples(st.floats(57.0, 240.0), st.floats(-3.0, 3.0), st.floats(0.0, 6.0), st.floats(-0.5, 1.5)),
       to_go=st.floats(-1.0, 12.0), driver=st.tuples(*[st.floats(-3.0, 3.0)] * 4))
def test_the_guards_change_the_action_only_where_they_say(braking, phase, state, to_go, driver):
    """v4 against v3 at any state: a shift wherever v3 shifts, and also a leg standing on its mark (whose next
    phase then acts as after any shift); otherwise the same brake; a higher request only as the creep floor (a machine crawling short of its mark in phase 1 or 3), a
    lower one only through the TC lift-off; a bucket different from v3's only where a guard says (phases 1-2
    with TC braking, phase 4's last lift) and always under the curve that stops it at the dump height."""
    from wl_env.assist import CREEP_SPEED, MIN_MOVING_SPEED, assisted_action, bucket_command
    from wl_env.episode import DISTANCE_TOL
    from wl_env.params import DEFAULT_PARAMS as p

    y = (*state, 0.0, 0.0)
    v3, v4 = (np.array([float(v) for v in assisted_action(y, phase, to_go, driver, p, braking, 0.1, coast=True,
                                                          guards=guards)]) for guards in (False, True))
    speed = abs(state[1])
    leg = phase in (1, 3)
    on_mark = leg and speed < MIN_MOVING_SPEED and abs(to_go) <= DISTANCE_TOL
    ended_on_mark = v4[3] > 0 > v3[3] and on_mark
    assert v4[3] == v3[3] or ended_on_mark, (v3, v4)
    assert v4[2] == v3[2] or ended_on_mark, (v3, v4)  # (a leg ended on its mark brakes its last cm/s, as any)
    crawling = leg and v4[3] < 0 and speed < CREEP_SPEED and to_go > DISTANCE_TOL
    tc_lift = braking == "tc" and phase in (1, 2)
    assert v4[0] <= v3[0] + 1e-12 or crawling or ended_on_mark, (v3, v4)
    assert v4[0] >= v3[0] - 1e-12 or tc_lift or ended_on_mark, (v3, v4)
    last_braking = phase == 4 or (phase == 3 and v4[3] > 0)
    assert v4[1] == v3[1] or tc_lift or last_braking or ended_on_mark, (v3, v4)
    assert 2.5 * v4[1] <= float(bucket_command(state[2], state[3], 2.5, p, 0.1)) + 1e-9


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_the_creep_floor_and_the_last_lift_finish_a_cycle_an_idling_driver_would_not(braking):
    """A 13 t machine at c_r 0.05 with the driver idling the engine (the v3 policies' failures at 1.5 T_min):
    standing 30 cm short of the truck, v3 leaves it standing, v4 asks the engine speed that moves it off at
    CREEP_ACCELERATION (the model's own acceleration there); standing on its mark, v4 ends the leg; braking to
    the stop with 1.5 m of lift left, v4 lifts."""
    from wl_env import cycle
    from wl_env.assist import CREEP_ACCELERATION, assisted_action
    from wl_env.codec import encode_speed_request
    from wl_env.model import derivatives
    from wl_env.params import DEFAULT_PARAMS

    p = Scenario(braking=braking, payload=13000.0, rolling_resistance=0.05).params(DEFAULT_PARAMS)
    idle = (-1.0, -1.0, 1.0, 1.0)

    def act(y, phase, to_go, guards):
        return [float(v) for v in assisted_action(y, phase, to_go, idle, p, braking, 0.1, coast=True, guards=guards)]

    standing = (p.omega_min + 5.0, 0.0, p.H_T, 0.0, 0.0, 0.0)
    v3, v4 = act(standing, 3, 0.3, False), act(standing, 3, 0.3, True)
    assert v3[0] == -1.0 and v4[0] > -1.0 and v4[3] < 0
    spec = cycle.phase_specs(braking, p)[2]
    omega = next(w for w in np.linspace(p.omega_min, p.omega_max, 4000) if encode_speed_request(w, p) >= v4[0])
    assert derivatives(omega, 0.0, p.H_T, 0.0, 0.0, 0.0, 0.0, spec.gear, spec.direction, p)[1] >= 0.99 * CREEP_ACCELERATION
    assert act(standing, 3, 0.03, False)[3] < 0 < act(standing, 3, 0.03, True)[3]  # on the mark: the leg ends
    braking_to_stop = (120.0, 0.5, p.H_T - 1.5, 0.0, 0.0, 0.0)  # (0.8 s to the stop; the lift left, ~2 s)
    assert act(braking_to_stop, 4, 0.2, True)[1] > act(braking_to_stop, 4, 0.2, False)[1]


def test_the_creep_speed_is_the_machines_and_follows_a_redrawn_loader():
    """The creep floor's engine speed, computed once per machine: a batch of three gives each machine's own, and
    a loader redrawn in place (as the vector env's autoreset does) gets its new machine's, not the cached one."""
    from wl_env.assist import creep_speed
    from wl_env.params import DEFAULT_PARAMS, ParamsView

    machines = [Scenario(braking="service", payload=m, rolling_resistance=c).params(DEFAULT_PARAMS)
                for m, c in ((6000.0, 0.015), (13000.0, 0.05), (9000.0, 0.03))]
    view = ParamsView(DEFAULT_PARAMS, M_load=np.array([q.M_load for q in machines]), c_r=np.array([q.c_r for q in machines]))
    own = [float(creep_speed(q, "service")) for q in machines]
    assert own[0] < own[2] < own[1]  # (heavier and harder to roll: a faster engine)
    np.testing.assert_array_equal(creep_speed(view, "service"), own)
    view.values["M_load"][1], view.values["c_r"][1] = machines[0].M_load, machines[0].c_r
    np.testing.assert_array_equal(creep_speed(view, "service"), [own[0], own[0], own[2]])


def test_the_guards_are_a_flag_of_the_assist():
    assert gym.make("WheelLoaderTarget-v4").unwrapped.guards is True
    assert gym.make("WheelLoaderTarget-v4").unwrapped.lift_floor is False
    assert gym.make("WheelLoaderTarget-v5").unwrapped.lift_floor is True
    with pytest.raises(ValueError, match="guards=True needs assist=True"):
        gym.make("WheelLoaderTarget-v1", guards=True)
    with pytest.raises(ValueError, match="guards must be True or False"):
        gym.make("WheelLoaderTarget-v4", guards="yes")
    with pytest.raises(ValueError, match="lift_floor=True needs assist=True"):
        gym.make_vec("WheelLoaderTarget-v1", num_envs=2, vectorization_mode="vector_entry_point", lift_floor=True)
    with pytest.raises(ValueError, match="lift_floor must be True or False"):
        gym.make("WheelLoaderTarget-v5", lift_floor=1)


def _at_tc_corners(env_id, driver, target_ratio):
    """A constant driver's end infos at every fourth TC corner of the scenario ranges (32), at a target ratio."""
    from wl_env.suites import corner_scenarios

    env = gym.make(env_id, braking="tc")
    return [_drive(env, driver, options={"scenario": c, "target_ratio": target_ratio}) for c in corner_scenarios("tc")[::4]]


# ------------------------------------------------------- WheelLoaderTarget-v5: the lift's engine floor
def test_the_lift_floor_keeps_an_idling_engine_running_under_the_lift_at_the_corners():
    """A driver that idles the engine and lifts at full acceleration (TC braking, 1.5 T_min): in v4 the lift's
    load, rising within each step faster than the governor meters, stalls the engine in phase 1 at 72 of the 128
    corners (measured); v5's floor keeps it running at every one (32 corners here, every fourth)."""
    stalled = {env_id: sum(i["stalled"] for i in _at_tc_corners(env_id, (-1.0, 1.0, 1.0, 1.0), 1.5))
               for env_id in ("WheelLoaderTarget-v4", "WheelLoaderTarget-v5")}
    assert stalled["WheelLoaderTarget-v4"] >= 10 and stalled["WheelLoaderTarget-v5"] == 0, stalled


@settings(max_examples=300, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4),
       state=st.tuples(st.floats(57.0, 240.0), st.floats(-3.0, 3.0), st.floats(0.0, 6.0), st.floats(-0.5, 1.5)),
       to_go=st.floats(-1.0, 12.0), driver=st.tuples(*[st.floats(-3.0, 3.0)] * 4))
def test_the_lift_floor_only_raises_the_request_of_a_lifting_bucket_to_the_floor(braking, phase, state, to_go, driver):
    """v5 against v4 at any state: the same bucket, brake and shift; the request the larger of v4's and the floor's
    where the bucket lifts (outside the TC metering), v4's elsewhere."""
    from wl_env.assist import IDLE_BUCKET_SPEED, LIFT_ENGINE_FLOOR, assisted_action
    from wl_env.codec import encode_speed_request
    from wl_env.params import DEFAULT_PARAMS as p

    y = (*state, 0.0, 0.0)
    v4, v5 = (np.array([float(v) for v in assisted_action(y, phase, to_go, driver, p, braking, 0.1, coast=True,
                                                          guards=True, lift_floor=floor)]) for floor in (False, True))
    np.testing.assert_array_equal(v5[1:], v4[1:])
    floor = float(encode_speed_request(LIFT_ENGINE_FLOOR * p.omega_min, p))
    assert v5[0] in (v4[0], floor) and v5[0] >= v4[0]
    if v5[0] != v4[0]:
        ab_lo, ab_hi = p.U_ab_bounds
        assert v4[1] > -(ab_hi + ab_lo) / (ab_hi - ab_lo) or state[3] > IDLE_BUCKET_SPEED  # (lifting)


# ------------------------------------------------------- WheelLoaderTarget-v6: the lift-off's full load
def test_v6_is_v5_with_the_lift_off_load():
    assert gym.make("WheelLoaderTarget-v6").unwrapped.lift_off_load is True
    assert gym.make("WheelLoaderTarget-v5").unwrapped.lift_off_load is False
    with pytest.raises(ValueError, match="lift_off_load=True needs guards=True"):
        gym.make("WheelLoaderTarget-v3", lift_off_load=True)
    with pytest.raises(ValueError, match="lift_off_load=True needs assist=True"):
        gym.make_vec("WheelLoaderTarget-v1", num_envs=2, vectorization_mode="vector_entry_point", lift_off_load=True)
    with pytest.raises(ValueError, match="lift_off_load must be True or False"):
        gym.make("WheelLoaderTarget-v6", lift_off_load="on")


def test_the_lift_off_load_keeps_the_deceleration_limit_where_a_driver_slows_the_lift():
    """A TC driver racing the engine (request +1) and braking the bucket (-1), at T_min: in v5 its lift-offs
    meet the shift into forward gear with the engine high and the converter brakes up to 171 % over the limit
    at 24 of these 32 corners (measured); v6's full lift through the lift-off keeps the limit at every one."""
    over = {env_id: sum(i["violations"]["max_excess"] > 0.0 for i in _at_tc_corners(env_id, (1.0, -1.0, 1.0, 1.0), 1.0))
            for env_id in ("WheelLoaderTarget-v5", "WheelLoaderTarget-v6")}
    assert over["WheelLoaderTarget-v5"] >= 12 and over["WheelLoaderTarget-v6"] == 0, over


@settings(max_examples=300, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4),
       state=st.tuples(st.floats(57.0, 240.0), st.floats(-3.0, 3.0), st.floats(0.0, 6.0), st.floats(-0.5, 1.5)),
       to_go=st.floats(-1.0, 12.0), driver=st.tuples(*[st.floats(-3.0, 3.0)] * 4))
def test_the_lift_off_load_only_ever_lifts_harder_and_only_with_tc_braking(braking, phase, state, to_go, driver):
    """v6 against v5 at any state: the same request, brake and shift; the bucket v5's, or (TC braking only)
    the bucket a driver asking the full lift gets."""
    from wl_env.assist import assisted_action
    from wl_env.params import DEFAULT_PARAMS as p

    y = (*state, 0.0, 0.0)

    def act(drv, load):
        return np.array([float(v) for v in assisted_action(y, phase, to_go, drv, p, braking, 0.1, coast=True,
                                                           guards=True, lift_floor=True, lift_off_load=load)])

    v5, v6 = act(driver, False), act(driver, True)
    np.testing.assert_array_equal(v6[[0, 2, 3]], v5[[0, 2, 3]])
    if v6[1] != v5[1]:
        assert braking == "tc" and v6[1] > v5[1]
        assert v6[1] == act((driver[0], 1.0, *driver[2:]), False)[1]  # (the full lift's command)


# ------------------------------------------------------- WheelLoaderTarget-v7: the braking on the step grid
def test_v7_is_v6_with_the_braking_on_the_step_grid():
    assert gym.make("WheelLoaderTarget-v7").unwrapped.step_braking is True
    assert gym.make("WheelLoaderTarget-v6").unwrapped.step_braking is False
    check_env(gym.make("WheelLoaderTarget-v7", braking="tc", scenario="train").unwrapped, skip_render_check=True)
    with pytest.raises(ValueError, match="step_braking=True needs assist=True"):
        gym.make_vec("WheelLoaderTarget-v1", num_envs=2, vectorization_mode="vector_entry_point", step_braking=True)
    with pytest.raises(ValueError, match="step_braking must be True or False"):
        gym.make("WheelLoaderTarget-v7", step_braking=1)


@settings(max_examples=500, deadline=None)
@given(speed=st.floats(0.0, 4.0), to_go=st.floats(0.0, 15.0), fraction=st.floats(0.5, 0.98))
def test_the_step_braking_leaves_the_planned_deceleration_to_the_mark(speed, to_go, fraction):
    """After the first braking step (point-mass kinematics over dt), braking at the planned deceleration stops
    on the mark; a machine that stops within the step asks what stops it there; never more than 98 % of the limit."""
    from wl_env.assist import MAX_BRAKING_FRACTION, step_braking_deceleration
    from wl_env.params import DEFAULT_PARAMS as p

    dt, a_limit = 0.1, p.decel_max * p.g
    planned = fraction * a_limit
    a = float(step_braking_deceleration(speed, to_go, planned, p, dt))
    assert 0.0 <= a <= MAX_BRAKING_FRACTION * a_limit
    if speed <= 1e-3:
        assert a == 0.0
        return
    d = max(to_go, 1e-3)  # (a machine on its mark or past it aims 1 mm ahead)
    v1, d1 = speed - a * dt, d - speed * dt + 0.5 * a * dt * dt
    if 0.0 < a < MAX_BRAKING_FRACTION * a_limit and v1 > 0.0:  # (unclipped, and the machine still rolls)
        assert v1 * v1 / (2.0 * planned) == pytest.approx(d1, rel=1e-9, abs=1e-9)
    elif v1 <= 0.0 and a < MAX_BRAKING_FRACTION * a_limit:  # (it stands within the step: on the mark)
        assert speed * speed / (2.0 * a) == pytest.approx(d, rel=1e-9)
    # a machine already on the planned curve keeps its deceleration
    on_curve = float(step_braking_deceleration(speed, speed * speed / (2.0 * planned), planned, p, dt))
    if speed > planned * dt:
        assert on_curve == pytest.approx(min(planned, MAX_BRAKING_FRACTION * a_limit), rel=1e-9)


@settings(max_examples=300, deadline=None)
@given(braking=st.sampled_from(["service", "tc"]), phase=st.integers(1, 4),
       state=st.tuples(st.floats(57.0, 240.0), st.floats(-3.0, 3.0), st.floats(0.0, 6.0), st.floats(-0.5, 1.5)),
       to_go=st.floats(-1.0, 12.0), driver=st.tuples(*[st.floats(-3.0, 3.0)] * 4))
def test_the_step_braking_moves_no_leg_end(braking, phase, state, to_go, driver):
    """v7 against v6 at any state: the same shift (where the legs end is the driver's), and outside a braking
    phase the same action."""
    from wl_env.assist import assisted_action
    from wl_env.params import DEFAULT_PARAMS as p

    y = (*state, 0.0, 0.0)

    def act(step_braking):
        return np.array([float(v) for v in assisted_action(y, phase, to_go, driver, p, braking, 0.1, coast=True,
                                                           guards=True, lift_floor=True, lift_off_load=True,
                                                           step_braking=step_braking)])

    v6, v7 = act(False), act(True)
    assert v7[3] == v6[3]
    braking_now = phase in (2, 4) or v6[3] > 0.0
    tc_lift_off = braking == "tc" and phase == 1
    if not braking_now and not tc_lift_off:
        np.testing.assert_array_equal(v7, v6)


def test_an_all_out_driver_ends_no_later_on_v7_and_a_step_earlier_on_some_cycles(tmp_path, monkeypatch):
    """scripts/bench_assist_floor.py's scheduled driver on v6 and v7, 6 service `test` cycles at T_min: v7 is never
    later, earlier on some (measured over 20: 9 a step earlier, median lateness 2.73 -> 2.09 %), on its marks
    and within the limits."""
    import importlib.util
    import json
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / "bench_assist_floor.py"
    spec = importlib.util.spec_from_file_location("bench_assist_floor", path)
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, bench)
    spec.loader.exec_module(bench)
    late = {}
    for env_id in ("WheelLoaderTarget-v6", "WheelLoaderTarget-v7"):
        out = tmp_path / f"{env_id}.json"
        summary = bench.run(bench.Options(braking="service", scenarios=6, env_id=env_id, out=str(out)))
        assert summary["success_rate"] == 1.0 and summary["max_violation"] == 0.0
        late[env_id] = np.array([r["lateness"] for r in json.loads(out.read_text())["records"]])
    earlier = late["WheelLoaderTarget-v7"] < late["WheelLoaderTarget-v6"] - 1e-9
    assert np.all(late["WheelLoaderTarget-v7"] <= late["WheelLoaderTarget-v6"] + 1e-9) and earlier.any(), late
    with pytest.raises(ValueError, match="--env-id"):
        bench.run(bench.Options(env_id="WheelLoaderTarget-v2"))


def test_the_last_lift_of_v7_reaches_the_dump_height_where_v6s_clock_would_stop_short():
    """A random plan on a `train` draw (found among 2048): v7 stops this machine a step earlier than v6, and v6's
    last-lift clock (the lift at the pump's speed, against the constant-deceleration stop) left its idle bucket
    2 cm short of the dump height; v7's clock (the bucket's acceleration and stop, the step braking's stop) lifts
    in time."""
    from unittest import mock

    import wl_env.assist as assist
    from wl_env.scenario import Scenario

    sc = Scenario(payload=7240.0, reverse_distance=6.68, forward_distance=8.73, rolling_resistance=0.0173,
                  dump_height=3.55, start_engine_speed=1574.0, start_bucket_height=0.75, braking="service")
    plan = np.array([0.631, -0.854, -0.286, -0.277, 0.928, 0.796, 0.746, 0.323, 0.497, -0.684, 0.135, -0.397, 0.733,
                     -0.76], dtype=np.float32)

    def run():
        env = gym.make("WheelLoaderPlan-v1", scenario=sc)
        env.reset(seed=0)
        return env.step(plan)[-1]

    assert run()["is_success"]
    with mock.patch.object(assist, "bucket_travel_time", lambda omega, H, V_b, p: assist.lift_time(omega, H, p)), \
         mock.patch.object(assist, "stopping_time", lambda speed, to_go, planned: 2.0 * to_go / np.maximum(speed, 1e-3)):
        info = run()
    assert not info["is_success"] and 0.02 < sc.dump_height - info["state"][2] < 0.05, info["state"]
