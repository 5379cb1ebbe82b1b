import dataclasses
import math
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wl_env.params import DEFAULT_PARAMS, PROVENANCE, LoaderParams, resolve


def test_defaults_match_the_specification():
    p = DEFAULT_PARAMS
    assert p.M_veh == 32000.0 and p.M_load == 10000.0 and p.r_w == 0.70
    assert p.tc_xi_poly[-1] == 406.2 and p.tc_kappa_poly[-1] == 675.4
    assert p.T_max_lines == ((8.0, 2.086), (2200.0, 0.0), (3855.0, -1.40))
    # derived constants of eqs. (17), (25), (27)
    assert p.A_piston == pytest.approx(2 * math.pi * (0.095**2 - 0.045**2))
    assert p.M_tot == pytest.approx(42000 + 4 * 1000 / 0.7**2)
    assert p.F_roll == pytest.approx(0.03 * 42000 * 9.81)


def test_every_field_has_provenance():
    names = {f.name for f in dataclasses.fields(LoaderParams) if f.init}
    assert names == set(PROVENANCE)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"M_veh": -1.0}, "M_veh"),
        ({"eta_gb": 1.2}, "eta_gb"),
        ({"eta_lift": 0.0}, "eta_lift"),
        ({"tc_xi_poly": (1.0, 2.0)}, "tc_xi_poly"),
        ({"c_fr": (1.0, 2.0, 3.0, 4.0)}, "c_fr"),
        ({"r_w": float("nan")}, "r_w"),
        ({"H_T": 9.0}, "H_T"),
        ({"omega_0": 300.0}, "omega_0"),
        ({"r_rod": 0.2}, "r_rod"),
    ],
)
def test_invalid_values_name_the_field(change, field):
    with pytest.raises(ValueError, match=field):
        DEFAULT_PARAMS.replace(**change)


@pytest.mark.parametrize("leg", ["reverse_distance", "forward_distance"])
def test_distance_sets_both_legs_and_is_refused_beside_a_leg(leg):
    assert DEFAULT_PARAMS.replace(distance=5.0).reverse_distance == DEFAULT_PARAMS.replace(distance=5.0).forward_distance == 5.0
    with pytest.raises(ValueError, match=f"distance or {leg}"):
        DEFAULT_PARAMS.replace(distance=5.0, **{leg: 6.0})


def test_unknown_field_is_rejected():
    with pytest.raises(ValueError, match="unknown LoaderParams field"):
        DEFAULT_PARAMS.replace(payload=3)


def test_variants_and_round_trip():
    heavy = DEFAULT_PARAMS.variant(payload_scale=1.2, rolling_scale=0.7)
    assert heavy.M_load == pytest.approx(12000.0) and heavy.c_r == pytest.approx(0.021)
    assert heavy.M_tot > DEFAULT_PARAMS.M_tot and heavy.fingerprint() != DEFAULT_PARAMS.fingerprint()
    assert LoaderParams.from_dict(heavy.to_dict()) == heavy
    both = resolve({"distance": 8.0})  # the paper's "each way": both legs
    assert both.reverse_distance == both.forward_distance == 8.0 and both.final_position == 0.0
    assert resolve({"reverse_distance": 8.0, "forward_distance": 5.0}).final_position == -3.0
    with pytest.raises(ValueError, match="params must be"):
        resolve(42)


