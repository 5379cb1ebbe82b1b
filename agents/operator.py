"""A rule-based operator: what a driver does in the short loading cycle.

Full throttle out of the pile, lift while travelling, brake at the stopping distance so the machine
stops on the mark, and stop the bucket at the target height. With ``braking="tc"`` the driver shifts
to forward gear instead of using the service brakes while reversing, and meters the deceleration with
the throttle, as drivers prefer. It reads only the environment's observation.
"""

from __future__ import annotations

import numpy as np

from wl_env import cycle
from wl_env.params import LoaderParams, resolve


class OperatorPolicy:
    """Rule-based driver for ``WheelLoader-v0`` (acts on single observations or batches).

    ``decel_margin`` is the fraction of the 0.18 g deceleration limit the driver plans with.
    """

    def __init__(self, braking: str = "service", params: LoaderParams | dict | None = None,
                 max_time: float = 40.0, decel_margin: float = 0.85, lift_accel: float = 1.5) -> None:
        self.braking = cycle.check_braking(braking)
        self.params = p = resolve(params)
        if not 0.1 <= decel_margin <= 1.0:
            raise ValueError(f"decel_margin must lie in [0.1, 1], got {decel_margin}")
        self.max_time = max_time
        self.a_plan = decel_margin * p.decel_max * p.g  # m/s^2 the driver brakes with
        self.lift_accel = lift_accel
        self._ab_lo, self._ab_hi = p.U_ab_bounds

    def reset(self) -> None:  # stateless; present for the controller protocol
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if obs.ndim == 2:
            return np.stack([self.act(o) for o in obs])
        p = self.params
        V = obs[1] * p.V_max
        H = obs[2] * p.H_T
        V_b = obs[3]
        to_go = obs[5] * p.distance
        phase = int(np.argmax(obs[8:12])) + 1
        speed = abs(V)
        stop_dist = speed * speed / (2.0 * self.a_plan)

        fuel, brake, shift = 1.0, -1.0, -1.0
        if phase in (1, 3) and stop_dist >= to_go - 0.02 and speed > 0.05:
            shift = 1.0
        if phase == 2 or phase == 4:
            # Deceleration that stops the machine on the mark, capped at the plan.
            a_req = min(speed * speed / (2.0 * max(to_go, 1e-3)), p.decel_max * p.g * 0.98) if speed > 1e-3 else 0.0
            if phase == 4 or self.braking == "service":
                f_brake = p.M_tot * a_req - p.F_roll
                u_b = min(max(f_brake * p.r_w, 0.0), p.U_b_max)
                brake = 2.0 * u_b / p.U_b_max - 1.0
                fuel = 2.0 * 0.45 - 1.0 if phase == 2 else 2.0 * 0.35 - 1.0  # keep the engine up for the lift
            else:
                # TC braking: the converter's braking torque grows with engine speed; meter it with fuel.
                omega = obs[0] * p.omega_max
                a_now_needed = a_req
                fuel = float(np.clip(-1.0 + 2.0 * (0.15 + 0.5 * a_now_needed / (p.decel_max * p.g)), -1, 1))
                if omega < p.omega_min * 1.4:
                    fuel = 0.0
        # Bucket: accelerate up, then decelerate to stop at H_T.
        h_left = p.H_T - H
        if h_left <= 0.0:
            u_ab = self._ab_lo
        elif V_b * V_b / (2.0 * max(h_left, 1e-4)) >= 0.8 * -self._ab_lo:
            u_ab = -V_b * V_b / (2.0 * max(h_left, 1e-4))
        else:
            u_ab = self.lift_accel
        u_ab = min(max(u_ab, self._ab_lo), self._ab_hi)
        a_bucket = 2.0 * (u_ab - self._ab_lo) / (self._ab_hi - self._ab_lo) - 1.0
        return np.array([fuel, a_bucket, brake, shift], dtype=np.float32)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs)


# run_episode lives with the environment; kept importable from here.
from wl_env.rollout import run_episode  # noqa: E402,F401
