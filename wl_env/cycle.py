"""The short loading cycle (Table II): phases, gears and brakes per braking alternative, start, targets.

Shared by the environment, the OCP and the MPC so that all three drive the same cycle.

| phase | travel         | gear (service / tc) | service brake allowed |
|-------|----------------|---------------------|-----------------------|
| 1     | reversing  d=-1| -60 / -60           | no                    |
| 2     | reversing  d=-1|   0 / +60           | yes / no              |
| 3     | forwarding d=+1| +60 / +60           | no                    |
| 4     | forwarding d=+1|   0 /   0           | yes                   |
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wl_env.params import LoaderParams, shown

BRAKING_MODES = ("service", "tc")
PHASES = (1, 2, 3, 4)
MIN_PHASE_DURATION = 0.1  # s, each phase lasts at least this long (MODEL.md, "The cycle")


def check_braking(braking: str) -> str:
    """``braking`` as the plain str of one of BRAKING_MODES; ValueError naming the allowed ones otherwise."""
    if isinstance(braking, str):  # (a str subclass, np.str_ say, as the str it holds: its == may say yes to anything)
        braking = str.__str__(braking)
    if not isinstance(braking, str) or braking not in BRAKING_MODES:  # (an array: numpy's "truth value ... ambiguous")
        raise ValueError(f"braking must be one of {BRAKING_MODES} ('service' brakes or 'tc' braking), got {shown(braking)}")
    return braking


@dataclass(frozen=True)
class PhaseSpec:
    phase: int
    gear: float  # gamma
    direction: float  # d: -1 reversing, +1 forwarding
    brake_allowed: bool


def phase_specs(braking: str, params: LoaderParams) -> tuple[PhaseSpec, ...]:
    """The four phases of the cycle for a braking alternative (index 0 is phase 1)."""
    check_braking(braking)
    g = params.gear_ratio
    tc = braking == "tc"
    return (
        PhaseSpec(1, -g, -1.0, False),
        PhaseSpec(2, g if tc else 0.0, -1.0, not tc),
        PhaseSpec(3, g, 1.0, False),
        PhaseSpec(4, 0.0, 1.0, True),
    )


def phase_tables(braking: str, params: LoaderParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gear, direction and brake-allowed as arrays indexed by phase number (index 0 unused)."""
    specs = phase_specs(braking, params)
    gear = np.array([0.0] + [s.gear for s in specs])
    direction = np.array([1.0] + [s.direction for s in specs])
    brake = np.array([0.0] + [1.0 if s.brake_allowed else 0.0 for s in specs])
    return gear, direction, brake


def initial_state(params: LoaderParams) -> np.ndarray:
    """[omega, V, H, V_b] at t = 0: omega_0 (1500 rpm), standing, bucket at H_0, bucket still (Table II)."""
    return np.array([params.omega_0, 0.0, params.H_0, 0.0])


def reversing_target(params: LoaderParams) -> float:
    """Position s (m) of the reversing point, the end of phase 2: reverse_distance behind the pile."""
    return -params.reverse_distance


def final_target(params: LoaderParams) -> dict[str, float]:
    """End of phase 4: at the truck (s = forward_distance - reverse_distance; 0 for equal legs), standing,
    bucket at H_T and still."""
    return {"s": params.final_position, "V": 0.0, "H": params.H_T, "V_b": 0.0}
