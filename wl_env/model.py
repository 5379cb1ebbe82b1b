"""The loader model: the physical components composed into x' = f(x, u).

This is the one model of the project. The simulator evaluates it on floats or numpy arrays, the OCP
and the MPC on CasADi symbols.

* state ``x = [omega (rad/s), V (m/s), H (m), V_b (m/s)]``: engine speed, signed vehicle speed
  (forward > 0), bucket height, bucket vertical speed;
* control ``u = [U_mf (mg/cycle), U_ab (m/s^2), U_b (N m)]``: fuel injection per cylinder and cycle,
  bucket vertical acceleration, service brake torque at the wheels;
* ``gear`` gamma in {-60, 0, +60} and ``direction`` d in {-1, +1} (travel direction of the phase).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from wl_env.params import LoaderParams, resolve
from wl_env.physics import driveline, engine, lift, torque_converter
from wl_env.physics.backend import is_symbolic

STATE_NAMES = ("omega", "V", "H", "V_b")
CONTROL_NAMES = ("U_mf", "U_ab", "U_b")


def derivatives(
    omega: Any, V: Any, H: Any, V_b: Any, U_mf: Any, U_ab: Any, U_b: Any, gear: Any, direction: Any, p: LoaderParams
) -> tuple[Any, Any, Any, Any, Any]:
    """(d omega/dt, dV/dt, dH/dt, dV_b/dt, fuel mass rate kg/s), component-wise (floats, arrays, symbols).

    ``gear`` may be 0 (neutral): the converter is then decoupled, T_p = T_w = 0.
    """
    coupled = abs(gear) / p.gear_ratio  # 1 in gear, 0 in neutral
    phi = torque_converter.speed_ratio(V, omega, gear, p)
    n = engine.speed_krpm(omega)
    n2 = n * n
    xi, kappa = torque_converter.characteristics(phi, p)
    t_pump = xi * n2 * coupled  # = P_trac / omega, eq. (24)
    t_ice = engine.engine_torque(omega, U_mf, p)
    d_omega = (t_ice - t_pump - lift.lift_power(V_b, U_ab, p) / omega) / p.J_ice  # eq. (1)
    d_v = driveline.vehicle_acceleration(driveline.wheel_torque(kappa * n2, gear, p), U_b, direction, p)
    return d_omega, d_v, V_b, U_ab, engine.fuel_mass_rate(omega, U_mf, p)


def estimated_derivatives(x: Any, u: Any, gear: Any, direction: Any, p: LoaderParams,
                          offset: Any = 0.0, gain: Any = 1.0, lift_gain: Any = 1.0) -> tuple[Any, Any, Any, Any, Any]:
    """:func:`derivatives` as a model-error estimate has the plant (the MPC's model of it).

    dV/dt = gain * model + d * offset (gain: model mass / plant mass; offset: an acceleration along the
    travel direction d, e.g. a rolling-resistance error), and the lift draws lift_gain times the model's
    power from the engine (its power is proportional to the payload, eq. (10)).
    """
    d_om, d_v, d_h, d_vb, m_dot = derivatives(x[0], x[1], x[2], x[3], u[0], u[1], u[2], gear, direction, p)
    d_v = gain * d_v + direction * offset
    d_om = d_om - (lift_gain - 1.0) * lift.lift_power(x[3], u[1], p) / (x[0] * p.J_ice)
    return d_om, d_v, d_h, d_vb, m_dot


def governed_injection(omega: Any, V: Any, H: Any, V_b: Any, speed_request: Any, U_ab: Any, gear: Any, direction: Any,
                       p: LoaderParams, tau: Any) -> Any:
    """The fuel injection U_mf (mg, unclipped) an engine-speed governor commands: the one that takes omega
    to ``speed_request`` (rad/s) in ``tau`` seconds under the present load (the converter's pump torque,
    the lift's power under U_ab, the friction). d omega/dt is affine in U_mf (eq. (1), (6)), so this
    inverts the model exactly at the state it is given; the machine then clips it to [0, U_mf,max] and
    the torque curve (:func:`wl_env.step.effective_controls`)."""
    d_omega_unfuelled = derivatives(omega, V, H, V_b, 0.0, U_ab, 0.0, gear, direction, p)[0]
    return p.J_ice * ((speed_request - omega) / tau - d_omega_unfuelled) / p.T_ig_per_mg


def governor_request(omega: Any, V: Any, H: Any, V_b: Any, U_mf: Any, U_ab: Any, gear: Any, direction: Any,
                     p: LoaderParams, tau: Any) -> Any:
    """The inverse of :func:`governed_injection`: the request (rad/s) for which the governor injects U_mf."""
    return omega + tau * derivatives(omega, V, H, V_b, U_mf, U_ab, 0.0, gear, direction, p)[0]


def dynamics(x: Any, u: Any, gear: float, direction: float, params: LoaderParams | dict | None = None) -> Any:
    """x' = f(x, u) for the given gear and travel direction.

    ``x`` has 4 rows and ``u`` 3 (numpy arrays of shape (4,) / (3,) or (4, N) / (3, N), or CasADi column
    vectors). Returns ``[d omega/dt, dV/dt, dH/dt, dV_b/dt]`` of the same kind.
    """
    p = resolve(params)
    _check_gear(gear, direction, p)
    if is_symbolic(x) or is_symbolic(u):
        import casadi as ca

        d = derivatives(x[0], x[1], x[2], x[3], u[0], u[1], u[2], gear, direction, p)
        return ca.vertcat(*d[:4])
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    if x.shape[0] != 4 or u.shape[0] != 3:
        raise ValueError(f"dynamics needs x with 4 rows and u with 3 rows, got shapes {x.shape} and {u.shape}")
    d = derivatives(x[0], x[1], x[2], x[3], u[0], u[1], u[2], gear, direction, p)
    return np.array(np.broadcast_arrays(*d[:4]), dtype=float)


def fuel_rate(x: Any, u: Any, params: LoaderParams | dict | None = None) -> Any:
    """Fuel mass flow (kg/s) of eq. (8) at state x and control u (numpy or CasADi)."""
    p = resolve(params)
    return engine.fuel_mass_rate(x[0], u[0], p)


def outputs(x: Any, u: Any, gear: float, direction: float, params: LoaderParams | dict | None = None) -> dict[str, Any]:
    """Every signal the constraints, the reports and the plots need, for a state x and control u.

    Keys: ``phi`` (TC speed ratio), ``tc_mode`` (1, 2, 3 as Table I; 0 in neutral), ``N_rpm``,
    ``T_ice``, ``T_ice_max`` (N m), ``T_limit_lines`` (list of 3), ``P_cyl`` (Pa), ``V_lift_max`` (m/s),
    ``k`` (k(theta2)), ``P_lift``, ``P_trac``, ``P_engine`` (W), ``T_pump``, ``T_wheel`` (N m),
    ``fuel_rate`` (kg/s), ``dVdt`` (m/s^2), ``domega_dt`` (rad/s^2).
    """
    p = resolve(params)
    _check_gear(gear, direction, p)
    omega, V, H, V_b = x[0], x[1], x[2], x[3]
    U_mf, U_ab, U_b = u[0], u[1], u[2]
    if not (is_symbolic(x) or is_symbolic(u)):
        omega, V, H, V_b, U_mf, U_ab, U_b = (np.asarray(v, dtype=float) for v in (omega, V, H, V_b, U_mf, U_ab, U_b))
    coupled = abs(gear) / p.gear_ratio
    phi = torque_converter.speed_ratio(V, omega, gear, p)
    t_pump = torque_converter.pump_torque(phi, omega, p) * coupled
    t_wheel = driveline.wheel_torque(torque_converter.turbine_torque(phi, omega, p), gear, p)
    t_ice = engine.engine_torque(omega, U_mf, p)
    p_lift = lift.lift_power(V_b, U_ab, p)
    d = derivatives(omega, V, H, V_b, U_mf, U_ab, U_b, gear, direction, p)
    mode = torque_converter.operating_mode(phi) if gear != 0 else 0 * phi
    return {
        "phi": phi,
        "tc_mode": mode,
        "N_rpm": omega * engine.RAD_S_TO_RPM,
        "T_ice": t_ice,
        "T_ice_max": engine.max_engine_torque(omega, p),
        "T_limit_lines": engine.torque_limit_lines(omega, p),
        "P_cyl": lift.cylinder_pressure(H, U_ab, p),
        "V_lift_max": lift.max_lift_speed(H, omega, p),
        "k": lift.k_factor(H, p),
        "P_lift": p_lift,
        "P_trac": t_pump * omega,
        "P_engine": t_ice * omega,
        "T_pump": t_pump,
        "T_wheel": t_wheel,
        "fuel_rate": d[4],
        "dVdt": d[1],
        "domega_dt": d[0],
        "U_mf_max_torque": engine.max_fuel_injection(omega, p),
    }


def _check_gear(gear: Any, direction: Any, p: LoaderParams) -> None:
    if isinstance(gear, (int, float)) and gear not in (-p.gear_ratio, 0.0, p.gear_ratio):
        raise ValueError(f"gear must be one of -{p.gear_ratio:g}, 0, +{p.gear_ratio:g} (gearbox ratio gamma), got {gear!r}")
    if isinstance(direction, (int, float)) and direction not in (-1, 1):
        raise ValueError(f"direction must be -1 (reversing) or +1 (forwarding), got {direction!r}")
