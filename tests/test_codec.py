"""The observation and action codec (wl_env.codec): what the environment encodes, a controller decodes
back, by name, for any parameter set; a bad observation is a clear error."""

import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import wl_env  # noqa: F401  (registers the env)
from wl_env.codec import GOVERNOR_FLOOR_MARGIN, N_OBS, OBS_HIGH, OBS_LOW, TIME_SCALE, Codec, encode_speed_request
from wl_env.params import DEFAULT_PARAMS as P


@settings(max_examples=200, deadline=None)
@given(st.floats(60.0, 230.0), st.floats(-2.5, 2.5), st.floats(0.7, 5.1), st.floats(0.0, 1.5),
       st.floats(-13.0, 6.0), st.floats(0.0, 0.3), st.integers(1, 4), st.floats(0.0, 55.0))
def test_decode_inverts_encode_within_float32(omega, V, H, V_b, s, m_f, phase, t):
    codec = Codec(P)
    obs = np.array(codec.encode_observation((omega, V, H, V_b, s, m_f), phase, t), dtype=np.float32)
    assert ((obs >= OBS_LOW) & (obs <= OBS_HIGH)).all()  # encoded clipped
    o = codec.decode_observation(obs)
    assert o.phase == phase
    for value, decoded in ((omega, o.engine_speed), (V, o.vehicle_speed), (H, o.bucket_height), (V_b, o.bucket_speed),
                           (s, o.position), (t, o.time), (m_f, o.fuel_kg)):
        assert decoded == pytest.approx(value, rel=1e-6, abs=1e-5)
    to_go = s + P.reverse_distance if phase <= 2 else P.final_position - s
    assert o.distance_to_go == pytest.approx(to_go, rel=1e-6, abs=1e-5)


def test_actions_round_trip_and_clip():
    codec = Codec(P)
    lo, hi = P.U_ab_bounds
    for u in ((0.0, lo, 0.0), (P.U_mf_max, hi, P.U_b_max), (130.0, 0.3, 12345.0)):
        a = codec.encode_action(*u, shift=True)
        assert a[3] == 1.0
        assert np.allclose(codec.decode_action(*a[:3].astype(float)), u, rtol=1e-6, atol=1e-3)
    a = codec.encode_action(1e9, math.nan, -5.0, shift=False)  # beyond the ranges, NaN: clipped, no brake
    assert a.tolist() == [1.0, -1.0, -1.0, -1.0]


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-50.0, 400.0), min_size=1, max_size=8))
def test_speed_requests_round_trip_for_one_loader_and_for_arrays(requests):
    """The governor's request encodes within [-1, 1], back to itself inside the governed range, the same
    for a float and an array of loaders (the assist meters a vector env's converters through it)."""
    codec = Codec(P)
    omegas = np.array(requests)
    encoded = encode_speed_request(omegas, P)
    assert ((encoded >= -1.0) & (encoded <= 1.0)).all()
    assert np.array_equal(encoded, [codec.encode_speed_request(w) for w in requests])
    lo = P.omega_min + GOVERNOR_FLOOR_MARGIN
    assert np.allclose(codec.decode_speed_request(encoded), np.clip(omegas, lo, P.omega_max), rtol=1e-12, atol=1e-9)


def test_the_env_observes_what_the_codec_decodes():
    """A controller reads state, time and phase from the codec alone (no copy of max_time or a scale)."""
    params = P.replace(distance=5.0, H_T=4.5)
    env = gym.make("WheelLoader-v1", braking="tc", params=params, max_time=25.0).unwrapped
    obs, _ = env.reset(seed=0)
    codec = Codec(params)
    for _ in range(15):
        obs, *_ = env.step(np.array([1.0, 0.5, -1.0, -1.0], np.float32))
    o = codec.decode_observation(obs)
    assert o.time == pytest.approx(env.time, abs=1e-5) and o.phase == env.phase
    assert np.allclose(o.state, [*env.state, env.position], rtol=1e-6, atol=1e-5)
    assert o.distance_to_go == pytest.approx(env.position + 5.0, abs=1e-5)  # the scenario's own distance
    assert TIME_SCALE == 40.0


def test_batches_decode_column_wise_and_bad_observations_are_named():
    codec = Codec(P)
    batch = np.stack([np.array(codec.encode_observation((150.0 + i, -1.0, 2.0, 0.3, -2.0, 0.01), 1 + i % 4, 1.0),
                               dtype=np.float32) for i in range(5)])
    o = codec.decode_observation(batch)
    assert o.engine_speed.shape == (5,) and o.phase.tolist() == [1, 2, 3, 4, 1]
    for bad in (np.zeros(N_OBS - 1), np.full(N_OBS, np.nan), np.zeros((2, 3, N_OBS))):
        with pytest.raises(ValueError, match="observations of shape"):
            codec.decode_observation(bad)


