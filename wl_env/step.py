"""THE control step of the loader: the machine's saturations, RK4 substeps with stiction, the cut at V = 0,
and the driver's limits checked within it.

Written once, generic over the number kind (Python floats, numpy arrays, CasADi symbols, the
flattener's recording floats; :mod:`wl_env.physics.backend`). The simulator (:mod:`wl_env.simulator`)
composes these functions with the phase logic on numbers; the MPC's grid model
(:mod:`mpc.controller.grid`) composes the same functions on CasADi symbols, so that a plan is what the
environment does.

The continuous state is the tuple ``y = (omega, V, H, V_b, s, m_f)``: the model's four states, the
travelled position s (m) and the fuel used m_f (kg). A substep holds the *effective* controls
``u = (U_mf, U_ab, U_b)`` constant over one classical RK4 step.

``est`` (optional, the MPC's estimate of the plant) is ``(accel offset m/s^2, accel gain, lift gain)``
(see :func:`wl_env.model.estimated_derivatives`); None is the model itself.
"""

from __future__ import annotations

from typing import Any

from wl_env import limits
from wl_env.model import derivatives, estimated_derivatives
from wl_env.params import LoaderParams
from wl_env.physics import engine, lift, torque_converter
from wl_env.physics.backend import is_symbolic, ops_for

# Engine speed floor used inside the right-hand side only: keeps P_load/omega finite if an engine
# stalls within a substep (the environment ends the episode at omega_min, far above this).
OMEGA_FLOOR = 1.0

State = tuple[Any, Any, Any, Any, Any, Any]  # omega, V, H, V_b, s, m_f
Stage = tuple[State, State]  # (the point an RK4 stage is evaluated at, the derivative there)


# ---------------------------------------------------------------------------------------- saturation
def effective_controls(y: State, gear: Any, brake: Any, u_mf: Any, u_ab: Any, u_b: Any, h: Any,
                       p: LoaderParams) -> tuple[Any, Any, Any, Any, Any]:
    """The controls the machine applies over a substep of length h (s) from y, for the commanded ones.

    The injection range and the torque curve, the governor at omega_max, the relief pressure, the pump
    flow (V_b <= V_lift,max) and the boom's end stop, no lowering of the bucket (V_b >= 0), the brake
    range and brakes only where the phase allows them (``brake`` 0/1). Returns ``(U_mf, U_ab, U_b,
    U_mf limit of the torque curve, U_ab limit of the relief pressure)``; the last two let a caller tell
    which saturation was active.
    """
    omega, V, H, V_b = y[0], y[1], y[2], y[3]
    ops = ops_for(omega)
    lo, hi = p.U_ab_bounds
    u_ab = ops.clip(u_ab, lo, hi)
    u_ab_pressure, v_lift_max = lift.lift_limits(H, omega, p)
    u_ab = ops.fmin(u_ab, u_ab_pressure)  # relief valve
    # Pump flow, and the boom's end stop: V_b at most what reaches the stop within the substep.
    v_cap = ops.fmin(v_lift_max, ops.fmax(lift.max_bucket_height(p) - H, 0.0) / h)
    u_ab = ops.fmin(u_ab, (v_cap - V_b) / h)
    u_ab = ops.fmax(u_ab, -V_b / h)  # the bucket is not lowered in this cycle
    u_mf_torque = engine.max_fuel_injection(omega, p)
    u_mf = ops.clip(u_mf, 0.0, u_mf_torque)  # injection range, torque limit
    # Governor: at most the injection that brings omega to omega_max by the end of the substep. (The loads at
    # OMEGA_FLOOR as in rhs: an engine that stalled to 0 within a step divided by zero here, where the
    # episode ends on the stall; the same values everywhere above it.)
    omega_load = ops.fmax(omega, OMEGA_FLOOR)
    phi = torque_converter.speed_ratio(V, omega_load, gear, p)
    t_pump = torque_converter.pump_torque(phi, omega_load, p) * (abs(gear) / p.gear_ratio)
    t_load = t_pump + lift.lift_power(V_b, u_ab, p) / omega_load
    t_needed = engine.friction_torque(omega, p) + t_load + p.J_ice * (p.omega_max - omega) / h
    u_mf = ops.fmin(u_mf, ops.fmax(t_needed / p.T_ig_per_mg, 0.0))
    u_b = ops.clip(u_b, 0.0, p.U_b_max) * brake
    return u_mf, u_ab, u_b, u_mf_torque, u_ab_pressure


