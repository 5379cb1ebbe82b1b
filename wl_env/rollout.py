"""Run a controller (anything with ``act(obs)``, optionally ``reset()``) through one episode.

The one rollout of the project: ``wl evaluate``, the training-time evaluation, the MPC's closed loop and
the report all run episodes here and get an :class:`EpisodeResult`.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import asdict, dataclass
from typing import Any


def takes_argument(fn: Any, name: str) -> bool:
    """True if a callable (a controller's reset) takes an argument ``name``."""
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):  # a builtin or an odd callable (or none): call it plainly
        return False


def takes_scenario(fn: Any) -> bool:
    """True if a callable (a controller's reset) takes a ``scenario`` argument."""
    return takes_argument(fn, "scenario")


def takes_target(controller: Any) -> bool:
    """True if a controller can be told a target cycle time (a wrapper says so for what it wraps)."""
    ask = getattr(controller, "takes_target", None)
    return bool(ask()) if callable(ask) else takes_argument(getattr(controller, "reset", None), "target_time")


def check_takes_target(controller: Any) -> None:
    """ValueError naming a controller that cannot be told a target cycle time (its reset takes no
    target_time; a wrapper's reset checks what it wraps)."""
    if not takes_argument(getattr(controller, "reset", None), "target_time"):
        raise ValueError(f"{type(controller).__name__}.reset takes no target_time: it cannot be given a target "
                         "cycle time (a target needs a controller conditioned on it, e.g. the MPC)")


def reset_controller(controller: Any, scenario: Any = None, target_time: float | None = None) -> None:
    """Start a controller's episode: told the scenario if its ``reset`` takes ``scenario``, and the
    target cycle time (s), which its ``reset`` must take as ``target_time`` (ValueError if it does not)."""
    if target_time is not None:
        check_takes_target(controller)
    if not hasattr(controller, "reset"):
        return
    kw: dict[str, Any] = {}
    if scenario is not None and takes_scenario(controller.reset):
        kw["scenario"] = scenario
    if target_time is not None:
        kw["target_time"] = float(target_time)
    controller.reset(**kw)


@dataclass(frozen=True)
class Trajectory:
    """An episode's samples: times (s), states [omega, V, H, V_b] after each step (the start first), the
    applied controls [U_mf, U_ab, U_b] of each step, and the phase after each step (the start first)."""

    t: list[float]
    states: list[list[float]]
    controls: list[list[float]]
    phase: list[int]


@dataclass(frozen=True)
class EpisodeResult:
    """How one episode ended. Errors are signed, in m; ``max_violation`` is the largest relative excess
    over the driver's limits (0.01 = 1 % over); ``T`` is the cycle time if it completed, else the time
    it ran."""

    seed: int | None
    T: float
    fuel_g: float
    success: bool
    completed: bool
    truncated: bool
    stalled: bool
    off_site: bool
    episode_return: float
    reversing_error_m: float | None  # None: the reversing point was never reached
    final_position_error_m: float
    final_height_error_m: float
    max_violation: float
    trajectory: Trajectory | None = None

    def to_dict(self, trajectory: bool = True) -> dict[str, Any]:
        d = asdict(self)
        if not trajectory:
            d.pop("trajectory")
        return d


def run_episode(env: Any, controller: Any, seed: int | None = None, trajectory: bool = True,
                scenario: Any = None, target_time: float | None = None) -> EpisodeResult:
    """Roll one episode of ``env`` (a ``WheelLoader`` env) under ``controller`` from ``reset(seed=seed)``
    (of ``scenario``, if given: then a controller whose ``reset`` takes ``scenario`` is told it; the
    start state it reads from the observation), with a ``target_time`` (s) if given: the controller is
    told it (:func:`reset_controller`), and an env with ``observe_target`` (``WheelLoaderTarget-v0``)
    shows it in the observation (a controller that reads it there need not take it)."""
    from wl_env.env import WheelLoaderEnv, check_target_time
    from wl_env.params import check_flag, plain

    # (each refused by name: a NaN or negative target reached the controller, a string was float()'s error)
    if not isinstance(getattr(env, "unwrapped", None), WheelLoaderEnv):
        raise ValueError(f"env must be a single WheelLoader env (gymnasium.make('WheelLoader-v2'), ...), got "
                         f"{type(env).__name__}")
    if not callable(getattr(controller, "act", None)):
        raise ValueError(f"controller must have an act(obs) method, got {type(controller).__name__}")
    if target_time is not None:
        target_time = check_target_time(target_time)
    trajectory = check_flag("trajectory", trajectory)  # ("no" recorded the trajectory)
    seed = plain(seed)  # (a numpy integer as the int it holds: np.int64 was recorded as itself, and to_dict() was no JSON)
    options = {} if scenario is None else {"scenario": scenario}
    observed = getattr(env.unwrapped, "observe_target", False)
    if observed and target_time is not None:  # the target env shows it in the observation
        options["target_time"] = float(target_time)
    obs, info = env.reset(seed=seed, options=options or None)
    told = target_time if not observed or takes_target(controller) else None
    reset_controller(controller, scenario, told)
    unwrapped = env.unwrapped
    ts, states, controls, phases = [0.0], [list(map(float, unwrapped.state))], [], [int(unwrapped.phase)]
    total, term, trunc = 0.0, False, False
    try:
        while not (term or trunc):
            obs, r, term, trunc, info = env.step(controller.act(obs))
            total += float(r)
            if trajectory:
                ts.append(float(info["t"]))
                states.append([float(v) for v in info["state"]])
                controls.append([float(v) for v in info["controls"]])
                phases.append(int(info["phase"]))
    finally:  # a controller with work in the background (the MPC's worker) ends it with the episode
        end = getattr(controller, "end_episode", None)
        if callable(end):
            end()
    rev = info["reversing_error"]
    return EpisodeResult(
        seed=seed, T=float(info["t"]), fuel_g=float(info["fuel_g"]), success=bool(info["is_success"]),
        completed=bool(info["completed"]), truncated=bool(trunc), stalled=bool(info["stalled"]),
        off_site=bool(info["off_site"]), episode_return=total,
        reversing_error_m=None if rev is None or math.isnan(rev) else float(rev),
        final_position_error_m=float(info["s"] - unwrapped.params.final_position), final_height_error_m=float(info["state"][2] - unwrapped.params.H_T),
        max_violation=float(info["violations"]["max_excess"]),
        trajectory=Trajectory(ts, states, controls, phases) if trajectory else None,
    )
