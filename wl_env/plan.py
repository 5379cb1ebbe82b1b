"""``WheelLoaderPlan-v1`` (and ``-v0``): the target task with one decision per cycle, a phase-parametric plan.

The per-step learners (WheelLoaderTarget-v0..v6) cruise in gear and lift all the way, where the optimum
pulses and glides: a short hard acceleration with the bucket held, the shift to neutral early, a long roll
with the engine at idle while the bucket rises, and a late hard stop (docs/benchmarks.md section 7). No
per-step learner found that shape in 12-24 M steps. Here it is the driver's structure, and what is learned
is its numbers: at the cycle's start the agent sees WheelLoaderTarget-v6's observation (the start state,
the scenario and the target) and picks 14 numbers; the plan driver (:func:`plan_action`) then drives the
whole cycle on v6's dynamics and assist, one v6 action per 0.1 s, reading only v6's observations. v1 drives
it on v7 (v6 with the braking on the step grid); the tables below hold for both.

## Action Space

``Box(-1, 1, (14,), float32)``: seven numbers per leg, the reversing leg (phases 1-2) then the forward leg
(phases 3-4); each is passed to v6 as it is, or mapped affinely:

| Num (reverse, forward) | In the leg's driving phase (1, 3) or its stop (2, 4) | -1 | +1 |
|---|---|---|---|
| 0, 7  | engine-speed request while driving (v6's action 0) | omega_min + 5 rad/s | omega_max |
| 1, 8  | coasting fraction (v6's action 3: where the leg ends to coast) | 15 % | 95 % of the limit |
| 2, 9  | braking fraction (v6's action 2) | 50 % | 95 % of the limit |
| 3, 10 | the bucket is held still (U_ab = -V_b / dt) until this time into the driving phase | 0 s | 4 s |
| 4, 11 | bucket acceleration asked after that (v6's action 1) | -2.5 m/s^2 | +2.5 m/s^2 |
| 5, 12 | engine-speed request while stopping (phase 2, 4) | omega_min + 5 rad/s | omega_max |
| 6, 13 | bucket acceleration asked while stopping | -2.5 m/s^2 | +2.5 m/s^2 |

v6's assist ends the legs, stops the machine on the marks, stops the bucket at the dump height and keeps
its guards, as under any v6 driver.

## Observation Space

WheelLoaderTarget-v6's at the cycle's start, ``Box((21,), float32)`` (see ``WheelLoaderEnv``): the start
state, the scenario's features and the target.

## Rewards

The v6 episode's return: the sum of its step rewards (fuel, the target and violation terms, the
lateness charge).

## Episode End

One step: the cycle driven to v6's end (completed, failed, or truncated at ``max_time``). ``info`` is v6's
at its last step, ``info["steps"]`` the number of v6 steps.

## Version History

* v1: the same plan on WheelLoaderTarget-v7, whose assist brakes on the step grid (the first braking step takes up
  what the grid leaves over, the rest at the plan's braking fraction). CMA-ES searches of the 14 numbers on `test`
  cycles 0-3 (service; ``scripts/bench_plan_ceiling.py``, stop 62) found plans 11.5-21.7 % over the optimum's fuel at
  T_min (v0: 20.7-24.0 %) at 1.3-2.3 % lateness, 5.1-6.7 % at 1.15 T_min (v0: 5.8-8.1 %), 3.5-5.2 % at 1.5 T_min
  (v0: 4.2-8.2 %).
* v0: the 14 numbers above on WheelLoaderTarget-v6.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from wl_env.codec import N_SCENARIO_OBS, Codec
from wl_env.env import WheelLoaderEnv, action_array
from wl_env.episode import check_control_interval
from wl_env.params import LoaderParams
from wl_env.vector_env import WheelLoaderVectorEnv

# the per-step env each plan version drives its cycle on (WheelLoaderTarget-vN's settings: wl_env/__init__.py)
DRIVEN_ON = {"WheelLoaderPlan-v0": "WheelLoaderTarget-v6", "WheelLoaderPlan-v1": "WheelLoaderTarget-v7"}
PLAN_NUMBERS = ("drive_request", "coast_fraction", "braking_fraction", "hold_time", "drive_bucket",
                "stop_request", "stop_bucket")  # per leg, in this order (the module's table)
N_PLAN_ACTIONS = 2 * len(PLAN_NUMBERS)
MAX_HOLD_TIME = 4.0  # s: the longest bucket hold the plan can ask (the optimum holds 1.5-1.6 s at T_min)


def plan_action(plan: np.ndarray, obs: np.ndarray, time_in_phase: np.ndarray, codec: Codec, dt: float) -> np.ndarray:
    """WheelLoaderTarget-v6's actions (N, 4) of the plan driver: ``plan`` (N, 14) in [-1, 1] (the module's
    table), ``obs`` (N, 21) v6's observations, ``time_in_phase`` (N,) s since the phase began; ``codec``
    the machine's (its bucket-acceleration range)."""
    o = codec.decode_observation(np.asarray(obs, dtype=np.float64)[:, :N_SCENARIO_OBS])
    phase = np.asarray(o.phase)
    n = len(phase)
    k = np.where(phase <= 2, 0, len(PLAN_NUMBERS))[:, None] + np.arange(len(PLAN_NUMBERS))
    leg = np.clip(np.take_along_axis(np.asarray(plan, dtype=np.float64), k, axis=1), -1.0, 1.0)
    driving = (phase == 1) | (phase == 3)
    hold_until = (leg[:, 3] + 1.0) * (0.5 * MAX_HOLD_TIME)
    lo, hi = codec.params.U_ab_bounds
    hold = np.clip((-np.asarray(o.bucket_speed) / dt - 0.5 * (hi + lo)) / (0.5 * (hi - lo)), -1.0, 1.0)
    bucket = np.where(driving, np.where(time_in_phase < hold_until - 1e-9, hold, leg[:, 4]), leg[:, 6])
    actions = np.empty((n, 4))
    actions[:, 0] = np.where(driving, leg[:, 0], leg[:, 5])
    actions[:, 1] = bucket
    actions[:, 2] = leg[:, 2]
    actions[:, 3] = leg[:, 1]
    return actions


