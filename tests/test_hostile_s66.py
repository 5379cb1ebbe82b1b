"""Stop 66's hostile-input round: a cached Pareto front of another point count, and a policy file whose metadata names
an env of other spaces. Each test's docstring says what the code before its fix did."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from fakes import fake_solve

import mpc.benchmark.pareto as pareto
import wl_env  # noqa: F401  (registers the envs)

POLICIES = Path(__file__).resolve().parents[1] / "agents" / "policies"


@pytest.fixture
def fake(monkeypatch):
    """The expensive solve replaced by :func:`fakes.fake_solve` (the cache's load and write paths are the real ones)."""
    fake_solve.calls = []
    monkeypatch.setattr(pareto, "solve_ocp", fake_solve)
    return fake_solve


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


# ---------------------------------------------------------------------------------------------- cached fronts
def test_a_cached_front_of_another_point_count_is_set_aside_and_solved(tmp_path, fake, caplog):
    """A front is cached in a folder named for its point count (``..._n11_v6/front.json``), but the count was never
    checked on reading: a 3-point front copied into the n11 folder was returned as the 11-point front, without a word
    and without a solve. It is a bad entry now: logged, set aside and the 11 points solved."""
    pareto.pareto_front("service", 3, cache=tmp_path, neighbour=False)
    n11 = pareto.front_folder("service", 11, cache=tmp_path)
    n11.mkdir(parents=True)
    shutil.copy(pareto.front_folder("service", 3, cache=tmp_path) / "front.json", n11 / "front.json")
    fake.calls.clear()
    with caplog.at_level(logging.WARNING):
        front = pareto.pareto_front("service", 11, cache=tmp_path, neighbour=False)
    assert len(front.points) == 11 and len(front.T) == 11 and fake.calls  # solved, not the copied 3 points
    (warning,) = _warnings(caplog)
    assert str(n11 / "front.json") in warning
    assert "field 'points' holds 3 point records, expected 11 (n_points" in warning
    assert len(list(n11.glob("front.json.bad-*"))) == 1
    # the new entry is taken as it is, and so is the 3-point front in its own folder
    caplog.clear()
    fake.calls.clear()
    with caplog.at_level(logging.WARNING):
        assert pareto.pareto_front("service", 11, cache=tmp_path, neighbour=False).T == front.T
        assert len(pareto.pareto_front("service", 3, cache=tmp_path, neighbour=False).points) == 3
    assert fake.calls == [] and _warnings(caplog) == []


# ---------------------------------------------------------------------------------------------- policy files
def _copy_policy(name: str, stem: Path) -> dict[str, bytes]:
    for suffix in (".safetensors", "_vecnormalize.npz", ".json"):
        shutil.copy(POLICIES / f"{name}{suffix}", f"{stem}{suffix}")
    return {p.name: p.read_bytes() for p in stem.parent.iterdir()}


@pytest.mark.parametrize("name, env_id, needle", [
    ("ppo_service", "WheelLoader-v2", r"takes 12 observations; its env 'WheelLoader-v2' \(config.env_id\) has 19: the "
                                      r"policy maps observations \(12,\) to actions \(4,\), 'WheelLoader-v2' takes "
                                      r"observations \(19,\) and actions \(4,\)"),
    ("ppo_target_v2_service", "WheelLoaderTarget-v0",
     r"gives 3 numbers per action; its env 'WheelLoaderTarget-v0' takes 4: the policy maps observations \(21,\) to "
     r"actions \(3,\), 'WheelLoaderTarget-v0' takes observations \(21,\) and actions \(4,\)"),
    ("ppo_service", "CartPole-v1", r"observations \(12,\) to actions \(4,\); its env 'CartPole-v1' \(config.env_id\) "
                                   r"is none of \['WheelLoader-v1'"),
])
def test_a_policy_whose_named_env_takes_other_spaces_is_not_written(tmp_path, name, env_id, needle):
    """``write_policy`` checked only that ``config.env_id`` was a string: a 12-observation policy named for
    WheelLoader-v2 (19 observations), a 3-action one for WheelLoaderTarget-v0 (4 actions) or one for an env that is no
    wheel loader was written (over the good policy there) without complaint, and ``load_policy`` then refused it ("the
    policy takes 12 observations; its env 'WheelLoader-v2' has 19", naming neither space). The write is refused now,
    naming the env id and both spaces, with nothing written; the loader's refusal names both spaces too."""
    from agents.policy_files import PolicyFileError, write_policy
    from agents.ppo import load_policy

    stem = tmp_path / "p"
    before = _copy_policy(name, stem)
    policy = load_policy(stem)
    meta = {**policy.meta, "config": {**(policy.meta.get("config") or {}), "env_id": env_id}}
    with pytest.raises(PolicyFileError, match=f"policy {re.escape(str(stem))} not written: .*{needle}"):
        write_policy(policy.network, policy.normalization, stem, meta)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing written, no temporary left
    # a file that says so by hand (the metadata has no checksum): the loader names it, the env id and both spaces
    meta_path = tmp_path / "p.json"
    on_disk = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**on_disk, "config": {**(on_disk.get("config") or {}), "env_id": env_id}}))
    with pytest.raises(PolicyFileError, match=f"policy {re.escape(str(meta_path))}: .*{needle}"):
        load_policy(stem)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # (WheelLoader-v1 is the shipped policy's env)
def test_a_policy_whose_named_env_fits_is_written_and_acts_as_before(tmp_path):
    """The env check at write takes what loading takes: the shipped policy named for its own env, and one whose
    metadata names no env (a training checkpoint's), are written and load."""
    from agents.policy_files import write_policy
    from agents.ppo import load_policy

    stem = tmp_path / "p"
    _copy_policy("ppo_service", stem)
    policy = load_policy(stem)
    obs, _ = gym.make("WheelLoader-v1").reset(seed=0)
    for meta in ({**policy.meta, "config": {**(policy.meta.get("config") or {}), "env_id": "WheelLoader-v1"}},
                 {"num_timesteps": 1}):
        write_policy(policy.network, policy.normalization, stem, meta)
        np.testing.assert_array_equal(load_policy(stem).act(obs), policy.act(obs))