# ------------------------------------------------------------------------------------------ hostile input
NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    "change, field",
    [
        ({"c_fr": [NAN, -0.1414, 0.3590]}, "c_fr"),
        ({"U_ab_bounds": [-INF, 2.5]}, "U_ab_bounds"),
        ({"T_max_lines": [[8.0, NAN], [2200.0, 0.0], [3855.0, -1.4]]}, "T_max_lines"),
        ({"M_veh": True}, "M_veh"),  # a bool is not 1 kg
        ({"n_cyl": 6.5}, "n_cyl"),
        ({"n_cyl": True}, "n_cyl"),
        ({"M_veh": "32000"}, "M_veh"),  # was a bare TypeError
        ({"T_max_lines": 5}, "T_max_lines"),  # was a bare TypeError
        ({"T_max_lines": [8.0, 2200.0, 3855.0]}, "T_max_lines"),  # wrong nesting
        ({"T_max_lines": [[8.0, 2.0], [2200.0, 0.0]]}, "T_max_lines"),
        ({"c_fr": ["0.7", "-0.1", "0.4"]}, "c_fr"),  # numbers as strings were taken by float()
        ({"U_ab_bounds": [-2.5, 2.5, 1.0]}, "U_ab_bounds"),
        ({"U_ab_bounds": [1.0, 2.5]}, "U_ab_bounds"),
        ({"M_veh": 1e300}, "M_veh"),
        ({"J_ice": 0.0}, "J_ice"),
        ({"c_r": -0.01}, "c_r"),
        ({"g": None}, "g"),
        ({"reverse_distance": INF}, "reverse_distance"),
        ({"forward_distance": 0.0}, "forward_distance"),
        ({"tc_xi_poly": [1.0] * 6 + [INF]}, "tc_xi_poly"),
        ({"c_fr": [0.0, 0.0, -1.0]}, "c_fr"),  # negative friction
        ({"T_max_lines": [[8.0, 2.086], [-10.0, 0.0], [3855.0, -1.4]]}, "T_max_lines"),  # no torque
        ({"x_c": 3.0}, "x_c"),  # the cylinder cannot lift the boom
        ({"M_veh": 10**400}, "M_veh"),  # JSON's ints have no limit: was a bare OverflowError
        ({"c_fr": [0.7196, -0.1414, -10**400]}, "c_fr"),
    ],
)
def test_hostile_values_are_rejected_naming_the_field(change, field):
    with pytest.raises(ValueError, match=rf"\b{field}\b"):
        LoaderParams.from_dict(change)


def test_allowed_values_message_gives_the_range():
    with pytest.raises(ValueError, match=r"M_veh must be a number in \[1000, 300000\] kg, got '32000' \(str\)"):
        LoaderParams.from_dict({"M_veh": "32000"})
    with pytest.raises(ValueError, match=r"n_cyl must be an integer in \[1, 24\], got 6\.5"):
        LoaderParams.from_dict({"n_cyl": 6.5})


def test_a_huge_bad_value_is_quoted_short():
    """An error quotes the start of a bad value: a 10 MB string is not a readable message."""
    for change in ({"M_veh": "x" * 10_000_000}, {"c_fr": "x" * 10_000_000}, {"n_cyl": 10**4000}, {"M_veh": -10**5000}):
        with pytest.raises(ValueError, match=rf"LoaderParams\.{next(iter(change))} must") as exc:
            LoaderParams.from_dict(change)
        assert len(str(exc.value)) < 300


def test_the_project_variants_and_spellings_are_accepted():
    for scale in (0.6, 1.0, 1.3, 3.0):  # payload studies (x3: the engine-stall case)
        assert DEFAULT_PARAMS.variant(payload_scale=scale).M_load == pytest.approx(10000.0 * scale)
    for c_r in (0.015, 0.03, 0.05):
        assert DEFAULT_PARAMS.replace(c_r=c_r).c_r == c_r
    # an int or a numpy number is the same parameter set as the float (same fingerprint, same cache)
    import numpy as np

    same = LoaderParams.from_dict({"M_veh": 32000, "n_cyl": np.int64(6), "c_fr": np.array([0.7196, -0.1414, 0.3590])})
    assert same == DEFAULT_PARAMS and same.fingerprint() == DEFAULT_PARAMS.fingerprint()
    assert type(same.M_veh) is float and type(same.n_cyl) is int and same.c_fr == DEFAULT_PARAMS.c_fr


@pytest.mark.parametrize("kw", [{"payload_scale": True}, {"payload_scale": "2"}, {"rolling_scale": NAN},
                                {"rolling_scale": -1.0}, {"payload_scale": 10**400}])