def driven_on(plan_id: str, name: str = "plan_id") -> str:
    """The id of the per-step env a plan env's cycle is driven on (``DRIVEN_ON``), ValueError naming ``name`` for
    another id."""
    if plan_id not in DRIVEN_ON:
        raise ValueError(f"{name} must be a plan env, one of {', '.join(DRIVEN_ON)}, got {plan_id!r}")
    return DRIVEN_ON[plan_id]


def target_arguments(plan_id: str, kwargs: dict[str, Any], signature_of: Any) -> dict[str, Any]:
    """The arguments of the per-step env under the plan env ``plan_id``: ``kwargs`` (``signature_of``'s, the
    per-step env's settings left as they are; ValueError naming any other) with those settings."""
    import inspect

    from gymnasium.envs.registration import registry

    target_id = driven_on(plan_id)
    settings = registry[target_id].kwargs
    known = set(inspect.signature(signature_of).parameters) - {"self", "num_envs"}
    unknown = sorted(set(kwargs) - known)
    if unknown:
        raise ValueError(f"{plan_id} takes no argument(s) {unknown}; known: {sorted(known - set(settings))}")
    fixed = sorted(k for k in settings if k in kwargs and not _same_setting(kwargs[k], settings[k]))
    if fixed:
        raise ValueError(f"{plan_id} drives {target_id}: {', '.join(fixed)} cannot be changed")
    return {**kwargs, **settings}


def _same_setting(given: Any, setting: Any) -> bool:
    """Whether an argument given to a plan env is the per-step env's setting itself (a number or a flag of the same
    value): an array compared with ``!=`` was numpy's "truth value of an array is ambiguous", naming no argument."""
    if isinstance(given, np.generic):
        given = given.item()
    if type(given) not in (bool, int, float, str) or isinstance(given, bool) != isinstance(setting, bool):
        return False
    return bool(given == setting)


def _check_plan(action: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = action_array(action, name)
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape} (the plan's {N_PLAN_ACTIONS} numbers, wl_env.plan), "
                         f"got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite numbers in [-1, 1], got non-finite entries")
    return np.clip(a, -1.0, 1.0)


class PlanDriver:
    """The plan driver as a controller of WheelLoaderTarget-v6 (one loader): ``act(obs)`` gives v6's action
    under ``plan`` (14 numbers), counting the time in each phase from the observations it is shown."""

    def __init__(self, plan: Any, params: LoaderParams | None = None, dt: float = 0.1) -> None:
        self.plan = _check_plan(plan, (N_PLAN_ACTIONS,), "plan")[None]
        self.codec = Codec(params, observe_scenario=True)
        # (the env's control interval: 0 or NaN held the bucket by a NaN action, blamed on the action; a string was
        # numpy's TypeError; a negative one ran a plan with no hold)
        self.dt = check_control_interval(dt)
        self.reset()

    def reset(self) -> None:
        self._phase, self._time_in_phase = 0, 0.0

    def act(self, obs: np.ndarray) -> np.ndarray:
        # (checked first, by name: a dict or a string was an IndexError, a batch "argmax of an empty sequence")
        o = self.codec._checked(obs)
        if o.ndim != 1:
            raise ValueError(f"PlanDriver.act takes one observation (shape ({o.shape[-1]},)), got a batch of shape {o.shape}")
        phase = int(np.argmax(o[8:12])) + 1
        if phase != self._phase:
            self._phase, self._time_in_phase = phase, 0.0
        action = plan_action(self.plan, o[None], np.array([self._time_in_phase]), self.codec, self.dt)[0]
        self._time_in_phase += self.dt
        return action.astype(np.float32)


