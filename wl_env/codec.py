"""The observation and action codec: physical quantities <-> the environment's normalized vectors, by name.

The environments encode with it; every controller (the MPC, the operator, a user's) decodes with it, so
a scale is written once. Elapsed time is normalized by a fixed :data:`TIME_SCALE`, not by the episode's
``max_time``: a controller needs nothing of the environment's configuration to read it.

Two layouts. ``WheelLoader-v1`` (12 entries) scales heights by the cycle's H_T and lengths by its
reverse distance. ``WheelLoader-v2`` (``observe_scenario``, 19 entries) scales them by fixed lengths
(the nominal cycle's 5 m and 6.6 m, so that its first 12 entries equal v1's on the nominal cycle) and
appends the scenario's features (:func:`wl_env.scenario.param_features`, each in [-1, 1]): an observation
alone tells the cycle, and a policy can condition on it.

Works on floats and numpy arrays (a batch: arrays of shape (N,), or observations of shape (N, n_obs)).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from wl_env.params import LoaderParams, check_flag, resolve, shown
from wl_env.physics.backend import ops_for
from wl_env.scenario import FIELDS, Scenario, param_features

TIME_SCALE = 40.0  # s: the observation's elapsed time is t / TIME_SCALE

OBS_NAMES = (
    "engine_speed/omega_max", "vehicle_speed/V_max", "bucket_height/H_T", "bucket_speed/(1 m/s)",
    "position/distance", "distance_to_go/distance", "time/(40 s)", "fuel/(1 kg)",
    "phase_1", "phase_2", "phase_3", "phase_4",
)
OBS_LOW = np.array([0, -1.5, 0, 0, -2.5, -1.5, 0, 0, 0, 0, 0, 0], dtype=np.float32)
OBS_HIGH = np.array([1.5, 1.5, 1.5, 2.0, 1.5, 2.5, 1.5, 5.0, 1, 1, 1, 1], dtype=np.float32)
ACTION_NAMES = ("fuel_injection", "bucket_acceleration", "service_brake", "shift")
# fuel_action="engine_speed" (WheelLoaderTarget-v1): action 0 is the governor's engine-speed request, -1 at
# this much above the stall speed omega_min (rad/s; the lean optimum rides omega_min, and a request right at
# it stalls on the smallest load step within the interval), +1 at omega_max
GOVERNOR_FLOOR_MARGIN = 5.0
FUEL_ACTIONS = ("injection", "engine_speed")
N_OBS, N_ACTIONS = len(OBS_NAMES), len(ACTION_NAMES)
# WheelLoader-v2: fixed length scales, then the scenario's features
SCENARIO_OBS_NAMES = (
    "engine_speed/omega_max", "vehicle_speed/V_max", "bucket_height/(5 m)", "bucket_speed/(1 m/s)",
    "position/(6.6 m)", "distance_to_go/(6.6 m)", *OBS_NAMES[6:], *(f"scenario.{name}" for name in FIELDS),
)
HEIGHT_SCALE, LENGTH_SCALE = 5.0, 6.6  # m: v2's fixed scales (the nominal H_T and distance)
N_SCENARIO_OBS = len(SCENARIO_OBS_NAMES)
SCENARIO_OBS_LOW = np.concatenate([OBS_LOW, -np.ones(len(FIELDS), dtype=np.float32)])
SCENARIO_OBS_HIGH = np.concatenate([OBS_HIGH, np.ones(len(FIELDS), dtype=np.float32)])
# WheelLoaderTarget-v0: v2's, then the episode's target cycle time (/ 40 s) and its ratio to T_min less 1
TARGET_OBS_NAMES = (*SCENARIO_OBS_NAMES, "target_time/(40 s)", "target_time/T_min - 1")
N_TARGET_OBS = len(TARGET_OBS_NAMES)
# (a target given in seconds may lie anywhere in [1, 40) s: up to ~6.3 T_min, down to ~0.16 T_min)
TARGET_OBS_LOW = np.concatenate([SCENARIO_OBS_LOW, np.array([0.0, -1.0], dtype=np.float32)])
TARGET_OBS_HIGH = np.concatenate([SCENARIO_OBS_HIGH, np.array([1.0, 6.0], dtype=np.float32)])
# Each layout's bounds and names, by its length (decode_observation checks an observation against them), and the
# slack of the check: the env clips to the float32 bounds exactly
OBS_LAYOUTS = {N_OBS: (OBS_LOW, OBS_HIGH, OBS_NAMES), N_SCENARIO_OBS: (SCENARIO_OBS_LOW, SCENARIO_OBS_HIGH, SCENARIO_OBS_NAMES),
               N_TARGET_OBS: (TARGET_OBS_LOW, TARGET_OBS_HIGH, TARGET_OBS_NAMES)}
OBS_TOL = 1e-6


def check_within(o: np.ndarray, low: np.ndarray, high: np.ndarray, names: Sequence[str] | None = None,
                 where: str = "") -> None:
    """ValueError naming the first entry of the observation ``o`` (or of any in a batch (N, n)) outside [low, high]
    (OBS_TOL of slack), its range and its farthest value; ``where`` follows the range in the message."""
    rows = o.reshape(-1, o.shape[-1])
    outside = np.flatnonzero(((rows < low - OBS_TOL) | (rows > high + OBS_TOL)).any(axis=0))
    if outside.size:
        i = int(outside[0])
        column = rows[:, i]
        worst = float(column[np.argmax(np.maximum(low[i] - column, column - high[i]))])
        raise ValueError(f"obs[{i}]{f' ({names[i]})' if names else ''} must lie in [{low[i]:g}, {high[i]:g}]{where}, "
                         f"got {worst:g}")


def _scalar_kind(value: Any) -> str:
    """numpy's dtype kind of a single value (a Python or numpy scalar, or a 0-d array); "" for anything else."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        return ""
    return a.dtype.kind if a.ndim == 0 else ""


