"""WheelLoader-v1: Gymnasium API, determinism, the vector env, robustness, bad input."""

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import wl_env  # noqa: F401  (registers the ids)
from agents.operator import OperatorPolicy, run_episode
from wl_env.env import WheelLoaderEnv

BRAKINGS = ["service", "tc"]


@pytest.mark.parametrize("braking", BRAKINGS)
def test_gymnasium_check_env(braking):
    gym_check_env(gym.make("WheelLoader-v1", braking=braking).unwrapped, skip_render_check=True)


@pytest.mark.parametrize("braking", BRAKINGS)
def test_sb3_check_env(braking):
    from stable_baselines3.common.env_checker import check_env

    check_env(WheelLoaderEnv(braking=braking), warn=True)


def test_registered_with_version_and_spec():
    spec = gym.spec("WheelLoader-v1")
    assert spec.version == 1 and spec.vector_entry_point is not None


@pytest.mark.parametrize("braking", BRAKINGS)
def test_deterministic_under_a_seed(braking):
    def rollout(seed):
        env = gym.make("WheelLoader-v1", braking=braking, init_noise=0.5)
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        out = [obs]
        for _ in range(80):
            obs, r, te, tr, _ = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
            out.append(np.append(obs, r))
            if te or tr:
                obs, _ = env.reset()
        return np.concatenate(out)

    np.testing.assert_array_equal(rollout(7), rollout(7))
    assert not np.array_equal(rollout(7), rollout(8))


def test_reset_takes_a_numpy_seed_and_refuses_others_by_name():
    """A numpy integer seeds as the int it holds; a negative, fractional, string or bool seed is a ValueError
    naming it (gymnasium's own error is not one, and it took True for seed 1), as the vector env's."""
    env = gym.make("WheelLoaderTarget-v5", init_noise=0.5)
    np.testing.assert_array_equal(env.reset(seed=np.int64(3))[0], env.reset(seed=3)[0])
    for bad in (-1, 1.5, "1", True):
        with pytest.raises(ValueError, match="seed must be an integer >= 0 or None"):
            env.reset(seed=bad)


@pytest.mark.parametrize("braking", BRAKINGS)
def test_vector_env_equals_single_envs(braking):
    n = 6
    venv = gym.make_vec("WheelLoader-v1", num_envs=n, vectorization_mode="vector_entry_point", braking=braking, init_noise=0.3)
    envs = [gym.make("WheelLoader-v1", braking=braking, init_noise=0.3) for _ in range(n)]
    ov, _ = venv.reset(seed=11)
    singles = [e.reset(seed=11 + i)[0] for i, e in enumerate(envs)]
    np.testing.assert_array_equal(ov, np.stack(singles))
    pilot = OperatorPolicy(braking)
    rng = np.random.default_rng(2)
    done = np.zeros(n, dtype=bool)
    ends = 0
    for _ in range(250):
        a = pilot.act(ov) + rng.normal(0, 0.2, (n, 4)).astype(np.float32)
        a = np.clip(a, -1, 1)
        ov, rv, tv, trv, iv = venv.step(a)
        for i, e in enumerate(envs):
            if done[i]:
                o, _ = e.reset()
                r, t, tr = 0.0, False, False
            else:
                o, r, t, tr, _ = e.step(a[i])
            np.testing.assert_array_equal(o, ov[i])
            assert r == rv[i] and t == tv[i] and tr == trv[i]
        done = tv | trv
        ends += int(done.sum())
    assert ends >= n  # every loader finished at least one episode and was auto-reset


def test_many_random_steps_stay_finite():
    venv = gym.make_vec("WheelLoader-v1", num_envs=200, vectorization_mode="vector_entry_point", braking="tc", init_noise=1.0)
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(500):  # 10^5 env steps of uniformly random actions, both ends of every range
        a = rng.uniform(-1.2, 1.2, (200, 4)).astype(np.float32)
        obs, rew, te, tr, info = venv.step(a)
        assert np.isfinite(obs).all() and np.isfinite(rew).all()
        assert venv.observation_space.contains(obs)