class WheelLoaderPlanEnv(WheelLoaderEnv):
    plan_id = "WheelLoaderPlan-v0"

    def __init__(self, **kwargs: Any) -> None:  # (WheelLoaderEnv's arguments)
        super().__init__(**target_arguments(self.plan_id, kwargs, WheelLoaderEnv.__init__))
        self.action_space = spaces.Box(-1.0, 1.0, (N_PLAN_ACTIONS,), np.float32)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if not self._y or self._done:
            return super().step(action)  # (its RuntimeError: reset first)
        driver = PlanDriver(_check_plan(action, (N_PLAN_ACTIONS,), "action"), self.machine, self.core.dt)
        total, steps, obs = 0.0, 0, self._obs()
        while True:
            obs, reward, terminated, truncated, info = self._advance([float(v) for v in driver.act(obs)])
            total, steps = total + reward, steps + 1
            if terminated or truncated:
                return obs, total, terminated, truncated, {**info, "steps": steps}


class WheelLoaderPlanVectorEnv(WheelLoaderVectorEnv):
    """N loaders of ``WheelLoaderPlan-v0`` (the same arguments as the single env), each step one whole cycle
    per loader, stepped together (the next step resets them all, as gymnasium's next-step autoreset)."""

    plan_id = "WheelLoaderPlan-v0"

    def __init__(self, num_envs: int = 1, **kwargs: Any) -> None:
        super().__init__(num_envs, **target_arguments(self.plan_id, kwargs, WheelLoaderVectorEnv.__init__))
        self.single_action_space = spaces.Box(-1.0, 1.0, (N_PLAN_ACTIONS,), np.float32)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.driver_codec = Codec(self.machine, observe_scenario=True)

    def step(self, actions: Any):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        n = self.num_envs
        plan = _check_plan(actions, (n, N_PLAN_ACTIONS), "actions")
        if self._needs_reset.any():  # (the one-step episodes all ended: they start anew, their plans unused)
            self._reset_where(self._needs_reset)
            zeros = np.zeros(n, dtype=bool)
            # (the infos of any other step, of the new starts: they were {}, and infos["is_success"] a KeyError)
            infos = {**self._infos(zeros.copy(), np.zeros(n)), "steps": np.zeros(n, dtype=np.int64)}
            return self._obs(), np.zeros(n), zeros, zeros.copy(), infos
        dt = self.core.dt
        total, steps = np.zeros(n), np.zeros(n, dtype=np.int64)
        done = np.zeros(n, dtype=bool)
        terminated, truncated = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
        last: dict[str, np.ndarray] = {}
        max_violation = np.zeros(n)
        time_in_phase, phase = np.zeros(n), self._phase.copy()
        obs = self._obs()
        while not done.all():
            kept = (self._y, self._phase, self._t, self._rev_err, self._violation)
            # (the loaders that have ended are stepped along from their end, as the vector env steps all; that step is
            # discarded, and so is its divergence: a stalled engine's step diverged where the single env had stopped)
            _, reward, term, trunc, info = self._advance(plan_action(plan, obs, time_in_phase, self.driver_codec, dt),
                                                         ignore=done)
            if done.any():  # (the loaders that have ended stay as they ended: their steps are not kept)
                self._y = tuple(np.where(done, a, b) for a, b in zip(kept[0], self._y, strict=True))
                self._phase, self._t, self._rev_err, self._violation = (
                    np.where(done, a, b) for a, b in zip(kept[1:], (self._phase, self._t, self._rev_err, self._violation),
                                                         strict=True))
            running = ~done
            total += np.where(running, reward, 0.0)
            steps += running
            max_violation = np.where(running, np.maximum(max_violation, info["violation"]), max_violation)
            ended = running & (term | trunc)
            for key, value in info.items():
                last[key] = np.where(ended, value, last[key]) if key in last else value.copy()
            terminated |= ended & term
            truncated |= ended & trunc & ~term
            done |= ended
            self._needs_reset[:] = False  # (no autoreset inside the cycle)
            time_in_phase = np.where(self._phase != phase, 0.0, time_in_phase + dt)
            phase = self._phase.copy()
            obs = self._obs()
        self._needs_reset[:] = True
        return obs, total, terminated, truncated, {**last, "violation": max_violation, "steps": steps}


class WheelLoaderPlanV1Env(WheelLoaderPlanEnv):
    plan_id = "WheelLoaderPlan-v1"


class WheelLoaderPlanV1VectorEnv(WheelLoaderPlanVectorEnv):
    plan_id = "WheelLoaderPlan-v1"


WheelLoaderPlanEnv.__doc__ = WheelLoaderPlanV1Env.__doc__ = __doc__  # (Gymnasium's convention: the env's docstring holds its tables)
