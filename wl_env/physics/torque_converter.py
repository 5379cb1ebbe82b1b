"""Torque converter, eqs. (21)-(24) and Table I.

The pump (engine side) and turbine (gearbox side) torques follow the characteristic curves xi(phi) and
kappa(phi), 6th-order polynomials fitted on 0 <= phi <= 1.5. Outside that range each curve continues
linearly with its end value and slope (C1), so gradients stay continuous for the optimizer.
"""

from __future__ import annotations

import functools
from typing import Any

from wl_env.physics.backend import ops_for
from wl_env.physics.engine import speed_krpm

MODE_I, MODE_II, MODE_III = 1, 2, 3  # Table I: phi < 0, 0 <= phi <= 1, phi > 1


def speed_ratio(vehicle_speed: Any, engine_speed: Any, gear: Any, p: Any) -> Any:
    """tc_speed_ratio phi = omega_gb / omega with omega_gb = V * gamma / r_w, eq. (21)."""
    return (vehicle_speed * (gear / p.r_w)) / engine_speed


@functools.lru_cache(maxsize=64)  # a parameter set's constants: computed once, not per call
def polynomial_extension(poly: tuple[float, ...], phi_hi: float) -> tuple[float, float, float, float]:
    """Value and slope of a polynomial at 0 and at phi_hi, for the linear continuations."""
    n = len(poly) - 1
    deriv = tuple(c * (n - i) for i, c in enumerate(poly[:-1]))

    def horner(coeffs: tuple[float, ...], x: float) -> float:
        acc = 0.0
        for c in coeffs:
            acc = acc * x + c
        return acc

    return horner(poly, 0.0), horner(deriv, 0.0), horner(poly, phi_hi), horner(deriv, phi_hi)


def characteristic(phi: Any, poly: tuple[float, ...], phi_hi: float, ext: tuple[float, float, float, float]) -> Any:
    """A TC characteristic curve (N m per krpm^2) with C1 linear continuation outside [0, phi_hi].

    ``ext`` is ``polynomial_extension(poly, phi_hi)`` (cached per parameter set).
    """
    ops = ops_for(phi)
    x = ops.clip(phi, 0.0, phi_hi)
    acc = poly[0]
    for c in poly[1:]:
        acc = acc * x + c
    # Inside the range both corrections vanish; outside, the polynomial is frozen at the end point and
    # the linear term carries on with the end slope.
    return acc + ext[1] * ops.fmin(phi, 0.0) + ext[3] * ops.fmax(phi - phi_hi, 0.0)


def characteristics(phi: Any, p: Any) -> tuple[Any, Any]:
    """(xi(phi), kappa(phi)) together: one clip and one pass over both polynomials (hot path)."""
    ops = ops_for(phi)
    x = ops.clip(phi, 0.0, p.tc_phi_hi)
    below, above = ops.fmin(phi, 0.0), ops.fmax(phi - p.tc_phi_hi, 0.0)
    xs, ks = p.tc_xi_poly, p.tc_kappa_poly
    a, b = xs[0], ks[0]
    for i in range(1, len(xs)):
        a = a * x + xs[i]
        b = b * x + ks[i]
    xe, ke = polynomial_extension(p.tc_xi_poly, p.tc_phi_hi), polynomial_extension(p.tc_kappa_poly, p.tc_phi_hi)
    return a + xe[1] * below + xe[3] * above, b + ke[1] * below + ke[3] * above


def xi(phi: Any, p: Any) -> Any:
    """Pump-torque characteristic xi(phi), N m/krpm^2."""
    return characteristic(phi, p.tc_xi_poly, p.tc_phi_hi, polynomial_extension(p.tc_xi_poly, p.tc_phi_hi))


def kappa(phi: Any, p: Any) -> Any:
    """Turbine-torque characteristic kappa(phi), N m/krpm^2."""
    return characteristic(phi, p.tc_kappa_poly, p.tc_phi_hi, polynomial_extension(p.tc_kappa_poly, p.tc_phi_hi))


def pump_torque(phi: Any, engine_speed: Any, p: Any) -> Any:
    """T_p = xi(phi) N_hat^2, eq. (22): the torque the TC takes from the engine (N m)."""
    n = speed_krpm(engine_speed)
    return xi(phi, p) * (n * n)


def turbine_torque(phi: Any, engine_speed: Any, p: Any) -> Any:
    """T_gb = kappa(phi) N_hat^2, eq. (22): the torque into the gearbox (N m)."""
    n = speed_krpm(engine_speed)
    return kappa(phi, p) * (n * n)


def operating_mode(phi: Any) -> Any:
    """TC mode of Table I: 1 (phi < 0, braking against the motion), 2 (0..1, driving), 3 (phi > 1)."""
    ops = ops_for(phi)
    return ops.where(phi < 0.0, MODE_I, ops.where(phi > 1.0, MODE_III, MODE_II))
