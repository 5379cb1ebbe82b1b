"""scripts/distill_plans.py: a plan policy improved by CMA-ES search on its training reward, then fitted to the
plans found (expert iteration)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import distill_plans as dp  # noqa: E402

from agents.ppo import load_policy  # noqa: E402
from agents.ppo_config import PPOConfig  # noqa: E402

SHIPPED = str(Path(__file__).resolve().parents[1] / "agents" / "policies" / "plan_target_tc")


def tiny(out: Path, **kw) -> dp.Options:
    return dp.Options(**{"policy": SHIPPED, "out": out, "cycles": 4, "batch": 2, "population": 6, "generations": 2,
                         "epochs": 3, "eval_cycles": 4, **kw})


@pytest.fixture(scope="module")
def distilled(tmp_path_factory):
    out = tmp_path_factory.mktemp("distill") / "d"
    return out, dp.main(tiny(out))


def test_the_search_never_keeps_a_plan_worse_than_the_policys_and_the_result_loads(distilled):
    out, record = distilled
    s = np.load(f"{out}_searches.npz", allow_pickle=False)
    assert s["obs"].shape == (4, 21) and s["best_plan"].shape == (4, 14)
    assert np.all(s["best_return"] >= s["policy_return"])  # a plan replaces the policy's only if it returned more
    assert np.all(np.abs(s["best_plan"]) <= 1.0)
    policy = load_policy(out)  # pickle-free, as shipped
    assert policy.env_id == load_policy(SHIPPED).env_id and policy.meta["distillation"]["searched"]["cycles"] == 4
    assert "evaluation" not in policy.meta  # (the original policy's evaluation is not this one's)
    # the kept epoch is the best held out, the start (epoch 0) included
    assert record["fit"]["validation_mse_after"] <= record["fit"]["validation_mse_before"]


def test_the_policys_return_in_the_search_is_its_plan_env_return(distilled):
    """The recorded return of the policy's plan is what the plan env gives its plan on the same reset."""
    out, _ = distilled
    s = np.load(f"{out}_searches.npz", allow_pickle=False)
    policy = load_policy(SHIPPED)
    env = dp.plan_env(PPOConfig.from_dict(policy.meta["config"]), 1)
    obs, r, _, _ = dp.run_plans(env, [1], s["policy_plan"][1:2])  # cycle 1 of --seed 0
    assert np.allclose(obs[0], s["obs"][1]) and r[0] == pytest.approx(s["policy_return"][1], rel=1e-9)


def test_a_rerun_resumes_from_the_searches_and_other_options_are_refused(distilled, tmp_path):
    out, record = distilled
    again = dp.main(tiny(out))  # every cycle already searched: nothing is searched again, the same rows
    assert again["searched"] == record["searched"] and again["search_wall_time_s"] < record["search_wall_time_s"]
    with pytest.raises(ValueError, match="other options"):
        dp.main(tiny(out, sigma=0.3))


def test_an_interrupted_search_resumes_where_it_stopped_with_the_same_searches(distilled, tmp_path, monkeypatch):
    """Ctrl-C after the first batch keeps that batch; the rerun searches only the rest, and the searches are those
    of the uninterrupted run (same seed, same cycles, same CMA-ES draws)."""
    out, _ = distilled
    search, calls = dp.search_batch, []

    def once_then_stop(env, policy, first, o):
        calls.append(first)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return search(env, policy, first, o)

    monkeypatch.setattr(dp, "search_batch", once_then_stop)
    with pytest.raises(KeyboardInterrupt):
        dp.main(tiny(tmp_path / "d"))
    assert not Path(f"{tmp_path / 'd'}.json").exists()  # no policy from a stopped run
    calls.clear()
    monkeypatch.setattr(dp, "search_batch", lambda *a: (calls.append(a[2]), search(*a))[1])
    dp.main(tiny(tmp_path / "d"))
    assert calls == [2]  # only the second batch (cycles 2, 3) was searched again
    resumed, whole = np.load(f"{tmp_path / 'd'}_searches.npz"), np.load(f"{out}_searches.npz")
    for f in dp.Searches.FIELDS:
        assert np.array_equal(resumed[f], whole[f]), f


@pytest.mark.parametrize("kw, match", [
    ({"cycles": 5}, "multiple of --batch"),
    ({"population": 2}, "--population must be an integer in"),
    ({"sigma": 0.0}, "--sigma must lie in"),
    ({"policy": str(Path(SHIPPED).with_name("ppo_target_tc"))}, "distillation takes a plan policy"),
])
def test_bad_options_are_refused_by_name(tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        dp.main(tiny(tmp_path / "d", **kw))


def test_a_corrupt_searches_file_is_refused(tmp_path):
    bad = tmp_path / "d_searches.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(ValueError, match="not a searches file"):
        dp.main(tiny(tmp_path / "d"))
