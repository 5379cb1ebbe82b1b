"""The cycle on the environment's control grid: the plant's own discrete-time model, in CasADi.

``WheelLoader-v1`` holds each control for one control step (``dt``, 0.1 s) and integrates it with
``substeps`` classical RK4 steps, after saturating it to what the machine can do; a substep in which the
speed crosses zero is cut at the crossing. This module composes the environment's own step functions
(:mod:`wl_env.step`: the RK4 step, the cut, the saturations in constraint form) on CasADi symbols, with
the model corrected by the MPC's estimate of the plant (:func:`wl_env.model.estimated_derivatives`), so
that a plan made with it is what the environment does, step for step:

* a *full step* holds the controls over ``substeps`` RK4 substeps. What the machine would saturate
  becomes a constraint (:func:`wl_env.step.saturation_residuals`) at each substep start, where the
  controls are applied, and the torque curve, the pump flow and the relief pressure also at the other
  RK4 stages and the substep's end (the machine saturates them within the step too: a plan stays clear
  of that, and its NLP smooth). The driver's
  limits (:mod:`wl_env.limits`) are rows where the environment checks them: the deceleration at every
  RK4 stage and at the substep's end (with a gear engaged; in neutral it is the same all along). The
  speed limit needs no row: V_max is the speed at omega_max without converter slip, out of reach;
* a *stop step* ends phase 2 or phase 4: its last substep crosses V = 0, is cut at the crossing
  (:func:`wl_env.step.cut_substep`) and runs the rest in phase 3 (the reversing point) or standing
  (the end of the cycle).

:class:`GridNLP` chains such steps over the phases still ahead: a multiple-shooting NLP with a whole
number of steps per phase (the *schedule*). The schedule fixes the cycle time, so the NLP minimizes fuel;
the choice of schedule (:mod:`mpc.controller.mpc`) trades time. Each phase has a fixed number of slots; a schedule
uses the last ``n`` of them and the slots before are idle (zero-length steps that carry the state
through), so one built NLP serves every schedule that fits, and the plan one step later is the same
vector with one more idle slot.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import weakref
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from mpc.controller import codegen
from wl_env import cycle, limits, step
from wl_env.model import estimated_derivatives
from wl_env.params import SCENARIO_FIELDS, LoaderParams, ParamsView, is_real_number, plain, resolve, shown
from wl_env.physics import lift
from wl_env.step import State

N_X = 5  # grid state [omega (rad/s), V (m/s), H (m), V_b (m/s), s (m)]
X_SCALE = np.array([200.0, 2.5, 5.0, 1.0, 6.6])
U_SCALE = np.array([260.0, 2.5, 57800.0])  # U_mf (mg), U_ab (m/s^2), U_b (N m)
N_EST = 3  # the plant estimate: [accel offset (m/s^2), accel gain, lift gain], see estimated_derivatives
# The scenario (wl_env.scenario) as the NLP's parameters, so that one built NLP and its solvers serve every
# scenario of a machine: the step functions take the plant's (payload kg, rolling coefficient), the rows the
# targets (dump height m, the legs' distances m). The start state is a parameter already.
GRID_SCENARIO = ("M_load", "c_r", "H_T", "reverse_distance", "forward_distance")
N_SCN = len(GRID_SCENARIO)
N_STEP_SCN = 2  # ... of which the step functions take the first two
NOMINAL_ESTIMATE = np.array([0.0, 1.0, 1.0])
TARGET_WEIGHT = 1.0e4  # objective (g) per unit of relative target miss: 15 g per cm of distance
# Deceleration, per unit of relative excess: over the limit itself (practically hard: 1 % costs as much as
# 6.6 m of target miss), and into the margin a plan keeps below it (robustness: a plan uses it only where
# the full margin would cost it a target or a step: 1 % at one step costs 10 g).
DECEL_EXCESS_WEIGHT = 1.0e6
DECEL_MARGIN_WEIGHT = 1.0e3
MIN_STOP_SPEED = 1e-3  # m/s: a stop step starts moving (the crossing's time is v0 / (v0 - v1))
# m/s: the speed a stop step would reach past the crossing if the simulator did not cut it. A plan that
# rides v1 = 0 stops at the step's very end, and a plant a hair slower does not stop within the step.
STOP_OVERSHOOT = 2e-3
IDLE_WEIGHT = 1.0  # objective per unit of an idle slot's scaled control squared (it acts on nothing)
MIN_MARGIN = 1e-6  # the least upper bound of the margin used (an interior-point method needs lb < ub)
# The part of the deceleration limit no plan may use, whatever the margin (relative): a real-time iteration's
# plan meets its rows only to a residual (3.7e-8 at the nominal service 13 s cycle's last stop, which then braked
# 2.7e-8 over the limit)
DECEL_FLOOR = 1e-6


def _state(x: Any) -> State:
    """The grid state as the step's state tuple, its fuel counted from 0."""
    return (x[0], x[1], x[2], x[3], x[4], 0.0)


def _vector(y: State) -> Any:
    return ca.vertcat(y[0], y[1], y[2], y[3], y[4])


def scenario_values(params: LoaderParams) -> np.ndarray:
    """The values of GRID_SCENARIO in ``params``: what an NLP built for its machine takes per solve."""
    return np.array([float(getattr(params, name)) for name in GRID_SCENARIO])


def needs_end_stop(p: LoaderParams, dt: float, substeps: int) -> bool:
    """The boom's end stop can act only if a bucket lifting at the pump's limit reaches it within a
    substep from H_T (the plan never goes above H_T: the bucket is not lowered and ends there)."""
    v_pump = max(float(lift.max_lift_speed(H, p.omega_max, p)) for H in np.linspace(p.H_0, lift.max_bucket_height(p), 50))
    return bool(p.H_T + v_pump * dt / substeps >= lift.max_bucket_height(p))


@functools.lru_cache(maxsize=64)  # (per solve, see GridNLP.arguments: 50 pump evaluations)
def model_structure(braking: str, params: LoaderParams, dt: float, substeps: int, omega_margin: float) -> tuple:
    """What a :class:`StepModel`'s functions depend on: the machine's fields (not the scenario's), the
    step, and whether the boom's end stop needs rows (it depends on H_0 and H_T, :func:`needs_end_stop`)."""
    machine = tuple((f.name, getattr(params, f.name)) for f in dataclasses.fields(LoaderParams)
                    if f.init and f.name not in SCENARIO_FIELDS)
    return (braking, machine, float(dt), int(substeps), float(omega_margin), needs_end_stop(params, dt, substeps))


def _symbolic_params(params: LoaderParams, scenario: Any) -> ParamsView:
    """``params``'s machine with the scenario's fields from ``scenario`` (symbols, GRID_SCENARIO's first
    entries); those it does not give are NaN, so that a function built on it and reading them is caught."""
    given = dict(zip(GRID_SCENARIO, [scenario[i] for i in range(int(scenario.numel()))], strict=False))
    return ParamsView(params, **{name: given.get(name, math.nan) for name in SCENARIO_FIELDS})


@dataclass(frozen=True)
class StepFunction:
    """A CasADi function (x0, u, h, est, scn) -> (x1, rows, fuel kg, s at the stop) and its rows' bounds
    (scn: the plant's GRID_SCENARIO[:N_STEP_SCN], :attr:`StepModel.step_scenario`)."""

    fn: ca.Function
    lb: np.ndarray
    ub: np.ndarray
    decel: tuple[int, ...]  # its rows of the deceleration limit

    @property
    def n_rows(self) -> int:
        return len(self.lb)


