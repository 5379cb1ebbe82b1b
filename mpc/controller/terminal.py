"""The MPC's terminal law: the machine standing at the truck, or a plan used up.

A plan needs a moving machine for its stop step; this serves a plant that stopped before the plan said:
brake, bring the bucket to H_T and hold it, and hold the engine's speed.
"""

from __future__ import annotations

import math

import numpy as np

from wl_env.params import LoaderParams
from wl_env.physics import engine, lift


def terminal_control(x: np.ndarray | None, p: LoaderParams, theta: np.ndarray, lift_gain: float, decel_margin: float,
                     dt: float) -> np.ndarray:
    """[U_mf, U_ab, U_b] for a machine at rest at the truck (x None: the plan is used up, hold still).

    ``theta`` = [accel gain, accel offset] and ``lift_gain`` are the estimated plant
    (:class:`mpc.controller.estimator.ModelErrorEstimator`); the brake decelerates at the limit less
    ``decel_margin`` (fraction) with the rolling resistance helping.
    """
    gain, offset = theta
    a_stop = (1.0 - decel_margin) * p.decel_max * p.g + offset
    u_b = min(max((a_stop * p.M_tot / gain - p.F_roll) * p.r_w, 0.0), p.U_b_max)
    if x is None:
        return np.array([0.0, p.U_ab_bounds[0], u_b])
    omega, _, H, V_b = x[0], x[1], x[2], x[3]
    lo, hi = p.U_ab_bounds
    # Approach H_T on the speed that stops there with 80 % of the lowest deceleration; a bucket already
    # too fast for that brakes with what stops it exactly at H_T (as much as it can).
    gap = p.H_T - H
    v_ref = math.copysign(math.sqrt(2.0 * 0.8 * -lo * abs(gap)), gap)
    u_ab = min(max((max(v_ref, 0.0) - V_b) / dt, lo), hi)
    if V_b > 0.0:
        decel_to_stop = V_b**2 / (2.0 * gap) if gap > 0.0 else math.inf
        if decel_to_stop > 0.8 * -lo:
            u_ab = max(-decel_to_stop, lo)
    load = lift_gain * lift.lift_power(max(V_b, 0.0), u_ab, p) / max(omega, 1.0)
    u_mf = (engine.friction_torque(omega, p) + load) / p.T_ig_per_mg  # hold the engine speed
    return np.array([min(max(u_mf, 0.0), p.U_mf_max), u_ab, u_b])