def saturation_residuals(y: State, u: Any, omega_rate: Any, h: Any, p: LoaderParams,
                         end_stop: bool = True) -> dict[str, list[Any]]:
    """:func:`effective_controls` as constraints: all residuals <= 0 iff it passes the control u unchanged
    (besides the bounds of the control ranges). For a planner, whose controls must be the applied ones.

    ``omega_rate`` is d omega/dt at y under u (the governor's condition is omega + h d omega/dt <=
    omega_max). ``end_stop``: include the boom's end stop (a planner that never reaches it may drop it).
    """
    omega, H, V_b = y[0], y[2], y[3]
    v_end = V_b + u[1] * h  # the bucket speed the substep ends with
    rows = {
        "torque": limits.torque(omega, u[0], p),
        "governor": [(omega + h * omega_rate) / p.omega_max - 1.0],
        "pump_flow": limits.lift_speed(H, omega, v_end, p),  # the speed it ends with, at the start's pump
        "relief_pressure": limits.cylinder_pressure(H, u[1], p),
    }
    if end_stop:
        h_stop = lift.max_bucket_height(p)
        rows["end_stop"] = [(H + h * v_end) / h_stop - 1.0]
    return rows


# ---------------------------------------------------------------------------------------- integration
def rhs(y: State, u: Any, gear: Any, d: Any, p: LoaderParams, est: Any = None, held: Any = 0.0,
        saturate: bool = True) -> State:
    """dy/dt under the applied controls u; ``held`` (0/1): stiction holds the machine (dV/dt = 0).

    ``saturate``: the machine's own limits hold at this point too, not only where the control was
    applied (:func:`effective_controls`): the engine's torque curve (the injection is capped at the
    point's engine speed), the relief pressure (U_ab at the point's height) and the pump flow (the bucket
    rises at most at V_lift,max of the point). A planner whose rows keep the controls inside the
    saturations (where they are the identity) passes False and keeps its NLP smooth.
    """
    ops = ops_for(y[0])
    omega = ops.fmax(y[0], OMEGA_FLOOR)
    u_mf, u_ab, v_b = u[0], u[1], y[3]
    if saturate:  # (at y[0] itself, as effective_controls: the first stage shares its arithmetic)
        u_mf = ops.fmin(u_mf, engine.max_fuel_injection(y[0], p))
        u_ab_pressure, v_lift_max = lift.lift_limits(y[2], y[0], p)
        u_ab = ops.fmin(u_ab, u_ab_pressure)
        v_b = ops.fmin(v_b, v_lift_max)
    x = (omega, y[1], y[2], v_b)
    if est is None:
        d_omega, d_v, d_h, d_vb, fuel = derivatives(*x, u_mf, u_ab, u[2], gear, d, p)
    else:
        d_omega, d_v, d_h, d_vb, fuel = estimated_derivatives(x, (u_mf, u_ab, u[2]), gear, d, p, est[0], est[1], est[2])
    return d_omega, d_v * (1.0 - held), d_h, d_vb, y[1], fuel


