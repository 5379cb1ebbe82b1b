"""Diesel engine: indicated torque, friction, fuel rate and the torque limit, eqs. (5)-(8) and (31).

Engine speed ``engine_speed`` is omega in rad/s; the friction map and the torque-limit lines use the
speed in rpm (N) or krpm (N_hat = N/1000) as the specification says.
"""

from __future__ import annotations

import math
from typing import Any

from wl_env.params import LoaderParams
from wl_env.physics.backend import ops_for

RAD_S_TO_RPM = 30.0 / math.pi


def speed_krpm(engine_speed: Any) -> Any:
    """N_hat = N / 1000 with N = omega * 30 / pi (krpm)."""
    return engine_speed * (RAD_S_TO_RPM / 1000.0)


def indicated_torque(fuel_injection: Any, p: LoaderParams) -> Any:
    """T_ig of eq. (6), N m, from the injected fuel U_mf in mg per cylinder and cycle."""
    return p.T_ig_per_mg * fuel_injection


def friction_torque(engine_speed: Any, p: LoaderParams) -> Any:
    """T_fric of eq. (7), N m. The friction coefficients are for N_hat in krpm (MODEL.md)."""
    n = speed_krpm(engine_speed)
    c1, c2, c3 = p.c_fr
    return p._derived["T_fric_scale"] * ((c1 * n + c2) * n + c3)


def engine_torque(engine_speed: Any, fuel_injection: Any, p: LoaderParams) -> Any:
    """Net engine torque T_ice = T_ig - T_fric, eq. (5), N m."""
    return indicated_torque(fuel_injection, p) - friction_torque(engine_speed, p)


def fuel_mass_rate(engine_speed: Any, fuel_injection: Any, p: LoaderParams) -> Any:
    """Fuel mass flow of eq. (8), kg/s: U_mf (mg) per cylinder and 4-stroke cycle (4 pi rad)."""
    return p._derived["fuel_per_mg_rad"] * fuel_injection * engine_speed


def torque_limit_lines(engine_speed: Any, p: LoaderParams) -> list[Any]:
    """The three linear upper bounds a_i + b_i * N (N in rpm) on T_ice, Fig. 7 / eq. (31), N m."""
    n_rpm = engine_speed * RAD_S_TO_RPM
    return [a + b * n_rpm for a, b in p.T_max_lines]


def max_engine_torque(engine_speed: Any, p: LoaderParams) -> Any:
    """T_ice,max(omega): the lowest of the three torque-limit lines, N m."""
    ops = ops_for(engine_speed)
    l1, l2, l3 = torque_limit_lines(engine_speed, p)
    return ops.fmin(ops.fmin(l1, l2), l3)


def max_fuel_injection(engine_speed: Any, p: LoaderParams) -> Any:
    """The largest U_mf (mg) that keeps T_ice within both the torque limit and U_mf,max."""
    ops = ops_for(engine_speed)
    u_torque = (max_engine_torque(engine_speed, p) + friction_torque(engine_speed, p)) / p.T_ig_per_mg
    return ops.clip(u_torque, 0.0, p.U_mf_max)


def engine_acceleration(engine_speed: Any, engine_torque_nm: Any, load_power: Any, p: LoaderParams) -> Any:
    """d omega/dt = (T_ice - P_load / omega) / J_ice, eq. (1), rad/s^2."""
    return (engine_torque_nm - load_power / engine_speed) / p.J_ice
