"""Scenarios and suites: validation, determinism, the environment on a scenario, the vector env's draws."""

from __future__ import annotations

import json
import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import wl_env  # noqa: F401
from wl_env.codec import Codec
from wl_env.params import DEFAULT_PARAMS
from wl_env.scenario import FIELDS, Scenario, resolve_scenario
from wl_env.suites import SUITES, TEST_STREAM, TRAIN_STREAM, draw, load_suite, stream, suite_files

ACTIONS = [np.array([0.8, 0.4, -1.0, -1.0])] * 30 + [np.array([0.2, 0.2, -1.0, 1.0])] + \
          [np.array([0.0, 0.1, 0.6, -1.0])] * 30 + [np.array([0.9, 0.3, -1.0, 1.0])] * 40


# ---------------------------------------------------------------------------------------------- validation
@pytest.mark.parametrize("name", list(FIELDS))
@pytest.mark.parametrize("side", ["below", "above"])
def test_a_value_outside_its_range_names_the_field_and_the_range(name, side):
    spec = FIELDS[name]
    bad = spec.lo - 0.01 * (spec.hi - spec.lo) if side == "below" else spec.hi + 0.01 * (spec.hi - spec.lo)
    with pytest.raises(ValueError, match=rf"Scenario\.{name} must lie in \[{spec.lo:g}, {spec.hi:g}\]"):
        Scenario(**{name: bad})


@given(name=st.sampled_from(list(FIELDS)),
       value=st.one_of(st.none(), st.text(max_size=3), st.booleans(), st.just(math.nan), st.just(math.inf),
                       st.floats(allow_nan=False, allow_infinity=False), st.integers(0, 20000),
                       st.sampled_from([10**400, -10**400])))  # (JSON's ints: 10**400 was an OverflowError)
@settings(max_examples=150, deadline=None)
def test_any_value_is_accepted_in_range_or_refused_by_name(name, value):
    spec = FIELDS[name]
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and spec.lo <= value <= spec.hi  # (not NaN)
    if ok:
        assert getattr(Scenario(**{name: value}), name) == value
    else:
        with pytest.raises(ValueError, match=rf"Scenario\.{name}"):
            Scenario(**{name: value})


def test_the_ranges_cover_what_the_issue_asks():
    need = {"payload": (6000, 13000), "reverse_distance": (4, 10), "forward_distance": (4, 10),
            "rolling_resistance": (0.015, 0.05), "dump_height": (3.5, 5.1), "start_engine_speed": (800, 2000),
            "start_bucket_height": (0.5, 1.2)}
    for name, (lo, hi) in need.items():
        assert FIELDS[name].lo <= lo and FIELDS[name].hi >= hi, name
    for s in (Scenario(**{n: FIELDS[n].lo for n in FIELDS}), Scenario(**{n: FIELDS[n].hi for n in FIELDS})):
        s.params()  # every corner of the ranges is a valid machine


def test_nominal_is_the_papers_cycle_and_round_trips():
    s = Scenario.nominal()
    assert s.params() == DEFAULT_PARAMS  # the same fingerprint, so the same cached optima
    assert s.params().omega_0 == pytest.approx(1500 * math.pi / 30)
    assert Scenario.from_params(DEFAULT_PARAMS) == s
    assert Scenario.from_dict(s.to_dict()) == s and Scenario.parse(json.dumps({"payload": 10000})) == s
    other = Scenario(payload=12000.0, reverse_distance=5.0, braking="tc")
    assert other.params().M_load == 12000.0 and other.params().final_position == pytest.approx(1.6)
    assert other.fingerprint() != s.fingerprint() and other.replace(braking="service").fingerprint() != other.fingerprint()


