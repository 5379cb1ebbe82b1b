"""The limits of eq. (31) as named, normalized residuals: ``r <= 0`` holds the limit, ``r > 0`` is the
relative excess over it (0.1 = 10 % over).

One definition for every user: the environment's ``info`` and violation score, the OCP's path
constraints, the grid MPC's rows and the verification of optima. Each function works on floats, numpy
arrays and CasADi symbols (:mod:`wl_env.physics.backend`). A limit with several smooth pieces (the
torque curve's three lines, the pump's two regimes) returns one residual per piece: their maximum is the
relative excess over the limit (``x / min(a, b) - 1 = max(x / a, x / b) - 1`` for positive limits), and
an NLP solver prefers the pieces to a non-smooth ``fmin``.

| name               | limit                                   | residual                       |
|--------------------|-----------------------------------------|--------------------------------|
| torque             | T_ice <= T_ice,max(omega) (3 lines)     | T_ice / line_i - 1             |
| lift_speed         | V_b <= V_lift,max(H, omega) (2 pieces)  | V_b / piece_i - 1              |
| cylinder_pressure  | P_cyl(H, U_ab) <= P_cyl,max             | P_cyl / P_cyl,max - 1          |
| deceleration       | d dV/dt >= -0.18 g                      | -d dV/dt / (0.18 g) - 1        |
| speed              | d V <= V_max                            | d V / V_max - 1                |
| direction          | d V >= 0 (no travel against the phase)  | -d V / V_max                   |
| engine_speed       | omega_min <= omega <= omega_max         | 1 - omega / omega_min, omega / omega_max - 1 |
"""

from __future__ import annotations

from typing import Any

from wl_env.params import LoaderParams
from wl_env.physics import engine, lift
from wl_env.physics.backend import ops_for

NAMES = ("torque", "lift_speed", "cylinder_pressure", "deceleration", "speed", "direction", "engine_speed")
# What the environment scores (``info["violations"]``): the driver's limits. The machine's own (torque curve,
# pump flow, relief pressure) saturate within every step (wl_env.step.rhs), the engine-speed range is the
# governor's and the stall's (it ends the episode), the direction the stiction's: none can be exceeded there.
ENV_NAMES = ("deceleration", "speed")


def torque(engine_speed: Any, fuel_injection: Any, p: LoaderParams) -> list[Any]:
    t_ice = engine.engine_torque(engine_speed, fuel_injection, p)
    return [t_ice / line - 1.0 for line in engine.torque_limit_lines(engine_speed, p)]


def lift_speed(bucket_height: Any, engine_speed: Any, bucket_speed: Any, p: LoaderParams) -> list[Any]:
    return [bucket_speed / v - 1.0 for v in lift.max_lift_speed_pieces(bucket_height, engine_speed, p)]


def cylinder_pressure(bucket_height: Any, bucket_acceleration: Any, p: LoaderParams) -> list[Any]:
    return [lift.cylinder_pressure(bucket_height, bucket_acceleration, p) / p.P_cyl_max - 1.0]


def deceleration(vehicle_acceleration: Any, direction: Any, p: LoaderParams) -> list[Any]:
    return [-direction * vehicle_acceleration / (p.decel_max * p.g) - 1.0]


def speed(vehicle_speed: Any, direction: Any, p: LoaderParams) -> list[Any]:
    return [direction * vehicle_speed / p.V_max - 1.0]


def direction(vehicle_speed: Any, direction: Any, p: LoaderParams) -> list[Any]:
    return [-direction * vehicle_speed / p.V_max]


def engine_speed(engine_speed: Any, p: LoaderParams) -> list[Any]:
    return [1.0 - engine_speed / p.omega_min, engine_speed / p.omega_max - 1.0]


def residuals(x: Any, u: Any, vehicle_acceleration: Any, travel_direction: Any, p: LoaderParams,
              names: tuple[str, ...] = NAMES) -> dict[str, list[Any]]:
    """The residuals ``names`` at state x = [omega, V, H, V_b, ...] under the applied control
    u = [U_mf, U_ab, U_b] with dV/dt = ``vehicle_acceleration``, in a phase of travel direction d."""
    omega, V, H, V_b = x[0], x[1], x[2], x[3]
    every = {
        "torque": lambda: torque(omega, u[0], p),
        "lift_speed": lambda: lift_speed(H, omega, V_b, p),
        "cylinder_pressure": lambda: cylinder_pressure(H, u[1], p),
        "deceleration": lambda: deceleration(vehicle_acceleration, travel_direction, p),
        "speed": lambda: speed(V, travel_direction, p),
        "direction": lambda: direction(V, travel_direction, p),
        "engine_speed": lambda: engine_speed(omega, p),
    }
    return {name: every[name]() for name in names}


def excess(rows: list[Any]) -> Any:
    """The relative excess over a limit from its residuals: max(0, max(rows)) (float, array or symbol)."""
    ops = ops_for(rows[0])
    worst = 0.0 * rows[0]
    for r in rows:
        worst = ops.fmax(worst, r)
    return worst


def worst(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Per name, the larger of two excess records (for a running maximum over a step or an episode)."""
    return {k: ops_for(a[k], b[k]).fmax(a[k], b[k]) for k in a}
