"""The cycle as an episode: actions -> controls, phase changes, reward, termination, observation.

Written once for one loader (Python floats) and for a batch (numpy arrays), like the simulator under
it, so that ``WheelLoaderEnv`` and ``WheelLoaderVectorEnv`` compute the same numbers. For one loader,
:meth:`CycleStepper.step` runs itself flattened to straight-line float code (:mod:`wl_env.physics.flatten`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from wl_env import cycle
from wl_env.params import LoaderParams
from wl_env.physics.backend import ops_for
from wl_env.physics.flatten import flatten_cached
from wl_env.simulator import Simulator

# Tolerances of the end targets (the project's acceptance figures: 5 cm in distance, 2 cm in height).
DISTANCE_TOL = 0.05  # m
HEIGHT_TOL = 0.02  # m
STILL_SPEED = 1e-6  # m/s: the bucket counts as still below this

# The flattened step unrolls the substeps (~150 lines of code each); beyond this many it is not worth it.
MAX_FLAT_SUBSTEPS = 8

OBS_NAMES = (
    "omega/omega_max", "V/V_max", "H/H_T", "V_b/(1 m/s)", "s/distance", "to_go/distance",
    "t/max_time", "fuel/(1 kg)", "phase_1", "phase_2", "phase_3", "phase_4",
)
OBS_LOW = np.array([0, -1.5, 0, 0, -2.5, -1.5, 0, 0, 0, 0, 0, 0], dtype=np.float32)
OBS_HIGH = np.array([1.5, 1.5, 1.5, 2.0, 1.5, 2.5, 1.5, 5.0, 1, 1, 1, 1], dtype=np.float32)


@dataclass(frozen=True)
class RewardConfig:
    """Reward weights. Per step: -(w_fuel * fuel/fuel_ref_g + w_time * dt/time_ref) - penalties + shaping.

    ``w_fuel`` and ``w_time`` trace the fuel-time trade-off (the paper's W1, W2); the references make
    both terms about 1 over a cycle. Penalties: ``violation`` per second and per unit of relative excess
    over the driver's limits (deceleration 0.18 g, speed V_max); ``target_distance`` per metre of error
    at the reversing point and at the end; ``target_height`` per metre of bucket-height error at the end;
    ``failure`` once for an engine stall or leaving the site. ``shaping`` scales a potential-based term
    (progress along the 13.2 m path and the lift), which leaves the optimal policy unchanged.
    """

    w_fuel: float = 0.5
    w_time: float = 0.5
    fuel_ref_g: float = 100.0
    time_ref: float = 12.0
    violation: float = 5.0
    target_distance: float = 5.0
    target_height: float = 5.0
    failure: float = 20.0
    shaping: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"RewardConfig.{f.name} must be a finite number, got {v!r}")
            if v < 0:
                raise ValueError(f"RewardConfig.{f.name} must be >= 0, got {v!r}")
        for name in ("fuel_ref_g", "time_ref"):
            if getattr(self, name) <= 0:
                raise ValueError(f"RewardConfig.{name} must be > 0, got {getattr(self, name)!r}")


class CycleStepper:
    """Advances loaders by one control interval of the cycle. State (floats or arrays of shape (N,)):

    ``y = (omega, V, H, V_b, s, m_f)``, ``phase`` (1..4), ``t`` (s), ``rev_err`` (signed error of the
    reversing point, m; NaN until reached) and ``violation`` (the largest relative excess over the
    driver's limits so far).
    """

    def __init__(
        self,
        params: LoaderParams,
        braking: str,
        dt: float,
        substeps: int,
        max_time: float,
        reward: RewardConfig,
    ) -> None:
        if isinstance(dt, bool) or not (isinstance(dt, (int, float)) and math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise ValueError(f"dt (the control interval) must lie in (0, 1] s, got {dt!r}")
        if isinstance(substeps, bool) or not (isinstance(substeps, int) and 1 <= substeps <= 1000):
            raise ValueError(f"substeps must be an integer in [1, 1000], got {substeps!r}")
        if isinstance(max_time, bool) or not (isinstance(max_time, (int, float)) and math.isfinite(max_time) and max_time >= 5 * dt):
            raise ValueError(f"max_time must be a finite number of seconds >= 5 dt, got {max_time!r}")
        self.params = params
        self.braking = cycle.check_braking(braking)
        self.sim = Simulator(params, braking)
        self.dt = float(dt)
        self.substeps = substeps
        self.h = self.dt / substeps
        self.max_time = float(max_time)
        self.reward = reward
        lo, hi = params.U_ab_bounds
        self._ab_mid, self._ab_half = 0.5 * (hi + lo), 0.5 * (hi - lo)
        self._decel_max = params.decel_max * params.g

    # -------------------------------------------------------------- actions
    def controls(self, a_fuel: Any, a_bucket: Any, a_brake: Any) -> tuple[Any, Any, Any]:
        """Normalized actions in [-1, 1] -> commanded (U_mf mg, U_ab m/s^2, U_b N m)."""
        p = self.params
        return (
            (a_fuel + 1.0) * (0.5 * p.U_mf_max),
            self._ab_mid + a_bucket * self._ab_half,
            (a_brake + 1.0) * (0.5 * p.U_b_max),
        )

    # -------------------------------------------------------------- progress
    def potential(self, y: Any, phase: Any) -> Any:
        """Progress potential: minus the normalized path still to go and the height still to lift."""
        p = self.params
        ops = ops_for(y[4])
        to_go = self.distance_to_go(y[4], phase)
        path_left = to_go + ops.where(phase <= 2, p.distance, 0.0)
        lift_left = ops.fmax(p.H_T - y[2], 0.0) / (p.H_T - p.H_0)
        return -(path_left / p.distance + lift_left)

    def distance_to_go(self, s: Any, phase: Any) -> Any:
        """Distance to the current leg's end (m): the reversing point in phases 1-2, s = 0 after."""
        ops = ops_for(s)
        return ops.where(phase <= 2, s + self.params.distance, -s)

    def observation(self, y: Any, phase: Any, t: Any) -> list[Any]:
        """The observation's features (see OBS_NAMES), each a float or an array."""
        p = self.params
        ops = ops_for(y[0])
        return [
            y[0] / p.omega_max,
            y[1] / p.V_max,
            y[2] / p.H_T,
            y[3],
            y[4] / p.distance,
            self.distance_to_go(y[4], phase) / p.distance,
            t / self.max_time,
            y[5],
            ops.where(phase == 1, 1.0, 0.0),
            ops.where(phase == 2, 1.0, 0.0),
            ops.where(phase == 3, 1.0, 0.0),
            ops.where(phase == 4, 1.0, 0.0),
        ]

    # -------------------------------------------------------------- one control interval
    def step(self, y: Any, phase: Any, t: Any, rev_err: Any, violation: Any, action: tuple[Any, Any, Any, Any]) -> dict[str, Any]:
        """One control interval. ``action`` = (fuel, bucket, brake, shift), each in [-1, 1].

        Returns a dict with the new ``y, phase, t, rev_err, violation`` and ``reward``, ``terminated``,
        ``truncated`` and the step's diagnostics (see WheelLoaderEnv's info).
        """
        if type(y[0]) is float and self.substeps <= MAX_FLAT_SUBSTEPS:
            # One loader: this method flattened to float arithmetic (same numbers, ~2x faster). It returns
            # None if a substep reached V = 0 and must be cut there: that rare case runs the code below.
            flat = self._flat
            if flat is None or flat[1] is not self.sim._flat:  # new, or the simulator was reconfigured
                flat = self._flatten_step()
            r = flat[0](y, phase, t, rev_err, violation, action)
            if r is not None:
                return r
        return self._step(y, phase, t, rev_err, violation, action)

    def __setattr__(self, name: str, value: Any) -> None:
        # The flattened step bakes in the configuration: assigning any attribute (e.g. a reward
        # curriculum replacing ``reward``) discards it.
        object.__setattr__(self, name, value)
        object.__setattr__(self, "_flat", None)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_flat": None}  # generated code is rebuilt after unpickling, not pickled

    def _flatten_step(self) -> tuple[Any, Any]:
        sim = self.sim
        # Everything _step reads, from this stepper and from its simulator.
        key = repr((
            type(self), self.params, self.reward, self.dt, self.h, self.substeps, self.max_time, self._ab_mid,
            self._ab_half, self._decel_max, type(sim), sim.params, sim._h_stop, sim._tables_py,
        ))
        inputs = (("y", 6), "phase", "t", "rev_err", "violation", ("action", 4))
        step = flatten_cached(key, self._step, *inputs, name="step", speculate=True)
        object.__setattr__(self, "_flat", (step, sim._flattened()))  # (sim's part tells when it goes stale)
        return self._flat

    def _step(self, y: Any, phase: Any, t: Any, rev_err: Any, violation: Any, action: tuple[Any, Any, Any, Any]) -> dict[str, Any]:
        p, rw, sim = self.params, self.reward, self.sim
        ops = ops_for(y[0])
        u_cmd = self.controls(action[0], action[1], action[2])
        rev_pending = rev_err != rev_err  # reversing point not reached yet
        # Shift requests end phases 1 and 3; a machine standing in phase 2 is at its reversing point.
        phase = ops.where(((phase == 1) | (phase == 3)) & (action[3] > 0.0), phase + 1, phase)
        at_rev = (phase == 2) & (y[1] == 0.0)
        rev_err = ops.where(at_rev, y[4] + p.distance, rev_err)
        phase = ops.where(at_rev, 3, phase)
        if isinstance(phase, np.ndarray):
            phase = phase.astype(np.int64)

        phi0 = self.potential(y, phase)
        m_f0 = y[5]
        over = 0.0 * y[0]  # integral of the relative excess over the driver's limits
        worst = 0.0 * y[0]
        stalled = y[0] < p.omega_min
        u_first = None
        for _ in range(self.substeps):
            u = sim.effective_controls(y, phase, u_cmd[0], u_cmd[1], u_cmd[2], self.h)
            u_first = u_first or u
            d = sim.phase_constants(phase)[1]
            y, phase, s_rev, accel = sim.substep(y, phase, u[:3], self.h)
            rev_err = ops.where(s_rev == s_rev, s_rev + p.distance, rev_err)  # NaN != NaN
            # Deceleration limit d dV/dt >= -0.18 g, checked at each substep start (as the OCP checks
            # it at its collocation points).
            decel = ops.fmax(-d * accel - self._decel_max, 0.0) / self._decel_max
            speed = ops.fmax(ops.fmax(y[1], -y[1]) - p.V_max, 0.0) / p.V_max
            excess = decel + speed
            over = over + excess * self.h
            worst = ops.fmax(worst, excess)
            stalled = stalled | (y[0] < p.omega_min)
        t = t + self.dt
        violation = ops.fmax(violation, worst)

        # ---- episode end
        still = ops.fmax(y[3], -y[3]) < STILL_SPEED
        completed = (phase == 4) & (y[1] == 0.0) & still
        off_site = (y[4] < -2.0 * p.distance) | (y[4] > p.distance)
        failed = stalled | off_site
        terminated = completed | failed
        truncated = (t >= self.max_time - 1e-9) & ~terminated

        # ---- reward
        fuel_g = (y[5] - m_f0) * 1000.0
        reward = -(rw.w_fuel * fuel_g / rw.fuel_ref_g + rw.w_time * self.dt / rw.time_ref)
        reward = reward - rw.violation * over
        reward = reward + rw.shaping * (self.potential(y, phase) - phi0)
        rev_abs = ops.fmax(rev_err, -rev_err)
        # The reversing-point error is charged once, in the step that reaches it (NaN until then).
        reward = reward - ops.where(rev_pending & (rev_err == rev_err), rw.target_distance * rev_abs, 0.0)
        end_dist = ops.fmax(y[4], -y[4])
        end_height = ops.fmax(p.H_T - y[2], y[2] - p.H_T)
        reward = reward - ops.where(
            completed, rw.target_distance * end_dist + rw.target_height * end_height, 0.0
        )
        reward = reward - ops.where(failed, rw.failure, 0.0)
        success = completed & (rev_abs <= DISTANCE_TOL) & (end_dist <= DISTANCE_TOL) & (end_height <= HEIGHT_TOL)
        return {
            "y": y, "phase": phase, "t": t, "rev_err": rev_err, "violation": violation,
            "reward": reward, "terminated": terminated, "truncated": truncated,
            "completed": completed, "success": success, "stalled": stalled, "off_site": off_site,
            "u": u_first[:3], "u_mf_torque": u_first[3], "u_ab_pressure": u_first[4], "u_cmd": u_cmd,
            "excess": worst,
        }
