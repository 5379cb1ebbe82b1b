"""The imitation baseline: behaviour cloning of MPC demonstrations on ``train`` scenarios (``scripts/train_bc.py``).

* :func:`collect_demos` - MPC episodes in ``WheelLoaderTarget-v1`` (or v0) on fresh draws of the ``train``
  distribution, each at a target cycle time (a ratio to the scenario's estimated T_min; a share of them
  as fast as possible, the MPC's minimum-time mode, observed at ratio 1), one file per episode, written
  atomically: a killed collection resumes with the episodes it has. Only episodes the expert completes
  with its targets met and no violation are imitated. In v1 the expert's injection is labelled as the
  engine-speed request for which the governor injects it (``CycleStepper.translate_fuel_action``): the
  same cycle, and a label that is the engine speed the expert drives to.
* :func:`clone` - the policy network of a PPO run (same architecture, so PPO can fine-tune it:
  ``PPOConfig.init_policy``) regressed onto the expert's actions, observations normalized by the demos'
  statistics; written as a run's ``final/`` folder (pickle-free policy and summary), so ``wl evaluate
  --model``, :func:`agents.ppo.load_policy` and :func:`agents.ppo.export_policy` take it as they take a
  trained run.

Demonstration files are ``.npz`` read with ``allow_pickle=False``: nothing in them is executed.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import math
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.ppo_config import COAST_ENV_IDS, MAX_RUN_JSON_BYTES, TARGET_ENV_IDS, PPOConfig
from wl_env.atomic_io import read_regular_file, write_atomic
from wl_env.codec import N_TARGET_OBS
from wl_env.params import is_real_number, plain, shown

log = logging.getLogger(__name__)

EXPERTS = ("mpc", "operator")
DEMO_STREAM_SEED = 1_000_000  # train-stream seeds of the demos: apart from training (env rngs) and evaluation (10_000)


@dataclass(frozen=True)
class DemoSettings:
    """What one collection draws: its seed, the target ratios (uniform in ``target``) and the share of
    episodes run as fast as possible (``fast_share``)."""

    braking: str
    seed: int = 0
    target: tuple[float, float] = (1.05, 2.5)
    fast_share: float = 0.2
    expert: str = "mpc"  # "mpc" (the optimum's stand-in), or "operator" (rule-based: quick demonstrations for tests)
    learner: str = ""  # DAgger: a pickle-free policy that drives (the expert only labels its states); '': the expert drives
    beta: float = 0.0  # DAgger: the chance per step that the expert's own action is applied instead
    env_id: str = "WheelLoaderTarget-v1"  # v1: action 0 an engine-speed request (the governor's); v0: the injection

    def __post_init__(self) -> None:
        if isinstance(self.learner, os.PathLike):  # (a path as the text it spells, as the demos' meta records it)
            object.__setattr__(self, "learner", os.fspath(self.learner))
        if not isinstance(self.learner, str):  # (5 or True was a TypeError inside the first episode, naming nothing)
            raise ValueError(f"learner must be '' (the expert drives) or the path of a pickle-free policy, got "
                             f"{shown(self.learner)} ({type(self.learner).__name__})")
        if self.env_id not in TARGET_ENV_IDS[:2] and not (self.env_id in COAST_ENV_IDS and self.learner
                                                           and self.expert == "mpc"):
            # (a driver's actions are not the MPC's controls: the expert drives v0 or v1; in v3 to v6 a DAgger
            # learner drives and the MPC's plans label its states, plan_labels)
            raise ValueError(f"env_id must be one of {', '.join(TARGET_ENV_IDS[:2])} (or {' or '.join(COAST_ENV_IDS)} "
                             f"with a learner and the MPC as the expert: DAgger), got {self.env_id!r}")
        if self.expert not in EXPERTS:
            raise ValueError(f"expert must be one of {', '.join(EXPERTS)}, got {self.expert!r}")
        from wl_env.cycle import check_braking
        from wl_env.env import check_target_ratios

        check_braking(self.braking)
        object.__setattr__(self, "target", check_target_ratios(self.target))
        # (numpy scalars as the numbers they hold: np.int64 seeds were refused; True was a fast_share of 1)
        for name in ("seed", "fast_share", "beta"):
            object.__setattr__(self, name, plain(getattr(self, name)))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {shown(self.seed)}")
        if not (is_real_number(self.fast_share) and 0.0 <= self.fast_share <= 1.0):
            raise ValueError(f"fast_share must lie in [0, 1], got {shown(self.fast_share)}")
        if not (is_real_number(self.beta) and 0.0 <= self.beta <= 1.0):
            raise ValueError(f"beta must lie in [0, 1], got {shown(self.beta)}")


def demo_path(out: str | Path, index: int) -> Path:
    return Path(out) / f"episode_{index:05d}.npz"


def demo_draw(settings: DemoSettings, index: int) -> tuple[np.random.Generator, Any, bool, float]:
    """What episode ``index`` of a collection draws before it runs: (its generator, drawn on later by a DAgger
    learner's episode; the scenario; whether it runs as fast as possible; its target ratio to T_min)."""
    from wl_env.suites import TRAIN_STREAM, draw, stream

    rng = stream(TRAIN_STREAM, DEMO_STREAM_SEED + 10_000 * settings.seed + index)
    scenario = draw(rng, settings.braking)
    fast = bool(rng.uniform() < settings.fast_share)
    ratio = 1.0 if fast else float(rng.uniform(*settings.target))
    return rng, scenario, fast, ratio


def demo_episode(settings: DemoSettings, index: int) -> dict[str, Any]:
    """Episode ``index`` of a collection: its scenario, target, the expert's observations and actions."""
    import gymnasium as gym

    import wl_env  # noqa: F401
    from mpc.controller.mpc import MPCController

    rng, scenario, fast, ratio = demo_draw(settings, index)
    env = gym.make(settings.env_id, braking=settings.braking)
    governed = env.unwrapped.core.fuel_action == "engine_speed"
    obs, info = env.reset(seed=index, options={"scenario": scenario, "target_ratio": ratio})
    target_time = float(info["target_time"])
    if settings.expert == "mpc":
        expert: Any = MPCController(settings.braking)
        expert.reset(scenario=scenario, target_time=None if fast else target_time)  # fast: minimum-time mode
    else:
        from agents.operator import OperatorPolicy

        expert = OperatorPolicy(settings.braking, params=scenario.params())
    learner = None
    if settings.learner:
        from agents.ppo import load_policy

        learner = load_policy(settings.learner)
    if settings.env_id in COAST_ENV_IDS:
        return _driver_dagger_episode(settings, env, expert, learner, rng, obs, scenario, target_time, fast, ratio)
    observations, actions = [], []
    done = False
    core = env.unwrapped
    while not done:
        a = np.asarray(expert.act(obs), dtype=np.float32)  # (an injection action: the experts' own space)
        if governed:
            a[0] = core.core.translate_fuel_action(core.state, core.phase, a, to="engine_speed")
        observations.append(obs)
        actions.append(a)
        if learner is not None and rng.uniform() >= settings.beta:  # the learner drives; the expert labels
            a = np.asarray(learner.act(obs), dtype=np.float32)
            if hasattr(expert, "applied"):  # what was applied, in the expert's space
                injection = a.copy()
                if governed:
                    injection[0] = core.core.translate_fuel_action(core.state, core.phase, a, to="injection")
                expert.applied(injection)
        obs, _, term, trunc, info = env.step(a)
        done = term or trunc
    env.close()
    return {"obs": np.asarray(observations, np.float32), "actions": np.asarray(actions, np.float32),
            **_episode_record(settings, info, scenario, target_time, fast, ratio)}


def _episode_record(settings: DemoSettings, info: dict[str, Any], scenario: Any, target_time: float,
                    fast: bool, ratio: float) -> dict[str, Any]:
    """What a demonstration file records of its episode besides its steps: the draw (and the settings that drew it,
    checked when a collection resumes: :func:`check_drawn`) and the outcome."""
    return {"scenario": scenario.to_dict(), "target_time": target_time, "fast": fast, "T": float(info["t"]),
            "fuel_g": float(info["fuel_g"]), "success": bool(info["is_success"]),
            "lateness": float(info["lateness"]), "max_violation": float(info["violations"]["max_excess"]),
            "learner": settings.learner, "env_id": settings.env_id, "target_ratio": ratio, "expert": settings.expert,
            "beta": float(settings.beta)}


def _driver_dagger_episode(settings: DemoSettings, env: Any, expert: Any, learner: Any, rng: np.random.Generator,
                           obs: np.ndarray, scenario: Any, target_time: float, fast: bool,
                           ratio: float) -> dict[str, Any]:
    """A DAgger episode of a WheelLoaderTarget-v3 driver: the learner drives (the label's action with
    probability ``beta``), the MPC plans from every state it visits and its plan labels it
    (:func:`plan_labels`); the MPC is told what the assist applied. Stored with its labels and weights."""
    core = env.unwrapped
    p, dt = core.params, core.core.dt
    observations, labelled, weights = [], [], []
    done = False
    while not done:
        a = np.asarray(expert.act(obs), dtype=np.float32)
        request = core.core.translate_fuel_action(core.state, core.phase, a, to="engine_speed")
        label, weight = plan_labels(expert.planned_steps(), int(core.phase), float(request), float(a[1]), p,
                                    settings.braking, dt)
        observations.append(obs)
        labelled.append(label)
        weights.append(weight)
        drive = label if rng.uniform() < settings.beta else np.asarray(learner.act(obs), dtype=np.float32)
        phase = int(core.phase)
        obs, _, term, trunc, info = env.step(drive)
        shift = phase in (1, 3) and int(info["phase"]) > phase
        expert.applied(expert.action(np.asarray(info["controls"], dtype=float), shift))
        done = term or trunc
    env.close()
    return {"obs": np.asarray(observations, np.float32), "actions": np.asarray(labelled, np.float32),
            "weights": np.asarray(weights, np.float32),
            **_episode_record(settings, info, scenario, target_time, fast, ratio)}


def plan_labels(plan: dict[str, np.ndarray] | None, phase: int, request: float, bucket: float, p: Any, braking: str,
                dt: float) -> tuple[np.ndarray, np.ndarray]:
    """WheelLoaderTarget-v3's driver action at a state the MPC planned from, and its weights: the request
    and bucket are the MPC's (``request`` its injection as the governor's request), the braking and coasting
    fractions those at which the assist would brake and end the leg where the plan does (as
    :func:`driver_labels` reads them off the expert's own cycle): the coasting fraction from the plan's
    shift, the braking fraction from its service brakes' onset (with TC braking in phase 1: from its shift).
    Weight 0 where an action does nothing (as :func:`driver_labels`) or the plan does not say (no plan,
    or its event already behind)."""
    from wl_env.assist import COAST_FRACTION, coasting_legs, fraction_action
    from wl_env.codec import Codec

    label = np.array([request, bucket, 1.0, 1.0], dtype=np.float32)
    weight = np.array([1.0, 1.0, 0.0, 0.0], dtype=np.float32)
    leg = phase if phase in (1, 3) else phase - 1
    legs = coasting_legs(braking)
    if braking == "tc" and phase == 2:
        weight[0] = 0.0  # (the assist meters the converter there)
    if plan is None or phase == 2 and braking == "tc":
        return label, weight
    phases, states, codec = np.asarray(plan["phase"]), np.asarray(plan["states"]), Codec(p)

    def fraction_at(j: int, bounds: tuple[float, float] | None = None) -> float:
        speed, to_go = abs(float(states[j][1])), float(codec.distance_to_go(states[j][4], leg))
        return float(fraction_action(speed, to_go, p, dt, *(() if bounds is None else (bounds,))))

    shift = np.flatnonzero(phases > leg)
    if leg in legs:
        onset = np.flatnonzero((phases == leg + 1) & (np.asarray(plan["controls"])[:, 2] > 0.0))
        if onset.size:
            label[2], weight[2] = fraction_at(int(onset[0])), 1.0
        if phase == leg and shift.size:
            label[3], weight[3] = fraction_at(int(shift[0]), COAST_FRACTION), 1.0
    elif phase == leg and shift.size:  # (the braking fraction sets where the leg ends)
        label[2], weight[2] = fraction_at(int(shift[0])), 1.0
    return label, weight


def _write_demo(path: Path, demo: dict[str, Any]) -> None:
    buf = io.BytesIO()
    arrays = {k: demo[k] for k in ("obs", "actions", "weights") if k in demo}
    meta = {k: v for k, v in demo.items() if k not in arrays}
    np.savez(buf, **arrays, meta=np.array(json.dumps(meta)))
    write_atomic(path, buf.getvalue())


# a demonstration's meta fields the readers use, by type (bool before int: isinstance(True, int))
_DEMO_META: dict[str, type | tuple[type, ...]] = {
    "env_id": str, "success": bool, "learner": (str, type(None)), "fast": bool, "max_violation": (int, float), "T": (int, float),
    "target_time": (int, float), "fuel_g": (int, float), "scenario": dict, "target_ratio": (int, float), "expert": str,
    "beta": (int, float)}


def read_demo(path: str | Path) -> dict[str, Any]:
    """One demonstration file, checked (ValueError naming the file if it is not one)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            obs, actions, meta = f["obs"], f["actions"], json.loads(str(f["meta"]))
            extra = {"weights": f["weights"]} if "weights" in f.files else {}
    except (OSError, ValueError, KeyError, json.JSONDecodeError, RecursionError, EOFError, zipfile.BadZipFile,
            MemoryError) as exc:
        # (a truncated file: BadZipFile; an empty one: EOFError, neither an OSError; an .npy header that claims 2^45
        # values: numpy's MemoryError, a traceback)
        raise ValueError(f"{path} is not a demonstration file: {exc}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: its meta must be a JSON object, got {type(meta).__name__}")
    absent = [k for k in ("env_id", "success", "max_violation", "scenario") if k not in meta]
    if absent:
        raise ValueError(f"{path}: its meta has no field {absent[0]!r}")
    bad = [k for k, kind in _DEMO_META.items() if k in meta and not isinstance(meta[k], kind)]
    if bad or set(meta) & {"obs", "actions", "weights"}:
        raise ValueError(f"{path}: its meta field {(bad or sorted(set(meta) & {'obs', 'actions', 'weights'}))[0]!r} "
                         f"is {'of the wrong type' if bad else 'an array name'}")
    if any(a.dtype.kind != "f" for a in (obs, actions, *extra.values())):
        raise ValueError(f"{path}: obs, actions and weights must be float arrays, got {obs.dtype} and {actions.dtype}")
    if obs.ndim != 2 or obs.shape[1] != N_TARGET_OBS or len(obs) == 0 or actions.shape != (len(obs), 4) or not (
            np.isfinite(obs).all() and np.isfinite(actions).all()):
        raise ValueError(f"{path}: expected finite obs (n, {N_TARGET_OBS}) and actions (n, 4), "
                         f"got {obs.shape} and {actions.shape}")
    if extra and (extra["weights"].shape != actions.shape or not np.isfinite(extra["weights"]).all()
                  or (extra["weights"] < 0).any()):  # (a negative weight turns the fit's loss into one it maximizes)
        raise ValueError(f"{path}: expected finite weights >= 0 {actions.shape}, got {extra['weights'].shape}")
    from wl_env.scenario import Scenario

    try:  # (the assisted drivers' labels read it: a bad one failed there with a KeyError, naming no file)
        Scenario.from_dict(meta["scenario"])
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: its meta field 'scenario' is not a scenario ({exc})") from None
    return {"obs": obs, "actions": actions, **meta, **extra}


def collect_chunk(settings: dict[str, Any], indices: list[int], out: str) -> list[int]:
    """Episodes ``indices`` into ``out`` (skipping those on disk); a worker's job. Returns those it ran."""
    s = DemoSettings(**{**settings, "target": tuple(settings["target"])})
    ran = []
    for i in indices:
        path = demo_path(out, i)
        if path.exists():
            continue
        t0 = time.perf_counter()
        demo = demo_episode(s, i)
        _write_demo(path, demo)
        ran.append(i)
        log.info("demo %d: T %.1f s (target %.1f s%s), %.1f g, success %s, %.0f s", i, demo["T"], demo["target_time"],
                 ", fastest" if demo["fast"] else "", demo["fuel_g"], demo["success"], time.perf_counter() - t0)
    return ran


def collect_demos(settings: DemoSettings, episodes: int, out: str | Path, workers: int = 1) -> list[dict[str, Any]]:
    """``episodes`` demonstrations into the folder ``out`` (resumed: episodes on disk are kept), in
    ``workers`` processes; all of them, read back."""
    episodes = plain(episodes)  # (a numpy integer as the int it holds, as evaluate_controller takes it)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {shown(episodes)}")
    from mpc.workers import check_workers

    workers = check_workers(workers)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    d = dataclasses.asdict(settings)  # plain data for the workers
    todo = [i for i in range(episodes) if not demo_path(out, i).exists()]
    if workers == 1 or len(todo) <= 1:
        collect_chunk(d, todo, str(out))
    else:
        from mpc.workers import run_in_workers

        run_in_workers({f"demos{w}": ("agents.imitation:collect_chunk", (d, todo[w::workers], str(out)))
                        for w in range(min(workers, len(todo)))}, log_level=logging.INFO)
    demos = [read_demo(demo_path(out, i)) for i in range(episodes)]
    for i, d in enumerate(demos):  # a folder resumed with other settings' episodes would mix two action spaces
        if d.get("env_id", TARGET_ENV_IDS[0]) != settings.env_id:
            raise ValueError(f"{demo_path(out, i)} is a {d.get('env_id', TARGET_ENV_IDS[0])} episode; this collection "
                             f"is of {settings.env_id} (use another folder)")
        check_drawn(demo_path(out, i), d, settings, i)
    return demos


def check_drawn(path: str | Path, demo: dict[str, Any], settings: DemoSettings, index: int) -> None:
    """ValueError naming ``path`` unless the episode on disk is episode ``index`` of ``settings``' collection: its
    scenario, speed and target as they draw it, its expert, learner and beta. (A folder resumed with another braking,
    seed, --target or --fast-share was taken as it was: a TC clone was fitted to service cycles, and the policy's
    metadata named the settings given, not those of its demonstrations.) Files written before the target ratio
    and the expert were recorded are checked on their scenario and speed."""
    from wl_env.scenario import Scenario

    _, scenario, fast, ratio = demo_draw(settings, index)
    differ = []
    if Scenario.from_dict(demo["scenario"]).to_dict() != scenario.to_dict():
        differ.append("its scenario (braking, seed)")
    if demo.get("fast", fast) != fast:
        differ.append("its speed (fast_share)")
    if demo.get("target_ratio", ratio) != ratio:
        differ.append("its target (target)")
    for name in ("expert", "beta"):
        if demo.get(name, getattr(settings, name)) != getattr(settings, name):
            differ.append(name)
    if bool(demo.get("learner")) != bool(settings.learner):
        differ.append("learner")
    if differ:
        raise ValueError(f"{path} is an episode of another collection ({', '.join(differ)} differ from this one's "
                         f"settings): use another folder, or the settings it was collected with")


def usable(demo: dict[str, Any]) -> bool:
    """An episode worth imitating: the expert's own, completed with its targets met and no violation; or a
    DAgger episode (the learner drove: its outcome is the learner's, the labels the expert's)."""
    return bool(demo.get("learner")) or (bool(demo["success"]) and demo["max_violation"] == 0.0)


SHIFT = 3  # the shift request's action index: > 0 ends phase 1 or 3
COAST = 3  # WheelLoaderTarget-v3's to v6's coasting fraction's action index
# The assisted drivers (WheelLoaderTarget-v2 to v6) are cloned from WheelLoaderTarget-v1 episodes: the expert drives
# its own machine (injection, brake, shift) and its actions are labelled as the driver's (driver_labels).
DRIVER_ENV_IDS = TARGET_ENV_IDS[2:]
DEMO_ENV_ID = {**{e: e for e in TARGET_ENV_IDS[:2]}, **dict.fromkeys(DRIVER_ENV_IDS, TARGET_ENV_IDS[1])}
METHOD = "behaviour cloning (MPC)"  # the method a clone's metadata names
SHIFT_RAMP = 0.4  # per step: the shift label's slope before the expert's shift (see shift_labels)


def _phases(obs: np.ndarray) -> np.ndarray:
    from wl_env.codec import Codec

    return np.asarray(Codec().decode_observation(obs).phase)


def shift_steps(phase: np.ndarray, actions: np.ndarray) -> dict[int, int]:
    """Where the expert ended each leg: the first step of phase 1 and of phase 3 with the shift asked (> 0);
    a leg it did not end (an episode cut short) is left out."""
    out = {}
    for leg in (1, 3):
        steps = np.flatnonzero(phase == leg)
        shifted = steps[actions[steps, SHIFT] > 0.0]
        if shifted.size:
            out[leg] = int(shifted[0])
    return out


def shift_labels(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """One episode's actions with the shift request relabelled as a ramp to the expert's shift. The expert
    asks for it once per phase (+1 once, -1 before): a regression of that pulse predicts "hold" everywhere
    (or, weighted up, "shift" too early). The ramp, ``SHIFT_RAMP`` per step, crosses 0 half a step before
    the expert's shift, so the clone's threshold (> 0) shifts where the expert did."""
    out = actions.copy()
    phase = _phases(obs)
    for leg, k in shift_steps(phase, actions).items():
        steps = np.flatnonzero(phase == leg)
        out[steps, SHIFT] = np.clip(SHIFT_RAMP * (steps - k + 0.5), -1.0, 1.0)
    return out


def driver_labels(obs: np.ndarray, actions: np.ndarray, scenario: dict[str, Any], braking: str, coast: bool = False,
                  dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A WheelLoaderTarget-v1 expert episode as the assisted driver's actions (WheelLoaderTarget-v2; with
    ``coast`` v3's), with per-sample weights. The engine-speed request and the bucket are the expert's own.
    The braking fraction (:func:`wl_env.assist.fraction_action`, held over each leg and its braking) is the
    one at which the assist brakes where the expert did: in v2 it ends the leg where the expert shifted; in
    v3 it starts the service brakes where the expert's did, and the coasting fraction is the one whose
    braking point is the expert's shift. Weight 0 where an action does nothing: the fractions outside the
    legs they act in (the coasting fraction: in phase 3, and phase 1 with service braking), and with TC
    braking the request in phase 2 (the assist meters the converter there). ``dt``: the episode's control
    interval in s."""
    from wl_env.assist import COAST_FRACTION, coasting_legs, fraction_action
    from wl_env.codec import Codec
    from wl_env.scenario import Scenario

    p = Scenario.from_dict(scenario).params()
    o = Codec(p, observe_scenario=True).decode_observation(obs)
    phase, speed, to_go = np.asarray(o.phase), np.abs(np.asarray(o.vehicle_speed)), np.asarray(o.distance_to_go)
    shifts = shift_steps(phase, actions)
    legs = coasting_legs(braking)  # (v3: where the service brakes end a leg, and a leg may end early)
    fraction = np.zeros(len(obs), dtype=np.float32)
    weights = np.ones((len(obs), 4 if coast else 3), dtype=np.float32)
    for leg in (1, 3):
        in_leg = (phase == leg) | (phase == leg + 1)
        k = shifts.get(leg)  # the expert's shift
        if coast and leg in legs:  # the service brakes' onset (brake action > -1)
            braking_steps = np.flatnonzero(phase == leg + 1)
            onset = braking_steps[actions[braking_steps, 2] > -1.0]
            k = int(onset[0]) if onset.size else None
        if k is not None:
            fraction[in_leg] = fraction_action(speed[k], to_go[k], p, dt)
        else:  # (an episode cut short, or braking that never started: nothing to label)
            weights[in_leg, 2] = 0.0
    if not coast:  # (v3's braking fraction also sets where the brakes start in phases 2 and 4)
        weights[~np.isin(phase, (1, 3)), 2] = 0.0
    if braking == "tc":
        weights[phase == 2, 0] = 0.0
        if coast:
            weights[phase == 2, 2] = 0.0
    columns = [actions[:, 0], actions[:, 1], fraction]
    if coast:  # the coasting fraction whose braking point is the expert's shift, held over the leg
        coasting = np.ones(len(obs), dtype=np.float32)
        for leg, k in shifts.items():
            if leg in legs:
                coasting[(phase == leg) | (phase == leg + 1)] = fraction_action(speed[k], to_go[k], p, dt, COAST_FRACTION)
        columns.append(coasting)
        weights[~np.isin(phase, legs), COAST] = 0.0  # (where it can end a leg)
    return np.column_stack(columns).astype(np.float32), weights


def labels(demo: dict[str, Any], env_id: str, braking: str) -> tuple[np.ndarray, np.ndarray]:
    """One episode's regression targets in ``env_id``'s action space and their per-sample weights."""
    if "weights" in demo:  # (labelled when collected: a driver's DAgger episode, plan_labels)
        return demo["actions"], demo["weights"]
    if env_id in DRIVER_ENV_IDS:
        return driver_labels(demo["obs"], demo["actions"], demo["scenario"], braking, coast=env_id in COAST_ENV_IDS)
    actions = np.clip(shift_labels(demo["obs"], demo["actions"]), -1.0, 1.0)
    return actions, action_weights(demo["obs"], actions)


def action_weights(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """Per-sample weights of the squared action errors: 1, but 0 for the shift request outside phases 1 and
    3, where it does nothing."""
    weights = np.ones_like(actions, dtype=np.float32)
    weights[~np.isin(_phases(obs), (1, 3)), SHIFT] = 0.0
    return weights


def check_demo_env(demos: list[dict[str, Any]], env_id: str) -> None:
    """ValueError unless every episode of ``demos`` is of the env whose labels ``env_id`` takes."""
    # (demos before v1 carry no env_id: v0's; an episode labelled when collected is of the env it labels)
    envs = {d.get("env_id", TARGET_ENV_IDS[0]) for d in demos if "weights" not in d}
    labelled = {d["env_id"] for d in demos if "weights" in d}
    if envs != {DEMO_ENV_ID[env_id]} or not labelled <= {env_id}:
        raise ValueError(f"the demonstrations are {', '.join(sorted(envs | labelled))} episodes; {env_id} needs "
                         f"{DEMO_ENV_ID[env_id]} episodes" + (" (and its own DAgger episodes)" if labelled else ""))


def demo_samples(demos: list[dict[str, Any]], env_id: str, braking: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The raw observations, the ``env_id`` action labels and their weights of ``demos``' steps, stacked."""
    labelled = [labels(d, env_id, braking) for d in demos]
    return (np.concatenate([d["obs"] for d in demos]), np.concatenate([a for a, _ in labelled]),
            np.concatenate([w for _, w in labelled]))


def demo_paths(folder: str | Path, what: str = "bc_demos") -> list[Path]:
    """The episode files of a demonstration folder, sorted; ValueError starting with ``what`` (the option or the
    field that gave ``folder``) if there are none or the path cannot be used."""
    try:
        paths = sorted(Path(folder).glob("episode_*.npz"))
    except OSError as exc:  # (a name too long for the system: "[Errno 36] File name too long", naming no option)
        raise ValueError(f"{what} {folder}: cannot use the path ({exc.strerror or exc})") from None
    if not paths:
        raise ValueError(f"{what} {folder}: no demonstration episodes (episode_*.npz) in it")
    return paths


def read_demo_folder(folder: str | Path, env_id: str) -> list[dict[str, Any]]:
    """The usable episodes of a demonstration folder (:func:`collect_demos`' layout) for ``env_id``'s labels;
    ValueError if there are none or they are another env's."""
    demos = [read_demo(p) for p in demo_paths(folder)]
    check_demo_env(demos, env_id)
    good = [d for d in demos if usable(d)]
    if not good:
        raise ValueError(f"bc_demos {folder}: none of its {len(demos)} episodes is usable (targets met, no violation)")
    return good


@dataclass
class CloneResult:
    """What :func:`clone` did: the demos used, the fit, and where the policy is."""

    episodes: int  # usable demonstration episodes
    episodes_dropped: int  # expert episodes not imitated (targets missed or a violation)
    samples: int
    train_loss: float  # weighted mean squared error of the actions in [-1, 1] (shift_labels, action_weights), training episodes
    validation_loss: float  # the same on the held-out episodes
    wall_time_s: float
    policy: str  # the stem of the pickle-free policy


def clone(demos: list[dict[str, Any]], cfg: PPOConfig, epochs: int = 200, learning_rate: float = 1e-3,
          batch_size: int = 1024, validation_share: float = 0.1, extra: dict[str, Any] | None = None,
          base: str | Path | None = None) -> CloneResult:
    """Regress the mean action of ``cfg``'s PPO policy network onto the demos' actions; the policy is saved
    as ``cfg.run_dir/final/`` (the layout of a trained run), with ``extra`` in its metadata (e.g. the
    command). Episodes are split, not samples: the validation loss is measured on whole held-out cycles.

    ``base``: a trained pickle-free policy of ``cfg``'s env and braking, whose network (actor and critic) and
    observation statistics the clone starts from (else: a fresh network, the demos' statistics). Only the
    actor is regressed: PPO fine-tuning from the clone then starts with a critic trained on the task (a fresh
    critic's first advantages are noise, and with them the first updates of the cloned actor)."""
    import torch as th

    from agents.policy_files import ObsNormalization
    from agents.ppo import build_model, make_env

    check_demo_env(demos, cfg.env_id)
    check_run_folder(cfg)
    if not cfg.norm_obs:
        raise ValueError("behaviour cloning normalizes the observations by the demos' statistics: norm_obs must be true")
    good = [d for d in demos if usable(d)]
    if len(good) < 2:
        raise ValueError(f"{len(good)} usable demonstration episodes (of {len(demos)}): need at least 2")
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    order = rng.permutation(len(good))
    n_val = max(1, int(round(validation_share * len(good))))
    parts = {"val": [good[i] for i in order[:n_val]], "train": [good[i] for i in order[n_val:]]}
    samples = {k: demo_samples(v, cfg.env_id, cfg.braking) for k, v in parts.items()}
    obs, act = {k: v[0] for k, v in samples.items()}, {k: v[1] for k, v in samples.items()}
    norm = ObsNormalization(obs["train"].mean(0).astype(np.float64), obs["train"].var(0).astype(np.float64))

    network = None
    if base is not None:  # (read before the env is made: a bad base leaves nothing open)
        network, norm, _ = read_base(base, cfg, cfg.env_id)

    th.manual_seed(cfg.seed)
    th.set_num_threads(max(1, cfg.torch_threads))
    env = make_env(cfg, num_envs=1)
    model = build_model(cfg, env, cfg.run_dir / "tb")
    policy = model.policy
    if network is not None:
        try:
            _start_from(policy, network, base, cfg)
        except ValueError:
            env.close()
            raise
    x = {k: th.as_tensor(norm.apply(v)) for k, v in obs.items()}
    y = {k: th.as_tensor(v) for k, v in act.items()}
    w = {k: th.as_tensor(v[2]) for k, v in samples.items()}
    params = list(policy.mlp_extractor.policy_net.parameters()) + list(policy.action_net.parameters())
    optimizer = th.optim.Adam(params, lr=learning_rate)

    def mean_action(z: th.Tensor) -> th.Tensor:
        latent_pi, _ = policy.mlp_extractor(policy.extract_features(z, policy.pi_features_extractor))
        return policy.action_net(latent_pi)

    def loss_of(part: str, b: Any = slice(None)) -> th.Tensor:
        return th.mean(w[part][b] * (mean_action(x[part][b]) - y[part][b]) ** 2)

    n = len(x["train"])
    for epoch in range(epochs):
        perm = th.randperm(n)
        for i in range(0, n, batch_size):
            b = perm[i:i + batch_size]
            loss = loss_of("train", b)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        if epoch % 50 == 0 or epoch == epochs - 1:
            with th.no_grad():
                val = float(loss_of("val"))
            log.info("[bc] epoch %d: train loss %.5f, validation loss %.5f", epoch, float(loss.detach()), val)
    with th.no_grad():
        train_loss, val_loss = float(loss_of("train")), float(loss_of("val"))
    if not (math.isfinite(train_loss) and math.isfinite(val_loss)):
        env.close()
        raise ValueError(f"behaviour cloning diverged: train loss {train_loss}, validation loss {val_loss}; nothing saved")
    wall = time.perf_counter() - t0
    result = CloneResult(episodes=len(good), episodes_dropped=len(demos) - len(good), samples=n + len(x["val"]),
                         train_loss=train_loss, validation_loss=val_loss, wall_time_s=wall,
                         policy=str(cfg.run_dir / "final" / "policy"))
    _save_run(model, env, norm, float(n), cfg, {"method": METHOD, "clone": result.__dict__, "epochs": epochs,
                                                "learning_rate": learning_rate, "batch_size": batch_size,
                                                **({"base": str(base)} if base is not None else {}), **(extra or {})})
    return result


def check_run_folder(cfg: PPOConfig) -> None:
    """ValueError naming ``cfg.run_dir`` unless it is new or holds a clone or graft (which a rerun fits again): the
    clone's ``final/`` and ``config.json`` replaced a PPO run's of the same name (``train_bc.py --run-name``)."""
    run_dir = cfg.run_dir
    checkpoints, summary = run_dir / "checkpoints", run_dir / "final" / "summary.json"
    method = None
    if summary.is_file():
        try:  # (a regular file, bounded: a huge one was read whole)
            raw = read_regular_file(summary, MAX_RUN_JSON_BYTES, "a run summary holds")
        except FileNotFoundError:  # (gone since)
            raw = b""
        except ValueError as exc:
            raise ValueError(f"{summary} is {exc}: cannot tell whether {run_dir} holds a clone; give another "
                             f"--run-name or --log-dir") from None
        try:
            method = json.loads(raw).get("method")
        except (ValueError, AttributeError, RecursionError):
            pass
    if (checkpoints.is_dir() and any(checkpoints.iterdir())) or ((run_dir / "final").exists()
                                                                 and method not in (METHOD, GRAFT_METHOD)):
        raise ValueError(f"{run_dir} holds a training run, not a clone: its policy would be replaced; give another "
                         f"--run-name or --log-dir")


def _start_from(policy: Any, network: Any, base: str | Path, cfg: PPOConfig, one_more_action: bool = False) -> None:
    """``policy`` (a fresh ``cfg`` network) loaded with the trained ``network``'s weights, actor and critic; with
    ``one_more_action`` the action head has a row more than the base's, left as it is (the graft fits it)."""
    state = policy.state_dict()
    for k, v in network.state_dict().items():
        if k not in state:
            raise ValueError(f"base {base}: tensor {k} has no place in a {cfg.env_id} network of net_arch {list(cfg.net_arch)}")
        if state[k].shape == v.shape:
            state[k] = v.clone()
        elif (one_more_action and k in ("action_net.weight", "action_net.bias", "log_std")
              and state[k].shape[0] == v.shape[0] + 1):
            state[k][:v.shape[0]] = v
        else:
            raise ValueError(f"base {base}: {k} has shape {tuple(v.shape)}, the {cfg.env_id} network "
                             f"{tuple(state[k].shape)} (net_arch {list(cfg.net_arch)})")
    policy.load_state_dict(state)


def read_base(base: str | Path, cfg: PPOConfig, env_id: str) -> tuple[Any, Any, dict[str, Any]]:
    """A trained pickle-free policy of ``env_id`` with its observation statistics, for ``cfg``'s braking."""
    from agents.policy_files import read_policy

    network, norm, meta = read_policy(base)
    if meta.get("config", {}).get("env_id") != env_id or norm is None:
        raise ValueError(f"base {base} must be a {env_id} policy with its normalization, "
                         f"got env_id {meta.get('config', {}).get('env_id')!r}")
    if meta.get("braking", cfg.braking) != cfg.braking:
        raise ValueError(f"base {base} drives {meta['braking']} braking; the config's is {cfg.braking}")
    return network, norm, meta


def _save_run(model: Any, env: Any, norm: Any, count: float, cfg: PPOConfig, meta: dict[str, Any]) -> None:
    """A fitted (not trained) policy as the run ``cfg.run_dir``'s ``final/`` (PPO's layout, pickle-free policy
    too), its observation statistics ``norm`` in the env's VecNormalize so PPO fine-tuning starts from them."""
    from agents.ppo import save_model_files, write_json_atomic

    env.obs_rms.mean, env.obs_rms.var, env.obs_rms.count = norm.mean.copy(), norm.var.copy(), count
    meta = {"num_timesteps": 0, "wall_time": meta.get("clone", {}).get("wall_time_s", 0.0), "braking": cfg.braking,
            "seed": cfg.seed, "config": cfg.to_dict(), "commands": [], "last_eval": None,
            "stopped_by_time_limit": False, **meta}
    cfg.run_dir.mkdir(parents=True, exist_ok=True)
    # (summary.json staged with the folder: written after it, a kill between left a final/ without it, which a rerun
    # takes for a training run's and refuses: check_run_folder)
    save_model_files(model, env, cfg.run_dir / "final", meta, export=True, summary=True)
    write_json_atomic(cfg.run_dir / "config.json", {"config": cfg.to_dict(), "commands": meta["commands"]})
    env.close()


GRAFT_METHOD = "PPO (WheelLoaderTarget-v2) with the coasting fraction cloned from the MPC"
COAST_RIDGE = 1e-3  # the least-squares fit's ridge on the 64 features (they are tanh outputs, O(1))


@dataclass
class GraftResult:
    """What :func:`graft_early_shift` fitted: the coasting head's weighted squared error against the best constant's."""

    episodes: int
    samples: int  # the samples the coasting fraction acts in (weight 1)
    loss: float  # weighted mean squared error of the coasting-fraction label (an action in [-1, 1])
    constant_loss: float  # the same for the best constant prediction
    policy: str


def graft_early_shift(base: str | Path, demos: list[dict[str, Any]], cfg: PPOConfig,
                      extra: dict[str, Any] | None = None) -> GraftResult:
    """A WheelLoaderTarget-v3 policy from a trained v2 one (``base``, pickle-free): v2's network, value net
    and observation statistics as they are, and a fourth action, the coasting fraction, fitted to the MPC's
    shifts in ``demos`` (:func:`driver_labels`) by least squares on the v2 actor's last hidden layer; PPO
    fine-tuning (``init_policy``) then learns when to coast. Saved as ``cfg.run_dir/final/`` like :func:`clone`."""
    import torch as th

    from agents.ppo import build_model, make_env

    if cfg.env_id != DRIVER_ENV_IDS[1]:
        raise ValueError(f"graft_early_shift makes a {DRIVER_ENV_IDS[1]} policy; the config's env is {cfg.env_id}")
    check_run_folder(cfg)
    network, norm, meta = read_base(base, cfg, DRIVER_ENV_IDS[0])
    good = [d for d in demos if usable(d) and d.get("env_id") == DEMO_ENV_ID[cfg.env_id]]
    if len(good) < 2:
        raise ValueError(f"{len(good)} usable {DEMO_ENV_ID[cfg.env_id]} demonstration episodes (of {len(demos)}): need at least 2")
    th.manual_seed(cfg.seed)
    env = make_env(cfg, num_envs=1)
    model = build_model(cfg, env, cfg.run_dir / "tb")
    policy = model.policy
    _start_from(policy, network, base, cfg, one_more_action=True)  # (v2's three actions; the fourth fitted below)
    labelled = [driver_labels(d["obs"], d["actions"], d["scenario"], cfg.braking, coast=True) for d in good]
    obs = np.concatenate([d["obs"] for d in good])
    y = np.concatenate([a[:, COAST] for a, _ in labelled]).astype(np.float64)
    w = np.concatenate([wt[:, COAST] for _, wt in labelled]).astype(np.float64)
    with th.no_grad():
        z = th.as_tensor(norm.apply(obs), dtype=th.float32)
        features = policy.mlp_extractor.forward_actor(policy.extract_features(z, policy.pi_features_extractor))
    X = np.column_stack([features.numpy().astype(np.float64), np.ones(len(obs))])
    sw = np.sqrt(w)[:, None]
    coef = np.linalg.solve((X * sw).T @ (X * sw) + COAST_RIDGE * np.eye(X.shape[1]), (X * sw).T @ (y * sw[:, 0]))
    with th.no_grad():
        policy.action_net.weight[COAST] = th.as_tensor(coef[:-1], dtype=th.float32)
        policy.action_net.bias[COAST] = float(coef[-1])
    mean_y = float(np.sum(w * y) / np.sum(w))
    result = GraftResult(episodes=len(good), samples=int(np.sum(w > 0)),
                         loss=float(np.sum(w * (X @ coef - y) ** 2) / np.sum(w)),
                         constant_loss=float(np.sum(w * (y - mean_y) ** 2) / np.sum(w)),
                         policy=str(cfg.run_dir / "final" / "policy"))
    _save_run(model, env, norm, 1e6, cfg, {"method": GRAFT_METHOD, "base": str(base), "graft": result.__dict__,
                                           **(extra or {})})
    return result
