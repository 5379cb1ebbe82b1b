"""Native vectorized ``WheelLoader-v2`` (and ``-v1``): N loaders stepped together as numpy arrays.

Built by ``gymnasium.make_vec("WheelLoader-v2", num_envs=N, vectorization_mode="vector_entry_point")``.
It runs the same :class:`~wl_env.episode.CycleStepper` as the single environment on arrays of shape
(N,), so loader i follows exactly the trajectory of a single ``WheelLoaderEnv`` seeded with ``seed + i``.
Finished loaders are reset on the next call to ``step`` (Gymnasium's next-step autoreset). With a suite
as ``scenario``, each loader draws its own scenario at each (auto)reset from its own seeded generator:
the scenario's fields are then arrays of shape (N,) in a :class:`~wl_env.params.ParamsView`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from wl_env.assist import assisted_action
from wl_env.codec import TARGET_OBS_HIGH, TARGET_OBS_LOW
from wl_env.env import (
    TARGET_RATIOS,
    action_array,
    check_assist,
    check_target_cycle,
    check_target_power,
    check_target_ratios,
    episode_target,
    lateness_charge,
    make_reward_config,
    n_actions,
    scenario_source,
    start_scenario,
    target_features,
)
from wl_env.episode import CycleStepper, RewardConfig
from wl_env.params import (
    MAX_NUM_ENVS,
    SCENARIO_FIELDS,
    LoaderParams,
    ParamsView,
    check_flag,
    check_no_overridden,
    plain,
    resolve_machine,
    shown,
)
from wl_env.scenario import Scenario
from wl_env.suites import Suite


class WheelLoaderVectorEnv(VectorEnv):
    """N wheel loaders in the short loading cycle (same arguments as ``WheelLoaderEnv``)."""

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(
        self,
        num_envs: int = 1,
        braking: str | None = None,
        params: LoaderParams | dict | None = None,
        dt: float = 0.1,
        substeps: int = 1,
        max_time: float = 40.0,
        reward: RewardConfig | dict | None = None,
        w_fuel: float | None = None,
        w_time: float | None = None,
        init_noise: float = 0.0,
        render_mode: str | None = None,
        scenario: Scenario | dict | str | None = None,
        observe_scenario: bool = True,
        observe_target: bool = False,
        target: float | tuple[float, float] = TARGET_RATIOS,
        target_power: float = 1.0,
        fuel_action: str = "injection",
        assist: bool = False,
        coast: bool = False,
        guards: bool = False,
        lift_floor: bool = False,
        lift_off_load: bool = False,
        step_braking: bool = False,
    ) -> None:
        num_envs = plain(num_envs)
        if isinstance(num_envs, bool) or not (isinstance(num_envs, int) and 1 <= num_envs <= MAX_NUM_ENVS):
            raise ValueError(f"num_envs must be an integer in [1, {MAX_NUM_ENVS}], got {shown(num_envs)}")
        if render_mode is not None:
            raise ValueError(f"the vector env does not render (render_mode must be None, got {shown(render_mode)}); "
                             f"use the single environment")
        init_noise = plain(init_noise)
        if isinstance(init_noise, bool) or not (isinstance(init_noise, (int, float)) and 0.0 <= init_noise <= 1.0):
            raise ValueError(f"init_noise must lie in [0, 1], got {shown(init_noise)}")
        self.num_envs = num_envs
        self.assist = check_assist(assist, fuel_action, coast, guards, lift_floor, lift_off_load, step_braking)
        self.coast, self.guards, self.lift_floor, self.lift_off_load = coast, guards, lift_floor, lift_off_load
        self.step_braking = step_braking
        self.observe_target = check_flag("observe_target", observe_target)
        observe_scenario = check_flag("observe_scenario", observe_scenario)
        if self.observe_target and not observe_scenario:
            raise ValueError("observe_target needs observe_scenario (the target's observation extends v2's)")
        self.target_ratios = check_target_ratios(target)
        self.target_power = check_target_power(target_power)
        self.target_time, self.min_time_estimate = np.full(num_envs, np.nan), np.full(num_envs, np.nan)
        self.machine = resolve_machine(params)
        self._source, self.braking = scenario_source(scenario, braking, self.machine)
        check_no_overridden(params, self._source)
        check_target_cycle(self.observe_target, self._source, self.machine, self.braking)
        self.init_noise = float(init_noise)
        if isinstance(self._source, Suite):  # one scenario per loader, drawn at each reset
            self.params: LoaderParams | ParamsView = ParamsView(
                self.machine, **{f: np.full(num_envs, float(getattr(self.machine, f))) for f in SCENARIO_FIELDS})
        else:
            self.params = self._source.params(self.machine) if self._source is not None else self.machine
        self.scenarios: list[Scenario | None] = [self._source if isinstance(self._source, Scenario) else None] * num_envs
        self.core = CycleStepper(self.params, self.braking, dt, substeps, max_time,
                                 make_reward_config(reward, w_fuel, w_time), observe_scenario, fuel_action)
        codec = self.core.codec
        self.single_action_space = spaces.Box(-1.0, 1.0, (n_actions(self.assist, self.coast),), np.float32)
        low, high = (TARGET_OBS_LOW, TARGET_OBS_HIGH) if self.observe_target else (codec.obs_low, codec.obs_high)
        self.single_observation_space = spaces.Box(low, high, dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.render_mode = None
        self._rngs: list[np.random.Generator] = [np.random.default_rng() for _ in range(num_envs)]
        n = num_envs
        self._y = tuple(np.zeros(n) for _ in range(6))
        self._phase = np.ones(n, dtype=np.int64)
        self._t = np.zeros(n)
        self._rev_err = np.full(n, np.nan)
        self._violation = np.zeros(n)
        self._needs_reset = np.zeros(n, dtype=bool)
        self._started = False

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None):
        if options is not None and options != {}:  # (0, False, "" and [] passed a truthiness test)
            raise ValueError(f"WheelLoaderVectorEnv.reset takes no options (None or {{}}), got {shown(options)}")
        if seed is not None:
            seed = plain(seed)
            if isinstance(seed, int) and not isinstance(seed, bool):
                seeds = [seed + i for i in range(self.num_envs)]
            elif isinstance(seed, (list, tuple)):
                seeds = [plain(s) for s in seed]
            else:
                raise ValueError(f"seed must be an integer >= 0, a list of num_envs={self.num_envs} of them, or None; "
                                 f"got {shown(seed)}")
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed list must have num_envs={self.num_envs} entries, got {len(seeds)}")
            if not all(s is None or (isinstance(s, int) and not isinstance(s, bool) and s >= 0) for s in seeds):
                raise ValueError(f"seed must be an integer >= 0 (or None) for each env, got {shown(seed)}")
            # as gymnasium's np_random(seed); a None entry keeps that loader's generator going, as a single env's
            # reset(seed=None) does (it was a fresh, unseeded generator: the loader's episodes no longer the seed's)
            self._rngs = [rng if s is None else np.random.default_rng(s) for rng, s in zip(self._rngs, seeds, strict=True)]
        self._reset_where(np.ones(self.num_envs, dtype=bool))
        self._started = True
        # (the single env's reset info, per loader, but its scenario: they were {}, a target env's targets unsaid)
        return self._obs(), {"t": self._t.copy(), "fuel_g": self._y[5] * 1000.0, "phase": self._phase.copy(),
                             **({"target_time": self.target_time.copy()} if self.observe_target else {})}

    def _reset_where(self, mask: np.ndarray) -> None:
        p = self.params
        idx = np.flatnonzero(mask)
        drawn: dict[int, LoaderParams] = {}
        if isinstance(self._source, Suite):
            for i in idx:
                s = self.scenarios[i] = self._source.sample(self._rngs[i], self.braking)
                drawn[i] = s.params(self.machine)
                for f in SCENARIO_FIELDS:
                    p.values[f][i] = getattr(drawn[i], f)
        omega = np.broadcast_to(p.omega_0, (self.num_envs,))[idx].astype(float)
        H = np.broadcast_to(p.H_0, (self.num_envs,))[idx].astype(float)
        if self.init_noise > 0.0:
            for j, i in enumerate(idx):
                du = self._rngs[i].uniform(-1.0, 1.0, size=2)
                omega[j] += float(du[0]) * self.init_noise * 100.0 * math.pi / 30.0
                H[j] += float(du[1]) * self.init_noise * 0.1
        if self.observe_target:  # each loader's target, from its own start (as the single env draws it)
            for j, i in enumerate(idx):
                s = self.scenarios[i]
                if self.init_noise > 0.0 or s is None:
                    p_i = drawn.get(i) or (s.params(self.machine) if s is not None else self.machine)
                    # (a perturbed start outside the ranges: the unperturbed one's target, as the single env's)
                    unperturbed = s or start_scenario(p_i, self.braking, p_i.omega_0, p_i.H_0)
                    start = (start_scenario(p_i, self.braking, omega[j], H[j]) if self.init_noise > 0.0 else None) or unperturbed
                else:
                    start = s
                self.min_time_estimate[i], self.target_time[i] = episode_target(
                    start, self.target_ratios, self._rngs[i], power=self.target_power)
        y = tuple(a.copy() for a in self._y)
        for a in y:
            a[idx] = 0.0
        y[0][idx] = omega
        y[2][idx] = H
        self._y = y
        self._phase[idx] = 1
        self._t[idx] = 0.0
        self._rev_err[idx] = np.nan
        self._violation[idx] = 0.0
        self._needs_reset[idx] = False

    def step(self, actions: Any):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        a = action_array(actions, "actions")
        n_act = self.single_action_space.shape[0]
        if a.shape != (self.num_envs, n_act):
            raise ValueError(f"actions must have shape ({self.num_envs}, {n_act}), got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = np.flatnonzero(~np.all(np.isfinite(a), axis=1)).tolist()
            raise ValueError(f"actions must be finite numbers in [-1, 1]; non-finite in envs {bad[:10]}")
        return self._advance(a)

    def _advance(self, a: np.ndarray, ignore: np.ndarray | None = None):
        """One step under the checked actions ``a`` (N, this env's actions; the plan env's driver acts here).
        ``ignore``: a mask of loaders whose step the caller discards (the plan env's loaders that have ended), not
        checked for divergence."""
        resetting = self._needs_reset.copy()
        t0 = self._t.copy()
        if self.assist:
            y, phase = self._y, self._phase
            action = assisted_action(y, phase, self.core.codec.distance_to_go(y[4], phase), a.T, self.params,
                                     self.braking, self.core.dt, self.coast, self.guards,
                                     self.lift_floor, self.lift_off_load, self.step_braking)
        else:
            action = (a[:, 0], a[:, 1], a[:, 2], a[:, 3])
        r = self.core.step(self._y, self._phase, self._t, self._rev_err, self._violation, action)
        skip = resetting if ignore is None else resetting | ignore
        if self.core.diverged(r["y"], ignore=skip):  # (a finished loader's step is discarded: it starts anew)
            kept = ~skip  # (the message says what the loaders that diverged reached, not a discarded step's numbers)
            raise self.core.divergence(tuple(np.asarray(c)[kept] for c in r["y"][:2]), self._t[kept])
        self._y, self._phase, self._t = r["y"], r["phase"], r["t"]
        self._rev_err, self._violation = r["rev_err"], r["violation"]
        reward = np.asarray(r["reward"], dtype=np.float64)
        if self.observe_target:
            reward = reward - lateness_charge(t0, np.asarray(r["t"], dtype=float), self.target_time, self.core.reward.late)
        terminated = np.asarray(r["terminated"], dtype=bool)
        truncated = np.asarray(r["truncated"], dtype=bool)
        success = np.asarray(r["success"], dtype=bool)
        if resetting.any():  # next-step autoreset: these envs start anew and ignore their action
            self._reset_where(resetting)
            reward[resetting] = 0.0
            terminated[resetting] = False
            truncated[resetting] = False
            success[resetting] = False
        self._needs_reset = terminated | truncated
        return self._obs(), reward, terminated, truncated, self._infos(success, np.asarray(r["excess"], dtype=np.float64))

    def _infos(self, success: np.ndarray, violation: np.ndarray) -> dict[str, np.ndarray]:
        """A step's infos (per loader, arrays of shape (N,)): the loaders' state now, their success and violation."""
        return {
            "t": self._t.copy(),
            "fuel_g": self._y[5] * 1000.0,
            "phase": self._phase.copy(),
            "is_success": success,
            "reversing_error": self._rev_err.copy(),
            "violation": violation,
            **({"target_time": self.target_time.copy()} if self.observe_target else {}),
        }

    def _obs(self) -> np.ndarray:
        cols = self.core.codec.encode_observation(self._y, self._phase, self._t)  # (after the autoresets)
        if self.observe_target:
            cols = (*cols, *target_features(self.target_time, self.min_time_estimate))
        return np.stack([np.broadcast_to(c, (self.num_envs,)) for c in cols], axis=1).astype(np.float32)  # (clipped)

    @property
    def states(self) -> np.ndarray:
        """Model states, shape (N, 4): [omega, V, H, V_b]."""
        return np.stack(self._y[:4], axis=1)