@pytest.mark.slow
@pytest.mark.parametrize("braking", BRAKINGS)
def test_57_million_random_vector_steps_stay_finite(braking):
    """The issue's figure (#12): 57 M env-steps (two brakings x 28 M) of random actions beyond both ends of
    every range, no NaN or inf and no observation out of bounds (about 1 min each at N = 1024)."""
    n = 1024
    venv = gym.make_vec("WheelLoader-v1", num_envs=n, vectorization_mode="vector_entry_point", braking=braking,
                        init_noise=1.0)
    obs, _ = venv.reset(seed=1)
    rng = np.random.default_rng(1)
    low, high = venv.single_observation_space.low, venv.single_observation_space.high
    for _ in range(28_000_000 // n):
        obs, rew, *_ = venv.step(rng.uniform(-1.2, 1.2, (n, 4)).astype(np.float32))
        assert np.isfinite(obs).all() and np.isfinite(rew).all()
        assert (obs >= low).all() and (obs <= high).all()


@pytest.mark.parametrize("braking", BRAKINGS)
def test_operator_completes_the_cycle(braking):
    env = gym.make("WheelLoader-v1", braking=braking)
    r = run_episode(env, OperatorPolicy(braking), seed=0)
    # the end targets met (5 cm, 2 cm) within the driver's limits: a baseline, not a rule-breaker
    assert r.completed and r.success and not r.stalled
    assert abs(r.final_height_error_m) < 0.02 and r.max_violation == 0.0
    env = gym.make("WheelLoader-v1", braking=braking, init_noise=1.0)
    assert all(run_episode(env, OperatorPolicy(braking), seed=s).success for s in (1, 2, 3))


def test_info_reports_limits_each_step():
    env = gym.make("WheelLoader-v1")
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([1, 1, -1, -1], dtype=np.float32))
    for key in ("t", "fuel_g", "phase", "gear", "tc_mode", "phi", "saturations", "violations", "controls"):
        assert key in info
    assert set(info["saturations"]) == {"torque_limit", "governor", "relief_pressure", "pump_flow"}
    assert info["gear"] == -60.0 and info["phase"] == 1 and info["fuel_g"] > 0


def test_stall_ends_the_episode_as_failure():
    env = gym.make("WheelLoader-v1", braking="tc")
    env.reset(seed=0)
    # no fuel while lifting hard: the engine speed falls below omega_min
    for _ in range(200):
        _, r, te, tr, info = env.step(np.array([-1, 1, -1, -1], dtype=np.float32))
        if te or tr:
            break
    assert te and info["stalled"] and not info["is_success"]


def test_reward_weights_trace_fuel_and_time():
    a = np.array([1, 0.2, -1, -1], dtype=np.float32)
    rewards = {}
    for w in (0.0, 1.0):
        env = gym.make("WheelLoader-v1", w_fuel=w, w_time=1 - w, reward={"shaping": 0.0})
        env.reset(seed=0)
        rewards[w] = env.step(a)[1]
    assert rewards[0.0] == pytest.approx(-0.1 / 12.0)  # time only: dt / time_ref
    assert rewards[1.0] < 0 and rewards[1.0] != rewards[0.0]


@pytest.mark.parametrize(
    "action, match",
    [
        ([np.nan, 0, 0, 0], "finite"),
        ([0, 0, 0], "shape"),
        ([[0, 0, 0, 0]], "shape"),
    ],
)
def test_bad_actions_raise(action, match):
    env = gym.make("WheelLoader-v1").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(np.array(action, dtype=np.float32))


NOT_NUMBERS = [  # were cast silently ("0.5", complex) or failed with a bare TypeError or OverflowError
    ["a"] * 4, ["0.5"] * 4, [1j] * 4, np.zeros(4, np.complex128), {"fuel": 1.0}, np.array([object()] * 4),
    [10**400] * 4, [[0.0], [0.0, 1.0]],
]


@pytest.mark.parametrize("action", NOT_NUMBERS, ids=range(len(NOT_NUMBERS)))
def test_actions_that_are_not_real_numbers_raise_naming_them(action):
    env = gym.make("WheelLoader-v2").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must be finite numbers in \[-1, 1\]"):
        env.step(action)
    env.step([0.0, 0, -1, False])  # ints and bools are numbers
    venv = gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must be finite numbers in \[-1, 1\]"):
        venv.step([action, action] if not isinstance(action, np.ndarray) else np.stack([action, action]))


@pytest.mark.parametrize("num_envs", [0, 16385, 10**9, 10**400, 2.0, True, "8"])
def test_a_vector_env_size_out_of_range_is_refused_by_name(num_envs):
    with pytest.raises(ValueError, match=r"num_envs must be an integer in \[1, 16384\]"):
        gym.make_vec("WheelLoader-v2", num_envs=num_envs, vectorization_mode="vector_entry_point")


