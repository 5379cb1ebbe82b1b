"""A rule-based operator: what a driver does in the short loading cycle.

Full throttle out of the pile, lift while travelling, brake at the stopping distance so the machine
stops on the mark, and stop the bucket at the target height. With ``braking="tc"`` the driver shifts
to forward gear instead of using the service brakes while reversing, as drivers prefer: they lift off
the throttle shortly before the braking point (the converter would brake far too hard with the engine
at full speed), shift, and meter the deceleration with the throttle. They also time the lift to run into
the braking, since the pump's load is what brings the engine down for the shift. The driver's "feel" for the machine
is the model itself: the deceleration the converter gives at an engine speed. It reads only the
environment's observation. Its stopping laws are :mod:`wl_env.assist`'s, which WheelLoaderTarget-v2 puts
under a learned driver.
"""

from __future__ import annotations

import numpy as np

from wl_env import cycle
from wl_env.assist import (
    brake_torque,
    braking_point,
    bucket_command,
    lift_done_early,
    stopping_deceleration,
    stopping_distance,
    tc_braking_speed,
)
from wl_env.codec import Codec, real_observations
from wl_env.model import derivatives
from wl_env.params import LoaderParams, Range, is_real_number, resolve
from wl_env.scenario import Scenario, resolve_scenario
from wl_env.step import OMEGA_FLOOR


class OperatorPolicy:
    """Rule-based driver for ``WheelLoader-v1`` (acts on single observations or batches).

    ``decel_margin`` is the fraction of the 0.18 g deceleration limit the driver plans with;
    ``lift_off_time`` (s) is how long before the braking point a TC-braking driver lifts off the throttle.
    """

    def __init__(self, braking: str = "service", params: LoaderParams | dict | None = None,
                 decel_margin: float = 0.85, lift_accel: float = 1.5,
                 lift_off_time: float = 1.2, dt: float = 0.1) -> None:
        self.braking = cycle.check_braking(braking)
        self.params = p = resolve(params)
        # (nan, inf and strings slipped past the comparisons: lift_accel nan never lifted the bucket)
        for name, value, allowed, unit in (("decel_margin", decel_margin, Range(0.1, 1.0), ""),
                                           ("lift_accel", lift_accel, Range(0.0, p.U_ab_bounds[1], lo_open=True),
                                            " m/s^2 (the bucket's upper bound)"),
                                           ("lift_off_time", lift_off_time, Range(0.0, 5.0), " s"),
                                           ("dt", dt, Range(0.01, 1.0), " s")):
            if not (is_real_number(value) and value in allowed):
                raise ValueError(f"{name} must lie in {allowed}{unit}, got {value!r}")
        decel_margin, lift_accel, lift_off_time, dt = map(float, (decel_margin, lift_accel, lift_off_time, dt))
        self.dt = dt
        self.a_limit = p.decel_max * p.g
        self.a_plan = decel_margin * self.a_limit  # m/s^2 the driver brakes with
        self.lift_accel = lift_accel
        self.lift_off_time = lift_off_time
        self._ab_lo, self._ab_hi = p.U_ab_bounds
        self._specs = cycle.phase_specs(braking, p)
        self.codec = Codec(p)

    def reset(self, scenario: Scenario | None = None) -> None:
        """Start a cycle; ``scenario``: drive that cycle (its distances, dump height, payload) from now on."""
        if scenario is not None:
            if not isinstance(scenario, Scenario):  # (a dict or JSON, as the env and the MPC take them)
                scenario = resolve_scenario(scenario, self.braking)
            if scenario.braking != self.braking:
                raise ValueError(f"the operator drives {self.braking} braking; the scenario has {scenario.braking!r}")
            self.params = scenario.params(self.params)
            self.codec = Codec(self.params)

    def act(self, obs: np.ndarray) -> np.ndarray:
        # (real numbers only, checked before any cast: a bool, digit-string or complex observation was read as numbers
        # without a word, a dict was float()'s TypeError)
        obs = real_observations(obs)
        if obs.ndim == 2:
            if len(obs) == 0:
                raise ValueError("obs: a batch of no observation (shape (0, n))")
            return np.stack([self.act(o) for o in obs])
        p = self.params
        o = self.codec.decode_observation(obs)
        omega, V, H, V_b, to_go, phase = o.engine_speed, o.vehicle_speed, o.bucket_height, o.bucket_speed, o.distance_to_go, o.phase
        omega = max(omega, OMEGA_FLOOR)  # (a stalled engine reads 0: the model divides by it)
        speed = abs(V)
        fuel, brake = p.U_mf_max, 0.0
        shift = bool(braking_point(phase, speed, to_go, self.a_plan, self.dt))
        braking_phase = phase + 1 if shift else phase
        if braking_phase in (2, 4):
            a_req = float(stopping_deceleration(speed, to_go, p))  # stops the machine on the mark
            if self._specs[braking_phase - 1].brake_allowed:
                brake = float(brake_torque(a_req, p))
                fuel = (0.45 if braking_phase == 2 else 0.35) * p.U_mf_max  # keep the engine up for the lift
            else:  # TC braking: the throttle sets the engine speed, the engine speed the converter's braking
                fuel = self._tc_throttle(omega, V, H, V_b, a_req, 2)
        elif phase == 1 and self.braking == "tc" and stopping_distance(speed, self.a_plan) + speed * self.lift_off_time >= to_go:
            # ease off before the braking point, to the engine speed at which the shift brakes as planned
            fuel = self._tc_throttle(omega, V, H, V_b, self.a_plan, 1)
        lift = self.lift_accel
        if phase == 1 and self.braking == "tc" and lift_done_early(omega, speed, H, to_go, self.a_plan, p):
            lift = -V_b / self.dt  # hold the bucket: its lift must run into the braking (see lift_done_early)
        u_ab = float(bucket_command(H, V_b, lift, p, self.dt))  # lift, and stop at H_T
        return self.codec.encode_action(fuel, u_ab, brake, shift)

    def _tc_throttle(self, omega: float, V: float, H: float, V_b: float, a_req: float, phase: int) -> float:
        """Injection (mg) that moves the engine towards the speed at which the converter, in forward gear,
        brakes with a_req; the engine's load is that of ``phase`` (the gear it is in now)."""
        p = self.params
        target = float(tc_braking_speed(V, H, V_b, a_req, p, self.braking))
        spec = self._specs[phase - 1]
        # with no injection the engine decelerates by d_omega0 (friction, converter, lift); add the torque
        # that moves it to the target in ~0.2 s
        d_omega0 = derivatives(omega, V, H, V_b, 0.0, 0.0, 0.0, spec.gear, spec.direction, p)[0]
        torque = p.J_ice * ((target - omega) / 0.2 - d_omega0)
        return min(max(torque / p.T_ig_per_mg, 0.0), p.U_mf_max)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs)


# run_episode lives with the environment; kept importable from here.
from wl_env.rollout import run_episode  # noqa: E402,F401
