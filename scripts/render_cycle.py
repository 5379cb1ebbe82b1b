#!/usr/bin/env python
"""Render one short loading cycle to an animated GIF (or MP4), in the env its controller drives.

    python scripts/render_cycle.py --braking service --out cycle.gif
    python scripts/render_cycle.py --braking tc --out cycle_tc.mp4 --fps 20   # needs imageio-ffmpeg

Runs a controller (default: the rule-based operator; any ``wl evaluate --controller``) in its own env (a learned
policy's ``env_id``, else ``WheelLoader-v2``; a plan policy's plan driven on the per-step env under its plan env (``WheelLoaderTarget-v6`` or ``-v7``), a frame per
step) with ``render_mode="rgb_array"``, one frame at the reset and one per control step (dt = 0.1 s, so the default
10 fps plays in real time),
and writes the animation atomically (a temporary file in the same directory, then ``os.replace``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repo, if not installed

from mpc import interrupt  # noqa: E402
from wl_env import cycle  # noqa: E402
from wl_env.atomic_io import check_output_file  # noqa: E402
from wl_env.env import WheelLoaderEnv  # noqa: E402
from wl_env.rendering import MAX_FPS, MIN_FPS, check_fps, mp4_available, save_animation  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--braking", choices=cycle.BRAKING_MODES, default="service",
                    help="stop the reversing machine with the service brakes or the torque converter")
    ap.add_argument("--out", default=None, help="output file, .gif or .mp4 (default: cycle_<braking>.gif)")
    ap.add_argument("--fps", type=float, default=float(WheelLoaderEnv.metadata["render_fps"]),
                    help=f"frames per second of the animation, in [{MIN_FPS:g}, {MAX_FPS:g}] (10 = real time at dt = 0.1 s)")
    ap.add_argument("--controller", default="operator",
                    help="who drives: ppo, operator, mpc, module:Class or path/to/file.py:Class (as wl evaluate)")
    ap.add_argument("--model", default=None, help="policy file for --controller ppo (default: the shipped one)")
    ap.add_argument("--seed", type=int, default=0, help="reset seed")
    ap.add_argument("--max-steps", type=int, default=None,
                    help="stop after this many steps (frames = steps + 1); default: the whole cycle")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args(argv)
    if args.out is None:
        args.out = f"cycle_{args.braking}.gif"
    ext = os.path.splitext(args.out)[1].lower()
    if ext not in (".gif", ".mp4"):
        ap.error(f"--out must end in .gif or .mp4, got {args.out!r}")
    if ext == ".mp4" and not mp4_available():
        ap.error("writing .mp4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                 "or write a .gif (Pillow) instead")
    try:  # (before the run: inf wrote a GIF without delays, 1e-300 failed after the whole rendering)
        check_fps(args.fps, "--fps")
        check_output_file(args.out, "--out")
    except ValueError as exc:
        ap.error(str(exc))
    if args.max_steps is not None and args.max_steps < 0:
        ap.error(f"--max-steps must be >= 0, got {args.max_steps}")
    if args.seed < 0:
        ap.error(f"--seed must be >= 0, got {args.seed}")
    return args


def run(args: argparse.Namespace) -> dict:
    import gymnasium as gym

    import wl_env  # noqa: F401  (registers the envs)
    from agents.evaluate import load_controller
    from wl_env.plan import DRIVEN_ON, PlanDriver

    policy = load_controller(args.controller, args.braking, args.model)
    # (the env the controller was made for: a 12-number policy in the 19-number default env failed to broadcast)
    env_id = getattr(policy, "env_id", None) or "WheelLoader-v2"
    plan = env_id in DRIVEN_ON  # (one env step per cycle: its plan is driven step by step on the env under it)
    env = gym.make(DRIVEN_ON[env_id] if plan else env_id, braking=args.braking, render_mode="rgb_array")
    t0 = time.perf_counter()
    obs, info = env.reset(seed=args.seed)
    if hasattr(policy, "reset"):
        policy.reset()
    if plan:
        policy = PlanDriver(policy.act(obs), env.unwrapped.machine, env.unwrapped.core.dt)
    frames = [env.render()]
    steps, info, done = 0, {}, False
    while not done and (args.max_steps is None or steps < args.max_steps):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        frames.append(env.render())
        steps += 1
        done = terminated or truncated
    sim_render_s = time.perf_counter() - t0
    n = save_animation(frames, args.out, args.fps)
    env.close()
    return {"frames": n, "steps": steps, "done": done, "info": info, "seconds": sim_render_s}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        r = run(args)
    except (ValueError, OSError) as exc:  # a bad --controller or --model: one line naming it, no traceback
        print(f"render_cycle.py: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # (the animation is written at the end: nothing partial is left)
        print("render_cycle.py: interrupted", file=sys.stderr)
        return interrupt.exit_code()
    info = r["info"]
    size_kb = os.path.getsize(args.out) / 1024
    summary = f"wrote {args.out} ({r['frames']} frames at {args.fps:g} fps, {size_kb:.0f} kB)"
    if info:
        status = "success" if info["is_success"] else ("completed" if info["completed"] else "not finished")
        summary += (f"; {args.braking} braking, {args.controller}: t = {info['t']:.1f} s, fuel = {info['fuel_g']:.1f} g,"
                    f" {status}")
    print(summary)
    return 0


if __name__ == "__main__":
    with interrupt.handling():  # (SIGTERM too: it left the animation's temporary file behind)
        code = main()
    sys.exit(code)