def test_bad_reset_options_raise_naming_them():
    env = gym.make("WheelLoaderTarget-v3").unwrapped
    for options, match in [(["scenario"], "options must be a dict"), ("scenario", "options must be a dict"),
                           ({"target_ratio": 5.0}, r"target_ratio must be a ratio to T_min in \[1, 3\]"),
                           ({"target_ratio": 10**400}, "target_ratio"), ({"target_time": 10**400}, "target_time"),
                           # (5e-324 s passed and made the first reward -inf and the lateness inf)
                           ({"target_time": 5e-324}, r"target_time must lie in \[1, 40\) s"),
                           ({"scenario": {"payload": 10**400}}, r"Scenario\.payload must lie in"),
                           ({"scenario": "trian"}, r"suite name \('nominal', 'train', 'test', 'corners'\)")]:
        with pytest.raises(ValueError, match=match):
            env.reset(seed=0, options=options)


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="braking"):
        gym.make("WheelLoader-v1", braking="engine")
    with pytest.raises(ValueError, match="M_load"):
        gym.make("WheelLoader-v1", params={"M_load": -5})
    with pytest.raises(ValueError, match="unknown LoaderParams"):
        gym.make("WheelLoader-v1", params={"payload": 5})
    with pytest.raises(ValueError, match="dt"):
        gym.make("WheelLoader-v1", dt=0.0)
    with pytest.raises(ValueError, match="w_fuel"):
        gym.make("WheelLoader-v1", w_fuel=float("nan"))
    with pytest.raises(ValueError, match=r"target_distance must lie in \[0, 1e\+06\]"):  # (1e308: reward -inf)
        gym.make("WheelLoader-v1", reward={"target_distance": 1e308})
    with pytest.raises(ValueError, match="num_envs"):
        gym.make_vec("WheelLoader-v1", num_envs=0, vectorization_mode="vector_entry_point")
    venv = gym.make_vec("WheelLoader-v1", num_envs=2, vectorization_mode="vector_entry_point")
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="finite"):
        venv.step(np.full((2, 4), math.nan, dtype=np.float32))


def test_deceleration_between_step_starts_is_reported_and_scored():
    """A TC-braking sequence that holds 0.18 g exactly at every step start while the converter's drag
    rises within the steps: v0 of the environment checked substep starts only and saw nothing; v1
    checks every RK4 stage and the step's end, reports the excess in info and charges it."""
    from wl_env import step
    from wl_env.params import DEFAULT_PARAMS as P

    limit = P.decel_max * P.g
    env = gym.make("WheelLoader-v1", braking="tc").unwrapped
    free = gym.make("WheelLoader-v1", braking="tc", reward={"violation": 0.0}).unwrapped  # the same, uncharged
    gear, d, _ = env.core.sim.phase_constants(2)

    def start_decel(y):  # relative to the limit, at a substep start (what v0 checked)
        return -d * step.rhs(y, (0.0, 0.0, 0.0), gear, d, P)[1] / limit

    for e in (env, free):
        e.reset(seed=0)
    for _ in range(16):  # reverse at full throttle
        for e in (env, free):
            e.step(np.array([1.0, -1.0, -1.0, -1.0]))
    riding = 0
    for k in range(30):
        y, phase = env._y, env._phase
        shift = 1.0 if phase == 1 else -1.0
        lo, hi = -1.0, 1.0  # the throttle that brings the next step's start to the limit, from below
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            r = env.core._step(y, phase, env._t, env._rev_err, env._violation, (mid, -1.0, -1.0, shift))
            lo, hi = (mid, hi) if start_decel(r["y"]) < 0.9999 else (lo, mid)
        a = np.array([lo, -1.0, -1.0, shift])
        at_start = start_decel(y) if phase == 2 else 0.0
        _, reward, term, trunc, info = env.step(a)
        _, reward_free, *_ = free.step(a)
        if info["phase"] != 2:
            break
        if k > 0 and at_start <= 1.0:  # held at every step start ...
            assert info["violations"]["deceleration"] > 1e-3  # ... exceeded within the step, and said so
            assert info["violations"]["excess"] >= info["violations"]["deceleration"]
            assert reward < reward_free  # and charged
            riding += 1
    assert riding >= 3 and env._violation > 1e-3