def test_bad_scenario_inputs_are_named(tmp_path):
    with pytest.raises(ValueError, match="unknown Scenario field"):
        Scenario.from_dict({"payloda": 9000})
    with pytest.raises(ValueError, match="braking must be one of"):
        Scenario(braking="air")
    with pytest.raises(ValueError, match="not valid JSON"):
        Scenario.parse("{payload: 9000")
    with pytest.raises(ValueError, match="no file"):
        Scenario.parse(str(tmp_path / "missing.json"))
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"dump_height": 4.0}))
    assert Scenario.parse(str(f)).dump_height == 4.0
    # hostile JSON: each a ValueError saying what is wrong (were RecursionError, OSError, a 10 MB message, "no file")
    for text, match in [("[1, 2]", "JSON object of its fields, got list"),
                        ('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested too deeply"),
                        ("x" * 5000, "no file"),
                        ('{"payload": ' + "9" * 400 + "}", r"Scenario\.payload must lie in"),
                        # (a bare "Exceeds the limit (4300 digits) ..." from json, naming neither option nor field)
                        ('{"payload": ' + "9" * 5000 + "}", "--scenario is not valid JSON"),
                        ('{"payload": "' + "x" * 10_000_000 + '"}', r"Scenario\.payload must be a number")]:
        with pytest.raises(ValueError, match=match) as exc:
            Scenario.parse(text)
        assert len(str(exc.value)) < 500
    f.write_bytes(b"\xff\xfe{")
    with pytest.raises(ValueError, match=f"--scenario file {f}: cannot read it as text"):
        Scenario.parse(str(f))
    # through the library: named as its argument (not the CLI's option), with the file
    f.write_text("root:x:0:0:root:/root:/bin/bash\n")
    for call in (lambda: resolve_scenario(str(f)), lambda: gym.make("WheelLoader-v2").reset(options={"scenario": str(f)})):
        with pytest.raises(ValueError, match=f"^scenario file {f} is not valid JSON"):
            call()


def test_a_scenario_file_is_taken_as_a_path_too(tmp_path):
    """resolve_scenario (and so reset's options) took a file's path as text but refused it as a pathlib.Path."""
    f = tmp_path / "heavy.json"
    f.write_text('{"payload": 12000, "braking": "tc"}')
    assert resolve_scenario(f) == resolve_scenario(str(f)) == Scenario.from_dict({"payload": 12000, "braking": "tc"})
    _, info = gym.make("WheelLoader-v2", braking="tc").reset(seed=0, options={"scenario": f})
    assert info["scenario"] == resolve_scenario(f)
    with pytest.raises(ValueError, match="contradicts"):
        resolve_scenario(f, "service")


# ---------------------------------------------------------------------------------------------- suites
def test_suite_files_are_their_definitions_and_load():
    for name, data in suite_files().items():
        assert json.loads((wl_env.suites.FOLDER / f"{name}.json").read_text()) == data, name
        assert load_suite(name).version >= 1
    test = load_suite("test")
    for b in ("service", "tc"):
        assert len(test.of(b)) >= 50
    assert [s.replace(braking="tc") for s in test.of("service")] == list(test.of("tc"))
    assert load_suite("nominal").of("tc") == (Scenario.nominal("tc"),)
    corners = load_suite("corners").of("service")
    for name, spec in FIELDS.items():
        assert {getattr(s, name) for s in corners} >= {spec.lo, spec.hi}
    with pytest.raises(ValueError, match="unknown suite"):
        load_suite("nope")
    assert set(SUITES) == {"nominal", "train", "test", "corners"}


def test_train_draws_are_seeded_and_disjoint_from_test():
    a = [draw(stream(TRAIN_STREAM, seed), "service") for seed in range(3)]
    assert a == [draw(stream(TRAIN_STREAM, seed), "service") for seed in range(3)]  # same seed, same draw
    test = {s.replace(braking="service") for s in load_suite("test").of("service")}
    train = {load_suite("train").sample(stream(TRAIN_STREAM, seed), "service") for seed in range(2000)}
    assert not (train & test)
    first_test = draw(stream(TEST_STREAM), "service")  # the test stream reproduces the committed list
    assert first_test == load_suite("test").of("service")[0]


# ---------------------------------------------------------------------------------------------- environment
def _rollout(env, seed=0, options=None):
    obs, info = env.reset(seed=seed, options=options)
    out = [obs]
    for a in ACTIONS:
        obs, r, term, trunc, info = env.step(a)
        out.append(np.append(obs, r))
        if term or trunc:
            break
    return np.array([o[:12] for o in out[1:]]), np.array([o[-1] for o in out[1:]]), info


def test_v2_under_the_nominal_scenario_runs_v1s_numbers():
    o1, r1, i1 = _rollout(gym.make("WheelLoader-v1"))
    o2, r2, i2 = _rollout(gym.make("WheelLoader-v2", scenario=Scenario.nominal()))
    assert np.array_equal(o1, o2) and np.array_equal(r1, r2)
    assert i1["fuel_g"] == i2["fuel_g"] and i2["scenario"] == Scenario.nominal()


def test_the_scenario_is_observed_and_changes_the_cycle():
    s = Scenario(payload=13000.0, reverse_distance=4.0, forward_distance=9.0, dump_height=3.6,
                 start_engine_speed=900.0, start_bucket_height=1.1)
    env = gym.make("WheelLoader-v2", scenario=s)
    obs, info = env.reset(seed=0)
    assert info["scenario"] == s and obs.shape == (19,)
    assert np.allclose(obs[12:], s.features(), atol=1e-6)
    assert Codec(s.params(), observe_scenario=True).decode_scenario(obs, "service").payload == pytest.approx(13000, abs=0.01)
    o = env.unwrapped.codec.decode_observation(obs)
    assert o.engine_speed == pytest.approx(900 * math.pi / 30, rel=1e-6) and o.bucket_height == pytest.approx(1.1, rel=1e-6)
    assert o.distance_to_go == pytest.approx(4.0, rel=1e-6)
    with pytest.raises(ValueError, match="only the option 'scenario'"):
        env.reset(options={"speed": 1})
    _, info = env.reset(options={"scenario": {"payload": 7000}})
    assert info["scenario"].payload == 7000.0 and env.unwrapped.params.M_load == 7000.0
    with pytest.raises(ValueError, match="contradicts"):
        gym.make("WheelLoader-v2", scenario=s, braking="tc")


def test_a_suite_env_draws_per_reset_deterministically():
    env = gym.make("WheelLoader-v2", scenario="train")
    first = [env.reset(seed=5)[1]["scenario"] for _ in range(2)]
    again = gym.make("WheelLoader-v2", scenario="train")
    assert [again.reset(seed=5)[1]["scenario"] for _ in range(2)] == first
    draws = {env.reset()[1]["scenario"] for _ in range(5)}
    assert len(draws) == 5


def test_the_vector_env_draws_a_scenario_per_loader_and_matches_single_envs():
    n = 3
    vec = gym.make_vec("WheelLoader-v2", num_envs=n, vectorization_mode="vector_entry_point", scenario="train")
    obs, _ = vec.reset(seed=11)
    singles = [gym.make("WheelLoader-v2", scenario="train") for _ in range(n)]
    sobs = [e.reset(seed=11 + i)[0] for i, e in enumerate(singles)]
    assert np.allclose(obs, np.array(sobs), atol=1e-7)
    assert len({tuple(o[12:]) for o in obs}) == n  # each loader its own scenario
    for a in ACTIONS[:40]:
        obs, rew, term, trunc, _ = vec.step(np.tile(a, (n, 1)))
        res = [e.step(a) for e in singles]
        assert np.allclose(obs, np.array([r[0] for r in res]), atol=1e-6)
        assert np.allclose(rew, [r[1] for r in res], atol=1e-9)
        if term.any() or trunc.any():
            break


def test_the_vector_env_on_drawn_scenarios_cuts_a_substep_for_some_loaders_only():
    """Loaders of different scenarios reach the reversing point in different steps: the substep cut then runs
    on those loaders alone, with their own scenario's parameters (it once took all loaders' and failed)."""
    n = 4
    vec = gym.make_vec("WheelLoader-v2", num_envs=n, vectorization_mode="vector_entry_point", scenario="train")
    singles = [gym.make("WheelLoader-v2", scenario="train") for _ in range(n)]
    vec.reset(seed=3)
    for i, e in enumerate(singles):
        e.reset(seed=3 + i)
    for k in range(50):  # reverse, shift at step 22, brake gently to the reversing point, drive on
        a = np.array([0.3, 0.5, 0.3 if k >= 22 else -1.0, 1.0 if k >= 22 else -1.0], np.float32)
        obs, rew, term, trunc, info = vec.step(np.tile(a, (n, 1)))
        res = [e.step(a) for e in singles]
        assert np.allclose(obs, np.array([r[0] for r in res]), atol=1e-6), k
        assert np.allclose(rew, [r[1] for r in res], atol=1e-9), k
    assert (info["phase"] >= 3).all()  # every loader passed its reversing point


# ---------------------------------------------------------------------------------------------- controllers
def test_the_operator_and_the_mpc_drive_the_scenarios_cycle():
    """Told the episode's scenario, both stop on its own marks (5 m legs, a 4 m truck, 12 t): the operator
    once assumed 6.6 m and missed the reversing point by 12-24 cm."""
    from agents.evaluate import evaluate_controller, load_controller

    s = Scenario(payload=12000.0, reverse_distance=5.0, forward_distance=5.0, dump_height=4.0, braking="service")
    for name in ("operator", "mpc"):
        ev = evaluate_controller(load_controller(name, "service"), scenarios=[s], score=False)
        e = ev["per_episode"][0]
        assert e["scenario"] == s.to_dict()
        assert e["success"] and abs(e["reversing_error_m"]) <= 0.05 and abs(e["final_height_error_m"]) <= 0.02, name
        assert e["max_violation"] == 0.0, name


@pytest.mark.parametrize("payload", [6000.0, 13000.0])
def test_the_tc_operator_keeps_the_limit_where_its_lift_would_end_before_the_braking(payload):
    """A 10 m reverse to a 3.5 m truck: lifting from the start, the bucket stood at the dump height 1.2 s before
    the braking point, the wheels held the unloaded engine at ~148 rad/s, and the shift into forward gear braked
    at up to 2.6 times the deceleration limit (max_violation 1.55-1.58). The driver now times the lift to run
    into the braking."""
    from agents.operator import OperatorPolicy
    from wl_env.rollout import run_episode

    env = gym.make("WheelLoader-v2", braking="tc")
    for rolling in (0.015, 0.05):
        s = Scenario(payload=payload, reverse_distance=10.0, forward_distance=4.0, rolling_resistance=rolling,
                     dump_height=3.5, start_engine_speed=800.0, start_bucket_height=1.2, braking="tc")
        r = run_episode(env, OperatorPolicy("tc"), seed=0, scenario=s, trajectory=False)
        assert r.success and r.max_violation == 0.0, (rolling, r.max_violation)


def test_the_min_time_estimate_is_within_one_percent_of_every_test_optimum():
    """wl_env.suites.min_time, fitted on train draws only, against the 50 shipped test-suite optima per
    braking alternative (measured: median 0.14 % / 0.12 %, max 0.69 % / 0.45 %)."""
    from mpc.benchmark.reference import shipped_fronts
    from wl_env.suites import load_suite
    from wl_env.suites.min_time import estimate_min_time

    fronts = shipped_fronts()
    for braking in ("service", "tc"):
        errors = [estimate_min_time(sc) / fronts[f"{braking}_{sc.params().fingerprint()}"].T_min - 1.0
                  for sc in load_suite("test").of(braking)]
        assert len(errors) == 50 and max(map(abs, errors)) < 0.01, braking


def test_a_malformed_min_time_model_is_refused_by_name(tmp_path, monkeypatch):
    import wl_env.suites.min_time as mt

    bad = tmp_path / "min_time_model.json"
    bad.write_text('{"braking": {"service": {"coefficients": [1, 2]}, "tc": {"coefficients": [1]}}}')
    monkeypatch.setattr(mt, "MODEL_FILE", bad)
    mt._model.cache_clear()
    try:
        with pytest.raises(RuntimeError, match="min_time_model.json.*coefficients"):
            mt.estimate_min_time(Scenario.nominal("service"))
    finally:
        mt._model.cache_clear()


def test_a_suite_the_machine_cannot_drive_is_refused_when_the_env_is_made():
    """omega_max 207 rad/s is under the 2000 rpm (209 rad/s) start of the ranges: the vector env used to build,
    reset and raise at an autoreset 152 steps into training, naming LoaderParams.omega_0."""
    from wl_env.params import resolve

    for make in (lambda: gym.make("WheelLoader-v2", scenario="train", params={"omega_max": 207.0}),
                 lambda: gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point",
                                      scenario="train", params={"omega_max": 207.0})):
        with pytest.raises(ValueError, match=r"suite 'train' .*Scenario\.start_engine_speed = 2000 rpm"):
            make()
    with pytest.raises(ValueError, match=r"Scenario\.start_engine_speed = 1600 rpm does not fit"):
        Scenario(start_engine_speed=1600.0).params(resolve({"omega_max": 160.0}))
    env = gym.make("WheelLoader-v2", params={"omega_max": 200.0})  # the machine alone is fine
    with pytest.raises(ValueError, match="suite 'test'"):  # (its fastest start: 1945 rpm, 203.7 rad/s)
        env.reset(seed=0, options={"scenario": "test"})