class StepModel:
    """The control step of each phase as the environment takes it (see the module doc), for the machine
    of ``params``, with the scenario (the payload, the rolling resistance) as its functions' parameter.

    Models of one machine (:attr:`key`: the braking, the control interval, every field of the machine's
    but the scenario's) compare and hash equal, so an NLP built on one serves them all
    (:func:`mpc.controller.solver.grid_nlp`); :meth:`with_params` gives another scenario's model on the
    same functions. ``params`` and :attr:`step_scenario` are this one's scenario."""

    def __init__(self, braking: str, params: LoaderParams | dict | None = None, dt: float = 0.1, substeps: int = 1,
                 omega_margin: float = 0.0) -> None:
        # (as MPCController checks them: True was taken as 1 substep, and as a 1 s control interval; a string
        # omega_margin was math.isfinite's TypeError)
        substeps, omega_margin = plain(substeps), plain(omega_margin)
        if isinstance(substeps, bool) or not (isinstance(substeps, int) and 1 <= substeps <= 1000):
            raise ValueError(f"substeps must be an integer in [1, 1000], got {shown(substeps)}")
        if not (is_real_number(omega_margin) and omega_margin >= 0.0):
            raise ValueError(f"omega_margin must be >= 0 rad/s, got {shown(omega_margin)}")
        self.braking = cycle.check_braking(braking)
        self.params = resolve(params)
        dt = plain(dt)
        if not (is_real_number(dt) and dt > 0):
            raise ValueError(f"dt (the control interval) must be > 0 s, got {shown(dt)}")
        self.dt, self.substeps, self.omega_margin = float(dt), substeps, float(omega_margin)
        self.key = model_structure(self.braking, self.params, self.dt, substeps, self.omega_margin)
        self.end_stop = self.key[-1]  # (needs_end_stop)
        self.specs = {s.phase: s for s in cycle.phase_specs(braking, self.params)}
        self.full = {ph: self._step(ph, stop=False) for ph in (1, 2, 3, 4)}
        self.stop = {ph: self._step(ph, stop=True) for ph in (2, 4)}

    def fits(self, params: LoaderParams) -> bool:
        """``params`` is a scenario of this model's machine: its functions (and NLPs) serve it."""
        return model_structure(self.braking, params, self.dt, self.substeps, self.omega_margin) == self.key

    def with_params(self, params: LoaderParams) -> StepModel:
        """This machine's model for the scenario of ``params`` (the same functions: no build)."""
        params = resolve(params)
        if not self.fits(params):
            raise ValueError("with_params: another machine (or an end stop the model has no rows for); build a StepModel")
        other = copy.copy(self)
        other.params = params
        return other

    @property
    def step_scenario(self) -> np.ndarray:
        """The step functions' scenario input for this model's params (payload kg, rolling coefficient)."""
        return scenario_values(self.params)[:N_STEP_SCN]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StepModel) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)

    def _step(self, phase: int, stop: bool) -> StepFunction:
        """A full step, or a stop step (its last substep crosses V = 0; rows besides the full step's: the
        step starts moving, the crossing lies within the substep and, at the reversing point, the drive
        pushes forward, as the simulator needs to let the machine go on in phase 3).

        Rows are residuals (<= 0 holds; the deceleration's bounds are set per solve, see
        :meth:`GridNLP.arguments`), written so that h = 0 (an idle slot) leaves them finite."""
        spec = self.specs[phase]
        d, gear = spec.direction, spec.gear
        x0, u, h, est = ca.SX.sym("x0", N_X), ca.SX.sym("u", 3), ca.SX.sym("h"), ca.SX.sym("est", N_EST)
        scn = ca.SX.sym("scn", N_STEP_SCN)
        p = _symbolic_params(self.params, scn)
        hs = h / self.substeps
        y, fuel, rows, lb, ub = _state(x0), 0.0, [], [], []
        decel_all: list[int] = []
        # With a gear engaged the converter's drag changes within a step (TC braking: it rises as the
        # machine slows): the deceleration at every RK4 stage and at the end, as the environment checks
        # it. In neutral it is the brake's and the rolling resistance's, the same all along.
        geared = gear != 0.0

        def add(r: list, lo: float = -math.inf, hi: float = 0.0, decel: bool = False) -> None:
            if decel:
                decel_all.extend(range(len(rows), len(rows) + len(r)))
            rows.extend(r)
            lb.extend([lo] * len(r))
            ub.extend([hi] * len(r))

        def start_rows(y: State, stages: list) -> None:  # what the machine saturates where u is applied
            for r in step.saturation_residuals(y, u, stages[0][1][0], hs, p, self.end_stop).values():
                add(r)

        def decel_rows(stages: list, end: State, end_held: float = 0.0) -> None:
            if geared:
                points = step.driver_limit_points(stages, end, step.rhs(end, u, gear, d, p, est, end_held, saturate=False))
            else:  # in neutral the same all along
                points = stages[:1]
            add([r for _, k in points for r in limits.deceleration(k[1], d, p)], decel=True)

        def end_rows(y: State) -> None:  # the torque curve and the pump flow at a substep's end, u still held
            add(limits.torque(y[0], u[0], p) + limits.lift_speed(y[2], y[0], y[3], p))

        def stage_rows(stages: list) -> None:
            # The machine saturates at every RK4 stage (wl_env.step.rhs); the plan keeps clear of it there
            # (the stages' points are not on the trajectory: a plan held at its ends only is clipped, by
            # 0.2-0.6 % of the torque curve, between them).
            for x, _ in stages[1:]:
                add(limits.torque(x[0], u[0], p) + limits.lift_speed(x[2], x[0], x[3], p)
                    + limits.cylinder_pressure(x[2], u[1], p))

        for j in range(self.substeps):
            y1, stages, _ = step.rk4(y, u, gear, d, hs, p, est, held=0.0, saturate=False)
            if stop and j == self.substeps - 1:
                break  # the crossing substep: its rows below, on the part up to the crossing
            start_rows(y, stages)
            stage_rows(stages)
            decel_rows(stages, y1)
            end_rows(y1)
            fuel += y1[5]
            if j < self.substeps - 1:  # inside the step: the checks the step's end state has as bounds
                add(limits.direction(y1[1], d, p) + limits.speed(y1[1], d, p))
                add(limits.engine_speed(y1[0], p)[:1], hi=-self.omega_margin / p.omega_min)
            y = (*y1[:5], 0.0)
        s_stop = y[4]
        if stop:
            nxt = self.specs[3] if phase == 2 else spec  # the rest: phase 3's gear and no brakes, or standing
            rest_held = 0.0 if phase == 2 else 1.0  # (standing: the brakes and the rolling resistance hold it)
            y_end, y_stop, stop_stages, rest_stages, _ = step.cut_substep(
                y, y1, u, gear, d, hs, p, nxt.gear, nxt.direction, 1.0 if nxt.brake_allowed else 0.0, est,
                rest_held=rest_held, saturate=False)
            start_rows(y, stop_stages)
            stage_rows(stop_stages)
            stage_rows(rest_stages)
            decel_rows(stop_stages, y_stop)  # at the stop the converter's drag peaks (phi = 0)
            end_rows(y_stop)
            add([d * y[1]], lo=MIN_STOP_SPEED, hi=math.inf)  # the step starts moving (m/s)
            add([d * y1[1] / p.V_max], hi=-STOP_OVERSHOOT / p.V_max)  # ... and crosses V = 0 within it
            if phase == 2:  # the drive pushes forward at the reversing point
                add([nxt.direction * rest_stages[0][1][1]], lo=0.0, hi=math.inf)
            end_rows(y_end)
            s_stop, fuel, y = y_stop[4], fuel + y_stop[5] + (y_end[5] - y_stop[5]), y_end
        name = f"{'stop' if stop else 'full'}_step_{phase}"
        return StepFunction(ca.Function(name, [x0, u, h, est, scn], [_vector(y), ca.vertcat(*rows), fuel, s_stop]),
                            np.array(lb, dtype=float), np.array(ub, dtype=float), tuple(decel_all))


