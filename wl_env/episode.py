"""The cycle as an episode: actions -> controls, phase changes, reward, termination, observation.

Written once for one loader (Python floats) and for a batch (numpy arrays), like the simulator under
it, so that ``WheelLoaderEnv`` and ``WheelLoaderVectorEnv`` compute the same numbers. For one loader,
:meth:`CycleStepper.step` runs itself flattened to straight-line float code (:mod:`wl_env.physics.flatten`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from wl_env import cycle, limits
from wl_env.codec import FUEL_ACTIONS, Codec
from wl_env.model import governed_injection, governor_request
from wl_env.params import LoaderParams, is_finite, plain, shown
from wl_env.physics import torque_converter
from wl_env.physics.backend import ops_for
from wl_env.physics.flatten import Flattened, config_key, flatten_cached
from wl_env.simulator import Simulator
from wl_env.step import OMEGA_FLOOR

# Tolerances of the end targets (the project's acceptance figures: 5 cm in distance, 2 cm in height).
DISTANCE_TOL = 0.05  # m
HEIGHT_TOL = 0.02  # m
STILL_SPEED = 1e-6  # m/s: the bucket counts as still below this

# The flattened step unrolls the substeps (~150 lines of code each); beyond this many it is not worth it.
MAX_FLAT_SUBSTEPS = 8
# Flattening takes ~40 ms, some 25 episodes' worth of the time it saves: a configuration is flattened once
# it has run this many steps (an env drawing a new scenario every episode never pays for it).
FLATTEN_AFTER_STEPS = 300


MAX_REWARD_WEIGHT = 1e6  # each term of a step's reward stays finite in float32 under any weight up to this
# the references the fuel (g) and time (s) terms divide by: time_ref 5e-324 made the first reward -inf (1e-300: -5e298,
# -inf in float32); down to this, a term under the largest weight stays far inside float32
MIN_REWARD_REF = 1e-3


@dataclass(frozen=True)
class RewardConfig:
    """Reward weights. Per step: -(w_fuel * fuel/fuel_ref_g + w_time * dt/time_ref) - penalties + shaping.

    ``w_fuel`` and ``w_time`` trace the fuel-time trade-off (the paper's W1, W2); the references make
    both terms about 1 over a cycle. Penalties: ``violation`` per second and per unit of relative excess
    over each limit of eq. (31) within the step (:data:`wl_env.limits.ENV_NAMES`); ``target_distance`` per metre of error
    at the reversing point and at the end; ``target_height`` per metre of bucket-height error at the end;
    ``failure`` once for an engine stall or leaving the site. ``shaping`` scales a potential-based term
    (progress along the 13.2 m path and the lift), which leaves the optimal policy unchanged. ``late``
    (``WheelLoaderTarget-v0``, an episode with a target cycle time T): per unit of (t - T) / T past the target,
    charged as it accrues.
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
    # WheelLoaderTarget, an episode with a target cycle time T: per unit of lateness (t - T) / T, as it accrues
    late: float = 10.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = plain(getattr(self, f.name))
            object.__setattr__(self, f.name, v)  # (a numpy scalar kept as the Python number it holds)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and is_finite(v)):
                raise ValueError(f"RewardConfig.{f.name} must be a finite number, got {shown(v)}")
            lo = MIN_REWARD_REF if f.name in ("fuel_ref_g", "time_ref") else 0
            if not lo <= v <= MAX_REWARD_WEIGHT:  # (1e308 passed as finite and made the first reward -inf)
                raise ValueError(f"RewardConfig.{f.name} must lie in [{lo:g}, {MAX_REWARD_WEIGHT:g}], got {shown(v)}")


MAX_EPISODE_TIME = 3600.0  # s: a cycle takes 8-25 s; an hour bounds an episode's work (and its arrays)
# s: the shortest control interval (5e-324 s never moved the clock, t + dt == t, and the plan env at 1e-7 s drove
# 10^8 steps per plan: neither ever ended)
MIN_DT = 1e-3


def check_control_interval(dt: Any) -> float:
    """``dt`` (s) as a float if it lies in [MIN_DT, 1] (numpy's numbers too), else ValueError naming it."""
    dt = plain(dt)
    if isinstance(dt, bool) or not (isinstance(dt, (int, float)) and is_finite(dt) and MIN_DT <= dt <= 1.0):
        raise ValueError(f"dt (the control interval) must lie in [{MIN_DT:g}, 1] s, got {shown(dt)}")
    return float(dt)


# A state past these multiples of the machine's top engine speed (the observation space ends at 1.5x) and top
# speed in gear did not come from the physics but from a fixed-step RK4 made unstable by the parameters
# (eta_lift 0.01: 8865 rad/s after one step, 6.8e14 after two)
DIVERGED_OMEGA, DIVERGED_SPEED = 2.0, 2.0


class IntegrationDiverged(RuntimeError):
    """The step's fixed-step integration blew up: the parameters make the dynamics too fast for its substeps."""


class CycleStepper(Flattened):
    """Advances loaders by one control interval of the cycle. State (floats or arrays of shape (N,)):

    ``y = (omega, V, H, V_b, s, m_f)``, ``phase`` (1..4), ``t`` (s), ``rev_err`` (signed error of the
    reversing point, m; NaN until reached) and ``violation`` (the largest relative excess over the
    limits so far, :data:`wl_env.limits.ENV_NAMES`, checked within every substep).
    """

    _steps_unflattened = 0  # (not configuration: flatten.config_key leaves it out)

    def __init__(
        self,
        params: LoaderParams,
        braking: str,
        dt: float,
        substeps: int,
        max_time: float,
        reward: RewardConfig,
        observe_scenario: bool = False,
        fuel_action: str = "injection",
    ) -> None:
        if not isinstance(fuel_action, str) or fuel_action not in FUEL_ACTIONS:  # (an array: "ambiguous")
            raise ValueError(f"fuel_action must be one of {FUEL_ACTIONS}, got {shown(fuel_action)}")
        dt, substeps, max_time = check_control_interval(dt), plain(substeps), plain(max_time)
        if isinstance(substeps, bool) or not (isinstance(substeps, int) and 1 <= substeps <= 1000):
            raise ValueError(f"substeps must be an integer in [1, 1000], got {shown(substeps)}")
        if isinstance(max_time, bool) or not (isinstance(max_time, (int, float)) and is_finite(max_time)
                                              and 5 * dt <= max_time <= MAX_EPISODE_TIME):
            raise ValueError(f"max_time must be a number of seconds in [5 dt, {MAX_EPISODE_TIME:g}], got {shown(max_time)}")
        self.params = params
        self.omega_diverged = DIVERGED_OMEGA * params.omega_max
        self.speed_diverged = DIVERGED_SPEED * max(params.V_max, params.omega_max * params.r_w / params.gear_ratio)
        self.braking = cycle.check_braking(braking)
        self.sim = Simulator(params, braking)
        self.dt = float(dt)
        self.substeps = substeps
        self.h = self.dt / substeps
        self.max_time = float(max_time)
        self.reward = reward
        self.codec = Codec(params, observe_scenario)
        self.fuel_action = fuel_action

    # -------------------------------------------------------------- progress
    def potential(self, y: Any, phase: Any) -> Any:
        """Progress potential: minus the path still to go (per mean leg length) and the height still to lift
        (per height to lift)."""
        p = self.params
        ops = ops_for(y[4])
        to_go = self.codec.distance_to_go(y[4], phase)
        path_left = to_go + ops.where(phase <= 2, p.forward_distance, 0.0)
        lift_left = ops.fmax(p.H_T - y[2], 0.0) / (p.H_T - p.H_0)
        return -(path_left / (0.5 * (p.reverse_distance + p.forward_distance)) + lift_left)

    # -------------------------------------------------------------- one control interval
    def step(self, y: Any, phase: Any, t: Any, rev_err: Any, violation: Any, action: tuple[Any, Any, Any, Any]) -> dict[str, Any]:
        """One control interval. ``action`` = (fuel, bucket, brake, shift), each in [-1, 1].

        Returns a dict with the new ``y, phase, t, rev_err, violation`` and ``reward``, ``terminated``,
        ``truncated`` and the step's diagnostics (see WheelLoaderEnv's info).
        """
        if type(y[0]) is float and self.substeps <= MAX_FLAT_SUBSTEPS:
            # One loader: this method flattened to float arithmetic (same numbers, ~2x faster), once for
            # substeps that run through and once for a substep cut at V = 0. Each returns None where its
            # speculation fails; several substeps that differ in that run the code below.
            flat = self._flat
            if flat is None or flat[2] is not self.sim._flat:  # new, or the simulator was reconfigured
                if self._steps_unflattened < FLATTEN_AFTER_STEPS:
                    object.__setattr__(self, "_steps_unflattened", self._steps_unflattened + 1)
                    return self._step(y, phase, t, rev_err, violation, action)
                flat = self._flatten_step()
            r = flat[0](y, phase, t, rev_err, violation, action)
            if r is None:
                r = flat[1](y, phase, t, rev_err, violation, action)
            if r is not None:
                return r
        return self._step(y, phase, t, rev_err, violation, action)

    def diverged(self, y: Any, ignore: Any = None) -> bool:
        """The state ``y`` after a step lies past what the physics reaches (DIVERGED_OMEGA, DIVERGED_SPEED; NaN
        too): the envs raise :meth:`divergence` then. (They compare inline, as floats: the single env's step
        takes ~20 us, and a call more cost 2-3 % of it.) ``ignore``: a mask of loaders whose step is discarded
        (the vector env's autoresets)."""
        omega, V = y[0], y[1]
        if type(omega) is float:
            return not (omega <= self.omega_diverged and -self.speed_diverged <= V <= self.speed_diverged)
        ok = (omega <= self.omega_diverged) & (np.abs(V) <= self.speed_diverged)
        return not np.all(ok if ignore is None else ok | ignore)

    def divergence(self, y: Any, t: Any) -> IntegrationDiverged:
        return IntegrationDiverged(
            f"the integration diverged in the step from t = {float(np.max(t)):.1f} s (engine speed up to "
            f"{float(np.max(y[0])):.4g} rad/s against omega_max {self.params.omega_max:g}, vehicle speed up to "
            f"{float(np.max(np.abs(y[1]))):.4g} m/s): these parameters make the dynamics too fast for {self.substeps} "
            f"RK4 substep(s) in {self.dt:g} s; raise substeps, or check the parameters (eta_lift, J_ice, "
            f"gear_ratio, ...)")

    def _flatten_step(self) -> tuple[Any, Any, Any]:
        inputs = (("y", 6), "phase", "t", "rev_err", "violation", ("action", 4))
        key = config_key(self)
        through = flatten_cached(f"{key} through", self._step, *inputs, name="step", speculate=False)
        cut = flatten_cached(f"{key} cut", self._step, *inputs, name="step_cut", speculate=True)
        object.__setattr__(self, "_flat", (through, cut, self.sim._flattened()))  # (sim's part tells when it goes stale)
        return self._flat

    def _interval_phase(self, y: Any, phase: Any, shift: Any) -> tuple[Any, Any]:
        """The phase an interval runs in, and whether the machine stands at its reversing point: shift
        requests end phases 1 and 3; a machine standing in phase 2 is at its reversing point (phase 3)."""
        ops = ops_for(y[0])
        phase = ops.where(((phase == 1) | (phase == 3)) & (shift > 0.0), phase + 1, phase)
        at_rev = (phase == 2) & (y[1] == 0.0)
        return ops.where(at_rev, 3, phase), at_rev

    def _governor_view(self, y: Any, phase: Any, u_ab: Any) -> tuple[Any, ...]:
        """What the engine's governor sees at an interval's start, as :func:`wl_env.model.governed_injection`
        takes it after the state's four: (U_ab, gear, direction, params, tau), where phase is the one after
        the shift request. It reaches the request within the interval (deadbeat: tau = dt)."""
        ops = ops_for(y[0])
        gear, d = self.sim.phase_constants(phase)[:2]
        return (ops.fmax(y[0], OMEGA_FLOOR), y[1], y[2], y[3], ops.clip(u_ab, *self.params.U_ab_bounds), gear, d,
                self.params, self.dt)

    def translate_fuel_action(self, y: Any, phase: Any, action: Any, to: str) -> Any:
        """Action 0 of one fuel action's space in the other's, at this state: ``to="engine_speed"`` the
        request for which the governor injects what an injection action asks (an expert of the injection
        driving the governed env), ``to="injection"`` the injection the governor makes of a request.
        Clipped to [-1, 1]. ``action`` is the 4-vector (its shift request and U_ab count)."""
        if to not in FUEL_ACTIONS:
            raise ValueError(f"to must be one of {FUEL_ACTIONS}, got {shown(to)}")
        c = self.codec
        a = [min(max(float(v), -1.0), 1.0) for v in action]
        y = [float(v) for v in y[:4]]
        u_mf, u_ab, _ = c.decode_action(a[0], a[1], a[2])
        view = self._governor_view(y, self._interval_phase(y, phase, a[3])[0], u_ab)
        if to == "engine_speed":
            return float(c.encode_speed_request(governor_request(*view[:4], u_mf, *view[4:])))
        return float(c.encode_action(governed_injection(*view[:4], c.decode_speed_request(a[0]), *view[4:]), u_ab, 0.0,
                                     False)[0])

    def _step(self, y: Any, phase: Any, t: Any, rev_err: Any, violation: Any, action: tuple[Any, Any, Any, Any]) -> dict[str, Any]:
        p, rw, sim = self.params, self.reward, self.sim
        ops = ops_for(y[0])
        action = tuple(ops.clip(action[i], -1.0, 1.0) for i in range(4))  # values outside [-1, 1] are clipped
        u_cmd = self.codec.decode_action(action[0], action[1], action[2])
        rev_pending = ops.isnan(rev_err)  # reversing point not reached yet
        phase, at_rev = self._interval_phase(y, phase, action[3])
        rev_err = ops.where(at_rev, y[4] + p.reverse_distance, rev_err)
        if isinstance(phase, np.ndarray):
            phase = phase.astype(np.int64)
        if self.fuel_action == "engine_speed":
            view = self._governor_view(y, phase, u_cmd[1])
            u_cmd = (governed_injection(*view[:4], self.codec.decode_speed_request(action[0]), *view[4:]), u_cmd[1], u_cmd[2])

        phi0 = self.potential(y, phase)
        m_f0 = y[5]
        over = 0.0 * y[0]  # integral of the relative excess over the limits
        worst = {name: 0.0 * y[0] for name in limits.ENV_NAMES}
        stalled = y[0] < p.omega_min
        u_first = None
        for _ in range(self.substeps):
            u = sim.effective_controls(y, phase, u_cmd[0], u_cmd[1], u_cmd[2], self.h)
            u_first = u_first or u
            y, phase, s_rev, excess = sim.substep(y, phase, u[:3], self.h)
            y = (ops.fmax(y[0], 0.0), *y[1:])  # a stalled engine stops at 0 (it does not turn backwards)
            rev_err = ops.where(ops.isnan(s_rev), rev_err, s_rev + p.reverse_distance)
            # Every limit at every RK4 stage and at the substep's end (wl_env.step.within_step_excess).
            total = 0.0 * y[0]
            for name in limits.ENV_NAMES:
                total = total + excess[name]
            over = over + total * self.h
            worst = limits.worst(worst, excess)
            stalled = stalled | (y[0] < p.omega_min)
        t = t + self.dt
        step_excess = limits.excess(list(worst.values()))
        violation = ops.fmax(violation, step_excess)

        # ---- episode end
        still = abs(y[3]) < STILL_SPEED
        completed = (phase == 4) & (y[1] == 0.0) & still
        # twice the reversing distance behind the pile, or a reversing distance past the truck
        off_site = (y[4] < -2.0 * p.reverse_distance) | (y[4] > p.final_position + p.reverse_distance)
        failed = stalled | off_site
        terminated = completed | failed
        truncated = (t >= self.max_time - 1e-9) & ~terminated

        # ---- reward
        fuel_g = (y[5] - m_f0) * 1000.0
        reward = -(rw.w_fuel * fuel_g / rw.fuel_ref_g + rw.w_time * self.dt / rw.time_ref)
        reward = reward - rw.violation * over
        reward = reward + rw.shaping * (self.potential(y, phase) - phi0)
        rev_abs = abs(rev_err)
        # The reversing-point error is charged once, in the step that reaches it (NaN until then).
        reward = reward - ops.where(rev_pending & ~ops.isnan(rev_err), rw.target_distance * rev_abs, 0.0)
        end_dist = abs(y[4] - p.final_position)
        end_height = abs(p.H_T - y[2])
        reward = reward - ops.where(
            completed, rw.target_distance * end_dist + rw.target_height * end_height, 0.0
        )
        reward = reward - ops.where(failed, rw.failure, 0.0)
        # (a stall is a failure, also where the machine stands at the truck: the cycle counted as a success before)
        success = completed & ~failed & (rev_abs <= DISTANCE_TOL) & (end_dist <= DISTANCE_TOL) & (end_height <= HEIGHT_TOL)
        # what the machine made of the commands (the first substep's saturations), and its converter now
        u_mf, u_ab, u_b, u_mf_torque, u_ab_pressure = u_first
        cmd_mf, cmd_ab = ops.clip(u_cmd[0], 0.0, p.U_mf_max), ops.clip(u_cmd[1], *p.U_ab_bounds)
        gear = sim.phase_constants(phase)[0]
        phi = torque_converter.speed_ratio(y[1], ops.fmax(y[0], OMEGA_FLOOR), gear, p)  # (a stalled engine: 0)
        return {
            "y": y, "phase": phase, "t": t, "rev_err": rev_err, "violation": violation,
            "reward": reward, "terminated": terminated, "truncated": truncated,
            "completed": completed, "success": success, "stalled": stalled, "off_site": off_site,
            "u": (u_mf, u_ab, u_b),
            "excess": step_excess, **{f"excess_{name}": v for name, v in worst.items()},  # (flat: no nested dict)
            "obs": self.codec.encode_observation(y, phase, t),
            "gear": gear, "phi": phi, "tc_mode": ops.where(gear == 0.0, 0, torque_converter.operating_mode(phi)),
            "saturations": {
                "torque_limit": cmd_mf > u_mf_torque + 1e-9,
                "governor": u_mf < ops.fmin(cmd_mf, u_mf_torque) - 1e-9,
                "relief_pressure": cmd_ab > u_ab_pressure + 1e-9,
                "pump_flow": u_ab < ops.fmin(cmd_ab, u_ab_pressure) - 1e-9,
            },
        }
