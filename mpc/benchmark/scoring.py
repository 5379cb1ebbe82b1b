"""Scoring a controller's cycle against the optimum.

Cycle time against the minimum cycle time; fuel against the minimum fuel at the *same* cycle time
(the Pareto front), as the paper compares the braking alternatives.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass
from typing import Any

from mpc.benchmark.pareto import ParetoFront, optimal_fuel_at, pareto_front
from wl_env.params import LoaderParams


@dataclass(frozen=True)
class Score:
    """A cycle's gaps to the optimum: its time T (s) against the minimum cycle time T_min, its fuel
    against the minimum fuel at the same cycle time, fuel_opt_g. Gaps are relative: 0.05 = 5 % above."""

    braking: str
    T: float
    fuel_g: float
    T_min: float
    time_gap: float
    fuel_opt_g: float
    fuel_gap: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def score_run(
    T: float,
    fuel_g: float,
    braking: str,
    params: LoaderParams | dict | None = None,
    front: ParetoFront | None = None,
    cache: str | os.PathLike | None = None,
) -> Score:
    """Score one cycle (its time T in s and fuel in g, as run in the environment): the one scoring of the
    project, for every controller and every evaluation."""
    for name, v in (("T", T), ("fuel_g", fuel_g)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    front = front or pareto_front(braking, params=params, cache=cache)
    if T < front.T_min - 1e-6:
        # Faster than the optimum is only possible by breaking a constraint or missing a target.
        fuel_opt = front.fuel_g[0]
    else:
        fuel_opt = optimal_fuel_at(T, braking, params=params, cache=cache, front=front)
    return Score(braking=braking, T=float(T), fuel_g=float(fuel_g), T_min=front.T_min, time_gap=T / front.T_min - 1.0,
                 fuel_opt_g=float(fuel_opt), fuel_gap=fuel_g / fuel_opt - 1.0)
