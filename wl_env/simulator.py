"""Fixed-step integration of the loader through the cycle's phases.

One code path serves a single loader (Python floats: fast for one environment) and a batch of
loaders (numpy arrays of shape (N,): the vector environment). The continuous state is the tuple
``(omega, V, H, V_b, s, m_f)``: the model's four states, the travelled position s (m) and the fuel used
m_f (kg). Each substep holds the *effective* controls constant and takes one classical RK4 step.

What the machine enforces by itself is applied here as saturation of the commanded controls
(:meth:`Simulator.effective_controls`): the injection range and the engine's torque limit, the
governor at omega_max, the relief pressure, the pump flow (V_b <= V_lift,max) and the bucket not being
lowered (V_b >= 0), the brake range, and brakes only in the phases that use them. Stiction: a standing
machine that the forces would push against the phase's travel direction stays put. A substep in which
the speed crosses zero is cut at the crossing (no overshoot past V = 0): at the reversing point (end of
phase 2) the machine switches to phase 3 and the rest of the substep runs forward; otherwise it stands.

On Python floats, :meth:`Simulator.effective_controls` and :meth:`Simulator.rk4` run their own code
flattened by :mod:`wl_env.physics.flatten` into straight-line float arithmetic: same results, less overhead.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from wl_env import cycle
from wl_env.model import derivatives
from wl_env.params import LoaderParams, resolve
from wl_env.physics import engine, lift, torque_converter
from wl_env.physics.backend import ops_for
from wl_env.physics.flatten import Sym, flatten_cached, take

# Engine speed floor used inside the right-hand side only: keeps P_load/omega finite if an engine
# stalls within a substep (the environment ends the episode at omega_min, far above this).
_OMEGA_FLOOR = 1.0

State = tuple[Any, Any, Any, Any, Any, Any]  # omega, V, H, V_b, s, m_f


class Simulator:
    """Integrates one loader (floats) or a batch (numpy arrays) with the cycle's phase logic."""

    def __init__(self, params: LoaderParams | dict | None = None, braking: str = "service") -> None:
        self.params = resolve(params)
        self.braking = cycle.check_braking(braking)
        gear, direction, brake = cycle.phase_tables(braking, self.params)
        self._tables_np = (gear, direction, brake)
        self._tables_py = (tuple(gear.tolist()), tuple(direction.tolist()), tuple(brake.tolist()))
        self._h_stop = lift.max_bucket_height(self.params)

    def __setattr__(self, name: str, value: Any) -> None:
        # The flattened code bakes in the attributes' values: assigning any one discards it.
        object.__setattr__(self, name, value)
        object.__setattr__(self, "_flat", None)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_flat": None}  # generated code is rebuilt after unpickling, not pickled

    def _flattened(self) -> tuple[Any, Any]:
        """``_controls`` and ``_rk4`` flattened to straight-line float code (see ``physics.flatten``): on
        floats they are mostly call and dispatch overhead. Built on first use with floats."""
        if self._flat is None:
            key = repr((type(self), self.params, self._h_stop))  # all that _controls and _rk4 read
            controls_inputs = (("y", 4), "gear", "brake", "u_mf", "u_ab", "u_b", "h")
            flat = (
                flatten_cached(f"{key} controls", self._controls, *controls_inputs, name="controls"),
                flatten_cached(f"{key} rk4", self._rk4, ("y", 6), ("u", 3), "gear", "d", "h", name="rk4"),
            )
            object.__setattr__(self, "_flat", flat)
        return self._flat

    # ------------------------------------------------------------------ phase tables
    def phase_constants(self, phase: Any) -> tuple[Any, Any, Any]:
        """(gear, direction, brake allowed 0/1) of a phase number or an array of them."""
        if isinstance(phase, np.ndarray):
            g, d, b = self._tables_np
            return g[phase], d[phase], b[phase]
        g, d, b = self._tables_py
        if isinstance(phase, Sym):  # a whole step being flattened (CycleStepper): look up at run time
            return take(g, phase), take(d, phase), take(b, phase)
        return g[phase], d[phase], b[phase]

    # ------------------------------------------------------------------ machine limits
    def effective_controls(self, y: State, phase: Any, u_mf: Any, u_ab: Any, u_b: Any, h: float) -> tuple[Any, ...]:
        """The controls the machine actually applies over a substep of length h (s), see module doc.

        Returns ``(U_mf, U_ab, U_b, U_mf limit of the torque curve, U_ab limit of the relief pressure)``;
        the last two let a caller tell which saturation was active.
        """
        gear, _, brake = self.phase_constants(phase)
        if type(y[0]) is float:  # one loader: the same code flattened to plain float arithmetic
            return self._flattened()[0](y, gear, brake, u_mf, u_ab, u_b, h)
        return self._controls(y, gear, brake, u_mf, u_ab, u_b, h)

    def _controls(self, y: State, gear: Any, brake: Any, u_mf: Any, u_ab: Any, u_b: Any, h: float) -> tuple[Any, ...]:
        p = self.params
        omega, V, H, V_b = y[0], y[1], y[2], y[3]
        ops = ops_for(omega)
        lo, hi = p.U_ab_bounds
        u_ab = ops.clip(u_ab, lo, hi)
        u_ab_pressure, v_lift_max = lift.lift_limits(H, omega, p)
        u_ab = ops.fmin(u_ab, u_ab_pressure)  # relief valve
        # Pump flow, and the boom's end stop: V_b at most what reaches the stop within the substep.
        v_cap = ops.fmin(v_lift_max, ops.fmax(self._h_stop - H, 0.0) / h)
        u_ab = ops.fmin(u_ab, (v_cap - V_b) / h)
        u_ab = ops.fmax(u_ab, -V_b / h)  # the bucket is not lowered in this cycle
        u_mf_torque = engine.max_fuel_injection(omega, p)
        u_mf = ops.clip(u_mf, 0.0, u_mf_torque)  # injection range, torque limit
        # Governor: at most the injection that brings omega to omega_max by the end of the substep.
        phi = torque_converter.speed_ratio(V, omega, gear, p)
        t_pump = torque_converter.pump_torque(phi, omega, p) * (abs(gear) / p.gear_ratio)
        t_load = t_pump + lift.lift_power(V_b, u_ab, p) / omega
        t_needed = engine.friction_torque(omega, p) + t_load + p.J_ice * (p.omega_max - omega) / h
        u_mf = ops.fmin(u_mf, ops.fmax(t_needed / p.T_ig_per_mg, 0.0))
        u_b = ops.clip(u_b, 0.0, p.U_b_max) * brake
        return u_mf, u_ab, u_b, u_mf_torque, u_ab_pressure

    # ------------------------------------------------------------------ integration
    def _rhs(self, y: State, u: tuple[Any, Any, Any], gear: Any, d: Any, held: Any) -> State:
        ops = ops_for(y[0])
        omega = ops.fmax(y[0], _OMEGA_FLOOR)
        d_omega, d_v, d_h, d_vb, fuel = derivatives(omega, y[1], y[2], y[3], u[0], u[1], u[2], gear, d, self.params)
        if held is not None:
            d_v = d_v * (1.0 - held)
        return d_omega, d_v, d_h, d_vb, y[1], fuel

    def rk4(self, y: State, u: tuple[Any, Any, Any], gear: Any, d: Any, h: Any) -> tuple[State, Any]:
        """One RK4 step of length h with controls u held; stiction decided from the first stage.

        Returns the new state and dV/dt at the start of the step (m/s^2).
        """
        if type(y[0]) is float:  # one loader: the same code flattened to plain float arithmetic
            return self._flattened()[1](y, u, gear, d, h)
        return self._rk4(y, u, gear, d, h)

    def _rk4(self, y: State, u: tuple[Any, Any, Any], gear: Any, d: Any, h: Any) -> tuple[State, Any]:
        ops = ops_for(y[0])
        k1 = self._rhs(y, u, gear, d, None)
        # Stiction: standing (d V <= 0) and pushed against the travel direction -> held for the substep.
        held = ops.where((d * y[1] <= 0.0) & (d * k1[1] <= 0.0), 1.0, 0.0)
        k1 = (k1[0], k1[1] * (1.0 - held), k1[2], k1[3], k1[4], k1[5])
        h2 = 0.5 * h
        y2 = (y[0] + h2 * k1[0], y[1] + h2 * k1[1], y[2] + h2 * k1[2], y[3] + h2 * k1[3], y[4] + h2 * k1[4], y[5] + h2 * k1[5])
        k2 = self._rhs(y2, u, gear, d, held)
        y3 = (y[0] + h2 * k2[0], y[1] + h2 * k2[1], y[2] + h2 * k2[2], y[3] + h2 * k2[3], y[4] + h2 * k2[4], y[5] + h2 * k2[5])
        k3 = self._rhs(y3, u, gear, d, held)
        y4 = (y[0] + h * k3[0], y[1] + h * k3[1], y[2] + h * k3[2], y[3] + h * k3[3], y[4] + h * k3[4], y[5] + h * k3[5])
        k4 = self._rhs(y4, u, gear, d, held)
        h6 = h / 6.0
        out = [y[i] + h6 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]) for i in range(6)]
        out[3] = ops.fmax(out[3], 0.0)  # V_b lands on 0 exactly when the bucket stops (rounding)
        return tuple(out), k1[1]  # type: ignore[return-value]

    def substep(self, y: State, phase: Any, u: tuple[Any, Any, Any], h: float) -> tuple[State, Any, Any, Any]:
        """Advance h seconds with the effective controls u held.

        Returns (state, phase, position of the reversing point if it was reached in the substep or NaN,
        dV/dt at the start of the substep).
        """
        gear, d, _ = self.phase_constants(phase)
        y1, accel = self.rk4(y, u, gear, d, h)
        crossed = (d * y[1] > 0.0) & (d * y1[1] < 0.0)
        if isinstance(crossed, np.ndarray):
            s_rev = np.full_like(y1[4], np.nan)
            idx = np.flatnonzero(crossed)
            if idx.size == 0:
                return y1, phase, s_rev, accel
            sub = tuple(a[idx] for a in y)
            sub_u = tuple(a[idx] if isinstance(a, np.ndarray) else a for a in u)
            ys, ph, sr = self._cut_at_stop(sub, tuple(a[idx] for a in y1), phase[idx], sub_u, h)
            y1 = tuple(a.copy() for a in y1)
            for a, b in zip(y1, ys, strict=True):
                a[idx] = b
            phase = phase.copy()
            phase[idx] = ph
            s_rev[idx] = sr
            return y1, phase, s_rev, accel
        if crossed:
            return (*self._cut_at_stop(y, y1, phase, u, h), accel)
        return y1, phase, math.nan, accel

    def _cut_at_stop(self, y0: State, y1: State, phase: Any, u: tuple, h: float) -> tuple[State, Any, Any]:
        """The speed crossed zero within the substep: stop exactly at V = 0, then finish the substep."""
        ops = ops_for(y0[0])
        gear, d, _ = self.phase_constants(phase)
        v0, v1 = d * y0[1], d * y1[1]
        frac = v0 / (v0 - v1)  # linear estimate of the crossing time, in (0, 1]
        ys, _ = self.rk4(y0, u, gear, d, frac * h)
        ys = (ys[0], 0.0 * ys[1], ys[2], ys[3], ys[4], ys[5])
        at_reversal = phase == 2
        s_rev = ops.where(at_reversal, ys[4], math.nan)
        phase = ops.where(at_reversal, 3, phase)
        if isinstance(phase, np.ndarray):
            phase = phase.astype(np.int64)
        gear, d, brake = self.phase_constants(phase)
        rest, _ = self.rk4(ys, (u[0], u[1], u[2] * brake), gear, d, (1.0 - frac) * h)
        return rest, phase, s_rev