def test_step_after_the_end_raises_until_reset():
    env = gym.make("WheelLoader-v1", braking="service").unwrapped
    env.reset(seed=0)
    for _ in range(1000):
        *_, term, trunc, _ = env.step(np.array([1.0, 0.0, -1.0, 1.0], np.float32))  # shifts at once: done soon
        if term or trunc:
            break
    assert term or trunc
    with pytest.raises(RuntimeError, match="reset"):
        env.step(env.action_space.sample())  # no more physics, no second failure penalty
    env.reset(seed=1)
    env.step(env.action_space.sample())


def test_a_failed_reset_leaves_no_episode_to_step():
    """A reset refused part-way (its scenario set, its target not) used to leave the new start with the old
    target, and step() ran it; now step() raises until a reset succeeds."""
    env = gym.make("WheelLoaderTarget-v3").unwrapped
    env.reset(seed=0, options={"target_time": 10.0})
    env.step(env.action_space.sample())
    with pytest.raises(ValueError, match="target_time"):
        env.reset(seed=0, options={"scenario": {"payload": 12000.0}, "target_time": 50.0})
    with pytest.raises(RuntimeError, match="reset failed"):
        env.step(env.action_space.sample())
    env.reset(seed=0, options={"scenario": {"payload": 12000.0}, "target_time": 12.0})
    assert env.target_time == 12.0
    env.step(env.action_space.sample())


def test_a_stalled_engine_stops_at_zero_and_ends_the_episode():
    """Payload x3 with no fuel: the engine stalls; its speed is clamped at 0 (it does not turn backwards)
    and the episode ends as a failure with a finite observation."""
    from wl_env.params import DEFAULT_PARAMS as P

    env = gym.make("WheelLoader-v1", braking="service", params=P.variant(payload_scale=3.0)).unwrapped
    obs, _ = env.reset(seed=0)
    for _ in range(400):
        obs, r, term, trunc, info = env.step(np.array([-1.0, 1.0, -1.0, -1.0], np.float32))  # lift, no fuel
        assert env.state[0] >= 0.0 and np.isfinite(obs).all() and obs[0] >= 0.0
        if term or trunc:
            break
    assert term and info["stalled"] and not info["is_success"]


# ------------------------------------------------------------------ hostile inputs (stop 60's env round)
def test_a_stalled_engine_is_no_success_even_at_the_truck():
    """The operator's heavy cycle with the fuel cut for its last stop: the machine stands at the truck as the engine
    stalls. The failure charge was paid and ``is_success`` said True (evaluations counted the cycle a success)."""
    from wl_env import Scenario

    sc = Scenario(payload=13000, dump_height=5.1)
    env = gym.make("WheelLoader-v2", scenario=sc).unwrapped
    op = OperatorPolicy(params=sc.params())
    obs, _ = env.reset(seed=0)
    for k in range(400):
        a = op.act(obs)
        if k >= 59:
            a[0] = -1.0
        obs, _, terminated, truncated, info = env.step(a)
        if terminated or truncated:
            break
    assert info["stalled"] and info["completed"] and not info["is_success"]


def test_a_loader_that_stalls_to_zero_is_reset_with_the_batch_and_never_divides_by_zero():
    """A tiny engine inertia (in range) stalls the engine to 0 rad/s. The vector env's next-step autoreset stepped
    that loader once more from omega 0 (NaN, then IntegrationDiverged for the whole batch); a single env with 2
    substeps divided by zero (a bare ZeroDivisionError). Now the batch goes on, and the single env ends on the stall
    or names the integration (IntegrationDiverged)."""
    from wl_env.episode import IntegrationDiverged

    params = {"J_ice": 0.5, "D_pump": 0.005}
    venv = gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point", params=params)
    venv.reset(seed=0)
    ends = 0
    for _ in range(5):
        obs, _, terminated, _, _ = venv.step(np.tile([-1.0, 1.0, -1.0, -1.0], (2, 1)))
        ends += int(terminated.sum())
        assert np.isfinite(obs).all()
    assert ends >= 2
    env = gym.make("WheelLoader-v2", braking="tc", substeps=2, params={"J_ice": 0.5, "D_pump": 0.01}).unwrapped
    env.reset(seed=0)
    try:
        for n in range(20):
            _, _, terminated, _, _ = env.step(np.array([1, 1, -1, -1] if n < 5 else [-1, 1, -1, 1], np.float32))
            if terminated:
                break
    except IntegrationDiverged:
        pass


