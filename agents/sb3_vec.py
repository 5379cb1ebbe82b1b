"""The native vectorized ``WheelLoader-v1`` (or v2, WheelLoaderTarget-v0) as a stable-baselines3 ``VecEnv``.

Gymnasium's vector env (``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``) autoresets
on the *next* step: the step that ends an episode returns the final observation, and the following
``step`` call resets that loader, ignores its action and returns reward 0. Stable-baselines3 expects a
*same-step* autoreset instead: the step that ends an episode returns the first observation of the next
one, with the final observation in ``infos[i]["terminal_observation"]`` and
``infos[i]["TimeLimit.truncated"]`` telling a time-out from a real end.

:class:`WheelLoaderSB3VecEnv` converts by resetting the finished loaders right after the step that
ended their episodes (through the vector env's masked reset ``_reset_where``), so every SB3 step is a
real transition: no zero-reward "reset step" enters a rollout, and no transition mixes two episodes.
The per-loader random generators are the ones the native autoreset would use, so loader i follows the
same trajectory as a single ``WheelLoaderEnv`` seeded with ``seed + i`` in SB3's ``DummyVecEnv``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

import wl_env  # noqa: F401  (registers WheelLoader-v1)
from wl_env.vector_env import WheelLoaderVectorEnv

ENV_ID = "WheelLoader-v1"


class WheelLoaderSB3VecEnv(VecEnv):
    """Stable-baselines3 view of a :class:`~wl_env.vector_env.WheelLoaderVectorEnv` (same-step autoreset).

    ``infos[i]`` holds the native per-loader infos of the step (``t``, ``fuel_g``, ``phase``,
    ``is_success``, ``reversing_error`` (None until reached)), ``TimeLimit.truncated`` and, on the step
    that ends an episode, ``terminal_observation``.
    """

    def __init__(self, venv: WheelLoaderVectorEnv) -> None:
        native = venv.unwrapped
        if not isinstance(native, WheelLoaderVectorEnv):
            raise TypeError(f"expected a WheelLoaderVectorEnv, got {type(native).__name__}")
        self.venv = native
        super().__init__(native.num_envs, native.single_observation_space, native.single_action_space)
        self.metadata = {"render_modes": []}
        self.render_mode = None
        self._actions: np.ndarray | None = None

    # ------------------------------------------------------------------ VecEnv API
    def reset(self) -> VecEnvObs:
        seeds = self._seeds
        if all(s is None for s in seeds):
            obs, _ = self.venv.reset()
        elif any(s is None for s in seeds):
            raise ValueError("seed either all loaders or none")
        else:
            obs, _ = self.venv.reset(seed=[int(s) for s in seeds])
        self._reset_seeds()
        self._reset_options()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_async() must come before step_wait()")
        obs, reward, terminated, truncated, native_infos = self.venv.step(self._actions)
        self._actions = None
        dones = terminated | truncated
        infos = self._split_infos(native_infos, terminated, truncated)
        if dones.any():
            # Same-step autoreset: keep the final observations, start the finished loaders anew now (the
            # native env would do it, with the same per-loader generators, on the next step call).
            obs = obs.copy()
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = obs[i].copy()
            self.venv._reset_where(dones)
            obs[dones] = self.venv._obs()[dones]
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None] * self.num_envs

    # attribute access: one native env holds all loaders, so every index sees the same object.
    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.venv, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        if list(self._get_indices(indices)) != list(range(self.num_envs)):
            raise ValueError("attributes of the vector WheelLoader env can only be set for all loaders at once")
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        if list(self._get_indices(indices)) != list(range(self.num_envs)):
            raise ValueError("methods of the vector WheelLoader env can only be called for all loaders at once")
        return [getattr(self.venv, method_name)(*method_args, **method_kwargs)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    # ------------------------------------------------------------------ helpers
    def _split_infos(self, native: dict[str, np.ndarray], terminated: np.ndarray, truncated: np.ndarray) -> list[dict]:
        infos: list[dict[str, Any]] = []
        for i in range(self.num_envs):
            info: dict[str, Any] = {}
            for key, values in native.items():
                v = values[i].item() if isinstance(values, np.ndarray) else values
                if key == "reversing_error" and isinstance(v, float) and math.isnan(v):
                    v = None
                info[key] = v
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            infos.append(info)
        return infos


def make_sb3_vec_env(num_envs: int, braking: str = "service", seed: int | None = None, env_id: str = ENV_ID,
                     **env_kwargs: Any) -> WheelLoaderSB3VecEnv:
    """``gymnasium.make_vec(env_id, num_envs, vectorization_mode="vector_entry_point", ...)`` (default
    ``WheelLoader-v1``; any of the registered WheelLoader ids) as an SB3 ``VecEnv``; ``seed`` (loader i gets
    ``seed + i``) is applied at the first ``reset``."""
    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", braking=braking, **env_kwargs)
    env = WheelLoaderSB3VecEnv(venv)
    if seed is not None:
        env.seed(seed)
    return env
