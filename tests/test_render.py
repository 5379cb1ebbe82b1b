"""Rendering: rgb_array frames, the figure cache, check_env's render check, "human" without a display,
and scripts/render_cycle.py writing an animated GIF."""

import importlib.util
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from PIL import Image

import wl_env  # noqa: F401  (registers the ids)
from agents.operator import OperatorPolicy
from wl_env import rendering
from wl_env.env import WheelLoaderEnv

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "render_cycle.py"
SCENE_ROWS = slice(0, 270)  # the side view, above the text panel


def _load_script():
    spec = importlib.util.spec_from_file_location("render_cycle", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _drive(env, policy, steps, obs):
    for _ in range(steps):
        obs, *_ = env.step(policy.act(obs))
    return obs


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_rgb_array_frames_have_shape_dtype_and_follow_the_loader(braking):
    env = WheelLoaderEnv(braking=braking, render_mode="rgb_array")
    policy = OperatorPolicy(braking)
    obs, _ = env.reset(seed=0)
    f0 = env.render()
    assert isinstance(f0, np.ndarray) and f0.dtype == np.uint8
    assert f0.shape == (rendering.HEIGHT, rendering.WIDTH, 3) and f0.flags.c_contiguous
    kept = f0.copy()
    obs = _drive(env, policy, 12, obs)
    assert env.position < -0.5  # reversing
    f1 = env.render()
    np.testing.assert_array_equal(f0, kept)  # a frame is a copy: later renders do not change it
    assert f1.shape == f0.shape and f1.dtype == np.uint8
    moved = np.any(f0[SCENE_ROWS] != f1[SCENE_ROWS], axis=2)
    assert moved.mean() > 0.01  # the loader moved in the picture, not just the numbers
    # Same state -> same frame; a frame is not blank.
    np.testing.assert_array_equal(env.render(), f1)
    assert len(np.unique(f1.reshape(-1, 3), axis=0)) > 20
    env.close()


def test_blitted_frames_equal_a_full_redraw_in_every_phase():
    env = WheelLoaderEnv(render_mode="rgb_array")
    policy = OperatorPolicy()
    obs, _ = env.reset(seed=0)
    env.render()
    scene = rendering._cache[env]
    seen = set()
    for _ in range(200):
        obs, _, term, trunc, info = env.step(policy.act(obs))
        frame = env.render()
        assert rendering._cache[env] is scene  # the figure is built once and reused
        if info["phase"] not in seen or term or trunc:
            seen.add(info["phase"])
            scene._background = None  # force a full redraw of the same state
            np.testing.assert_array_equal(env.render(), frame)
        if term or trunc:
            break
    assert seen == {1, 2, 3, 4}


def test_render_before_reset_and_without_mode():
    frame = WheelLoaderEnv(render_mode="rgb_array").render()  # the starting state
    assert frame.shape == (rendering.HEIGHT, rendering.WIDTH, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert WheelLoaderEnv().render() is None


def test_each_env_has_its_own_figure_and_custom_sizes():
    a, b = WheelLoaderEnv(render_mode="rgb_array"), WheelLoaderEnv(braking="tc", render_mode="rgb_array")
    a.reset(), b.reset()
    a.render(), b.render()
    assert rendering._cache[a] is not rendering._cache[b]
    small = rendering.render_frame(a, size=(320, 240))
    assert small.shape == (240, 320, 3)
    with pytest.raises(ValueError):
        rendering.render_frame(a, size=(10, 10))
    rendering.release(a)
    assert a not in rendering._cache


@pytest.mark.parametrize("braking", ["service", "tc"])
def test_check_env_with_render_check(braking):
    env = gym.make("WheelLoader-v1", braking=braking, render_mode="rgb_array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "human" is checked too; no display here
        gym_check_env(env.unwrapped)  # skip_render_check=False: rgb_array and human
    env.close()


def test_human_mode_without_display_warns_once_and_runs(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(rendering, "_warned_headless", False)
    env = WheelLoaderEnv(render_mode="human")
    with pytest.warns(RuntimeWarning, match="no display"):
        env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # only one warning
        for _ in range(3):
            env.step(np.zeros(4, np.float32))
        assert env.render() is None
    fig, image = env._renderer
    assert image.get_array().shape == (rendering.HEIGHT, rendering.WIDTH, 3)
    env.close()
    env.close()


def test_show_falls_back_when_the_window_cannot_open(monkeypatch):
    import matplotlib

    monkeypatch.setattr(rendering, "_display_available", lambda: True)
    monkeypatch.setattr(matplotlib, "get_backend", lambda *a, **k: "tkagg")
    import matplotlib.pyplot as plt

    def broken(*a, **k):
        raise RuntimeError("no $DISPLAY")

    monkeypatch.setattr(plt, "figure", broken)
    monkeypatch.setattr(rendering, "_warned_headless", False)
    frame = np.zeros((rendering.HEIGHT, rendering.WIDTH, 3), np.uint8)
    with pytest.warns(RuntimeWarning, match="cannot open a window"):
        handle = rendering.show(frame, None)
    assert rendering.show(frame + 1, handle) is handle
    assert handle[1].get_array()[0, 0, 0] == 1


def test_save_gif_is_atomic_and_keeps_frames(tmp_path):
    frames = [np.full((60, 80, 3), v, np.uint8) for v in (0, 80, 160, 240)]
    out = tmp_path / "sub" / "a.gif"
    assert rendering.save_gif(frames, str(out), fps=5) == 4
    out.write_bytes(b"old")
    rendering.save_animation(frames, str(out), fps=5)
    with Image.open(out) as im:
        assert im.n_frames == 4 and im.size == (80, 60) and im.info["duration"] == 200
    assert sorted(p.name for p in out.parent.iterdir()) == ["a.gif"]  # no temporary files left
    with pytest.raises(ValueError):
        rendering.save_animation(frames, str(tmp_path / "a.avi"))
    with pytest.raises(ValueError):
        rendering.save_gif([], str(tmp_path / "b.gif"))


@pytest.mark.parametrize("fps", [math.inf, math.nan, 0, -1, 1e-300, 1000.0, True, "10"])
def test_an_animation_frame_rate_out_of_range_is_refused_by_name(tmp_path, fps):
    """inf wrote a GIF without frame delays (round(1000 / inf) = 0), 1e-300 an OverflowError in Pillow."""
    frames = [np.zeros((6, 8, 3), np.uint8)] * 2
    for path in (tmp_path / "a.gif", tmp_path / "a.mp4"):
        with pytest.raises(ValueError, match=r"fps must be a finite number of frames per second in \[0.01, 100\]"):
            rendering.save_animation(frames, str(path), fps=fps)
    assert not list(tmp_path.iterdir())
    assert rendering.check_fps(np.float32(20.0)) == 20.0


def test_render_cycle_script_checks_fps_and_out_before_the_run(tmp_path, capsys):
    script = _load_script()
    for argv, needle in [(["--fps", "inf"], "--fps must be a finite number"), (["--fps", "1e-300"], "[0.01, 100]"),
                         (["--out", str(tmp_path / "f.gif" / "x.gif")], "is not a folder"),
                         (["--out", str(tmp_path / "d.gif")], "is a folder")]:
        (tmp_path / "f.gif").write_text("a file")
        (tmp_path / "d.gif").mkdir(exist_ok=True)
        with pytest.raises(SystemExit):
            script.parse_args([*([] if "--out" in argv else ["--out", str(tmp_path / "c.gif")]), *argv])
        assert needle in capsys.readouterr().err


def test_render_cycle_script_writes_gif(tmp_path):
    out = tmp_path / "cycle.gif"
    steps = 8
    proc = subprocess.run([sys.executable, str(SCRIPT), "--braking", "tc", "--out", str(out), "--fps", "20",
                           "--max-steps", str(steps)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert out.stat().st_size > 0 and "wrote" in proc.stdout
    with Image.open(out) as im:
        assert im.n_frames == steps + 1  # the reset frame and one per step
        assert im.size == (rendering.WIDTH, rendering.HEIGHT)
        assert im.info["duration"] == 50
    assert os.listdir(tmp_path) == ["cycle.gif"]


@pytest.mark.parametrize("controller", ["ppo", "bc", "plan"])
def test_render_cycle_script_drives_a_learned_policy_in_its_own_env(tmp_path, capsys, controller):
    """Each shipped policy renders in the env it was trained on (the per-step policies' observations are 12 and 21
    numbers, the default env's 19; a plan policy's one action per cycle is driven a step at a time)."""
    out = tmp_path / f"{controller}.gif"
    assert _load_script().main(["--controller", controller, "--braking", "tc", "--max-steps", "3", "--out", str(out)]) == 0
    assert "t = 0.3 s" in capsys.readouterr().out
    with Image.open(out) as im:
        assert im.n_frames == 4


def test_render_cycle_script_full_cycle_and_errors(tmp_path, capsys, monkeypatch):
    script = _load_script()
    out = tmp_path / "full.gif"
    assert script.main(["--out", str(out)]) == 0
    with Image.open(out) as im:
        n = im.n_frames
    env, policy = WheelLoaderEnv(), OperatorPolicy()
    obs, _ = env.reset(seed=0)
    steps = 0
    while True:
        obs, _, term, trunc, _ = env.step(policy.act(obs))
        steps += 1
        if term or trunc:
            break
    assert n == steps + 1  # the whole cycle
    monkeypatch.setattr(script, "mp4_available", lambda: False)
    with pytest.raises(SystemExit):
        script.parse_args(["--out", str(tmp_path / "x.mp4")])
    assert "imageio-ffmpeg" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        script.parse_args(["--out", str(tmp_path / "x.avi")])
    assert not (tmp_path / "x.mp4").exists()


def test_record_video_wrapper(tmp_path):
    pytest.importorskip("moviepy")
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(gym.make("WheelLoader-v1", render_mode="rgb_array"), str(tmp_path), disable_logger=True)
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())
    env.close()
    assert any(p.suffix == ".mp4" for p in tmp_path.iterdir())