def test_the_vector_target_env_falls_back_to_the_unperturbed_start_as_the_single_env():
    """A start speed at the top of its range with init_noise: a perturbed start outside the ranges takes the
    unperturbed start's target in the single env; the vector env raised (at reset and at autoresets)."""
    params = {"omega_0": 2000 * math.pi / 30}
    env = gym.make("WheelLoaderTarget-v6", params=params, init_noise=0.5).unwrapped
    venv = gym.make_vec("WheelLoaderTarget-v6", num_envs=1, vectorization_mode="vector_entry_point", params=params,
                        init_noise=0.5)
    for seed in range(4):
        single = env.reset(seed=seed)[1]["target_time"]
        venv.reset(seed=seed)
        assert venv.unwrapped.target_time[0] == pytest.approx(single)


def test_a_control_interval_too_short_to_move_the_clock_is_refused_by_name():
    from mpc.controller.mpc import MPCController

    for dt in (5e-324, 1e-7, 0.0009):  # (5e-324 never advanced t; the plan env at 1e-7 ran 10^8 steps a plan)
        with pytest.raises(ValueError, match=r"dt \(the control interval\) must lie in \[0.001, 1\] s"):
            gym.make("WheelLoaderPlan-v0", dt=dt)
    with pytest.raises(ValueError, match=r"must lie in \[0.001, 1\] s"):
        MPCController("tc", dt=1e-7)


def test_a_scenario_at_reset_refuses_the_payload_params_set_and_json_takes_the_envs_braking():
    """A reset's scenario replaced M_load and c_r given by params= without a word (the constructor refused it);
    JSON text naming no braking was read as service in a TC env (a dict took the env's)."""
    env = gym.make("WheelLoader-v2", params={"M_load": 7000, "c_r": 0.02})
    with pytest.raises(ValueError, match="params sets M_load, c_r, which the scenario sets"):
        env.reset(options={"scenario": {"reverse_distance": 5.0}})
    tc = gym.make("WheelLoader-v2", braking="tc")
    _, info = tc.reset(options={"scenario": '{"payload": 7000}'})
    assert info["scenario"].braking == "tc" and info["scenario"].payload == 7000
    assert gym.make("WheelLoader-v2", braking="tc", scenario='{"payload": 7000}').unwrapped.scenario.braking == "tc"


# ------------------------------------------------------------------ hostile inputs (the environments' round)
def test_a_refused_reset_leaves_the_generator_as_it_was():
    """A reset refused for its options (a target of 50 s, a ratio of 9) reseeded the generator and drew a scenario
    before the check: the episodes after it were not those of the seed. An options dict with keys of two types was
    a TypeError (sorting them for the message)."""
    kw = {"scenario": "train", "init_noise": 0.5}
    a, b = (gym.make("WheelLoaderTarget-v6", **kw).unwrapped for _ in range(2))
    a.reset(seed=1)
    b.reset(seed=1)
    for options in ({"target_time": 50.0}, {"target_ratio": 9.0}, {"target_time": 10.0, "target_ratio": 2.0},
                    {1: 2, "colour": 3}):
        with pytest.raises(ValueError, match="target|colour"):
            b.reset(seed=5, options=options)
        obs_a, info_a = a.reset()
        obs_b, info_b = b.reset()
        assert np.array_equal(obs_a, obs_b) and info_a == info_b


def test_numpy_float32_params_are_taken_as_the_decimals_they_print():
    """np.float32(0.01) was refused as under decel_max's 0.01 ("must lie in [0.01, 2] g, got np.float32(0.01)"), and
    0.03 was stored as 0.0299999993: another machine's fingerprint than the default's."""
    from wl_env.params import DEFAULT_PARAMS

    env = gym.make("WheelLoader-v2", params={"decel_max": np.float32(0.01)}).unwrapped
    assert env.machine.decel_max == 0.01
    same = {"c_r": np.float32(0.03), "omega_max": np.float32(230.4), "c_fr": np.array(DEFAULT_PARAMS.c_fr, np.float32),
            "T_max_lines": np.array(DEFAULT_PARAMS.T_max_lines, np.float32)}
    env = gym.make("WheelLoader-v2", params=same).unwrapped
    assert env.machine == DEFAULT_PARAMS and env.machine.fingerprint() == DEFAULT_PARAMS.fingerprint()
    with pytest.raises(ValueError, match=r"LoaderParams\.c_fr\[0\] must be a number"):
        gym.make("WheelLoader-v2", params={"c_fr": np.zeros((3, 1))})