def real_observations(obs: Any) -> np.ndarray:
    """``obs`` as a float64 array if it holds real numbers (ints or floats), else ValueError naming ``obs``: a dict was
    a bare TypeError, and booleans, complex numbers or digit strings were cast without a word (a bool array read as
    the engine at omega_max), a masked entry read as the value under its mask. Every reader of observations takes
    them through here (the codec's decoders, the learned policies' act)."""
    if isinstance(obs, np.ma.MaskedArray) and np.ma.is_masked(obs):
        raise ValueError(f"obs must be WheelLoader observations (arrays of real numbers), got a masked array with "
                         f"{np.ma.count_masked(obs)} masked entries")
    try:
        kind = np.asarray(obs).dtype.kind
    except (TypeError, ValueError):  # (ragged nesting)
        kind = "O"
    if kind not in "iuf":
        raise ValueError(f"obs must be WheelLoader observations (arrays of real numbers), got {shown(obs)}")
    return np.asarray(obs, dtype=np.float64)


def encode_speed_request(speed_request: Any, p: Any) -> Any:
    """The governor's engine-speed request (rad/s) -> action 0 in [-1, 1] (``fuel_action="engine_speed"``),
    clipped; ``p`` a parameter set or a vector env's view of many (arrays)."""
    lo = p.omega_min + GOVERNOR_FLOOR_MARGIN
    return np.clip(2.0 * (speed_request - lo) / (p.omega_max - lo) - 1.0, -1.0, 1.0)


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
    """Encodes and decodes for one parameter set (the scales: omega_max, V_max, the control ranges and, in
    v1's layout, H_T and the reverse distance). ``observe_scenario``: v2's layout (see the module doc)."""

    def __init__(self, params: LoaderParams | dict | None = None, observe_scenario: bool = False) -> None:
        self.params = p = resolve(params)
        # (not bool(): "no" or a layout's name chose v2's layout without a word)
        self.observe_scenario = observe_scenario = check_flag("observe_scenario", observe_scenario)
        lo, hi = p.U_ab_bounds
        self._ab_mid, self._ab_half = 0.5 * (hi + lo), 0.5 * (hi - lo)
        low, high = (SCENARIO_OBS_LOW, SCENARIO_OBS_HIGH) if observe_scenario else (OBS_LOW, OBS_HIGH)
        self.obs_low, self.obs_high = low, high
        self.n_obs = len(low)
        self._low, self._high = tuple(low.tolist()), tuple(high.tolist())  # (Python floats: the flat step's literals)

    def _scales(self, observe_scenario: bool | None = None) -> tuple[Any, Any]:
        """(height scale, length scale) in m of a layout (default: this codec's)."""
        p = self.params
        v2 = self.observe_scenario if observe_scenario is None else observe_scenario
        return (HEIGHT_SCALE, LENGTH_SCALE) if v2 else (p.H_T, p.reverse_distance)

    # ------------------------------------------------------------------ actions
    def decode_action(self, a_fuel: Any, a_bucket: Any, a_brake: Any) -> tuple[Any, Any, Any]:
        """Normalized actions in [-1, 1] -> commanded (U_mf mg, U_ab m/s^2, U_b N m)."""
        p = self.params
        return (
            (a_fuel + 1.0) * (0.5 * p.U_mf_max),
            self._ab_mid + a_bucket * self._ab_half,
            (a_brake + 1.0) * (0.5 * p.U_b_max),
        )

    def decode_speed_request(self, a_fuel: Any) -> Any:
        """Action 0 in [-1, 1] -> the engine-speed governor's request (rad/s), ``fuel_action="engine_speed"``."""
        p = self.params
        lo = p.omega_min + GOVERNOR_FLOOR_MARGIN
        return lo + (a_fuel + 1.0) * (0.5 * (p.omega_max - lo))

    def encode_speed_request(self, speed_request: Any) -> Any:
        """The inverse of :meth:`decode_speed_request`, clipped to [-1, 1]."""
        return encode_speed_request(speed_request, self.params)

    def encode_action(self, u_mf: float, u_ab: float, u_b: float, shift: bool) -> np.ndarray:
        """Commanded (U_mf mg, U_ab m/s^2, U_b N m) and a shift request -> the action vector, clipped to
        [-1, 1] (a NaN control becomes the range's low end: no fuel, no brake)."""
        p = self.params
        # (checked by name: a NaN or "no" as the shift was a shift request, a string control numpy's TypeError)
        for name, u in (("u_mf", u_mf), ("u_ab", u_ab), ("u_b", u_b)):
            if _scalar_kind(u) not in ("i", "u", "f"):
                raise ValueError(f"encode_action's {name} must be a number (NaN: the range's low end), got {shown(u)}")
        if _scalar_kind(shift) != "b":
            raise ValueError(f"encode_action's shift must be True or False, got {shown(shift)}")
        a = np.array([2.0 * u_mf / p.U_mf_max - 1.0, (u_ab - self._ab_mid) / self._ab_half,
                      2.0 * u_b / p.U_b_max - 1.0, 1.0 if shift else -1.0])
        return np.clip(np.nan_to_num(a, nan=-1.0), -1.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------ observations
    def distance_to_go(self, s: Any, phase: Any) -> Any:
        """Distance to the current leg's end (m): the reversing point in phases 1-2, the truck after."""
        p = self.params
        return ops_for(s).where(phase <= 2, s + p.reverse_distance, p.final_position - s)

    def encode_observation(self, y: Any, phase: Any, t: Any) -> tuple[Any, ...]:
        """The observation's entries of the state y = (omega, V, H, V_b, s, m_f), each a float or an array,
        clipped to [obs_low, obs_high]."""
        p = self.params
        ops = ops_for(y[0])
        height, length = self._scales()
        features = (
            y[0] / p.omega_max,
            y[1] / p.V_max,
            y[2] / height,
            y[3],
            y[4] / length,
            self.distance_to_go(y[4], phase) / length,
            t / TIME_SCALE,
            y[5],
            ops.where(phase == 1, 1.0, 0.0),
            ops.where(phase == 2, 1.0, 0.0),
            ops.where(phase == 3, 1.0, 0.0),
            ops.where(phase == 4, 1.0, 0.0),
        )
        if self.observe_scenario:
            features += tuple(f + 0.0 * y[0] for f in param_features(p))  # (arrays for a batch)
        return tuple(ops.clip(f, lo, hi) for f, lo, hi in zip(features, self._low, self._high, strict=True))

    def _checked(self, obs: Any) -> np.ndarray:
        o = real_observations(obs)
        if o.shape[-1:] not in ((N_OBS,), (N_SCENARIO_OBS,), (N_TARGET_OBS,)) or o.ndim > 2 or not np.isfinite(o).all():
            raise ValueError(f"obs must be finite WheelLoader observations of shape ({N_TARGET_OBS},) (WheelLoaderTarget), "
                             f"({N_SCENARIO_OBS},) (v2) or ({N_OBS},) (v1), or a batch (N, ...) of them, got shape {o.shape}"
                             f"{'' if np.isfinite(o).all() else ' with non-finite entries'}")
        # (in the observation space: an engine speed of 50 omega_max or a time of -200 s was planned from as if real)
        check_within(o, *OBS_LAYOUTS[o.shape[-1]])
        phases = o[..., 8:12]
        if not (np.isin(phases, (0.0, 1.0)).all() and (phases.sum(axis=-1) == 1.0).all()):
            raise ValueError(f"obs[8:12] (the phase) must be one-hot: one 1 and three 0, got {phases.tolist()}"[:300])
        return o

    def decode_observation(self, obs: Any) -> Observation:
        """An observation of either layout (told by its length; shape (n,), or (N, n)) -> :class:`Observation`
        in SI units (v1's scales are this codec's parameters')."""
        p = self.params
        o = self._checked(obs)
        c = o.T
        height, length = self._scales(o.shape[-1] != N_OBS)
        phase = np.argmax(c[8:12], axis=0) + 1
        values = (c[0] * p.omega_max, c[1] * p.V_max, c[2] * height, c[3], c[4] * length, c[5] * length,
                  c[6] * TIME_SCALE, c[7], phase)
        if o.ndim == 1:
            return Observation(*(float(v) if i < 8 else int(v) for i, v in enumerate(values)))
        return Observation(*values)

    def decode_scenario(self, obs: Any, braking: str) -> Scenario:
        """The scenario a v2 observation (shape (n_obs,)) carries, to float32 precision."""
        o = self._checked(obs)
        if o.shape[-1] == N_OBS:
            raise ValueError("a WheelLoader-v1 observation carries no scenario; use WheelLoader-v2")
        if o.ndim != 1:
            raise ValueError(f"decode_scenario takes one observation, got shape {o.shape}")
        f = o[N_OBS:N_SCENARIO_OBS]
        values = {name: min(max(0.5 * (s.lo + s.hi) + v * 0.5 * (s.hi - s.lo), s.lo), s.hi)
                  for (name, s), v in zip(FIELDS.items(), f, strict=True)}
        return Scenario(braking=braking, **values)