def rk4(y: State, u: Any, gear: Any, d: Any, h: Any, p: LoaderParams, est: Any = None,
        held: Any = None, saturate: bool = True) -> tuple[State, list[Stage], Any]:
    """One classical RK4 step of length h with the controls u held (``saturate``: see :func:`rhs`).

    Stiction: ``held`` None decides it from the first stage (standing, d V <= 0, and pushed against the
    travel direction: held for the substep); a planner that knows passes 0 or 1. Returns the new state,
    the four stages (evaluation point, derivative) and ``held``.
    """
    ops = ops_for(y[0])
    k1 = rhs(y, u, gear, d, p, est, saturate=saturate)
    if held is None:
        held = ops.where((d * y[1] <= 0.0) & (d * k1[1] <= 0.0), 1.0, 0.0)
    k1 = (k1[0], k1[1] * (1.0 - held), k1[2], k1[3], k1[4], k1[5])
    h2 = 0.5 * h
    y2 = tuple(y[i] + h2 * k1[i] for i in range(6))
    k2 = rhs(y2, u, gear, d, p, est, held, saturate)
    y3 = tuple(y[i] + h2 * k2[i] for i in range(6))
    k3 = rhs(y3, u, gear, d, p, est, held, saturate)
    y4 = tuple(y[i] + h * k3[i] for i in range(6))
    k4 = rhs(y4, u, gear, d, p, est, held, saturate)
    h6 = h / 6.0
    out = [y[i] + h6 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]) for i in range(6)]
    if saturate:  # the bucket ends the step no faster than the pump delivers there
        out[3] = ops.fmin(out[3], lift.lift_limits(out[2], out[0], p)[1])
    if not is_symbolic(out[3]):  # V_b lands on 0 exactly when the bucket stops (rounding; a plan bounds it)
        out[3] = ops.fmax(out[3], 0.0)
    return tuple(out), [(y, k1), (y2, k2), (y3, k3), (y4, k4)], held  # type: ignore[return-value]


def crossing_fraction(y0: State, y1: State, d: Any) -> Any:
    """The fraction of a substep at which the speed crosses zero: the linear estimate v0 / (v0 - v1)."""
    v0, v1 = d * y0[1], d * y1[1]
    return v0 / (v0 - v1)


def cut_substep(y0: State, y1: State, u: Any, gear: Any, d: Any, h: Any, p: LoaderParams,
                rest_gear: Any, rest_d: Any, rest_brake: Any, est: Any = None, rest_held: Any = None,
                saturate: bool = True) -> tuple[State, State, list[Stage], list[Stage], Any]:
    """A substep from y0 whose full RK4 step y1 crosses V = 0: stop exactly at V = 0 (at the crossing
    fraction of the substep), then finish the substep in the gear, direction and brake permission that
    follow (phase 3 at the reversing point; the same phase, standing, at the end of the cycle).

    Returns (end state, state at the stop, stages up to the stop, stages of the rest, rest's ``held``).
    """
    frac = crossing_fraction(y0, y1, d)
    ys, stop_stages, _ = rk4(y0, u, gear, d, frac * h, p, est, 0.0, saturate)  # moving: d V > 0 before the stop
    ys = (ys[0], 0.0 * ys[1], ys[2], ys[3], ys[4], ys[5])
    rest, rest_stages, held = rk4(ys, (u[0], u[1], u[2] * rest_brake), rest_gear, rest_d, (1.0 - frac) * h, p,
                                  est, rest_held, saturate)
    return rest, ys, stop_stages, rest_stages, held


# ---------------------------------------------------------------------------------------- limits in a step
def driver_limit_points(stages: list[Stage], end: State, end_rate: State) -> list[Stage]:
    """Where the driver's limits (deceleration, speed) are checked in a substep: at every RK4 stage and
    at its end (with the control still held)."""
    return [*stages, (end, end_rate)]


def within_step_excess(points: list[Stage], d: Any, p: LoaderParams) -> dict[str, Any]:
    """The relative excess over the driver's limits (:data:`wl_env.limits.ENV_NAMES`: deceleration and
    speed) at ``points`` of a substep (see :func:`driver_limit_points`), 0 where they hold. The machine's
    own limits need no check: they saturate within the step (:func:`rhs`)."""
    decel, fast = [], []
    for x, k in points:
        decel += limits.deceleration(k[1], d, p)
        fast += limits.speed(x[1], d, p)
    return {"deceleration": limits.excess(decel), "speed": limits.excess(fast)}