def test_params_that_set_a_scenarios_fields_beside_the_scenario_are_refused():
    """They were dropped without a word: M_load 12000 and reverse_distance 8 m ran as 7000 kg and 6.6 m."""
    for make in (lambda **kw: gym.make("WheelLoader-v2", **kw),
                 lambda **kw: gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point", **kw)):
        with pytest.raises(ValueError, match="params sets M_load, reverse_distance, which the scenario sets"):
            make(params={"M_load": 12000.0, "reverse_distance": 8.0}, scenario={"payload": 7000.0})
    env = gym.make("WheelLoader-v2", params={"M_load": 12000.0}).unwrapped  # no scenario: the params are the cycle
    assert env.params.M_load == 12000.0


def test_the_distance_alias_beside_a_scenario_is_refused(tmp_path, capsys):
    """``distance`` sets both legs (LoaderParams.replace); beside a scenario it ran as 6.6 m without a word."""
    import wl.cli

    for make in (lambda **kw: gym.make("WheelLoader-v2", **kw),
                 lambda **kw: gym.make_vec("WheelLoader-v2", num_envs=2, vectorization_mode="vector_entry_point", **kw)):
        with pytest.raises(ValueError, match="params sets distance, which the scenario sets"):
            make(params={"distance": 5.0}, scenario={"payload": 7000.0})
    assert gym.make("WheelLoader-v2", params={"distance": 5.0}).unwrapped.params.reverse_distance == 5.0
    code = wl.cli.main(["ocp", "--params", '{"distance": 5}', "--scenario", '{"payload": 7000}',
                        "--out", str(tmp_path / "o.json")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--params sets distance, which the --scenario sets" in err, err


def test_library_entry_points_refuse_bad_arguments_by_name():
    """Were a TypeError ("unhashable type"), AttributeErrors, and a NaN target that reached the controller."""
    from agents.operator import OperatorPolicy
    from wl_env.rollout import run_episode
    from wl_env.suites.min_time import estimate_min_time

    assert len(load_suite("test").spread("service", np.int64(3))) == 3  # (a numpy integer, as MPCConfig takes it)
    for call, needle in [(lambda: load_suite(["test"]), "unknown suite"),
                         (lambda: estimate_min_time("abc"), "scenario must be a wl_env.scenario.Scenario"),
                         (lambda: run_episode("abc", OperatorPolicy("service")), "env must be a single WheelLoader env"),
                         (lambda: run_episode(gym.make("WheelLoader-v2"), None), "act\\(obs\\) method"),
                         (lambda: run_episode(gym.make("WheelLoader-v2"), OperatorPolicy("service"), target_time=math.nan),
                          "target_time must lie in")]:
        with pytest.raises(ValueError, match=needle):
            call()


@pytest.mark.parametrize("kwargs, needle", [
    ({"limit": 0}, "limit must be None or an integer >= 1"),  # (wrote the suite's file without its scenarios)
    ({"limit": -1}, "limit must be None or an integer >= 1"),  # (left out each chain's last scenario)
    ({"limit": 2.5}, "limit must be None or an integer >= 1"),  # (a TypeError from a slice)
    ({"n_points": 2}, r"n_points must be an integer in \[3, 100\]"),  # (failed in the workers, if at all)
    ({"ray_chunk": 0}, "ray_chunk must be an integer >= 1")])
def test_a_suite_solve_checks_its_arguments_before_any_work(tmp_path, kwargs, needle):
    from mpc.benchmark.suite import solve_suite

    with pytest.raises(ValueError, match=needle):
        solve_suite("nominal", cache=tmp_path, workers=1, job="fakes:fake_front_job", **kwargs)
    assert not any(tmp_path.iterdir())
    r = solve_suite("nominal", cache=tmp_path, workers=1, job="fakes:fake_front_job", limit=np.int64(1))
    assert len(r.entries) == 2


def test_scenario_text_replace_and_braking_are_read_or_refused_by_name(tmp_path):
    """Scenario.parse(5) and parse(b"...") were an AttributeError and a TypeError, parse("") said "'' is a folder",
    replace(colour=1) was a TypeError, and a braking spelled np.str_("tc") was kept as numpy's string."""
    from pathlib import Path

    for text, needle in [(5, r"scenario takes JSON text or the path of a JSON file, got 5 \(int\)"),
                         (b'{"payload": 7000}', r"got b'.*' \(bytes\)"), (None, "NoneType"),
                         ("", "got an empty text"), ("  \n", "got an empty text")]:
        with pytest.raises(ValueError, match=needle):
            Scenario.parse(text, "scenario")
    f = tmp_path / "s.json"
    f.write_text('{"payload": 7000}')
    assert Scenario.parse(Path(f)).payload == 7000.0
    with pytest.raises(ValueError, match=r"unknown Scenario field\(s\) \['colour'\]"):
        Scenario().replace(colour=1)
    s = Scenario(braking=np.str_("tc"))
    assert type(s.braking) is str and s == Scenario(braking="tc") and repr(s) == repr(Scenario(braking="tc"))


# ------------------------------------------------------------------ hostile inputs (eleventh round, wl_env's API)
def test_a_scenario_file_larger_than_any_scenario_or_no_regular_file_is_refused_by_name(tmp_path, monkeypatch):
    """A sparse 3 GB file was read whole (20 s, 6 GB); a FIFO that appeared after the check was waited on forever.
    Both are refused by name, on the file opened, before it is read; a byte order mark is read as JSON's UTF-8."""
    import os
    import threading
    import time

    import wl_env.scenario as scenario_module

    big = tmp_path / "big.json"
    with open(big, "wb") as fh:
        fh.truncate(3 * 2**30)
    start = time.monotonic()
    with pytest.raises(ValueError, match=rf"scenario file {big} is 3221225472 bytes, more than a scenario's JSON"):
        Scenario.parse(str(big), "scenario")
    with pytest.raises(ValueError, match="3221225472 bytes"):
        gym.make("WheelLoader-v2", scenario=str(big))
    assert time.monotonic() - start < 2.0
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    monkeypatch.setattr(scenario_module, "is_file", lambda path: True)  # (a regular file swapped for a FIFO after the check)
    result: list = []

    def parse() -> None:
        try:
            Scenario.parse(str(fifo), "scenario")
        except ValueError as exc:
            result.append(str(exc))

    thread = threading.Thread(target=parse, daemon=True)
    thread.start()
    thread.join(5.0)
    if thread.is_alive():  # (unblock the old code's read, then fail)
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("Scenario.parse waited on a FIFO")
    assert result and f"scenario file {fifo} is not a regular file" in result[0]
    monkeypatch.undo()
    bom = tmp_path / "bom.json"
    bom.write_bytes(b'\xef\xbb\xbf{"payload": 7000}')
    assert Scenario.parse(str(bom)).payload == 7000.0


def test_a_scenarios_machine_is_a_loader_params_or_an_error_naming_it():
    """Scenario.params(None), .fingerprint({}) and Scenario.from_params(None) were AttributeErrors."""
    from wl_env.params import LoaderParams

    for call, name in ((lambda b: Scenario().params(b), "base"), (lambda b: Scenario().fingerprint(b), "base"),
                       (lambda b: Scenario.from_params(b), "params")):
        for bad in (None, {}, {"M_veh": 30000.0}, 5):
            with pytest.raises(ValueError, match=rf"{name} must be a LoaderParams"):
                call(bad)
    assert Scenario.from_params(LoaderParams()) == Scenario() and Scenario().params(LoaderParams()) == LoaderParams()


def test_a_suite_draws_only_from_a_generator():
    """Suite.sample(5, ...) was an AttributeError; a legacy RandomState drew from the sampler without a word."""
    for name in ("train", "test"):
        for bad in (5, None, np.random.RandomState(0)):
            with pytest.raises(ValueError, match="rng must be a numpy Generator"):
                load_suite(name).sample(bad, "service")
    assert load_suite("train").sample(np.random.default_rng(0), "tc").braking == "tc"


# ---------------------------------------------------------------------------------------------------------------------
# Eleventh review round (mpc/benchmark/suite.py): each test fails on the code before its fix.
# ---------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("job, needle", [
    ("nope:solve", r"job 'nope:solve' names no function: ModuleNotFoundError"),
    ("fakes:nothing", r"job 'fakes:nothing' names no function: AttributeError"),
    ("fakes", r"job must name a function as 'module:function', got 'fakes'"),
    (5, r"job must name a function as 'module:function', got 5"),
    ("fakes:np", r"job 'fakes:np' is no function")])
def test_a_suite_solves_job_is_resolved_before_any_work(tmp_path, job, needle):
    """solve_suite(job=...) resolved the name only inside the workers (a ModuleNotFoundError, an AttributeError or a
    TypeError, after the cache's folder was made): a ValueError naming it, nothing made."""
    from mpc.benchmark.suite import solve_suite

    with pytest.raises(ValueError, match=needle):
        solve_suite("nominal", cache=tmp_path, workers=2, job=job)
    assert not any(tmp_path.iterdir())
