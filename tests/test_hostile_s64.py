"""The gaps the twelfth hostile round (stop 64) found: one policy by two spellings, CMA-ES seeds out of pycma's range,
numpy integers refused by the demonstrations' settings, and the folders an interrupted solve left empty. Each test
fails on the code before its fix."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from fakes import load_script

import wl.cli

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
POLICY = ROOT / "agents" / "policies" / "ppo_target_service"  # (read only: its paths, never written)


def _script(name: str):
    return load_script(name, "s64_")


def _interrupted(*args, **kwargs):
    raise KeyboardInterrupt


# ------------------------------------------------------------------------------- one policy by two spellings
@pytest.mark.parametrize("other", [f"{POLICY}.safetensors", f"{POLICY}.json", f"{POLICY}_vecnormalize.npz",
                                   f"{POLICY.parent}/../policies/{POLICY.name}"])
def test_select_policy_refuses_one_policy_by_two_spellings(other):
    """`--policies P P.safetensors` drove the one policy twice and counted it as two (only ./P and P were caught: the
    paths' real paths differ, the file each loads from does not)."""
    script = _script("select_policy.py")
    with pytest.raises(ValueError, match="--policies names a policy twice") as info:
        script.check(script.Options(policies=[str(POLICY), other]))
    assert str(POLICY) in str(info.value) and other in str(info.value)
    script.check(script.Options(policies=[str(POLICY), str(POLICY.with_name("ppo_target_tc"))]))  # (two: as before)


def test_bench_agents_refuses_a_run_and_its_final_folder(tmp_path, monkeypatch, capsys):
    """`--runs runs/a runs/a/final` (or runs/a/final/policy.safetensors) evaluated one policy twice and counted it
    twice in the spread over the runs."""
    script = _script("bench_agents.py")
    (tmp_path / "a" / "final").mkdir(parents=True)
    (tmp_path / "a" / "final" / "policy.safetensors").write_bytes(b"")  # (its path is all the check reads)

    def never(args):
        raise AssertionError("the runs were evaluated")

    monkeypatch.setattr(script, "runs_mode", never)
    run = tmp_path / "a"
    for other in (run / "final", run / "final" / "policy.safetensors", run / "final" / "policy"):
        monkeypatch.setattr(sys, "argv", ["bench_agents.py", "--suite", "test", "--runs", str(run), str(other)])
        with pytest.raises(SystemExit) as info:
            script.main()
        assert info.value.code == 2
        assert f"--runs names a run twice: {run} and {other}" in capsys.readouterr().err


# ------------------------------------------------------------------------------- CMA-ES seeds
@pytest.mark.parametrize("seed", [-1, 0, 2**32, 2**64, True])
def test_bench_plan_ceiling_refuses_a_seed_pycma_cannot_take(seed, monkeypatch):
    """-1 and 2**32 failed at the first search with pycma's "Seed must be between 0 and 2**32 - 1" (naming no option),
    and 0 was pycma's seed from the clock: a ceiling no run could repeat, recorded as seed 0."""
    script = _script("bench_plan_ceiling.py")
    monkeypatch.setattr(script, "search", lambda *args: pytest.fail("a search began"))
    with pytest.raises(ValueError, match=r"--seed must be an integer in \[1, 2\*\*32 - 1\]"):
        script.main(script.Options(seed=seed))
    for seed in (1, 2**32 - 1):
        script.check(script.Options(seed=seed))


def test_distill_plans_refuses_a_seed_whose_searches_pycma_cannot_take(tmp_path):
    """Its searches' CMA-ES seeds are --seed * 10**6 + c + 1: --seed 5000 (allowed up to 2**20) failed at the first
    search, after the policy's load, with pycma's error."""
    script = _script("distill_plans.py")
    with pytest.raises(ValueError, match=r"--seed must be an integer in \[0, 4293\], got 5000"):
        script.check(script.Options(policy=str(POLICY), out=tmp_path / "x", seed=5000))
    script.check(script.Options(policy=str(POLICY), out=tmp_path / "x", seed=4293))
    assert 4293 * script.SEED_STRIDE + script.MAX_CYCLES <= 2**32 - 1 < 4294 * script.SEED_STRIDE + script.MAX_CYCLES


# ------------------------------------------------------------------------------- numpy integers
def test_the_demonstrations_settings_take_numpy_numbers_and_refuse_bools():
    """DemoSettings(seed=np.int64(3)) and fast_share=np.float32(0.2) were refused, while fast_share=True and beta=True
    were taken as 1."""
    from agents.imitation import DemoSettings

    s = DemoSettings("service", seed=np.int64(3), fast_share=np.float32(0.2), beta=np.float64(0.5),
                     target=(np.float32(1.05), 2.5))
    assert (s.seed, s.fast_share, s.beta, s.target) == (3, 0.2, 0.5, (1.05, 2.5))
    assert type(s.seed) is int and type(s.fast_share) is float
    for field, bad in (("seed", True), ("seed", 2.5), ("seed", np.float64(3.0)), ("fast_share", True),
                       ("beta", np.bool_(True))):
        with pytest.raises(ValueError, match=f"{field} must (be an integer >= 0|lie in \\[0, 1\\]), got"):
            DemoSettings("service", **{field: bad})


def test_collect_demos_takes_numpy_integers(tmp_path, monkeypatch):
    """collect_demos(episodes=np.int64(2)) was "episodes must be an integer >= 1, got np.int64(2)", and workers
    np.int64(1) "workers must be an integer in [1, 8]" (check_workers: wl suite solve, train_runs, pareto_fronts)."""
    import agents.imitation as imitation
    from mpc.workers import check_workers

    ran = []

    def chunk(settings, indices, out):
        ran.append(indices)
        raise LookupError("collected")

    monkeypatch.setattr(imitation, "collect_chunk", chunk)
    settings = imitation.DemoSettings("service", expert="operator")
    with pytest.raises(LookupError, match="collected"):
        imitation.collect_demos(settings, np.int64(2), tmp_path, workers=np.int64(1))
    assert ran == [[0, 1]]
    for bad in (True, np.bool_(True), 2.5, np.float64(2.0), 0):
        with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
            imitation.collect_demos(settings, bad, tmp_path)
    assert check_workers(np.int64(1)) == 1 and type(check_workers(np.uint8(1))) is int
    for bad in (np.bool_(True), np.float64(1.0)):
        with pytest.raises(ValueError, match="workers must be an integer in"):
            check_workers(bad)


# ------------------------------------------------------------------------------- folders an interrupt left empty
def test_an_interrupted_pareto_leaves_no_empty_folder(tmp_path, monkeypatch, capsys):
    """Ctrl-C before the front's first point was solved left `<cache>/pareto/<front>/` empty (and so the --cache
    folder it created, which `wl` then kept); the folder is now made by the first entry written into it."""
    import mpc.benchmark.pareto as pareto

    monkeypatch.setattr(pareto, "solve_ocp", _interrupted)
    new = tmp_path / "new" / "cache"
    assert wl.cli.main(["pareto", "--braking", "tc", "--out", str(tmp_path / "out"), "--cache", str(new)]) == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    found = tmp_path / "found"  # a cache that was there: kept, with nothing of the front in it
    found.mkdir()
    assert wl.cli.main(["pareto", "--braking", "tc", "--out", str(tmp_path / "out"), "--cache", str(found)]) == 130
    assert sorted(tmp_path.iterdir()) == [found] and not any(found.iterdir())
    monkeypatch.setenv("WL_CACHE_DIR", str(found))  # the default cache
    assert wl.cli.main(["pareto", "--braking", "service", "--out", str(tmp_path / "out")]) == 130
    assert not any(found.iterdir())
    assert "wl: interrupted" in capsys.readouterr().err


def test_an_interrupted_suite_solve_leaves_no_empty_folder(tmp_path, monkeypatch, capsys):
    """The same in `wl suite solve`: `<cache>/suites/` (made by the check of the suite file's folder) and
    `<cache>/suites/<suite>_v1_n11_v6/` were left empty."""
    import mpc.benchmark.suite as suite

    monkeypatch.setattr(suite, "solve_one", _interrupted)
    cache = tmp_path / "cache"
    cache.mkdir()
    with pytest.raises(KeyboardInterrupt):
        suite.solve_suite("test", cache=cache, workers=1, limit=1)
    assert not any(cache.iterdir())
    argv = ["suite", "solve", "--suite", "test", "--workers", "1", "--limit", "1", "--cache", str(tmp_path / "new")]
    assert wl.cli.main(argv) == 130
    assert sorted(tmp_path.iterdir()) == [cache]
    capsys.readouterr()


def test_an_interrupted_atomic_write_removes_the_folders_it_made(tmp_path, monkeypatch):
    """A cache entry's write makes its folder: Ctrl-C inside the write removed the temporary file and left the new
    folder (and the parents it made) empty. A folder that was there, or holds a file, stays."""
    from wl_env import atomic_io

    monkeypatch.setattr(atomic_io, "current_umask", _interrupted)
    with pytest.raises(KeyboardInterrupt):
        atomic_io.write_json_atomic(tmp_path / "a" / "b" / "x.json", {"new": 1})
    assert not (tmp_path / "a").exists()
    (tmp_path / "kept").mkdir()
    with pytest.raises(KeyboardInterrupt):
        atomic_io.write_json_atomic(tmp_path / "kept" / "new" / "x.json", {"new": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"] and not any((tmp_path / "kept").iterdir())
    monkeypatch.undo()
    atomic_io.write_json_atomic(tmp_path / "a" / "b" / "x.json", {"new": 1})  # (a write that ends well: as before)
    assert (tmp_path / "a" / "b" / "x.json").read_text() == '{\n "new": 1\n}\n'
