"""The controller protocol: what :func:`wl_env.rollout.run_episode` and ``wl evaluate`` drive the loader with.

A controller sees the environment's normalized observation (shape (19,) in ``WheelLoader-v2``, the
scenario included; (12,) in v1; see :class:`wl_env.env.WheelLoaderEnv`) and returns the normalized action
(shape (4,): fuel injection, bucket acceleration, service brake, shift request, each in [-1, 1]).
``reset()`` is called before each episode, so a controller with memory (a plan, an estimator) starts every
cycle afresh; one whose ``reset`` takes ``scenario=`` is told the episode's :class:`wl_env.scenario.Scenario`
when an evaluation runs a suite or a scenario. An ``env_id`` attribute names the env it acts in (default
``WheelLoader-v2``).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Controller(Protocol):
    """Anything with ``reset()`` and ``act(obs) -> action``: the operator, the MPC, a PPO policy, yours."""

    def reset(self) -> None:
        """Forget the previous episode (called before the first step of each one)."""
        ...

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The action, shape (4,) in [-1, 1], for the observation ``obs``."""
        ...
