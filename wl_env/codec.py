"""The observation and action codec: physical quantities <-> the environment's normalized vectors, by name.

The environments encode with it; every controller (the MPC, the operator, a user's) decodes with it, so
a scale is written once. Elapsed time is normalized by a fixed :data:`TIME_SCALE`, not by the episode's
``max_time``: a controller needs nothing of the environment's configuration to read it.

Works on floats and numpy arrays (a batch: arrays of shape (N,), or observations of shape (N, 12)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from wl_env.params import LoaderParams, resolve
from wl_env.physics.backend import ops_for

TIME_SCALE = 40.0  # s: the observation's elapsed time is t / TIME_SCALE

OBS_NAMES = (
    "engine_speed/omega_max", "vehicle_speed/V_max", "bucket_height/H_T", "bucket_speed/(1 m/s)",
    "position/distance", "distance_to_go/distance", "time/(40 s)", "fuel/(1 kg)",
    "phase_1", "phase_2", "phase_3", "phase_4",
)
OBS_LOW = np.array([0, -1.5, 0, 0, -2.5, -1.5, 0, 0, 0, 0, 0, 0], dtype=np.float32)
OBS_HIGH = np.array([1.5, 1.5, 1.5, 2.0, 1.5, 2.5, 1.5, 5.0, 1, 1, 1, 1], dtype=np.float32)
_LOW, _HIGH = tuple(OBS_LOW.tolist()), tuple(OBS_HIGH.tolist())  # (as Python floats: the flattened step's literals)
ACTION_NAMES = ("fuel_injection", "bucket_acceleration", "service_brake", "shift")
N_OBS, N_ACTIONS = len(OBS_NAMES), len(ACTION_NAMES)


@dataclass(frozen=True)
class Observation:
    """A decoded observation, in SI units (floats, or arrays for a batch)."""

    engine_speed: Any  # omega, rad/s
    vehicle_speed: Any  # V, m/s, forward > 0
    bucket_height: Any  # H, m
    bucket_speed: Any  # V_b, m/s
    position: Any  # s, m (start = 0, forward > 0)
    distance_to_go: Any  # m to the current leg's end (the reversing point in phases 1-2, s = 0 after)
    time: Any  # s since the start of the cycle
    fuel_kg: Any  # fuel used so far
    phase: Any  # 1..4

    @property
    def state(self) -> np.ndarray:
        """The grid state [omega, V, H, V_b, s] (rows for a batch)."""
        return np.array([self.engine_speed, self.vehicle_speed, self.bucket_height, self.bucket_speed, self.position])


class Codec:
    """Encodes and decodes for one parameter set (the scales: omega_max, V_max, H_T, the distance, the
    control ranges)."""

    def __init__(self, params: LoaderParams | dict | None = None) -> None:
        self.params = p = resolve(params)
        lo, hi = p.U_ab_bounds
        self._ab_mid, self._ab_half = 0.5 * (hi + lo), 0.5 * (hi - lo)

    # ------------------------------------------------------------------ actions
    def decode_action(self, a_fuel: Any, a_bucket: Any, a_brake: Any) -> tuple[Any, Any, Any]:
        """Normalized actions in [-1, 1] -> commanded (U_mf mg, U_ab m/s^2, U_b N m)."""
        p = self.params
        return (
            (a_fuel + 1.0) * (0.5 * p.U_mf_max),
            self._ab_mid + a_bucket * self._ab_half,
            (a_brake + 1.0) * (0.5 * p.U_b_max),
        )

    def encode_action(self, u_mf: float, u_ab: float, u_b: float, shift: bool) -> np.ndarray:
        """Commanded (U_mf mg, U_ab m/s^2, U_b N m) and a shift request -> the action vector, clipped to
        [-1, 1] (a NaN control becomes the range's low end: no fuel, no brake)."""
        p = self.params
        a = np.array([2.0 * u_mf / p.U_mf_max - 1.0, (u_ab - self._ab_mid) / self._ab_half,
                      2.0 * u_b / p.U_b_max - 1.0, 1.0 if shift else -1.0])
        return np.clip(np.nan_to_num(a, nan=-1.0), -1.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------ observations
    def distance_to_go(self, s: Any, phase: Any) -> Any:
        """Distance to the current leg's end (m): the reversing point in phases 1-2, s = 0 after."""
        return ops_for(s).where(phase <= 2, s + self.params.distance, -s)

    def encode_observation(self, y: Any, phase: Any, t: Any) -> tuple[Any, ...]:
        """The observation's features (:data:`OBS_NAMES`) of the state y = (omega, V, H, V_b, s, m_f),
        each a float or an array, clipped to [OBS_LOW, OBS_HIGH]."""
        p = self.params
        ops = ops_for(y[0])
        features = (
            y[0] / p.omega_max,
            y[1] / p.V_max,
            y[2] / p.H_T,
            y[3],
            y[4] / p.distance,
            self.distance_to_go(y[4], phase) / p.distance,
            t / TIME_SCALE,
            y[5],
            ops.where(phase == 1, 1.0, 0.0),
            ops.where(phase == 2, 1.0, 0.0),
            ops.where(phase == 3, 1.0, 0.0),
            ops.where(phase == 4, 1.0, 0.0),
        )
        return tuple(ops.clip(f, lo, hi) for f, lo, hi in zip(features, _LOW, _HIGH, strict=True))

    def decode_observation(self, obs: Any) -> Observation:
        """An observation (shape (12,), or (N, 12)) -> :class:`Observation` in SI units."""
        p = self.params
        o = np.asarray(obs, dtype=np.float64)
        if o.shape[-1:] != (N_OBS,) or o.ndim > 2 or not np.isfinite(o).all():
            raise ValueError(f"obs must be finite WheelLoader observations of shape ({N_OBS},) or (N, {N_OBS}), "
                             f"got shape {o.shape}{'' if np.isfinite(o).all() else ' with non-finite entries'}")
        c = o.T
        phase = np.argmax(c[8:12], axis=0) + 1
        values = (c[0] * p.omega_max, c[1] * p.V_max, c[2] * p.H_T, c[3], c[4] * p.distance, c[5] * p.distance,
                  c[6] * TIME_SCALE, c[7], phase)
        if o.ndim == 1:
            return Observation(*(float(v) if i < 8 else int(v) for i, v in enumerate(values)))
        return Observation(*values)