def test_variant_scales_are_checked(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        DEFAULT_PARAMS.variant(**kw)


def test_from_dict_rejects_non_string_keys():
    with pytest.raises(ValueError, match="field names must be strings"):
        LoaderParams.from_dict({1: 2.0})


@pytest.mark.parametrize("kw, name", [
    ({"dt": True}, "dt"), ({"dt": NAN}, "dt"), ({"substeps": True}, "substeps"), ({"substeps": 2.0}, "substeps"),
    ({"max_time": True}, "max_time"), ({"max_time": INF}, "max_time"), ({"init_noise": True}, "init_noise"),
    ({"w_fuel": True}, "w_fuel"), ({"w_time": "1"}, "w_time"), ({"params": {"c_fr": [NAN, 0, 0]}}, "c_fr"),
    # ints too large for a float were a bare OverflowError
    ({"dt": 10**400}, "dt"), ({"max_time": 10**400}, "max_time"), ({"reward": {"w_fuel": 10**400}}, "w_fuel"),
    ({"target": 10**400}, "target"),
    # switches and the braking were taken by truth value: "no" switched on, "" and {} were service braking
    ({"observe_scenario": "no"}, "observe_scenario"), ({"observe_target": "yes"}, "observe_target"),
    ({"braking": ""}, "braking"), ({"braking": {}}, "braking"),
])
def test_env_arguments_are_checked(kw, name):
    import gymnasium as gym

    import wl_env  # noqa: F401

    with pytest.raises(ValueError, match=name):
        gym.make("WheelLoader-v1", **kw)
    with pytest.raises(ValueError, match=name):
        gym.make_vec("WheelLoader-v1", num_envs=2, vectorization_mode="vector_entry_point", **kw)


def test_numpy_scalars_are_the_numbers_they_hold():
    """Arguments from numpy (a float32 time step, an int64 substep count or seed) are taken as the numbers they
    hold, the same env as with Python numbers; a numpy bool is still no number. (They were refused, the message
    quoting a value in range.)"""
    import gymnasium as gym
    import numpy as np

    import wl_env  # noqa: F401

    kw = {"dt": np.float32(0.1), "substeps": np.int64(2), "init_noise": np.float32(0.5), "w_fuel": np.float64(2.0)}
    # (a float32 as the decimal it prints: np.float32(0.015).item() is 0.01499..., under a range's 0.015; stop 60)
    a, b = gym.make("WheelLoader-v2", **kw), gym.make("WheelLoader-v2", **{k: float(str(v)) if v.dtype.kind == "f" else
                                                                             v.item() for k, v in kw.items()})
    np.testing.assert_array_equal(a.reset(seed=3)[0], b.reset(seed=3)[0])
    assert a.unwrapped.core.dt == 0.1 and type(a.unwrapped.core.dt) is float
    t = gym.make("WheelLoaderTarget-v3")
    assert t.reset(seed=0, options={"target_time": np.float32(10.0)})[1] is not None and t.unwrapped.target_time == 10.0
    v = gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point")
    np.testing.assert_array_equal(v.reset(seed=np.int64(3))[0], v.reset(seed=3)[0])
    for bad in (1.5, -1, [1, "a"]):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            v.reset(seed=bad)
    with pytest.raises(ValueError, match="dt"):
        gym.make("WheelLoader-v2", dt=np.bool_(True))


def test_vector_env_num_envs_is_an_integer():
    import gymnasium as gym

    import wl_env  # noqa: F401

    for n in (True, 2.0, 0):
        with pytest.raises(ValueError, match="num_envs"):
            gym.make_vec("WheelLoader-v1", num_envs=n, vectorization_mode="vector_entry_point")


@pytest.mark.parametrize("overrides, field", [('{"M_veh": "32000"}', "M_veh"), ('{"c_fr": [NaN, 0, 0]}', "c_fr"),
                                              ('{"T_max_lines": 5}', "T_max_lines"), ('{"M_veh": true}', "M_veh"),
                                              ('{"M_veh": 1' + "0" * 400 + "}", "M_veh")])  # was a traceback
def test_wl_params_set_reports_one_line(capsys, overrides, field):
    import wl.cli

    assert wl.cli.main(["params", "--set", overrides]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and err.startswith("wl: error: LoaderParams." + field)


# ------------------------------------------------------------------------------------------ fuzz
FIELDS = [f.name for f in dataclasses.fields(LoaderParams) if f.init]
HOSTILE = st.one_of(
    st.sampled_from([NAN, INF, -INF, True, False, None, "32000", "", [], {}, -1.0, 0.0, 1e300, -1e300, 5, 6.5,
                     10**400, -10**400]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-10**9, 10**9),
    st.text(max_size=4),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=8),  # wrong lengths and entries
    st.lists(st.lists(st.floats(-1e4, 1e4), max_size=3), max_size=4),  # wrong nesting
)


def _perturbed(default, draw):
    """A value near the default: scaled by 0.5..2 (entry by entry), an int moved by up to 2."""
    if isinstance(default, tuple):
        return [_perturbed(v, draw) for v in default]
    if isinstance(default, int):
        return default + draw(st.integers(-2, 2))
    return default * draw(st.floats(0.5, 2.0))


@st.composite
def overrides(draw):
    names = draw(st.lists(st.sampled_from(FIELDS), min_size=1, max_size=3, unique=True))
    # two thirds valid perturbations: enough accepted sets to run, each hostile kind still drawn often
    return {n: _perturbed(getattr(DEFAULT_PARAMS, n), draw) if draw(st.integers(0, 2)) else draw(HOSTILE)
            for n in names}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(over=overrides(), seed=st.integers(0, 2**16))
def test_fuzz_overrides_are_rejected_by_name_or_run_finite(over, seed):
    """Every override is either rejected with a ValueError naming one of the given fields, or the
    environment built with it runs (reset and 20 random steps) with finite observations and rewards, or its
    step says that the integration diverged (IntegrationDiverged), never a silent blow-up."""
    import gymnasium as gym
    import numpy as np

    import wl_env  # noqa: F401
    from wl_env.episode import IntegrationDiverged

    try:
        env = gym.make("WheelLoader-v1", params=over)
    except ValueError as exc:
        assert any(re.search(rf"\b{re.escape(n)}\b", str(exc)) for n in over), (over, str(exc))
        return
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    assert np.all(np.isfinite(obs)), over
    for _ in range(20):
        try:
            obs, reward, terminated, truncated, info = env.step(rng.uniform(-1.0, 1.0, 4).astype(np.float32))
        except IntegrationDiverged as exc:
            assert "raise substeps" in str(exc), over
            return
        assert np.all(np.isfinite(obs)) and math.isfinite(reward), over
        omega, V = info["state"][:2]
        assert 0.0 <= omega <= 2.0 * env.unwrapped.params.omega_max and abs(V) < 10.0, (over, info["state"])
        if terminated or truncated:
            break


@pytest.mark.parametrize("over, substeps", [({"eta_lift": 0.01}, 1), ({"eta_lift": 1e-300}, 1), ({"J_ice": 0.5}, 1),
                                            ({"gear_ratio": 500.0}, 1)])
def test_a_step_made_unstable_by_the_parameters_raises_not_numbers(over, substeps):
    """In-range parameters that make the fixed-step RK4 unstable (found by hostile-input testing, stop 59:
    eta_lift 0.01 ran the engine to 8865 rad/s, then 6.8e14, and reported 135 kg of fuel; 1e-300 gave NaN) end
    the run with IntegrationDiverged naming the fix, within a few steps."""
    import gymnasium as gym
    import numpy as np

    import wl_env  # noqa: F401
    from wl_env.episode import IntegrationDiverged
    from wl_env.vector_env import WheelLoaderVectorEnv

    env = gym.make("WheelLoader-v2", params=over, substeps=substeps)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    with pytest.raises(IntegrationDiverged, match="raise substeps"):
        for _ in range(50):
            env.step(rng.uniform(-1.0, 1.0, 4).astype(np.float32))
    vec = WheelLoaderVectorEnv(4, params=over, substeps=substeps)
    vec.reset(seed=0)
    with pytest.raises(IntegrationDiverged, match="raise substeps"):
        for _ in range(50):
            vec.step(rng.uniform(-1.0, 1.0, (4, 4)).astype(np.float32))
