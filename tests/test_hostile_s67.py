"""Stop 67's hostile-input round: a cached front of another point count read by `known_front`, `nearest_front` and a
suite's entries (stop 66 fixed `pareto_front`'s own read only), and a trusted stable-baselines3 policy whose metadata or
normalization was taken unchecked. Each test's docstring says what the code before its fix did."""

from __future__ import annotations

import json
import logging
import pickle
import shutil
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mpc.benchmark.pareto as pareto
from mpc.benchmark import reference, store
from wl_env.params import DEFAULT_PARAMS, LoaderParams


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def _nominal_front() -> dict:
    """The shipped nominal service front (11 points) as the entry `pareto_front` writes."""
    return dict(reference.shipped_fronts()["service_" + DEFAULT_PARAMS.fingerprint()].__dict__)


def _with_points(front: dict, k: int) -> dict:
    """``front`` with ``k`` point records (its own, repeated or cut): a valid front entry of another point count."""
    points = front["points"]
    return {**front, "points": [points[i % len(points)] for i in range(k)]}


def _write(path: Path, entry: dict) -> Path:
    return store.write_entry(path, pareto.FRONT_KIND, entry, pareto.check_front)  # (checksum and all, as a copy would)


# ------------------------------------------------------------------------------ cached fronts of another point count
def test_known_front_passes_over_a_cached_front_of_another_point_count(tmp_path, caplog):
    """`known_front` (so every score, `wl evaluate` and `wl run`) took a 3-point front in the n11 folder as the cycle's
    cached 11-point front, without a word. It is a bad entry now: logged, set aside, and the shipped front used."""
    path = pareto.front_folder("service", 11, cache=tmp_path) / "front.json"
    _write(path, _with_points(_nominal_front(), 3))
    with caplog.at_level(logging.WARNING):
        front, source = reference.known_front("service", DEFAULT_PARAMS, tmp_path)
    assert source == "shipped" and len(front.points) == 11
    (warning,) = _warnings(caplog)
    assert str(path) in warning and "holds 3 point records, expected 11" in warning
    assert not path.exists() and len(list(path.parent.glob("front.json.bad-*"))) == 1


@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.integers(1, 30))
def test_known_front_takes_a_cached_front_only_of_its_folders_point_count(k):
    """Any count of point records but the folder's was taken as the cached front (a 3- or 30-point front in n11)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = pareto.front_folder("service", 11, cache=tmp) / "front.json"
        _write(path, _with_points(_nominal_front(), k))
        logging.disable(logging.WARNING)  # (the warning is the test above's)
        try:
            _, source = reference.known_front("service", None, tmp)
        finally:
            logging.disable(logging.NOTSET)
        assert source == ("cached" if k == 11 else "shipped")
        assert path.exists() == (k == 11)


def test_nearest_front_skips_a_neighbours_front_of_another_point_count(tmp_path, caplog):
    """`nearest_front` (the warm start of every other scenario's sweep, and of the direct solves of a cycle without a
    front) took a neighbour's 3-point front in an n11 folder as an 11-point front, and guided the sweep from its
    folder. It is a bad entry now, set aside with a warning; an 11-point one is still found."""
    front = _nominal_front()
    folder = tmp_path / "pareto" / f"service_{front['params_fingerprint']}_n11_{pareto.CACHE_VERSION}"
    heavier = LoaderParams(M_load=12000.0)  # (another scenario of the same machine)
    _write(folder / "front.json", front)
    assert pareto.nearest_front("service", 11, heavier, tmp_path) == folder
    _write(folder / "front.json", _with_points(front, 3))
    with caplog.at_level(logging.WARNING):
        assert pareto.nearest_front("service", 11, heavier, tmp_path) is None
    (warning,) = _warnings(caplog)
    assert str(folder / "front.json") in warning and "holds 3 point records, expected 11" in warning
    assert list(folder.glob("front.json.bad-*"))


def test_a_suites_entry_of_another_point_count_is_solved_again(tmp_path, caplog):
    """`wl suite solve` counted a scenario's entry of 3 point records in its `..._n11_...` folder as solved and
    assembled it into the suite's file of n_points 11. It is set aside with a warning and solved again."""
    from mpc.benchmark.suite import solve_suite

    first = solve_suite("nominal", cache=tmp_path, workers=1, job="fakes:fake_front_job", limit=1)
    assert first.solved == 2 and all(len(e["points"]) == 11 for e in first.entries.values())
    entry = sorted((tmp_path / "suites").glob("nominal_v1_n11_*/service_*.json"))[0]
    data = store.read_entry(entry, pareto.FRONT_KIND, pareto.check_front)
    _write(entry, _with_points(data, 3))
    with caplog.at_level(logging.WARNING):
        again = solve_suite("nominal", cache=tmp_path, workers=1, job="fakes:fake_front_job", limit=1)
    assert again.solved == 1
    assert any(str(entry) in w and "holds 3 point records, expected 11" in w for w in _warnings(caplog))
    suite_file = json.loads(again.file.read_text())
    assert all(len(e["points"]) == 11 for e in suite_file["entries"].values())


