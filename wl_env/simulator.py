"""The control step (:mod:`wl_env.step`) with the cycle's phase logic, on numbers.

One code path serves a single loader (Python floats: fast for one environment) and a batch of
loaders (numpy arrays of shape (N,): the vector environment). A substep saturates the commanded
controls to what the machine can do (:func:`wl_env.step.effective_controls`), takes one RK4 step with
stiction, and checks the limits within it (:func:`wl_env.step.within_step_excess`). A substep in which
the speed crosses zero is cut at the crossing (no overshoot past V = 0): at the reversing point (end of
phase 2) the machine switches to phase 3 and the rest of the substep runs forward; otherwise it stands.

On Python floats, :meth:`Simulator.effective_controls` and :meth:`Simulator.rk4` run their own code
flattened by :mod:`wl_env.physics.flatten` into straight-line float arithmetic: same results, less overhead.
"""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np

from wl_env import cycle, limits, step
from wl_env.params import LoaderParams, ParamsView, resolve
from wl_env.physics.backend import ops_for
from wl_env.physics.flatten import Flattened, Sym, config_key, flatten_cached, take
from wl_env.step import State


class Simulator(Flattened):
    """Integrates one loader (floats) or a batch (numpy arrays) with the cycle's phase logic."""

    def __init__(self, params: LoaderParams | dict | None = None, braking: str = "service") -> None:
        self.params = resolve(params)
        self.braking = cycle.check_braking(braking)
        gear, direction, brake = cycle.phase_tables(braking, self.params)
        self._tables_np = (gear, direction, brake)
        self._tables_py = (tuple(gear.tolist()), tuple(direction.tolist()), tuple(brake.tolist()))

    def _flattened(self) -> tuple[Any, Any, Any]:
        """``_controls``, ``_advance`` and ``_cut`` flattened to straight-line float code (see ``physics.flatten``): on
        floats they are mostly call and dispatch overhead. Built on first use with floats."""
        if self._flat is None:
            key = config_key(self)
            controls_inputs = (("y", 4), "gear", "brake", "u_mf", "u_ab", "u_b", "h")
            flat = (
                flatten_cached(f"{key} controls", self._controls, *controls_inputs, name="controls"),
                flatten_cached(f"{key} advance", self._advance, ("y", 6), ("u", 3), "gear", "d", "h", name="advance"),
                flatten_cached(f"{key} cut", self._cut, ("y0", 6), ("y1", 6), "phase", ("u", 3), "h", name="cut"),
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
        return step.effective_controls(y, gear, brake, u_mf, u_ab, u_b, h, self.params)

    # ------------------------------------------------------------------ integration
    def advance(self, y: State, u: tuple[Any, Any, Any], gear: Any, d: Any, h: Any) -> tuple[State, dict[str, Any]]:
        """One RK4 step of length h with the effective controls u held (stiction decided from its first
        stage), uncut: the new state and the limits' excess within it (see :meth:`substep`)."""
        if type(y[0]) is float:  # one loader: the same code flattened to plain float arithmetic
            return self._flattened()[1](y, u, gear, d, h)
        return self._advance(y, u, gear, d, h)

    def _advance(self, y: State, u: tuple[Any, Any, Any], gear: Any, d: Any, h: Any,
                 est: Any = None) -> tuple[State, dict[str, Any]]:
        y1, stages, held = step.rk4(y, u, gear, d, h, self.params, est)
        return y1, self._excess(stages, y1, u, gear, d, held, est)

    def substep(self, y: State, phase: Any, u: tuple[Any, Any, Any], h: float,
                est: Any = None) -> tuple[State, Any, Any, dict[str, Any]]:
        """Advance h seconds with the effective controls u held.

        Returns (state, phase, position of the reversing point if it was reached in the substep or NaN,
        the relative excess over each limit within the substep, :func:`wl_env.step.within_step_excess`).
        ``est`` (one loader): a planner's plant estimate [accel offset, accel gain, lift gain] on the model's
        derivatives (:func:`wl_env.model.estimated_derivatives`), e.g. the MPC's prediction of a step.
        """
        gear, d, _ = self.phase_constants(phase)
        # (the flattened code has no estimate: with one, the general path)
        y1, excess = self.advance(y, u, gear, d, h) if est is None else self._advance(y, u, gear, d, h, est)
        crossed = (d * y[1] > 0.0) & (d * y1[1] < 0.0)
        if isinstance(crossed, np.ndarray):
            s_rev = np.full_like(y1[4], np.nan)
            idx = np.flatnonzero(crossed)
            if idx.size == 0:
                return y1, phase, s_rev, excess
            sub = tuple(a[idx] for a in y)
            sub_u = tuple(a[idx] if isinstance(a, np.ndarray) else a for a in u)
            ys, ph, sr, ex = self._of_loaders(idx)._cut(sub, tuple(a[idx] for a in y1), phase[idx], sub_u, h)
            y1 = tuple(a.copy() for a in y1)
            for a, b in zip(y1, ys, strict=True):
                a[idx] = b
            for name in excess:
                excess[name] = np.array(np.broadcast_to(excess[name], y1[0].shape))
                excess[name][idx] = ex[name]
            phase = phase.copy()
            phase[idx] = ph
            s_rev[idx] = sr
            return y1, phase, s_rev, excess
        if crossed:
            if est is not None:
                return self._cut(y, y1, phase, u, h, est)
            cut = self._flattened()[2] if type(y[0]) is float else self._cut  # one loader: the cut flattened too
            return cut(y, y1, phase, u, h)
        return y1, phase, math.nan, excess

    def _of_loaders(self, idx: np.ndarray) -> Simulator:
        """This simulator for the loaders ``idx`` of a batch: a scenario's per-loader parameters (a ParamsView
        of arrays, the vector env on drawn scenarios) cut down to theirs, so they line up with the states."""
        p = self.params
        if not isinstance(p, ParamsView) or not any(np.ndim(v) for v in p.values.values()):
            return self
        sub = copy.copy(self)
        sub.params = ParamsView(p.base, **{k: (v[idx] if np.ndim(v) else v) for k, v in p.values.items()})
        return sub

    def _excess(self, stages: list, y1: State, u: tuple, gear: Any, d: Any, held: Any,
                est: Any = None) -> dict[str, Any]:
        """The limits within a substep: at its RK4 stages and its end (the control still held)."""
        end_rate = step.rhs(y1, u, gear, d, self.params, est, held=held)
        return step.within_step_excess(step.driver_limit_points(stages, y1, end_rate), d, self.params)

    def _cut(self, y0: State, y1: State, phase: Any, u: tuple, h: float,
             est: Any = None) -> tuple[State, Any, Any, dict[str, Any]]:
        """The speed crossed zero within the substep: stop exactly at V = 0, then finish the substep."""
        p = self.params
        ops = ops_for(y0[0])
        gear, d, _ = self.phase_constants(phase)
        at_reversal = phase == 2
        after = ops.where(at_reversal, 3, phase)
        if isinstance(after, np.ndarray):
            after = after.astype(np.int64)
        rest_gear, rest_d, rest_brake = self.phase_constants(after)
        rest, ys, stop_stages, rest_stages, held = step.cut_substep(y0, y1, u, gear, d, h, p, rest_gear, rest_d, rest_brake,
                                                                   est)
        s_rev = ops.where(at_reversal, ys[4], math.nan)
        # up to the stop, the stop itself (the converter's drag peaks at standstill), then the rest
        excess = self._excess(stop_stages, ys, u, gear, d, 0.0, est)
        rest_excess = self._excess(rest_stages, rest, (u[0], u[1], u[2] * rest_brake), rest_gear, rest_d, held, est)
        return rest, after, s_rev, limits.worst(excess, rest_excess)