N_R = 2  # the previous step's U_mf and U_ab (scaled), carried as states: the rate penalty stays stage-wise
N_XR = N_X + N_R
SLOT_VARS = 3 + 2 + N_XR  # a full slot's decision variables: control, excess, margin used, end state


N_SLOT_PAR = 3 + N_R  # a slot's own parameters: h, active, rate on, and the rate weights


@dataclass(frozen=True, eq=False)
class SlotFunction:
    """One slot of a :class:`GridNLP` (a control step and its costs), built once per machine and kind:
    (z, q, shared) -> (rows, objective in g, fuel in kg). z: the state before the slot (N_XR, scaled), then
    the slot's own variables (control, excess, margin used, the targets' misses, end state); q: the
    slot's parameters (N_SLOT_PAR; slot 0 the start, an open NLP's last slot the terminal cost's, after
    them); shared: the estimate and the scenario. Rows: the shooting gap, slot 0's start equality, then
    the step's rows and the targets'; ``lb``/``ub`` bound the latter.

    Its values and derivatives (:attr:`functions`) serve every NLP of the machine: an NLP's are these,
    mapped over its slots (:attr:`GridNLP.mapped_nlp`, :attr:`GridNLP.derivative_functions`), not
    generated anew from each whole NLP."""

    fn: ca.Function
    targets: tuple[str, ...]
    lb: np.ndarray
    ub: np.ndarray
    terminal: bool

    @functools.cached_property
    def functions(self) -> dict[str, ca.Function]:
        """"f", "g": (z, q, shared) -> the objective; -> the rows. "hess": (z, q, shared, lam_f, lam_g) ->
        the upper triangle of the Hessian of lam_f f + lam_g . rows in z; "jac": (z, q, shared) -> (rows,
        their Jacobian in z); "grad": -> (f, its gradient in z); "lam_p": (z, q, shared, lam_f, lam_g) -> the
        gradient of lam_f f + lam_g . rows in [q; shared] (CasADi's lam_p with the sign turned)."""
        z, q, shared = (ca.SX.sym(n, self.fn.sparsity_in(i)) for i, n in enumerate(("z", "q", "shared")))
        rows, f, _ = self.fn(z, q, shared)
        lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", rows.numel())
        lagrangian = lam_f * f + ca.dot(lam_g, rows)
        hess, _ = ca.hessian(lagrangian, z)
        name, inputs = self.fn.name(), [z, q, shared]
        return {"f": ca.Function(f"{name}_f", inputs, [f]), "g": ca.Function(f"{name}_g", inputs, [rows]),
                "hess": ca.Function(f"{name}_hess", [*inputs, lam_f, lam_g], [ca.triu(hess)]),
                "jac": ca.Function(f"{name}_jac", inputs, [rows, ca.jacobian(rows, z)]),
                "grad": ca.Function(f"{name}_grad", inputs, [f, ca.gradient(f, z)]),
                "lam_p": ca.Function(f"{name}_lam_p", [*inputs, lam_f, lam_g],
                                     [ca.gradient(lagrangian, ca.vertcat(q, shared))])}


# Each slot kind's compiled functions (None: interpreted), while the slot function lives
_COMPILED: weakref.WeakKeyDictionary[SlotFunction, dict[str, ca.Function] | None] = weakref.WeakKeyDictionary()


def _evaluation_functions(kinds: list[SlotFunction]) -> list[dict[str, ca.Function]]:
    """Each slot kind's functions as its NLPs evaluate them: compiled where :func:`codegen.mode` allows
    (:mod:`mpc.controller.codegen`, the kinds not compiled yet built together), else interpreted."""
    if codegen.mode() == "off":
        return [sf.functions for sf in kinds]
    todo = [sf for sf in kinds if sf not in _COMPILED]
    for sf, fns in zip(todo, codegen.compiled([sf.functions for sf in todo], [sf.fn for sf in todo]), strict=True):
        _COMPILED[sf] = fns
    return [_COMPILED[sf] or sf.functions for sf in kinds]


@functools.cache
def slot_function(model: StepModel, phase: int, kind: str, first: bool, terminal: bool) -> SlotFunction:
    """The slot function of ``phase``'s full or stop step for ``model``'s machine (see :class:`SlotFunction`);
    ``first``: slot 0 (the start equality), ``terminal``: an open NLP's last slot (the terminal cost)."""
    xs, us = ca.DM(X_SCALE), ca.DM(U_SCALE)
    step_fn = model.full[phase] if kind == "full" else model.stop[phase]
    targets = {(2, "stop"): ("reversing point",), (4, "stop"): ("end position", "end height")}.get((phase, kind), ())
    n_q = N_SLOT_PAR + (N_XR if first else 0) + (2 * N_XR + 1 if terminal else 0)
    z = ca.SX.sym("z", 2 * N_XR + 5 + 2 * len(targets))
    q, shared = ca.SX.sym("q", n_q), ca.SX.sym("shared", N_EST + N_SCN)
    est, scn = shared[:N_EST], shared[N_EST:]
    p = _symbolic_params(model.params, scn)
    x_prev, U, ex, em, Xk = z[:N_XR], z[N_XR:N_XR + 3], z[N_XR + 3], z[N_XR + 4], z[-N_XR:]
    h, active, rate_on, rate_w = q[0], q[1], q[2], q[3:N_SLOT_PAR]
    spec = model.specs[phase]
    cost = []
    misses = {}
    for i, name in enumerate(targets):  # a target's signed miss, penalized in L1
        e = z[N_XR + 5 + 2 * i:N_XR + 7 + 2 * i]
        misses[name] = e[0] - e[1]
        cost.append(TARGET_WEIGHT * (e[0] + e[1]))
    u = U * us
    x_now, r_now = x_prev[:N_X] * xs, x_prev[N_X:]
    x_end, rows, fuel_k, s_stop = step_fn.fn(x_now, u, h, est, scn[:N_STEP_SCN])
    sel = np.zeros(step_fn.n_rows)
    sel[list(step_fn.decel)] = 1.0
    path = [(rows - ca.DM(sel) * (ex + em), step_fn.lb, step_fn.ub)]  # (the deceleration's: elastic)
    if kind == "stop" and phase == 2:  # the reversing point
        path.append(((s_stop + p.reverse_distance) / p.reverse_distance - misses["reversing point"], 0.0, 0.0))
    if kind == "stop" and phase == 4:  # the end: at the truck, bucket at H_T and still, the machine at rest
        path.append(((s_stop - p.final_position) / p.reverse_distance - misses["end position"], 0.0, 0.0))
        path.append(((x_end[2] - p.H_T) / p.H_T - misses["end height"], 0.0, 0.0))
        path.append((x_end[3], 0.0, 0.0))
        # at rest (as the benchmark's end): the engine holds its speed with the last injection
        d_om = estimated_derivatives(x_end, ca.vertcat(u[0], 0.0, u[2]), spec.gear, spec.direction, p,
                                     est[0], est[1], est[2])[0]  # (at omega >= omega_min: no floor)
        path.append((d_om / 100.0, 0.0, 0.0))
    # the previous control moves on to this slot's where the slot is a step (h > 0), else stays
    r_next = r_now + active * (U[:N_R] - r_now)
    cost.append(rate_on * ca.dot(rate_w, (U[:N_R] - r_now) ** 2))
    cost.append(IDLE_WEIGHT * (1.0 - active) * ca.dot(U, U))  # an idle slot's control: 0
    cost.append(DECEL_EXCESS_WEIGHT * ex + DECEL_MARGIN_WEIGHT * em)
    out = [Xk[:N_X] - x_end / xs, Xk[N_X:] - r_next]
    if first:
        out.append(x_prev - q[N_SLOT_PAR:N_SLOT_PAR + N_XR])
    if terminal:  # the value of the cycle beyond the horizon, to second order about a plan's
        tp = q[-(2 * N_XR + 1):]
        dx = Xk - tp[:N_XR]
        cost.append(ca.dot(tp[N_XR:2 * N_XR], dx) + 0.5 * tp[-1] * ca.dot(dx, dx))
    out += [r[0] for r in path]
    name = f"slot_{kind}_{phase}{'_first' if first else ''}{'_terminal' if terminal else ''}"
    f = 1000.0 * fuel_k + ca.sum1(ca.vertcat(*cost))
    return SlotFunction(ca.Function(name, [z, q, shared], [ca.vertcat(*out), f, fuel_k]), targets,
                        np.concatenate([np.broadcast_to(lo, (int(r.numel()),)) for r, lo, _ in path]).astype(float),
                        np.concatenate([np.broadcast_to(hi, (int(r.numel()),)) for r, _, hi in path]).astype(float),
                        terminal)