def test_a_suite_file_whose_entries_hold_another_point_count_is_refused():
    """A suite file (shipped, or written by `wl suite solve`) was checked entry by entry but never against its own
    n_points: an entry of 3 point records in a file of 11 passed, and so did an n_points of "x"."""
    from mpc.benchmark.reference import check_suite_file

    front = store.as_read(_nominal_front())
    key = f"service_{front['params_fingerprint']}"
    data = {"suite": "x", "suite_version": 1, "cache_version": pareto.CACHE_VERSION, "n_points": 11,
            "entries": {key: front}}
    assert check_suite_file(data) is None
    assert "holds 3 point records, expected 11" in check_suite_file({**data, "entries": {key: _with_points(front, 3)}})
    assert "n_points must be an integer in [3, 100], got 'x'" in check_suite_file({**data, "n_points": "x"})


# ---------------------------------------------------------------------------- a trusted stable-baselines3 policy
@pytest.fixture(scope="module")
def sb3_run(tmp_path_factory) -> Path:
    """An untrained tiny model as training writes it (model.zip, vecnormalize.pkl, progress.json)."""
    from agents.ppo import build_model, make_env, save_model_files
    from agents.ppo_config import PPOConfig

    root = tmp_path_factory.mktemp("sb3")
    cfg = PPOConfig(num_envs=2, n_steps=8, batch_size=16, net_arch=(8,), score=False, progress_bar=False,
                    log_dir=str(root), run_name="own")
    env = make_env(cfg)
    env.reset()
    return save_model_files(build_model(cfg, env, root / "tb"), env, root / "own", {"braking": "service"})


_NORM = {"mean": [0.0] * 12, "var": [1.0] * 12, "clip_obs": 10.0, "epsilon": 1e-8}


@pytest.mark.parametrize("meta, needle", [
    ({"braking": "x", "obs_normalization": _NORM}, "braking must be \"service\" or \"tc\" (or absent), got 'x'"),  # (loaded)
    ({"config": {"braking": "zz"}, "obs_normalization": _NORM}, "got 'zz'"),  # (copied into the policy's braking)
    ({"config": "abc", "obs_normalization": _NORM}, "config must be an object"),  # (an AttributeError at the end)
    ({"obs_normalization": {"mean": [0.0] * 12}}, "obs_normalization must hold mean, var"),  # (a bare KeyError 'var')
    ({"obs_normalization": {**_NORM, "mean": "x"}}, "obs_normalization must hold mean, var"),  # (numpy's ValueError)
    ({"obs_normalization": {**_NORM, "mean": [0.0], "var": [1.0]}}, "mean and var must be 12 floats"),  # (broadcast)
    ({"obs_normalization": {**_NORM, "var": [-1.0] * 12}}, "mean and var must be finite, var >= 0"),  # (torch, at act)
    ({"obs_normalization": {**_NORM, "clip_obs": 0.0}}, "clip_obs must be a finite number > 0"),  # (every obs 0)
])
def test_a_trusted_zips_metadata_is_checked_as_a_pickle_free_policys(sb3_run, tmp_path, meta, needle):
    """With --trust-pickle, the metadata beside a stable-baselines3 zip was taken as it was: a braking "x" loaded, a
    config "abc" was an AttributeError, and the JSON copy of the normalization was unchecked (a missing entry a bare
    KeyError, a 1-entry mean broadcast over the 12 observations without a word, a negative variance a torch error at
    the first act). Each is a PolicyFileError naming the file, as for a pickle-free policy."""
    from agents.policy_files import PolicyFileError
    from agents.ppo import load_policy

    folder = shutil.copytree(sb3_run, tmp_path / "own")
    (folder / "vecnormalize.pkl").unlink()  # (the JSON copy of older exports is read only without the pickle)
    (folder / "model.json").write_text(json.dumps(meta))
    with pytest.raises(PolicyFileError, match="model.json") as err:
        load_policy(folder / "model.zip", trust_pickle=True)
    assert needle in str(err.value)


def test_a_trusted_normalization_pickle_of_other_observations_is_refused(sb3_run, tmp_path):
    """A VecNormalize pickle whose statistics hold 3 observations (the policy takes 12) was loaded; the first act()
    failed with numpy's broadcast error, naming no file. It is refused when loaded, naming the pickle."""
    from agents.policy_files import PolicyFileError
    from agents.ppo import load_policy

    folder = shutil.copytree(sb3_run, tmp_path / "own")
    good = load_policy(folder / "model.zip", trust_pickle=True)  # (its own pickle loads, as before)
    assert good.normalization is not None and good.normalization.mean.shape == (12,)
    other = SimpleNamespace(norm_obs=True, obs_rms=SimpleNamespace(mean=np.zeros(3), var=np.ones(3)), clip_obs=10.0,
                            epsilon=1e-8)
    (folder / "vecnormalize.pkl").write_bytes(pickle.dumps(other))
    with pytest.raises(PolicyFileError, match=r"vecnormalize.pkl: mean and var must be 12 floats, got shapes \(3,\)"):
        load_policy(folder / "model.zip", trust_pickle=True)