@pytest.mark.parametrize("field", ["fuel_ref_g", "time_ref"])
@pytest.mark.parametrize("value", [5e-324, 1e-300, 1e-4, 0.0, -1.0])
def test_a_reward_reference_too_small_for_a_finite_reward_is_refused_by_name(field, value):
    """time_ref 5e-324 passed as > 0 and made the first reward -inf; 1e-300 gave -5e298 (-inf in float32)."""
    with pytest.raises(ValueError, match=rf"RewardConfig\.{field} must lie in \[0.001, 1e\+06\]"):
        gym.make("WheelLoader-v2", reward={field: value})
    env = gym.make("WheelLoader-v2", reward={field: 1e-3})
    env.reset(seed=0)
    assert np.isfinite(np.float32(env.step(np.ones(4, np.float32))[1]))


def test_a_braking_given_as_a_str_subclass_is_kept_as_the_plain_str():
    """np.str_("tc") was kept as numpy's string; a str subclass whose == says yes to anything passed as any braking."""
    class Anything(str):
        def __eq__(self, other):
            return True

        __hash__ = str.__hash__

    env = gym.make("WheelLoader-v2", braking=np.str_("tc"))
    assert type(env.unwrapped.braking) is str and env.unwrapped.braking == "tc"
    with pytest.raises(ValueError, match="braking must be one of"):
        gym.make("WheelLoader-v2", braking=Anything("brakes"))


# ------------------------------------------------------------------ hostile inputs (eleventh round, wl_env's API)
def test_an_integer_too_long_to_print_is_named_in_a_short_error():
    """init_noise, substeps, render_mode, fuel_action or braking of 10**5000 was Python's "Exceeds the limit (4300
    digits) for integer string conversion", naming no argument."""
    from wl_env.vector_env import WheelLoaderVectorEnv

    huge = 10**5000
    for name in ("init_noise", "substeps", "render_mode", "fuel_action", "braking"):
        for make in (WheelLoaderEnv, lambda **kw: WheelLoaderVectorEnv(2, **kw)):
            if make is not WheelLoaderEnv and name == "render_mode":
                continue
            with pytest.raises(ValueError, match=rf"^{name} must .* got <int of more digits than Python prints>$"):
                make(**{name: huge})


def test_a_masked_action_is_refused_not_read_as_its_filler():
    """A masked array's masked entry was driven with the value under the mask."""
    env = gym.make("WheelLoader-v2").unwrapped
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action must be finite numbers in \\[-1, 1\\], got a masked array with 1 masked"):
        env.step(np.ma.masked_array(np.zeros(4), mask=[1, 0, 0, 0]))
    env.step(np.ma.masked_array(np.zeros(4), mask=[0, 0, 0, 0]))  # (nothing masked: its values)


def test_the_vector_envs_reset_info_has_the_single_envs_keys_but_the_scenario():
    """The vector env's reset gave {}: a target env's targets were in the observation only."""
    for env_id in ("WheelLoader-v2", "WheelLoaderTarget-v7", "WheelLoaderPlan-v1"):
        single = gym.make(env_id, scenario="train")
        vector = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point", scenario="train")
        _, info = single.reset(seed=4)
        _, infos = vector.reset(seed=4)
        assert set(infos) == set(info) - {"scenario"}
        for key in infos:
            assert infos[key].shape == (3,) and infos[key][0] == info[key]


def test_an_atomic_write_reads_the_umask_without_changing_it(tmp_path, monkeypatch):
    """atomic_path set the umask to 0 and back to read it: a file another thread created meanwhile was world-writable."""
    import os

    from wl_env import atomic_io

    old = os.umask(0o027)
    try:
        monkeypatch.setattr(os, "umask", lambda mask: pytest.fail(f"os.umask({mask:o}) called"))
        path = atomic_io.write_atomic(tmp_path / "a.txt", "x")
    finally:
        monkeypatch.undo()
        os.umask(old)
    assert path.read_text() == "x" and (path.stat().st_mode & 0o777) == 0o640