def test_an_observation_outside_its_space_is_refused_naming_the_entry():
    """An engine speed of 50 omega_max, a speed of -20 V_max, a time of -200 s or no phase was planned from as if real
    (the MPC reported a solved plan); each is a ValueError naming the entry and its range."""
    import gymnasium as gym

    from wl_env.codec import Codec

    obs, _ = gym.make("WheelLoader-v1").reset(seed=0)
    codec = Codec()
    codec.decode_observation(obs)  # (the env's own: in range)
    for i, v, needle in [(0, 50.0, r"obs\[0\] \(engine_speed"), (1, -20.0, r"obs\[1\]"), (6, -5.0, r"obs\[6\] \(time")]:
        bad = obs.copy()
        bad[i] = v
        with pytest.raises(ValueError, match=needle + ".* must lie in"):
            codec.decode_observation(bad)
    for phases in ([0, 0, 0, 0], [1, 1, 0, 0], [0.5, 0.5, 0, 0]):
        bad = obs.copy()
        bad[8:12] = phases
        with pytest.raises(ValueError, match="one-hot"):
            codec.decode_observation(bad)


def test_an_observation_of_no_real_numbers_is_refused_by_name():
    """A dict was a bare TypeError; booleans, complex numbers or digit strings were cast without a word (a bool
    array read as the engine at omega_max) for every controller that decodes observations (operator, plan driver, MPC)."""
    obs, _ = gym.make("WheelLoader-v2").reset(seed=0)
    codec = Codec(observe_scenario=True)
    for bad in ({"a": 1}, obs.astype(bool), obs.astype(complex), np.array([str(v) for v in obs]), None):
        with pytest.raises(ValueError, match=r"obs must be WheelLoader observations \(arrays of real numbers\)"):
            codec.decode_observation(bad)
    assert codec.decode_observation(obs.astype(np.float16)).phase == 1


# ------------------------------------------------------------------ hostile inputs (eleventh round, wl_env's API)
def test_the_codec_refuses_a_layout_shift_or_control_that_is_no_bool_or_number_by_name():
    """Codec(observe_scenario="no") chose v2's layout; encode_action's shift NaN or "no" was a shift request, a string
    control numpy's TypeError."""
    for bad in ("no", 1, None, np.nan):
        with pytest.raises(ValueError, match="observe_scenario must be True or False"):
            Codec(observe_scenario=bad)
    assert Codec(observe_scenario=np.bool_(True)).n_obs == 19
    codec = Codec()
    for bad in (math.nan, "no", 1.0, None):
        with pytest.raises(ValueError, match="shift must be True or False"):
            codec.encode_action(100.0, 0.0, 0.0, bad)
    for bad in ("1", None, [1.0, 2.0], np.array([1.0, 2.0]), True):
        with pytest.raises(ValueError, match="u_mf must be a number"):
            codec.encode_action(bad, 0.0, 0.0, False)
    same = codec.encode_action(np.float64(130.0), np.array(0.0), 0, np.bool_(True))
    assert np.array_equal(same, codec.encode_action(130.0, 0.0, 0.0, True))
    assert codec.encode_action(math.nan, 0.0, 0.0, False)[0] == -1.0  # (a NaN control: the range's low end, as before)


def test_the_plan_driver_refuses_what_is_no_single_observation_by_name():
    """PlanDriver.act on a dict or a string was an IndexError, on a batch "attempt to get argmax of an empty
    sequence"; a single observation drives as before."""
    from wl_env.plan import N_PLAN_ACTIONS, PlanDriver, plan_action

    obs, _ = gym.make("WheelLoaderTarget-v7").reset(seed=0)
    driver = PlanDriver(np.zeros(N_PLAN_ACTIONS))
    for bad in ({"a": 1}, "abc", None):
        with pytest.raises(ValueError, match=r"obs must be WheelLoader observations"):
            driver.act(bad)
    with pytest.raises(ValueError, match=r"PlanDriver.act takes one observation \(shape \(21,\)\), got a batch"):
        driver.act(np.stack([obs, obs]))
    expected = plan_action(np.zeros((1, N_PLAN_ACTIONS)), obs[None], np.zeros(1), Codec(observe_scenario=True), 0.1)[0]
    assert np.array_equal(driver.act(list(obs)), expected.astype(np.float32))
