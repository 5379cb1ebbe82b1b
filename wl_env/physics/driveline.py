"""Gearbox, wheels and longitudinal dynamics, eqs. (23), (25)-(28) in the specification's sign form.

``direction`` d is the travel direction of the phase (-1 reversing, +1 forwarding): brakes and rolling
resistance act against it, M_tot dV/dt = T_w / r_w - d (U_b / r_w + F_roll).
"""

from __future__ import annotations

from typing import Any

from wl_env.params import LoaderParams


def wheel_torque(turbine_torque_nm: Any, gear: float, p: LoaderParams) -> Any:
    """T_w = eta_gb gamma T_gb, eq. (23), N m (zero in neutral)."""
    return (p.eta_gb * gear) * turbine_torque_nm


def tractive_force(wheel_torque_nm: Any, p: LoaderParams) -> Any:
    """Driveline force at the ground T_w / r_w, N."""
    return wheel_torque_nm / p.r_w


def vehicle_acceleration(wheel_torque_nm: Any, brake_torque: Any, direction: float, p: LoaderParams) -> Any:
    """dV/dt = (T_w / r_w - d (U_b / r_w + F_roll)) / M_tot, eqs. (25)-(28), m/s^2."""
    return (wheel_torque_nm / p.r_w - direction * (brake_torque / p.r_w + p.F_roll)) / p.M_tot
