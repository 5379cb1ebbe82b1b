"""Lift system: boom geometry, k(theta2), cylinder pressure, pump-limited lift speed, lift power.

Eqs. (9)-(20) with the specification's reading of the geometry: the boom pivots at height G, the lift
cylinder runs from the frame point (x_c, y_c) (relative to the pivot) to the boom point at distance r1,
the bucket sits at r = r1 + r2. The cylinder's moment arm about the pivot is dL_cyl/dtheta2 (virtual
work). sin(theta2) = (H - G)/r, so everything is algebraic in H: no trigonometric calls.
"""

from __future__ import annotations

import math
from typing import Any

from wl_env.params import LoaderParams
from wl_env.physics.backend import ops_for

# Mechanical end stop of the boom at sin(theta2) = 0.98 (H = G + 0.98 r = 5.14 m with the defaults).
# The specification gives no stop; without one the geometry degenerates at the vertical boom (cos = 0).
BOOM_SIN_MAX = 0.98


def max_bucket_height(p: LoaderParams) -> float:
    """Height of the boom's end stop (m)."""
    return p.G + BOOM_SIN_MAX * p.r


def boom_angle_sin_cos(bucket_height: Any, p: LoaderParams) -> tuple[Any, Any]:
    """sin and cos of the boom angle theta2 = asin((H - G)/r), eq. (11); H clipped to the end stops."""
    ops = ops_for(bucket_height)
    s = ops.clip((bucket_height - p.G) / p.r, -BOOM_SIN_MAX, BOOM_SIN_MAX)
    return s, ops.sqrt(1.0 - s * s)


def boom_angle(bucket_height: Any, p: LoaderParams) -> Any:
    """theta2 in rad (for plots and reports; the model itself works with sin and cos)."""
    import numpy as np

    s, _ = boom_angle_sin_cos(bucket_height, p)
    try:
        return np.arcsin(s)
    except TypeError:  # casadi symbol
        import casadi as ca

        return ca.asin(s)


def cylinder_length_and_arm(bucket_height: Any, p: LoaderParams) -> tuple[Any, Any]:
    """L_cyl of eq. (12) and the moment arm dL_cyl/dtheta2 = r1 (x_c sin - y_c cos) / L_cyl (m)."""
    ops = ops_for(bucket_height)
    s, c = boom_angle_sin_cos(bucket_height, p)
    dx = p.r1 * c - p.x_c
    dy = p.r1 * s - p.y_c
    length = ops.sqrt(dx * dx + dy * dy)
    arm = p.r1 * (p.x_c * s - p.y_c * c) / length
    return length, arm


def k_factor(bucket_height: Any, p: LoaderParams) -> Any:
    """k(theta2) = d(bucket height)/d(cylinder length) = r cos(theta2) / (dL_cyl/dtheta2), eq. (13)."""
    _, c = boom_angle_sin_cos(bucket_height, p)
    _, arm = cylinder_length_and_arm(bucket_height, p)
    return p.r * c / arm


def load_force(bucket_acceleration: Any, p: LoaderParams) -> Any:
    """F_load = M_load (g + U_ab), eq. (9), N."""
    return p.M_load * (p.g + bucket_acceleration)


def lift_power(bucket_speed: Any, bucket_acceleration: Any, p: LoaderParams) -> Any:
    """P_lift = F_load V_b / eta_lift, eq. (10), W (drawn from the engine)."""
    return load_force(bucket_acceleration, p) * bucket_speed / p.eta_lift


def _pressure_coefficients(bucket_height: Any, p: LoaderParams) -> tuple[Any, Any]:
    """P_cyl is affine in U_ab: P_cyl = p0 + p1 * U_ab (Pa, Pa per m/s^2), from eqs. (14)-(16)."""
    _, c = boom_angle_sin_cos(bucket_height, p)
    _, arm = cylinder_length_and_arm(bucket_height, p)
    r_cos = p.r * c
    # F_p * arm = I_boom * U_ab / (r cos) + M_load (g + U_ab) r cos + M_boom (g + U_ab) (r/2) cos
    mass_moment = (p.M_load + 0.5 * p.M_boom) * r_cos
    scale = 1.0 / (arm * p.A_piston)
    p0 = mass_moment * p.g * scale
    p1 = (p.I_boom / r_cos + mass_moment) * scale
    return p0, p1


def cylinder_pressure(bucket_height: Any, bucket_acceleration: Any, p: LoaderParams) -> Any:
    """Lift cylinder pressure P_cyl = F_p / A_piston, eqs. (14)-(17), Pa."""
    p0, p1 = _pressure_coefficients(bucket_height, p)
    return p0 + p1 * bucket_acceleration


def max_bucket_acceleration_for_pressure(bucket_height: Any, p: LoaderParams) -> Any:
    """The largest U_ab that keeps P_cyl <= P_cyl,max (the relief valve's limit), m/s^2."""
    p0, p1 = _pressure_coefficients(bucket_height, p)
    return (p.P_cyl_max - p0) / p1


def lift_limits(bucket_height: Any, engine_speed: Any, p: LoaderParams) -> tuple[Any, Any]:
    """(largest U_ab within the relief pressure, V_lift,max): both limits from one geometry evaluation."""
    ops = ops_for(bucket_height)
    s, c = boom_angle_sin_cos(bucket_height, p)
    dx = p.r1 * c - p.x_c
    dy = p.r1 * s - p.y_c
    arm = p.r1 * (p.x_c * s - p.y_c * c) / ops.sqrt(dx * dx + dy * dy)
    r_cos = p.r * c
    mass_moment = (p.M_load + 0.5 * p.M_boom) * r_cos
    u_ab_max = (p.P_cyl_max * arm * p.A_piston - mass_moment * p.g) / (p.I_boom / r_cos + mass_moment)
    v_lift_max = (r_cos / arm) * pump_flow(engine_speed, p) * (p.eta_cyl / p.A_piston)
    return u_ab_max, v_lift_max


def pump_flow(engine_speed: Any, p: LoaderParams) -> Any:
    """Q_pump = min(omega, omega_sat)/(2 pi) D_pump eta_vol, eq. (18), m^3/s (pump speed saturates)."""
    ops = ops_for(engine_speed)
    return ops.fmin(engine_speed, p.pump_speed_sat) * (p.D_pump * p.eta_vol / (2.0 * math.pi))


def max_lift_speed(bucket_height: Any, engine_speed: Any, p: LoaderParams) -> Any:
    """V_lift,max = k(theta2) Q_pump eta_cyl / A_piston, eqs. (19)-(20), m/s."""
    return k_factor(bucket_height, p) * pump_flow(engine_speed, p) * (p.eta_cyl / p.A_piston)


def max_lift_speed_pieces(bucket_height: Any, engine_speed: Any, p: LoaderParams) -> tuple[Any, Any]:
    """The two smooth bounds whose minimum is V_lift,max: with the pump at engine speed and saturated.

    ``V_b <= min(a, b)`` is the same as ``V_b <= a and V_b <= b``, which an NLP solver prefers to fmin.
    """
    gain = k_factor(bucket_height, p) * (p.D_pump * p.eta_vol * p.eta_cyl / (2.0 * math.pi * p.A_piston))
    return gain * engine_speed, gain * p.pump_speed_sat
