"""The twelfth hostile-input round (stop 64), second pass: the grid model's substeps, the PPO evaluations' episode
counts and seed, a result JSON cannot hold, and paths too long for the system. Each test fails on the code before
its fix (the old behaviour is said in its docstring)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import wl.cli

LONG = "a" * 300  # a file name longer than the system's 255 bytes (ENAMETOOLONG)


# ------------------------------------------------------------------------------------------ the grid model
@pytest.mark.parametrize("kwargs, needle", [
    ({"substeps": True}, "substeps must be an integer in [1, 1000], got True"),
    ({"substeps": 1001}, "substeps must be an integer in [1, 1000], got 1001"),
    ({"dt": True}, "dt (the control interval) must be > 0 s, got True"),
    ({"omega_margin": "1"}, "omega_margin must be >= 0 rad/s, got '1'"),
])
def test_step_model_refuses_bools_strings_and_too_many_substeps(kwargs, needle):
    """StepModel(substeps=True) ran as 1 substep and dt=True as a 1 s interval; 10**9 substeps built for hours
    (MPCController's range is [1, 1000]); omega_margin="1" was math.isfinite's TypeError."""
    from mpc.controller.grid import StepModel

    with pytest.raises(ValueError) as info:
        StepModel("service", **kwargs)
    assert needle in str(info.value)


def test_step_model_takes_numpy_numbers():
    """np.int64(1) substeps was refused as "must be an integer >= 1" (MPCController takes numpy's numbers)."""
    from mpc.controller.grid import StepModel

    model = StepModel("service", substeps=np.int64(1), dt=np.float32(0.1))
    assert model.substeps == 1 and type(model.substeps) is int and model.dt == 0.1


# ------------------------------------------------------------------------------------ PPO's evaluations
def _wrong_shape(obs):  # (an act that would fail the first step: the episodes must not be reached)
    return np.zeros(1, np.float32)


@pytest.mark.parametrize("n_episodes", [-3, True, 2.5, "2"])
def test_evaluate_targets_checks_n_episodes(n_episodes):
    """evaluate_targets drew range(n_episodes) unchecked: -3 ran the paper's cycle alone, True one draw, 2.5 and "2"
    were range()'s TypeError (and 10**9 drew scenarios for hours)."""
    from agents.ppo import evaluate_targets

    with pytest.raises(ValueError, match=r"n_episodes must be an integer in \[0, 99999\]"):
        evaluate_targets(_wrong_shape, "service", n_episodes=n_episodes, with_score=False)


def test_evaluate_targets_checks_its_seed_before_the_draws():
    """A seed of -1 was numpy's "expected non-negative integer" from the draws' stream, naming no parameter."""
    from agents.ppo import evaluate_targets

    with pytest.raises(ValueError, match=r"seed must be an integer in \[0, "):
        evaluate_targets(_wrong_shape, "service", n_episodes=1, seed=-1, with_score=False)


def test_evaluate_names_n_episodes():
    """evaluate(n_episodes=-1) was refused as "episodes must be an integer in [1, 100000], got 0": another parameter,
    another value."""
    from agents.ppo import evaluate

    with pytest.raises(ValueError, match=r"n_episodes must be an integer in \[0, 99999\], got -1"):
        evaluate(_wrong_shape, "service", n_episodes=-1, with_score=False)


def test_export_policy_checks_n_episodes_before_any_work(tmp_path):
    """export_policy(n_episodes=-1) read the run and loaded its policy (and solved a front to score against) before
    the evaluation refused it."""
    from agents.ppo import export_policy

    with pytest.raises(ValueError, match="n_episodes must be an integer"):
        export_policy(tmp_path / "no_run", tmp_path / "out", "p", n_episodes=-1)


# ------------------------------------------------------------------------------ a result JSON cannot hold
def test_a_result_json_cannot_hold_is_one_line_not_a_traceback(monkeypatch, capsys, tmp_path):
    """A TypeError while the result was serialised (`_put_result`) left `wl` as a traceback; now one `wl: error:` line,
    exit 2, and no file written."""
    import mpc.controller.mpc

    class Result:
        def to_dict(self):
            st = dict(median_s=0.0, p99_s=0.0, max_s=0.0, fallbacks=0, deadline_misses=0, replans=0, safety_eased=0)
            return {"T": 8.0, "fuel_g": 80.0, "success": True, "completed": True, "solve_time": st, "score": None,
                    "odd": object()}

    monkeypatch.setattr(mpc.controller.mpc, "run_closed_loop", lambda *args, **kwargs: Result())
    out = tmp_path / "m.json"
    for argv in (["mpc", "--no-score"], ["mpc", "--no-score", "--out", str(out)]):
        code = wl.cli.main(argv)
        captured = capsys.readouterr()
        err = captured.err.strip().splitlines()
        assert code == 2 and err[-1].startswith("wl: error: the result cannot be written as JSON"), captured.err
        assert "object is not JSON serializable" in err[-1] and captured.out == ""
    assert not out.exists() and list(tmp_path.iterdir()) == []


# -------------------------------------------------------------------------------- paths too long to use
def test_output_checks_name_the_option_for_a_path_too_long(tmp_path):
    """check_output_file and check_output_folder promise a ValueError starting with the option; a name longer than the
    system takes was a bare OSError ("[Errno 36] File name too long") from Path.exists()."""
    from wl_env.atomic_io import check_output_file, check_output_folder

    with pytest.raises(ValueError, match=r"^--out x: cannot use the path .*File name too long"):
        check_output_file(tmp_path / f"{LONG}.json", "--out x")
    with pytest.raises(ValueError, match=r"^--cache y: cannot create or write in the folder .*File name too long"):
        check_output_folder(tmp_path / LONG, "--cache y")


@pytest.mark.parametrize("argv, option", [
    (["pareto", "--points", "3", "--out", "{long}"], "--out"),
    (["mpc", "--no-score", "--cache", "{long}"], "--cache"),
    (["evaluate", "--controller", "operator", "--out", "{long}.json"], "--out"),
    (["run", "--out", "{long}"], "--out"),
    (["train", "--log-dir", "{long}"], "--log-dir"),
])
def test_wl_names_the_option_of_a_path_too_long(argv, option, tmp_path, capsys, monkeypatch):
    """`wl pareto --out <300 characters>` said "wl: error: [Errno 36] File name too long: '...'", naming no option
    (the CLI's own look for the folders it would create raised first)."""
    monkeypatch.chdir(tmp_path)
    code = wl.cli.main([a.format(long=LONG) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith(f"wl: error: {option}") and "Errno" not in err and len(err.splitlines()) == 1, err
    assert list(tmp_path.iterdir()) == []


def test_a_policy_or_controller_path_too_long_is_a_value_error(tmp_path):
    """load_policy and load_controller raised a bare OSError for a path too long (the policy loader promises a
    PolicyFileError naming the file; the CLI named no option)."""
    from agents.evaluate import load_controller
    from agents.policy_files import PolicyFileError
    from agents.ppo import load_policy

    with pytest.raises(PolicyFileError, match="no policy at .*File name too long"):
        load_policy(tmp_path / LONG)
    with pytest.raises(ValueError, match=r"controller file .* cannot be read: File name too long \(from --controller"):
        load_controller(f"{tmp_path / LONG}.py:Cls", "service")


def test_wl_train_names_init_policy_for_a_path_too_long(tmp_path, capsys):
    """`wl train --init-policy <300 characters>` was "[Errno 36] File name too long", naming no option."""
    code = wl.cli.main(["train", "--log-dir", str(tmp_path), "--init-policy", str(Path(tmp_path) / LONG)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("wl: error: --init-policy ") and "File name too long" in err, err


# ---------------------------------------------------------------------------------------------- rendering
@pytest.mark.parametrize("size", [(float("nan"), 300), ("300", 300), (300,), 300, (250.9, 200.9), (True, 300),
                                  (10**400, 300), (70000, 300), [300, 200, 5]])
def test_render_frame_checks_its_size(size):
    """render_frame's size: NaN was int()'s "cannot convert float NaN", (300,) an IndexError, 300 a TypeError, 10**400
    an OverflowError; "300" and 250.9 were taken as numbers, True as 1 pixel, a third entry ignored, and no side had a
    limit (70000 x 300 drew an 84 MB frame; 65000 x 65000 would ask for 17 GB)."""
    from wl_env import rendering
    from wl_env.env import WheelLoaderEnv

    env = WheelLoaderEnv()
    env.reset(seed=0)
    try:
        with pytest.raises(ValueError, match=r"size must be \(width, height\) in pixels, integers in \[200, 8192\]"):
            rendering.render_frame(env, size=size)
        frame = rendering.render_frame(env, size=(np.int64(320), np.int16(240)))  # (numpy's integers: as before)
        assert frame.shape == (240, 320, 3)
    finally:
        rendering.release(env)


# -------------------------------------------------------------------------------------------------- the MPC
def test_run_closed_loop_checks_its_cache_before_the_cycle(tmp_path, monkeypatch):
    """run_closed_loop(cache=<a file>) drove the whole cycle, then failed at the score ("cache must be a folder");
    only the type was checked first."""
    import mpc.controller.mpc as mpc_module

    def never(*args, **kwargs):
        raise AssertionError("the controller was built: the cycle would run")

    monkeypatch.setattr(mpc_module, "MPCController", never)
    a_file = tmp_path / "cache"
    a_file.write_text("")
    for cache in (a_file, a_file / "below"):
        with pytest.raises(ValueError, match="cache must be a folder, but .* is a file"):
            mpc_module.run_closed_loop("service", cache=cache)
    # (a seed the env's reset refuses: refused by name only after the controller was built, about a second)
    for seed in (-1, True, 1.5, "3"):
        with pytest.raises(ValueError, match="seed must be an integer >= 0"):
            mpc_module.run_closed_loop("service", seed=seed)


# ------------------------------------------------------------------------------------------- a sweep's values
def test_a_sweep_takes_none_where_the_field_does():
    """`--sweep target_kl=none,0.01` was "'none' is not a float", though the field's flag takes `--target-kl none`
    (off) and PPOConfig takes None; log_std_final the same."""
    from agents.ppo_config import PPOConfig
    from agents.seeds import expand, parse_sweep

    sweep = parse_sweep(["target_kl=none,0.01", "log_std_final=None,-1"])
    assert sweep == {"target_kl": [None, 0.01], "log_std_final": [None, -1.0]}
    cfgs = expand(PPOConfig(), [0], sweep)
    assert {(c.target_kl, c.log_std_final) for c in cfgs} == {(None, None), (None, -1.0), (0.01, None), (0.01, -1.0)}
    with pytest.raises(ValueError, match="--sweep learning_rate: 'none' is not a float"):  # (a field without an off)
        parse_sweep(["learning_rate=none,1e-3"])
