"""Run a controller (anything with ``act(obs)``, optionally ``reset()``) through one episode."""

from __future__ import annotations

from typing import Any


def run_episode(env: Any, policy: Any, seed: int | None = None) -> dict[str, Any]:
    """Roll one episode; returns time, fuel, success and the trajectory (t, states, controls, phase)."""
    obs, info = env.reset(seed=seed)
    if hasattr(policy, "reset"):
        policy.reset()
    ts, states, controls, phases = [0.0], [list(env.unwrapped.state)], [], [1]
    total, info = 0.0, {}
    while True:
        obs, r, term, trunc, info = env.step(policy.act(obs))
        total += r
        ts.append(info["t"])
        states.append(list(info["state"]))
        controls.append(list(info["controls"]))
        phases.append(info["phase"])
        if term or trunc:
            break
    return {
        "T": info["t"], "fuel_g": info["fuel_g"], "success": info["is_success"], "completed": info["completed"],
        "return": total, "reversing_error": info["reversing_error"], "final_s": info["s"],
        "final_H": info["state"][2], "max_excess": info["violations"]["max_excess"],
        "t": ts, "states": states, "controls": controls, "phase": phases, "truncated": bool(trunc),
        "stalled": info["stalled"], "terminated": bool(term)
    }