@dataclass(frozen=True)
class Slot:
    """One step of a :class:`GridNLP`: its phase and kind, and where its variables and rows are.

    Stage-wise layout (what fatrop's structure detection and a Riccati recursion need): per slot the
    control, the deceleration excess and the margin used, a stop slot's elastic target misses, then the
    end state; its rows, then the N_XR shooting equalities to the end state."""

    phase: int
    kind: str  # "full" or "stop"
    u: int  # offset of the control (3) in z; the excess and the margin used (1 each) follow
    x: int  # offset of the end state (N_XR) in z
    g: int  # offset of the step's rows in g
    gap: int  # offset of the shooting equalities in g

    @property
    def ex(self) -> int:
        return self.u + 3

    @property
    def em(self) -> int:
        return self.u + 4


class GridNLP:
    """Multiple-shooting NLP over the phases from ``first_phase`` on, ``slots[phase]`` full steps each,
    and the stop steps of phases 2 and 4 (built once; a schedule is chosen per solve, :meth:`arguments`).

    ``symbolic``: "SX" inlines the slot functions (:func:`slot_function`), "MX" calls them: the same
    variables and rows. (IPOPT and sqpmethod solve either on :attr:`mapped_nlp` and the slot functions'
    derivatives: an NLP and its IPOPT build in ~0.1 s, against ~1.8 s on CasADi's derivatives of it.)

    Parameters: the start state (scaled) and the control applied before it, the plant estimate, the
    scenario (GRID_SCENARIO: one NLP serves every scenario of its machine), one step
    length per slot (dt, or 0 when idle: an idle slot carries its state through), the weight of each
    slot's control-rate term (0 where it does not count) and the rate penalty's weights. The decision
    vector is stage-wise (:class:`Slot`): the start state, then per slot the control (scaled), an elastic
    excess over the deceleration limit, the part of the margin below it the plan uses (bounded by the
    margin, set per solve) and the end state. Elastic, because a brake can always hold the limit and the
    converter's drag cannot always (it follows the engine speed at the shift, and a plant heavier than
    the model, found out late, leaves it too high): a plan with the least excess beats no plan.
    Objective: fuel (g) plus the elastic misses of the reversing point, the end position and the end
    height, the excesses and the margin used, each priced above any fuel (TARGET_WEIGHT,
    DECEL_EXCESS_WEIGHT, DECEL_MARGIN_WEIGHT), and the control-rate penalty: sum over steps of
    w . (u_k - u_{k-1})^2 on U_mf and U_ab (scaled; eq. (33) of the paper on the grid).
    """

    def __init__(self, model: StepModel, first_phase: int, slots: dict[int, int], symbolic: str = "SX",
                 open_phase: int | None = None, short: bool = False) -> None:
        if symbolic not in ("SX", "MX"):
            raise ValueError(f"symbolic must be 'SX' (fast to evaluate) or 'MX' (fast to build), got {symbolic!r}")
        self.symbolic = getattr(ca, symbolic)
        if first_phase not in (1, 2, 3, 4):
            raise ValueError(f"first_phase must be 1..4, got {first_phase!r}")
        if open_phase is not None and open_phase not in range(first_phase, 5):
            raise ValueError(f"open_phase must be None or {first_phase}..4, got {open_phase!r}")
        self.model = model
        self.first_phase = first_phase
        # A short horizon (open_phase): the NLP ends within that phase, without its stop step and targets,
        # and prices its end state with a terminal cost (the cycle's value beyond it, :meth:`with_terminal`).
        self.open_phase = open_phase
        self.short = short  # a short horizon's NLP (open or not): its solvers are cached apart from the full ones
        self.phases = tuple(range(first_phase, 5 if open_phase is None else open_phase + 1))
        self.stop_phases = tuple(ph for ph in self.phases if ph in (2, 4) and ph != open_phase)
        self.slots_per_phase = {ph: int(slots[ph]) for ph in self.phases}
        if any(n < 1 for n in self.slots_per_phase.values()):
            raise ValueError(f"every phase needs at least one slot, got {self.slots_per_phase}")
        self._build()

    def _build(self) -> None:
        m = self.model
        kinds = [(ph, "full") for ph in self.phases for _ in range(self.slots_per_phase[ph])]
        kinds = sorted(kinds + [(ph, "stop") for ph in self.stop_phases], key=lambda k: (k[0], k[1] == "stop"))
        n_slots = len(kinds)
        # parameters: the start, the estimate, the scenario, then per slot h, active, rate on
        self.scenario_offset = N_XR + N_EST
        self.h_offset = self.scenario_offset + N_SCN
        self._active_offset = self.h_offset + n_slots
        self._rate_offset = self._active_offset + n_slots
        # ... the rate weights, then (open_phase) the terminal cost's: reference end state, its gradient, weight
        self.terminal_offset = self._rate_offset + n_slots + N_R
        n_terminal = 2 * N_XR + 1 if self.open_phase is not None else 0
        n_par = self.terminal_offset + n_terminal
        p = m.params  # (its machine's fields: the bounds are the machine's, the scenario is a parameter)
        lbw, ubw, lbg, ubg = [], [], [], []
        size = {"w": 0, "g": 0}

        # (the layout in numbers only: the symbolic NLP, :attr:`nlp`, is built at its first use. IPOPT solves on
        # the slot functions mapped (:attr:`mapped_nlp`), so a first plan's layouts no longer inline every slot
        # into an SX graph it never evaluates: a first plan's layout part 0.20 -> 0.06 s, measured at stop 65)
        def var(n: int, lo: Any, hi: Any) -> int:
            lbw.append(np.full(n, lo, dtype=float))
            ubw.append(np.full(n, hi, dtype=float))
            size["w"] += n
            return size["w"] - n

        def con(n: int, lo: Any, hi: Any) -> int:
            lbg.append(np.full(n, lo, dtype=float))
            ubg.append(np.full(n, hi, dtype=float))
            size["g"] += n
            return size["g"] - n

        self._miss_index: dict[str, int] = {}
        r_lb = np.array([0.0, p.U_ab_bounds[0]]) / U_SCALE[:N_R]
        r_ub = np.array([p.U_mf_max, p.U_ab_bounds[1]]) / U_SCALE[:N_R]
        x_lb0 = np.array([p.omega_min, -p.V_max, -math.inf, 0.0, -math.inf])
        x_ub0 = np.array([p.omega_max, p.V_max, math.inf, math.inf, math.inf])
        var(N_XR, np.concatenate([x_lb0 / X_SCALE, r_lb]), np.concatenate([x_ub0 / X_SCALE, r_ub]))
        slots: list[Slot] = []
        self._slot_fns: list[SlotFunction] = []
        self._slot_q: list[list[int]] = []
        self.stage_controls, self.stage_rows = [], []  # per slot (stage): its controls and non-gap rows
        for k, (ph, kind) in enumerate(kinds):
            spec = m.specs[ph]
            sf = slot_function(m, ph, kind, first=k == 0, terminal=self.open_phase is not None and k == n_slots - 1)
            v_lo, v_hi = (-p.V_max, 0.0) if spec.direction < 0 else (0.0, p.V_max)
            if kind == "stop" and ph == 2:
                v_lo, v_hi = 0.0, p.V_max  # the rest of the step runs in phase 3
            # Bounds only where a row does not hold the state already (a bound costs the solver a
            # multiplier): the bucket rises monotonically to H_T (no lowering), the pump rows cap its speed.
            x_lb = np.array([p.omega_min + m.omega_margin, v_lo, -math.inf, 0.0, -math.inf])
            x_ub = np.array([p.omega_max, v_hi, math.inf, math.inf, math.inf])
            ab_lo, ab_hi = p.U_ab_bounds
            u_lb = np.array([0.0, ab_lo, 0.0])
            u_ub = np.array([p.U_mf_max, ab_hi, p.U_b_max if spec.brake_allowed else 0.0])
            w_before = size["w"]
            u_off = var(3, u_lb / U_SCALE, u_ub / U_SCALE)
            var(1, 0.0, math.inf)  # the excess over the deceleration limit
            var(1, 0.0, math.inf)  # the margin used (its upper bound, the margin, is set per solve)
            for name in sf.targets:  # a target's signed miss (the difference of two parts), penalized in L1
                self._miss_index[name] = var(2, 0.0, math.inf)
            self.stage_controls.append(size["w"] - w_before)
            x_off = var(N_XR, np.concatenate([x_lb / X_SCALE, r_lb]), np.concatenate([x_ub / X_SCALE, r_ub]))
            # the slot's parameters (q) in the NLP's: h, active, rate on, the rate weights, (slot 0) the start,
            # (an open NLP's last slot) the terminal cost's
            q = [self.h_offset + k, self._active_offset + k, self._rate_offset + k,
                 *range(self._rate_offset + n_slots, self.terminal_offset)]
            q += list(range(N_XR)) if k == 0 else []
            q += list(range(self.terminal_offset, n_par)) if sf.terminal else []
            self._slot_q.append(q)
            # rows in stage order (as fatrop's structure needs): the shooting gap, (slot 0) the start, the rest
            gap = con(N_XR, 0.0, 0.0)
            g_before = size["g"]
            if k == 0:
                con(N_XR, 0.0, 0.0)  # the measured start and the control applied before it
            g_off = con(sf.fn.numel_out(0) - (2 if k == 0 else 1) * N_XR, sf.lb, sf.ub)
            self.stage_rows.append(size["g"] - g_before)
            slots.append(Slot(ph, kind, u_off, x_off, g_off, gap))
            self._slot_fns.append(sf)
        self.slots = slots
        self.n_var, self.n_con, self.n_par = size["w"], size["g"], n_par
        self.lbw, self.ubw = np.concatenate(lbw), np.concatenate(ubw)
        self.lbg, self.ubg = np.concatenate(lbg), np.concatenate(ubg)
        self.equality = self.lbg == self.ubg  # fixed by the build: per solve only inequality rows are relaxed

    def _slot_inputs(self, x: Any, par: Any, k: int) -> tuple[Any, Any]:
        """Slot ``k``'s variables (the state before it, then its own) and parameters in the NLP's ``x``, ``par``."""
        s = self.slots[k]
        return x[s.u - N_XR:s.x + N_XR], ca.vertcat(*[par[i] for i in self._slot_q[k]])

    @functools.cached_property
    def nlp(self) -> dict[str, Any]:
        """The NLP (x, p, f, g) with every slot function inlined ("SX") or called ("MX"): what sqpmethod and
        fatrop solve (IPOPT solves :attr:`mapped_nlp`, the same values)."""
        x, par = self.symbolic.sym("w", self.n_var), self.symbolic.sym("par", self.n_par)
        shared = par[N_XR:self.h_offset]  # the estimate and the scenario
        rows, cost = [], []
        for k, sf in enumerate(self._slot_fns):
            g_k, f_k, _ = sf.fn(*self._slot_inputs(x, par, k), shared)
            rows.append(g_k)
            cost.append(f_k)
        return {"x": x, "p": par, "f": ca.sum1(ca.vertcat(*cost)), "g": ca.vertcat(*rows)}

    @functools.cached_property
    def _slot_groups(self) -> list[list[int]]:
        """The slots grouped by their slot function (each group's mapped as one), in order of first use."""
        groups: dict[int, list[int]] = {}
        for k, sf in enumerate(self._slot_fns):
            groups.setdefault(id(sf), []).append(k)
        return list(groups.values())

    def fuel_g(self, z: np.ndarray, p: np.ndarray) -> float:
        """The fuel (g) a solution of the parameters ``p`` burns: its slots' summed in slot order, as the NLP's
        objective sums them (CasADi's sum1: left to right)."""
        total = 0.0
        for kg in np.asarray(self._mapped_derivatives["slot_fuel"](z, p), dtype=float).ravel():
            total += kg
        return 1000.0 * total

    @functools.cached_property
    def derivative_functions(self) -> dict[str, ca.Function]:
        """The NLP's Hessian of the Lagrangian (upper triangle), constraint Jacobian and objective gradient as
        IPOPT's nlpsol takes them (options ``hess_lag``, ``jac_g``, ``grad_f``): each slot function's
        (:class:`SlotFunction`, built once per machine), mapped over the slots of its kind and summed into
        place. The same values as CasADi generates from the whole NLP, which took ~1.7 s more per NLP to build
        (measured, stop 45). ``sqpmethod`` takes them as :attr:`sqp_derivative_functions`. The slot functions
        are compiled where a C compiler is found (:mod:`mpc.controller.codegen`; the same values to the bit):
        the solvers on them then need ``solver.NO_NLP_GRAD``."""
        return {k: self._mapped_derivatives[k] for k in ("hess_lag", "jac_g", "grad_f")}

    @property
    def mapped_nlp(self) -> dict[str, ca.MX]:
        """The NLP (x, p, f, g) as the slot functions mapped over the slots (the same values as :attr:`nlp`):
        what IPOPT solves, so that nlpsol builds no derivatives of its own from the whole NLP."""
        return self._mapped_derivatives["nlp"]

    def lam_p(self, z: np.ndarray, p: np.ndarray, lam_g: np.ndarray) -> np.ndarray:
        """CasADi's ``lam_p`` at a solution (minus the objective's sensitivity to the parameters), from the
        slot functions (IPOPT on :attr:`mapped_nlp` leaves it out: its own evaluation is the whole NLP's)."""
        return np.array(self._mapped_derivatives["lam_p"](z, p, 1.0, lam_g)).ravel()

    @functools.cached_property
    def sqp_derivative_functions(self) -> dict[str, ca.Function]:
        """:attr:`derivative_functions` as ``sqpmethod`` takes them: the whole symmetric Hessian, and the
        objective's gradient with the constraints' Jacobian (``jac_fg``)."""
        return {"hess_lag": self._mapped_derivatives["sym_hess_lag"], "jac_fg": self._mapped_derivatives["jac_fg"]}

    @functools.cached_property
    def _mapped_derivatives(self) -> dict[str, Any]:
        """The slot functions mapped over the slots: the NLP ("nlp") and the functions of the properties above."""
        n, n_g, n_p = self.n_var, self.n_con, self.n_par
        x, par, lam_f, lam_g = ca.MX.sym("x", n), ca.MX.sym("p", n_p), ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g)
        shared = par[N_XR:self.h_offset]
        n_slots = len(self.slots)
        h_parts, h_at, j_parts, j_at, g_parts, g_rows, f_parts, d_parts, d_at = [], [], [], [], [], [], [], [], []
        value_f, value_g, p_parts, p_at, fuel_parts = [], [], [], [], []
        shared_idx = np.arange(N_XR, self.h_offset)
        kinds = [self._slot_fns[ks[0]] for ks in self._slot_groups]
        for ks, fns in zip(self._slot_groups, _evaluation_functions(kinds), strict=True):
            z_idx, q_idx, r_idx = [], [], []
            for k in ks:
                s = self.slots[k]
                z_idx.append(np.arange(s.u - N_XR, s.x + N_XR))  # the state before the slot, then the slot's own
                q_idx.append(self._slot_q[k])
                end = self.slots[k + 1].gap if k + 1 < n_slots else n_g
                r_idx.append(np.arange(s.gap, end))
            z_idx, r_idx = np.array(z_idx), np.array(r_idx)
            m = len(ks)
            Z = ca.reshape(x[z_idx.ravel().tolist()], z_idx.shape[1], m)
            Q = ca.reshape(par[np.array(q_idx).ravel().tolist()], len(q_idx[0]), m)
            L = ca.reshape(lam_g[r_idx.ravel().tolist()], r_idx.shape[1], m)
            H = fns["hess"].map(m)(Z, Q, shared, lam_f, L)
            G, J = fns["jac"].map(m)(Z, Q, shared)
            F, D = fns["grad"].map(m)(Z, Q, shared)
            value_f.append(ca.sum2(fns["f"].map(m)(Z, Q, shared)))
            value_g.append(ca.vec(fns["g"].map(m)(Z, Q, shared)))
            p_parts.append(ca.vec(fns["lam_p"].map(m)(Z, Q, shared, lam_f, L)))
            fuel_parts.append(ca.vec(self._slot_fns[ks[0]].fn.map(m)(Z, Q, shared)[2]))  # (kg, its slots')
            qs_idx = np.hstack([np.array(q_idx), np.tile(shared_idx, (m, 1))])
            p_at.append((qs_idx.ravel(), np.zeros(qs_idx.size, dtype=int)))
            # where each nonzero goes: block i's (row, col) offset by its slot's first variable (row)
            hs, js = fns["hess"].sparsity_out(0), fns["jac"].sparsity_out(1)
            hr, hc = (np.array(a) for a in hs.get_triplet())
            jr, jc = (np.array(a) for a in js.get_triplet())
            for i in range(m):
                h_at.append((z_idx[i][hr], z_idx[i][hc]))
                j_at.append((r_idx[i][jr], z_idx[i][jc]))
            h_parts.append(H.nz[:])
            j_parts.append(J.nz[:])
            g_parts.append(ca.vec(G))
            g_rows.append(r_idx.ravel())
            f_parts.append(ca.sum2(F))
            d_parts.append(ca.vec(D))
            d_at.append((z_idx.ravel(), np.zeros(z_idx.size, dtype=int)))

        def assemble(parts: list, at: list, shape: tuple[int, int]) -> ca.MX:
            rows, cols = (np.concatenate([a[i] for a in at]) for i in (0, 1))
            # the nonzeros in column-major order (CasADi's); entries of neighbouring slots' blocks (the state
            # between them) land on one nonzero and sum
            keys, nz = np.unique(cols.astype(np.int64) * shape[0] + rows, return_inverse=True)
            sp = ca.Sparsity.triplet(shape[0], shape[1], (keys % shape[0]).tolist(), (keys // shape[0]).tolist())
            values = ca.vertcat(*parts)
            if len(keys) == len(nz):  # (the Jacobian's: each nonzero from one block, a permutation)
                return ca.MX(sp, values[np.argsort(nz).tolist()])
            A = ca.DM(ca.Sparsity.triplet(sp.nnz(), len(nz), nz.tolist(), list(range(len(nz)))), 1.0)
            return ca.MX(sp, ca.mtimes(A, values))

        hess = assemble(h_parts, h_at, (n, n))
        jac = assemble(j_parts, j_at, (n_g, n))
        grad_f = ca.densify(assemble(d_parts, d_at, (n, 1)))
        order = np.argsort(np.concatenate(g_rows))
        order_slots = np.argsort(np.concatenate(self._slot_groups))
        g = ca.vertcat(*g_parts)[order.tolist()]
        f = ca.sum1(ca.vertcat(*f_parts))
        grad_p = ca.densify(assemble(p_parts, p_at, (n_p, 1)))
        inputs, names = [x, par, lam_f, lam_g], ["x", "p", "lam_f", "lam_g"]
        return {"nlp": {"x": x, "p": par, "f": ca.sum1(ca.vertcat(*value_f)),
                        "g": ca.vertcat(*value_g)[order.tolist()]},
                "grad_f": ca.Function("grid_grad_f", [x, par], [f, grad_f], ["x", "p"], ["f", "grad_f_x"]),
                "lam_p": ca.Function("grid_lam_p", inputs, [-grad_p], names, ["lam_p"]),
                # (each slot's fuel, in slot order: built with the rest, where the solver is prepared, not at the
                # first fuel_g, which may be on the real-time controller's worker thread: mpc.threads)
                "slot_fuel": ca.Function("grid_slot_fuel", [x, par], [ca.vertcat(*fuel_parts)[order_slots.tolist()]]),
                "hess_lag": ca.Function("grid_hess_lag", inputs, [hess], names, ["triu_hess_gamma_x_x"]),
                "sym_hess_lag": ca.Function("grid_sym_hess_lag", inputs, [ca.triu2symm(hess)], names,
                                            ["hess_gamma_x_x"]),
                "jac_g": ca.Function("grid_jac_g", [x, par], [g, jac], ["x", "p"], ["g", "jac_g_x"]),
                "jac_fg": ca.Function("grid_jac_fg", [x, par], [f, grad_f, g, jac], ["x", "p"],
                                      ["f", "grad_f_x", "g", "jac_g_x"])}

    # ------------------------------------------------------------------ per solve
    def arguments(self, counts: dict[int, int], x_start: np.ndarray, est: np.ndarray, dt: float,
                  tighten: tuple[float, float] = (0.0, 0.0), u_prev: np.ndarray | None = None,
                  rate_weight: tuple[float, float] = (0.0, 0.0), *, params: LoaderParams) -> dict[str, Any]:
        """Parameters and bounds for a schedule: ``counts[phase]`` full steps in each phase, besides the
        stop steps, in the scenario of ``params`` (the NLP's machine, :meth:`StepModel.with_params`). Idle slots carry the state through (the measured start before the first active step,
        the state of the phase before in later phases), their rows relaxed. ``tighten``: the margin
        (fraction of the deceleration limit) the plan keeps in its first step and in the later ones;
        the plan may use it at DECEL_MARGIN_WEIGHT, all but DECEL_FLOOR (kept whatever the margin).
        ``u_prev``: the control [U_mf, U_ab] applied before (None: the first step has no rate term);
        ``rate_weight``: the rate penalty's weights, per unit of scaled control change squared (g)."""
        if abs(dt - self.model.dt) > 1e-12:
            raise ValueError(f"dt {dt!r} s is not the model's control interval {self.model.dt!r} s")
        if not self.model.fits(params):
            raise ValueError("params: another machine than this NLP's (or an end stop it has no rows for)")
        active = self.active_slots(counts)
        n = len(self.slots)
        par = np.zeros(self.n_par)
        par[:N_X] = np.asarray(x_start, dtype=float)[:N_X] / X_SCALE
        if u_prev is not None:
            par[N_X:N_XR] = np.asarray(u_prev, dtype=float)[:N_R] / U_SCALE[:N_R]
        par[N_XR:N_XR + N_EST] = est
        par[self.scenario_offset:self.h_offset] = scenario_values(params)
        par[self.h_offset + active] = dt
        par[self._active_offset + active] = 1.0
        par[self._rate_offset + active] = 1.0
        if u_prev is None:
            par[self._rate_offset + active[0]] = 0.0
        par[self._rate_offset + n:self.terminal_offset] = rate_weight
        lbw, ubw, lbg, ubg = self.lbw.copy(), self.ubw.copy(), self.lbg.copy(), self.ubg.copy()
        idle = np.ones(n, dtype=bool)
        idle[active] = False
        for k in np.flatnonzero(idle):
            s = self.slots[k]
            lbg[s.g:s.g + self._rows(s)] = -math.inf
            ubg[s.g:s.g + self._rows(s)] = math.inf
            # an idle slot's state is the one before it (which its bounds need not admit: the start's)
            lbw[s.x:s.x + N_X] = -math.inf
            ubw[s.x:s.x + N_X] = math.inf
        lbw[:N_X], ubw[:N_X] = -math.inf, math.inf  # the measured start is what it is (the equality fixes it)
        for i, k in enumerate(active):
            s, margin = self.slots[k], tighten[0] if i == 0 else tighten[1]
            margin = max(margin, DECEL_FLOOR + MIN_MARGIN)
            ubg[s.g + np.array(self._step_of(s).decel)] = -margin
            ubw[s.em] = margin - DECEL_FLOOR
        return {"p": par, "lbx": lbw, "ubx": ubw, "lbg": lbg, "ubg": ubg}

    def fix_leading_idle(self, args: dict[str, Any]) -> dict[str, Any]:
        """The arguments with the start state and the idle slots before the first active step fixed by
        their bounds (at the start) and their equalities relaxed: the same solution, which IPOPT solves
        without them (its fixed variables become parameters). A Riccati solver keeps the equalities."""
        p = args["p"]
        first = int(np.flatnonzero(p[self._active_offset:self._rate_offset] > 0)[0])
        start = p[:N_XR]
        lbx, ubx, lbg, ubg = (np.array(args[k], dtype=float) for k in ("lbx", "ubx", "lbg", "ubg"))
        lbx[:N_XR] = ubx[:N_XR] = start
        s0 = self.slots[0]
        lbg[s0.gap + N_XR:s0.gap + 2 * N_XR] = -math.inf  # the start equality (slot 0's rows follow it)
        ubg[s0.gap + N_XR:s0.gap + 2 * N_XR] = math.inf
        for s in self.slots[:first]:
            lbx[s.x:s.x + N_XR] = ubx[s.x:s.x + N_XR] = start
            lbx[s.u:s.u + 3] = ubx[s.u:s.u + 3] = 0.0
            lbx[s.ex] = ubx[s.ex] = lbx[s.em] = ubx[s.em] = 0.0
            lbg[s.gap:s.gap + N_XR] = -math.inf
            ubg[s.gap:s.gap + N_XR] = math.inf
        return {**args, "lbx": lbx, "ubx": ubx, "lbg": lbg, "ubg": ubg}

    def fix_first_controls(self, args: dict[str, Any], controls: np.ndarray) -> dict[str, Any]:
        """The arguments with the first active steps' controls fixed at ``controls`` (one [U_mf, U_ab, U_b]
        per step, clipped to its bounds) and those steps' own rows and end-state bounds relaxed: controls
        already committed, whose limits nothing can change any more (a stop step's target rows stay).
        The plan then starts that many steps later (a real-time controller solves while it applies them,
        see ``MPCConfig.realtime``)."""
        p = args["p"]
        active = np.flatnonzero(p[self._active_offset:self._rate_offset] > 0)
        controls = np.atleast_2d(np.asarray(controls, dtype=float))
        if len(controls) > len(active):
            raise ValueError(f"{len(controls)} controls to fix, but the schedule has {len(active)} steps")
        lbx, ubx, lbg, ubg = (np.array(args[k], dtype=float) for k in ("lbx", "ubx", "lbg", "ubg"))
        for k, u in zip(active[:len(controls)], controls, strict=True):
            s = self.slots[int(k)]
            lbx[s.u:s.u + 3] = ubx[s.u:s.u + 3] = np.clip(u[:3] / U_SCALE, lbx[s.u:s.u + 3], ubx[s.u:s.u + 3])
            n = self._rows(s)
            lbg[s.g:s.g + n], ubg[s.g:s.g + n] = -math.inf, math.inf
            lbx[s.x:s.x + N_X], ubx[s.x:s.x + N_X] = -math.inf, math.inf  # (where it ends is committed too)
        return {**args, "lbx": lbx, "ubx": ubx, "lbg": lbg, "ubg": ubg}

    def with_terminal(self, args: dict[str, Any], x_ref: np.ndarray, gradient: np.ndarray, weight: float) -> dict[str, Any]:
        """The arguments with the terminal cost (an open NLP's): ``gradient`` . dX + ``weight`` / 2 |dX|^2,
        dX the end state's (scaled, N_XR: the state and the last control) difference from ``x_ref``."""
        if self.open_phase is None:
            raise ValueError("a terminal cost needs an NLP that ends open (open_phase)")
        if not (np.isfinite(weight) and weight >= 0.0):
            raise ValueError(f"the terminal weight must be finite and >= 0, got {weight!r}")
        p = np.array(args["p"], dtype=float)
        p[self.terminal_offset:self.terminal_offset + N_XR] = x_ref
        p[self.terminal_offset + N_XR:self.terminal_offset + 2 * N_XR] = gradient
        p[-1] = weight
        return {**args, "p": p}

    def slot_spans(self, k: int) -> tuple[slice, slice, slice]:
        """Slot k's decision variables (control, slacks, misses, end state), its shooting rows and its own
        rows (the start equality of slot 0 apart), as slices of z and g."""
        s = self.slots[k]
        end = self.slots[k + 1].gap if k + 1 < len(self.slots) else self.n_con
        return slice(s.u, s.x + N_XR), slice(s.gap, s.gap + N_XR), slice(s.g, end)

    def _step_of(self, s: Slot) -> StepFunction:
        return self.model.full[s.phase] if s.kind == "full" else self.model.stop[s.phase]

    def _rows(self, s: Slot) -> int:
        return self._step_of(s).n_rows

    def active_slots(self, counts: dict[int, int]) -> np.ndarray:
        """Indices of the slots a schedule uses, in order (the last ``counts[phase]`` full slots of each
        phase and the stop slots)."""
        out, k = [], 0
        for ph in self.phases:
            n, n_slots = int(counts.get(ph, 0)), self.slots_per_phase[ph]
            if not 0 <= n <= n_slots:
                raise ValueError(f"phase {ph}: {n} steps do not fit its {n_slots} slots")
            out.extend(range(k + n_slots - n, k + n_slots))
            k += n_slots
            if ph in self.stop_phases:
                out.append(k)
                k += 1
        return np.array(out, dtype=int)

    def tail(self, z: np.ndarray, lam_x: np.ndarray, lam_g: np.ndarray,
             phase: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A solution's part from ``phase`` on, as the NLP from ``phase`` on (same slots) lays it out: its
        start state is the end state of the slot before, whose shooting multipliers become the start
        equality's (the stage-wise rows: the first slot's gap, then the start equality, then its rows)."""
        i = next((i for i, s in enumerate(self.slots) if s.phase == phase), None)
        if i is None:
            raise ValueError(f"phase {phase} is not in this NLP (phases {self.phases})")
        if i == 0:
            return z, lam_x, lam_g
        before, first = self.slots[i - 1], self.slots[i]
        g_start = lam_g[before.gap:before.gap + N_XR]
        lam_g = np.concatenate([lam_g[first.gap:first.gap + N_XR], g_start, lam_g[first.gap + N_XR:]])
        return z[before.x:], lam_x[before.x:], lam_g

    def excess(self, z: np.ndarray) -> float:
        """The largest relative excess over the deceleration limit a solution plans (0: none)."""
        return float(max(z[s.ex] for s in self.slots))

    def misses_m(self, z: np.ndarray, p: np.ndarray) -> dict[str, float]:
        """The signed target misses (m) of a solution of the parameters ``p`` (its scenario's legs and dump
        height scale the relative misses the NLP prices)."""
        scn = dict(zip(GRID_SCENARIO, np.asarray(p, dtype=float).ravel()[self.scenario_offset:self.h_offset], strict=True))
        scale = {"reversing point": scn["reverse_distance"], "end position": scn["reverse_distance"],
                 "end height": scn["H_T"]}
        return {name: float((z[i] - z[i + 1]) * scale[name]) for name, i in self._miss_index.items()}

    def plan(self, z: np.ndarray, counts: dict[int, int], x_start: np.ndarray, dt: float) -> dict[str, np.ndarray]:
        """The active steps of a solution: per step its phase, kind, control and end state."""
        active = self.active_slots(counts)
        sl = [self.slots[k] for k in active]
        return {
            "t": dt * np.arange(len(sl) + 1),
            "phase": np.array([s.phase for s in sl]),
            "stop": np.array([s.kind == "stop" for s in sl]),
            "controls": np.array([z[s.u:s.u + 3] * U_SCALE for s in sl]),
            "states": np.vstack([np.asarray(x_start, dtype=float)[:N_X]] + [z[s.x:s.x + N_X] * X_SCALE for s in sl]),
        }

    def initial_guess(self, x_start: np.ndarray, counts: dict[int, int], controls: dict[int, np.ndarray],
                      states: dict[int, np.ndarray]) -> np.ndarray:
        """A decision vector from per-slot controls and end states (unscaled; slots not given, idle or
        not, carry the state before them and no control)."""
        z = np.zeros(self.n_var)
        x_prev = np.asarray(x_start, dtype=float)[:N_X] / X_SCALE
        r = np.zeros(N_R)
        z[:N_X] = x_prev
        for k, s in enumerate(self.slots):
            if k in controls:
                z[s.u:s.u + 3] = np.asarray(controls[k], dtype=float) / U_SCALE
                r = z[s.u:s.u + N_R].copy()
            if k in states:
                x_prev = np.asarray(states[k], dtype=float)[:N_X] / X_SCALE
            z[s.x:s.x + N_X] = x_prev
            z[s.x + N_X:s.x + N_XR] = r
        return z

    def resample(self, z: np.ndarray, lam_x: np.ndarray, lam_g: np.ndarray, counts: dict[int, int],
                 new_counts: dict[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A solution for ``counts`` moved to ``new_counts``: each phase whose step count changes gets its
        steps (variables and row multipliers) at phase-normalized times, so a schedule move starts from a
        stretched plan rather than from a jump where a step went or came."""
        z, lam_x, lam_g = np.array(z, dtype=float), np.array(lam_x, dtype=float), np.array(lam_g, dtype=float)
        old, new = self.active_slots(counts), self.active_slots(new_counts)
        for ph in self.phases:
            ko = [k for k in old if self.slots[k].phase == ph and self.slots[k].kind == "full"]
            kn = [k for k in new if self.slots[k].phase == ph and self.slots[k].kind == "full"]
            if len(ko) == len(kn) or not ko or not kn:
                continue
            n_rows = self._rows(self.slots[ko[0]])
            for vec, width, starts in ((z, SLOT_VARS, lambda k: self.slots[k].u), (lam_x, SLOT_VARS, lambda k: self.slots[k].u),
                                       (lam_g, N_XR, lambda k: self.slots[k].gap), (lam_g, n_rows, lambda k: self.slots[k].g)):
                rows = np.array([vec[starts(k):starts(k) + width] for k in ko])
                for k, r in zip(kn, _interp_rows(rows, len(kn)), strict=True):
                    vec[starts(k):starts(k) + width] = r
        # the idle slots before a phase's first step carry the state it starts from
        active = set(new.tolist())
        for ph in self.phases:
            ks = [k for k, s in enumerate(self.slots) if s.phase == ph]
            x_before = self.slots[ks[0] - 1].x if ks[0] > 0 else 0
            for k in ks:
                if k in active:
                    break
                z[self.slots[k].x:self.slots[k].x + N_XR] = z[x_before:x_before + N_XR]
                z[self.slots[k].u:self.slots[k].u + 3] = 0.0
        return z, lam_x, lam_g

    def transport(self, z: np.ndarray, src: LoaderParams, dst: LoaderParams) -> np.ndarray:
        """A solution for the scenario of ``src`` reshaped as a warm start for ``dst``'s: each state's
        position and height as :func:`mpc.benchmark.ocp.transport_states` maps them, the rest kept."""
        from mpc.benchmark.ocp import scenario_fields, transport_states

        z = np.array(z, dtype=float)
        at = [0] + [s.x for s in self.slots]
        x = np.array([z[i:i + N_X] * X_SCALE for i in at])
        x[:, :4], x[:, 4] = transport_states(x[:, :4], x[:, 4], [self.first_phase] + [s.phase for s in self.slots],
                                             scenario_fields(src), scenario_fields(dst))
        for i, row in zip(at, x, strict=True):
            z[i:i + N_X] = row / X_SCALE
        return z

    def sensitivities(self, lam_p: np.ndarray, counts: dict[int, int], dt: float) -> dict[int, float]:
        """First-order change of the optimal objective per step added to each phase.

        One more step stretches each of a phase's m steps by dt / m: dJ = (dt / m) * sum of dJ/dh over
        them, from the parametric sensitivities of the step lengths (CasADi's ``lam_p`` is minus dJ/dp).
        """
        active = self.active_slots(counts)
        dJ_dh = -np.asarray(lam_p, dtype=float).ravel()[self.h_offset:self._active_offset]
        out = {}
        for ph in self.phases:
            ks = [k for k in active if self.slots[k].phase == ph]
            out[ph] = dt / len(ks) * float(dJ_dh[ks].sum()) if ks else math.nan
        return out


def _interp_rows(values: np.ndarray, n_new: int) -> np.ndarray:
    """Rows of ``values`` (one per step) resampled to n_new steps at phase-normalized times."""
    n_old = len(values)
    if n_old == n_new or n_old == 0:
        return values.copy()
    s_old = (np.arange(n_old) + 1.0) / n_old
    s_new = (np.arange(n_new) + 1.0) / n_new
    return np.column_stack([np.interp(s_new, s_old, values[:, c]) for c in range(values.shape[1])])
