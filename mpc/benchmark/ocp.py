"""The multi-phase optimal control problem of the short loading cycle (the benchmark).

Four phases with fixed gears (Table II, :mod:`wl_env.cycle`), free durations (each >= 0.1 s), states
continuous across the boundaries, every constraint of eq. (31), the boundary conditions of Table II and
6.6 m each way. Direct collocation: Radau IIA of degree ``degree`` on ``intervals`` mesh intervals per
phase, controls piecewise constant on the mesh, solved with IPOPT. The right-hand side is
``wl_env.model.derivatives`` itself, evaluated on CasADi symbols: the simulator and the OCP share the model.

One NLP per (braking, machine, mesh) serves every objective and every scenario: the weights, a fixed
cycle time, the control-rate smoothing of eq. (33) and the scenario's payload and rolling resistance
enter as NLP parameters, its start state, distances and dump height as bounds. Pareto sweeps, smoothing
homotopies and a suite's scenarios reuse the built solver and warm-start from a neighbouring solution.
"""

from __future__ import annotations

import json
import logging
import math
import numbers
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from mpc import interrupt
from mpc.threads import exclusive, in_turn
from wl_env import cycle, limits
from wl_env.atomic_io import _json_default, write_json_atomic  # (write_json_atomic: re-exported too)
from wl_env.model import derivatives
from wl_env.params import (
    DEFAULT_PARAMS,
    SCENARIO_FIELDS,
    LoaderParams,
    ParamsView,
    check_flag,
    check_no_overridden,
    is_finite,
    is_integer,
    is_real_number,
    plain,
    resolve,
    shown,
)
from wl_env.physics import lift

log = logging.getLogger(__name__)

OBJECTIVES = ("time", "fuel", "weighted", "fuel_at_time")
LINEAR_SOLVERS = ("mumps", "spral")  # IPOPT's linear solvers in CasADi's wheels (HSL's need a licensed library)
# Nominal magnitudes: decision variables are scaled by these so IPOPT sees numbers of order one.
X_SCALE = np.array([200.0, 2.5, 5.0, 1.0, 6.6])  # omega, V, H, V_b, s
U_SCALE = np.array([260.0, 2.5, 57800.0])  # U_mf, U_ab, U_b
FUEL_REF_G = 100.0  # g, normalizes the fuel term of the weighted objective
TIME_REF = 10.0  # s, normalizes the time term
N_PARAMETERS = 5  # length of the NLP parameter vector, see nlp_parameters()
# Upper bound of each phase's duration (s). The braking phases 2 and 4 last under a second, so the
# longest cycle the NLP holds is two driving phases at the bound: 60 s, well past the fuel-optimal
# cycle (about 21.4 s; slower cycles only burn more fuel). Longer fixed times are rejected up front,
# not reported as infeasible.
MAX_PHASE_DURATION = 30.0
MAX_CYCLE_TIME = 2 * MAX_PHASE_DURATION
# Each of the cycle's phases lasts at least cycle.MIN_PHASE_DURATION: no shorter cycle exists in the NLP (and
# its start guesses need a few samples per leg). Shorter fixed times are rejected up front as well.
MIN_CYCLE_TIME = len(cycle.PHASES) * cycle.MIN_PHASE_DURATION


def nlp_parameters(w_fuel: float, w_time: float, smoothing: float, params: LoaderParams) -> list[float]:
    """The parameter vector of a :class:`CycleOCP` NLP: ``w_fuel`` per g and ``w_time`` per s weigh the
    objective; ``smoothing`` is k of eq. (33); the scenario's payload M_load (kg) and rolling resistance c_r."""
    return [w_fuel, w_time, smoothing, params.M_load, params.c_r]


def machine_key(params: LoaderParams) -> str:
    """The fingerprint of the machine alone (the scenario's fields at their defaults): one NLP per machine."""
    return params.replace(**{f: getattr(DEFAULT_PARAMS, f) for f in SCENARIO_FIELDS}).fingerprint()


class OCPError(RuntimeError):
    """The solver did not find an optimum; the message carries its status."""


MAX_PHASE_INTERVALS = 2000  # per phase (mesh refinement doubles them; 10**7 would build an NLP of 10**8 variables)


@dataclass(frozen=True)
class OCPSettings:
    """Mesh and solver settings. Defaults pass the mesh-refinement and re-simulation checks."""

    intervals: tuple[int, int, int, int] = (20, 12, 20, 12)
    degree: int = 3
    smoothing: tuple[float, ...] = (1e-4, 0.0)  # homotopy k of eq. (33), last must be 0
    max_iter: int = 3000
    tol: float = 1e-8
    solver: str = "ipopt"
    linear_solver: str = "mumps"
    hessian: str = "exact"  # or "limited-memory" (L-BFGS): the alternative the benchmarks compare
    print_level: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.intervals, (tuple, list)) and len(self.intervals) == 4
                and all(is_integer(n) and 2 <= n <= MAX_PHASE_INTERVALS for n in self.intervals)):
            raise ValueError(f"intervals must be 4 integers in [2, {MAX_PHASE_INTERVALS}] (one per phase), got "
                             f"{shown(self.intervals)}")
        object.__setattr__(self, "intervals", tuple(int(n) for n in self.intervals))
        if not (is_integer(self.degree) and 1 <= self.degree <= 9):
            raise ValueError(f"degree must be an integer in [1, 9], got {shown(self.degree)}")
        if not (isinstance(self.smoothing, (tuple, list)) and 1 <= len(self.smoothing) <= 20
                and all(is_real_number(k) and k >= 0 for k in self.smoothing) and self.smoothing[-1] == 0.0):
            raise ValueError(f"smoothing must be 1 to 20 numbers k >= 0 ending with 0, got {shown(self.smoothing)}")
        object.__setattr__(self, "smoothing", tuple(float(k) for k in self.smoothing))
        if not (is_integer(self.max_iter) and 1 <= self.max_iter <= 100_000):
            raise ValueError(f"max_iter must be an integer in [1, 100000], got {shown(self.max_iter)}")
        if not (is_real_number(self.tol) and 0.0 < self.tol < 1.0):
            raise ValueError(f"tol must be a number in (0, 1), got {shown(self.tol)}")
        if not (is_integer(self.print_level) and 0 <= self.print_level <= 12):
            raise ValueError(f"print_level must be an integer in [0, 12] (IPOPT's), got {shown(self.print_level)}")
        if self.solver != "ipopt":
            # fatrop was tried: its structure detection needs a stage-wise variable layout, and the free
            # phase durations are global variables of this NLP.
            raise ValueError(f"solver must be 'ipopt', got {self.solver!r}")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {self.linear_solver!r}")
        if self.hessian not in ("exact", "limited-memory"):
            raise ValueError(f"hessian must be 'exact' or 'limited-memory', got {self.hessian!r}")


def as_plain(obj: Any) -> Any:
    """``obj`` with numpy's scalars and arrays as the Python numbers and lists they hold (exactly: float32 0.1 as
    0.10000000149...), tuples as lists, NaN kept: what ``json.dumps`` takes and gives back (it failed on an int64)."""
    if isinstance(obj, (np.generic, np.ndarray)):
        return obj.tolist()
    if isinstance(obj, dict):
        return {k: as_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [as_plain(v) for v in obj]
    return obj


@dataclass
class OCPResult:
    """An optimal cycle. ``controls[i]`` holds on ``[t[i], t[i+1])``; ``phase[i]`` is the phase of sample i."""

    braking: str
    objective: str
    T: float
    fuel_g: float
    phase_durations: list[float]
    t: list[float]
    states: list[list[float]]  # rows [omega, V, H, V_b]
    controls: list[list[float]]  # rows [U_mf, U_ab, U_b], one per interval (len(t) - 1)
    phase: list[int]
    position: list[float]  # s (m) at each t
    status: str
    success: bool
    iterations: int
    wall_time: float
    w_fuel: float | None = None
    target_T: float | None = None
    params_fingerprint: str = ""
    mesh: list[int] = field(default_factory=list)
    degree: int = 3
    solver: str = "ipopt"
    smoothing: list[dict[str, float]] = field(default_factory=list)  # homotopy steps: k, objective
    starts: list[dict[str, Any]] = field(default_factory=list)  # multi-start record
    verification: dict[str, Any] = field(default_factory=dict)
    scenario_fields: dict[str, float] = field(default_factory=dict)  # the LoaderParams SCENARIO_FIELDS solved for
    scenario: dict[str, Any] | None = None  # the wl_env.scenario.Scenario solved (None: outside the scenario ranges)

    def to_dict(self) -> dict[str, Any]:
        return as_plain(asdict(self))

    def save(self, path: str | os.PathLike) -> Path:
        """Write as JSON, atomically (a temporary file renamed over the target); ValueError naming the file, and
        nothing written, if :meth:`load` would refuse what it wrote (a NaN fuel was written, then refused when
        read back)."""
        from mpc.benchmark.store import _float_sized_int

        data = self.to_dict()
        text = json.dumps(data, indent=1, default=_json_default)  # (as write_json_atomic writes it)
        try:
            type(self).from_dict(json.loads(text, parse_int=_float_sized_int))  # (as load reads it)
        except ValueError as exc:
            raise ValueError(f"refusing to write {path}: it is {exc}" if str(exc).startswith("not") else
                             f"refusing to write {path}: {exc}") from None
        return write_json_atomic(path, data)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OCPResult:
        """The result :meth:`to_dict` gave; ValueError if ``data`` is not a consistent one (as a cached result
        is checked: fields, types, finite numbers, shapes)."""
        from mpc.benchmark.pareto import check_result

        if not isinstance(data, dict):
            raise ValueError(f"an OCP result is a mapping, got {type(data).__name__}")
        missing = {"braking", "objective", "T", "fuel_g", "t", "states", "controls", "phase"} - set(data)
        if missing:
            raise ValueError(f"not an OCP result: missing fields {sorted(missing)}")
        problem = check_result(data)
        if problem:
            raise ValueError(f"not a consistent OCP result: {problem}")
        return cls(**{k: v for k, v in data.items() if k in cls.__dataclass_fields__})

    @classmethod
    def load(cls, path: str | os.PathLike) -> OCPResult:
        """A result :meth:`save` (or :func:`mpc.benchmark.pareto.save_result`, then its checksum too) wrote;
        ValueError naming the file if it is not a consistent one (a string T or states of another shape
        were taken as they were)."""
        from mpc.benchmark.store import _float_sized_int, read_regular_file

        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no OCP result at {path}")
        # (checked as a cache entry is before it is read: a FIFO blocked this for good, /dev/zero filled the memory,
        # a folder was an IsADirectoryError; an integer of 5000 digits was a ValueError naming no file)
        raw = read_regular_file(path)  # BadEntry (a ValueError) naming the file
        try:
            data = json.loads(raw.decode("utf-8"), parse_int=_float_sized_int)
        except (ValueError, UnicodeDecodeError, RecursionError) as exc:  # (JSONDecodeError is a ValueError)
            raise ValueError(f"{path} is not valid JSON: {exc}") from None
        if isinstance(data, dict) and "schema" in data:  # an entry: its schema and checksum checked too
            from mpc.benchmark.pareto import RESULT_KIND, check_result
            from mpc.benchmark.store import read_entry

            data = read_entry(path, RESULT_KIND, check_result)
        try:
            return cls.from_dict(data)
        except ValueError as exc:
            raise ValueError(f"{path} is {exc}" if str(exc).startswith("not") else f"{path}: {exc}") from None

    @property
    def mesh_times(self) -> np.ndarray:
        return np.asarray(self.t)


# ----------------------------------------------------------------------------------------------------
_NLP_CACHE: dict[tuple, dict[str, Any]] = {}
# Built NLPs kept per process (a suite's points take dozens of meshes, pareto.MESH_LADDER; 50-200 MB each,
# 1-5 s to build): $WL_NLP_CACHE_SIZE, for a long suite solve on a machine with the memory.
NLP_CACHE_ENV = "WL_NLP_CACHE_SIZE"


def nlp_cache_size() -> int:
    """$WL_NLP_CACHE_SIZE (default 12): an integer in [1, 1000], else ValueError naming it."""
    raw = os.environ.get(NLP_CACHE_ENV, "12").strip()
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if not 1 <= n <= 1000:
        raise ValueError(f"${NLP_CACHE_ENV} must be an integer in [1, 1000] (OCP NLPs kept per process), got {raw!r}")
    return n


def release_nlps() -> None:
    """Drop the OCP NLPs this process has built (see mpc.controller.solver.release_solvers)."""
    _NLP_CACHE.clear()


class CycleOCP:
    """The collocation NLP for one braking alternative, parameter set and mesh, from the scenario's start
    state in phase 1. The NLP and its solver are built once per machine and mesh (:func:`machine_key`) and
    shared by every scenario; an instance holds its scenario's bounds. (The MPC plans on the environment's
    own grid instead, :mod:`mpc.controller.grid`.)"""

    def __init__(self, braking: str = "service", params: LoaderParams | dict | None = None,
                 settings: OCPSettings | None = None) -> None:
        self.braking = cycle.check_braking(braking)
        self.params = resolve(params)
        self.settings = settings or OCPSettings()
        self.specs = cycle.phase_specs(self.braking, self.params)
        key = (self.braking, machine_key(self.params), replace(self.settings, smoothing=(0.0,)))  # (k: a parameter)
        if key not in _NLP_CACHE:
            if len(_NLP_CACHE) >= nlp_cache_size():  # the least recently used goes (each holds ~50-100 MB)
                del _NLP_CACHE[next(iter(_NLP_CACHE))]
            _NLP_CACHE[key] = self._build()
        _NLP_CACHE[key] = _NLP_CACHE.pop(key)  # (most recently used last)
        self.__dict__.update(_NLP_CACHE[key])
        p = self.params
        self._lbw, self._ubw = (np.concatenate([np.broadcast_to(b(p) if callable(b) else b, (n,)) for n, b in self._w_bounds[i]])
                                for i in (0, 1))
        self._lbg, self._ubg = (np.concatenate([np.broadcast_to(b(p) if callable(b) else b, (n,)) for n, b in self._g_bounds[i]])
                                for i in (0, 1))

    # ------------------------------------------------------------------ construction
    def _build(self) -> dict[str, Any]:
        """The NLP, its solver and its bounds as functions of the scenario's parameters (shared, see above)."""
        p, st = self.params, self.settings
        d = st.degree
        tau = np.append(0.0, ca.collocation_points(d, "radau"))
        C = np.zeros((d + 1, d + 1))  # C[r, c]: derivative of basis r at tau_c
        B = np.zeros(d + 1)  # quadrature weights
        for r in range(d + 1):
            coeff = np.poly1d([1.0])
            for m in range(d + 1):
                if m != r:
                    coeff *= np.poly1d([1.0, -tau[m]]) / (tau[r] - tau[m])
            dcoeff = np.polyder(coeff)
            for c in range(d + 1):
                C[r, c] = dcoeff(tau[c])
            B[r] = np.polyint(coeff)(1.0)
        self.tau = tau

        self._C, self._B = C, B
        self._interval_fns = [self._interval_function(spec) for spec in self.specs]
        self.phases = [spec.phase for spec in self.specs]
        xs = ca.DM(X_SCALE)
        us = ca.DM(U_SCALE)
        w, w_lb, w_ub = [], [], []  # bounds: arrays, or functions of the scenario's LoaderParams
        g, g_lb, g_ub = [], [], []
        self._index: dict[str, list] = {"dur": [], "dur_copies": [], "X": [], "XC": [], "U": []}
        n_w = 0

        def add_var(name: str, n: int, lb: Any, ub: Any) -> tuple[ca.SX, int]:
            nonlocal n_w
            v = ca.SX.sym(name, n)
            w.append(v)
            w_lb.append((n, lb))
            w_ub.append((n, ub))
            n_w += n
            return v, n_w - n

        def add_con(expr: ca.SX, lb: Any, ub: Any) -> None:
            n = int(expr.numel())
            g.append(expr)
            g_lb.append((n, lb))
            g_ub.append((n, ub))

        # NLP parameters: see nlp_parameters(); the model reads the scenario's M_load and c_r from them
        par = ca.SX.sym("par", N_PARAMETERS)
        self._pv = pv = ParamsView(p, M_load=par[3], c_r=par[4])
        H_stop = lift.max_bucket_height(p)
        path_lb, path_ub = self._path_bounds()
        fuel_total = 0
        smooth = 0
        durations = []
        u_prev = None
        def start(q: LoaderParams) -> np.ndarray:
            return np.append(cycle.initial_state(q), 0.0) / X_SCALE

        X_start, off = add_var("X0", 5, start, start)
        self._index["X"].append(off)
        x_k = X_start * xs
        min_dur = cycle.MIN_PHASE_DURATION
        for k, spec in enumerate(self.specs):
            n_int = st.intervals[spec.phase - 1]
            dur, off = add_var(f"T{spec.phase}", 1, np.array([min_dur]), np.array([MAX_PHASE_DURATION]))
            self._index["dur"].append(off)
            durations.append(dur)
            h = dur / n_int
            v_lo, v_hi = (-p.V_max, 0.0) if spec.direction < 0 else (0.0, p.V_max)

            def x_lb(q: LoaderParams, v_lo: float = v_lo) -> np.ndarray:
                return np.tile(np.array([q.omega_min, v_lo, q.H_0, 0.0, -2 * q.reverse_distance]) / X_SCALE, d)

            def x_ub(q: LoaderParams, v_hi: float = v_hi) -> np.ndarray:
                end = max(q.final_position, 0.0) + q.reverse_distance
                return np.tile(np.array([q.omega_max, v_hi, H_stop, 5.0, end]) / X_SCALE, d)

            ab_lo, ab_hi = p.U_ab_bounds
            u_lb = np.array([0.0, ab_lo, 0.0]) / U_SCALE
            u_ub = np.array([p.U_mf_max, ab_hi, p.U_b_max if spec.brake_allowed else 0.0]) / U_SCALE
            fn = self._interval_fns[k]
            self._index["dur_copies"].append([off])
            dur_prev = dur
            for j in range(n_int):
                if j > 0:
                    # Each interval carries its own copy of the phase duration, chained by equalities:
                    # the KKT system stays banded (a shared duration would be a dense column per phase).
                    dur_j, off = add_var(f"T{spec.phase}_{j}", 1, np.array([min_dur]), np.array([MAX_PHASE_DURATION]))
                    self._index["dur_copies"][-1].append(off)
                    add_con(dur_j - dur_prev, 0.0, 0.0)
                    dur_prev, h = dur_j, dur_j / n_int
                U, off = add_var(f"U{spec.phase}_{j}", 3, u_lb, u_ub)
                self._index["U"].append(off)
                u = U * us
                if u_prev is not None:  # eq. (33): squared rates of U_mf, U_ab
                    du = (U[:2] - u_prev[:2])
                    smooth += ca.sumsqr(du) / h
                u_prev = U
                XC, off = add_var(f"XC{spec.phase}_{j}", 5 * d, x_lb, x_ub)
                self._index["XC"].append(off)
                defects, fuel, path = fn(x_k, XC * ca.repmat(xs, d, 1), u, h, par[3:5])
                add_con(defects, 0.0, 0.0)
                add_con(path, path_lb, path_ub)
                fuel_total += fuel
                x_k = XC[5 * (d - 1):] * xs
            # boundary conditions at the end of the phase
            # (positions and heights in X_SCALE's units: the targets are the scenario's bounds)
            if spec.phase == 2:  # the reversing point
                add_con(x_k[1] / p.V_max, 0.0, 0.0)
                rev = lambda q: -q.reverse_distance / X_SCALE[4]  # noqa: E731
                add_con(x_k[4] / X_SCALE[4], rev, rev)
            if spec.phase == 4:  # end: standing at the truck, bucket up and still, U_ab = 0, engine steady
                add_con(x_k[1] / p.V_max, 0.0, 0.0)
                end = lambda q: q.final_position / X_SCALE[4]  # noqa: E731
                add_con(x_k[4] / X_SCALE[4], end, end)
                height = lambda q: q.H_T / X_SCALE[2]  # noqa: E731
                add_con(x_k[2] / X_SCALE[2], height, height)
                add_con(x_k[3], 0.0, 0.0)
                add_con(U[1], 0.0, 0.0)
                d_om = derivatives(x_k[0], x_k[1], x_k[2], x_k[3], u[0], u[1], u[2], spec.gear, spec.direction, pv)[0]
                add_con(d_om / 100.0, 0.0, 0.0)
        T = sum(durations)
        self._g_T_index = sum(int(x.numel()) for x in g)
        add_con(T, 0.0, math.inf)  # bounds set per solve for a fixed cycle time
        fuel_g = fuel_total * 1000.0
        J = par[0] * fuel_g + par[1] * T + par[2] * smooth

        z = ca.vertcat(*w)
        nlp = {"x": z, "p": par, "f": J, "g": ca.vertcat(*g)}
        return {"tau": tau, "_C": C, "_B": B, "_interval_fns": self._interval_fns, "phases": self.phases,
                "_index": self._index, "n_var": int(z.numel()), "_g_T_index": self._g_T_index,
                "_w_bounds": (w_lb, w_ub), "_g_bounds": (g_lb, g_ub),
                "_fn_parts": ca.Function("parts", [z], [fuel_g, T, smooth]), "_nlp": nlp,
                "_solver": self._make_solver(nlp)}

    def _interval_function(self, spec: cycle.PhaseSpec) -> ca.Function:
        """Collocation of one mesh interval of a phase: (x_start, X_colloc, u, h) -> (defects, fuel kg, path).

        Built once per phase as an SX function, so the NLP inlines it instead of re-tracing the model.
        """
        d = self.settings.degree
        x0 = ca.SX.sym("x0", 5)
        xc = ca.SX.sym("xc", 5 * d)
        u = ca.SX.sym("u", 3)
        h = ca.SX.sym("h")
        scenario = ca.SX.sym("scenario", 2)  # M_load, c_r
        p = ParamsView(self.params, M_load=scenario[0], c_r=scenario[1])
        pts = [x0] + [xc[5 * c:5 * (c + 1)] for c in range(d)]
        defects, path = [], []
        fuel = 0
        for c in range(d + 1):
            x = pts[c]
            d_om, d_v, d_h, d_vb, m_dot = derivatives(x[0], x[1], x[2], x[3], u[0], u[1], u[2], spec.gear, spec.direction, p)
            # Path constraints at the collocation points and at the interval start, where the control
            # switches (the simulator applies the new control from that point on).
            rows = self._path_expressions(x, u, d_v, spec.direction, p)
            path.append(rows)
            if c == 0:
                continue
            xp = sum(self._C[r, c] * pts[r] for r in range(d + 1))
            defects.append((h * ca.vertcat(d_om, d_v, d_h, d_vb, x[1]) - xp) / ca.DM(X_SCALE))
            fuel += self._B[c] * m_dot * h
        return ca.Function(f"interval_{spec.phase}", [x0, xc, u, h, scenario],
                           [ca.vertcat(*defects), fuel, ca.vertcat(*path)])

    # eq. (31) at the collocation points (:mod:`wl_env.limits`); speed and engine speed are state bounds
    PATH_LIMITS = ("torque", "lift_speed", "cylinder_pressure", "deceleration")

    def _path_expressions(self, x, u, d_v, dirn, p) -> ca.SX:
        """The path constraints' residuals (<= 0)."""
        rows = limits.residuals(x, u, d_v, dirn, p, names=self.PATH_LIMITS)
        return ca.vertcat(*(r for name in self.PATH_LIMITS for r in rows[name]))

    def _path_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        n = (self.settings.degree + 1) * 7  # 3 torque lines, 2 pump pieces, pressure, deceleration per point
        return np.full(n, -math.inf), np.zeros(n)

    def _make_solver(self, nlp: dict[str, Any]) -> ca.Function:
        st = self.settings
        opts = {
            "ipopt.print_level": st.print_level,
            "print_time": False,
            "ipopt.max_iter": st.max_iter,
            "ipopt.tol": st.tol,
            "ipopt.acceptable_tol": 1e-6,
            "ipopt.linear_solver": st.linear_solver,
            "ipopt.mu_strategy": "adaptive",
            "ipopt.hessian_approximation": st.hessian,
            "ipopt.sb": "yes",
        }
        return ca.nlpsol("cycle_ocp", "ipopt", nlp, opts)

    # ------------------------------------------------------------------ initial guesses
    def guess_from_trajectory(self, t: np.ndarray, states: np.ndarray, position: np.ndarray,
                              controls: np.ndarray, phase: np.ndarray) -> np.ndarray:
        """A scaled decision vector from any trajectory with phases (a simulation or a previous optimum).

        Each phase of the trajectory is mapped onto the phase's mesh by phase-normalized time, so a
        guess with different phase durations still lands sample for sample. Phases of this NLP that
        the trajectory lacks (it may start later) take the trajectory's first sample, lasting 0.1 s.
        """
        t, states, position, controls, phase = map(np.asarray, (t, states, position, controls, phase))
        z = np.zeros(self.n_var)
        full = np.column_stack([states, position])
        ctrl_phase = phase[:-1] if len(phase) == len(t) else phase
        d = self.settings.degree
        ui = xci = 0
        z[self._index["X"][0]:self._index["X"][0] + 5] = full[0] / X_SCALE
        for k, ph in enumerate(self.phases):
            idx = np.flatnonzero(phase == ph)
            cmask = np.flatnonzero(ctrl_phase == ph)
            if idx.size == 0 or cmask.size == 0:
                seg_t, seg_x = np.array([0.0, 1.0]), np.repeat(full[:1], 2, axis=0)
                dur = cycle.MIN_PHASE_DURATION
                ctrl = np.repeat(controls[:1], 1, axis=0)
                cmask = np.array([0])
            else:
                # include the sample at the boundary (end of this phase = start of the next)
                lo, hi = idx[0] - (1 if idx[0] > 0 else 0), min(idx[-1] + 1, len(t) - 1)
                dur = max(t[hi] - t[lo], cycle.MIN_PHASE_DURATION)
                seg_t = (t[lo:hi + 1] - t[lo]) / dur
                seg_x = full[lo:hi + 1]
                ctrl = controls
            z[self._index["dur_copies"][k]] = dur
            n_int = self.settings.intervals[ph - 1]
            for j in range(n_int):
                ci = cmask[min(int((j + 0.5) / n_int * len(cmask)), len(cmask) - 1)]
                z[self._index["U"][ui]:self._index["U"][ui] + 3] = ctrl[ci] / U_SCALE
                ui += 1
                for c in range(d):
                    tp = (j + self.tau[c + 1]) / n_int
                    xv = np.array([np.interp(tp, seg_t, seg_x[:, m]) for m in range(5)])
                    off = self._index["XC"][xci] + 5 * c
                    z[off:off + 5] = xv / X_SCALE
                xci += 1
        return np.clip(z, self._lbw, self._ubw)

    # ------------------------------------------------------------------ solve
    def solve(self, z0: np.ndarray, objective: str, T: float | None = None, w_fuel: float | None = None,
              smoothing: tuple[float, ...] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Solve from the scaled guess z0. Returns (z, info); raises OCPError if IPOPT fails."""
        if objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
        lbg, ubg = self._lbg.copy(), self._ubg.copy()
        if objective == "time":
            weights = (0.0, 1.0)
        elif objective == "fuel":
            weights = (1.0, 0.0)
        elif objective == "weighted":
            if w_fuel is None or not 0.0 <= w_fuel <= 1.0:
                raise ValueError(f"w_fuel must lie in [0, 1] for the weighted objective, got {w_fuel!r}")
            weights = (w_fuel / FUEL_REF_G, (1.0 - w_fuel) / TIME_REF)
        else:
            if T is None or not (math.isfinite(T) and T > 0):
                raise ValueError(f"a fixed cycle time T > 0 is needed for objective 'fuel_at_time', got {T!r}")
            weights = (1.0, 0.0)
            lbg[self._g_T_index] = ubg[self._g_T_index] = T
        ks = self.settings.smoothing if smoothing is None else smoothing
        history = []
        t_start = time.perf_counter()
        iterations = 0
        lam_x = lam_g = None
        z = np.asarray(z0, dtype=float)
        stats: dict[str, Any] = {}
        for k in ks:
            # the smoothing penalty is scaled like the objective so k means the same for every objective
            scale = max(weights)
            args = dict(x0=z, p=nlp_parameters(weights[0], weights[1], k * scale, self.params), lbx=self._lbw,
                        ubx=self._ubw, lbg=lbg, ubg=ubg)
            if lam_x is not None:
                args.update(lam_x0=lam_x, lam_g0=lam_g)
            log.debug("IPOPT: the %s %s OCP, smoothing k = %g", self.braking, objective, k)
            with exclusive(self._solver):  # (one thread at a time in a solver: mpc.threads)
                sol = self._solver(**args)
                stats = self._solver.stats()
            iterations += int(stats.get("iter_count", 0) or 0)
            status = str(stats.get("return_status", stats.get("success", "unknown")))
            interrupt.check(status)  # an interrupted solve is no failed start: stop, record nothing
            if not stats.get("success", False) and status not in ("Solved_To_Acceptable_Level",):
                raise OCPError(
                    f"{self.settings.solver} failed on the {self.braking} {objective} problem"
                    f"{'' if T is None else f' at T = {T:.3f} s'} (smoothing k = {k:g}): status {status}"
                )
            z = np.array(sol["x"]).ravel()
            lam_x, lam_g = sol["lam_x"], sol["lam_g"]
            fuel_g, T_sol, _ = (float(v) for v in self._fn_parts(z))
            history.append({"k": k, "objective": float(sol["f"]), "T": T_sol, "fuel_g": fuel_g})
        return z, {"status": status, "iterations": iterations, "wall_time": time.perf_counter() - t_start,
                   "smoothing": history}

    # ------------------------------------------------------------------ unpack
    def unpack(self, z: np.ndarray) -> dict[str, Any]:
        """Mesh-point trajectory from a scaled decision vector: t, states, position, controls, phase.

        ``phase[i]`` is the phase of the interval that starts at sample i; the last sample closes phase 4.
        """
        d = self.settings.degree
        durs = [float(z[i]) for i in self._index["dur"]]
        x_start = z[self._index["X"][0]:self._index["X"][0] + 5] * X_SCALE
        ts, xs, us, phase = [0.0], [np.asarray(x_start, dtype=float)], [], []
        t0, ui, xci = 0.0, 0, 0
        for k, ph in enumerate(self.phases):
            n_int = self.settings.intervals[ph - 1]
            steps = [durs[k] / n_int] * n_int
            for h in steps:
                us.append(z[self._index["U"][ui]:self._index["U"][ui] + 3] * U_SCALE)
                ui += 1
                off = self._index["XC"][xci] + 5 * (d - 1)
                xs.append(z[off:off + 5] * X_SCALE)
                xci += 1
                t0 += h
                ts.append(t0)
                phase.append(ph)
        xs = np.array(xs)
        return {"durations": durs, "t": np.array(ts), "states": xs[:, :4], "position": xs[:, 4],
                "controls": np.array(us), "phase": np.array(phase + [4])}

    def objective_parts(self, z: np.ndarray) -> tuple[float, float]:
        fuel_g, T, _ = (float(v) for v in self._fn_parts(z))
        return fuel_g, T


# ----------------------------------------------------------------------------------------------------
def template_guess(params: LoaderParams, leg_time: float, accel_fraction: float, dt: float = 0.05) -> dict[str, np.ndarray]:
    """A plain guess: triangular speed profile each way, steady lift over the cycle, mid engine speed.

    ``accel_fraction`` splits each leg's time between the driving phase (1 or 3) and the braking phase.
    Not dynamically consistent; IPOPT only needs the shape.
    """
    p = params
    T = 2.0 * leg_time
    t = np.arange(0.0, T + 1e-9, dt)
    t[-1] = T
    v_peak = 2.0 * p.reverse_distance / leg_time
    ta = accel_fraction * leg_time

    def leg_speed(tl: np.ndarray) -> np.ndarray:
        return np.where(tl < ta, v_peak * tl / ta, v_peak * (leg_time - tl) / (leg_time - ta))

    first = t <= leg_time
    V = np.where(first, -leg_speed(t), leg_speed(t - leg_time))
    s = np.concatenate([[0.0], np.cumsum(0.5 * (V[1:] + V[:-1]) * np.diff(t))])
    s[first] *= p.reverse_distance / max(-s[first].min(), 1e-9)
    s[~first] = -p.reverse_distance + (s[~first] - s[~first][0]) * p.forward_distance / max(s[-1] - s[~first][0], 1e-9)
    H = p.H_0 + (p.H_T - p.H_0) * np.clip(t / (0.9 * T), 0.0, 1.0)
    V_b = np.gradient(H, t)
    omega = np.full_like(t, 0.5 * (p.omega_0 + p.omega_max))
    phase = np.where(first, np.where(t < ta, 1, 2), np.where(t - leg_time < ta, 3, 4))
    phase[-1] = 4
    n = len(t) - 1
    controls = np.zeros((n, 3))
    controls[:, 0] = 150.0
    controls[:, 2] = np.where(np.isin(phase[:-1], (2, 4)), 0.5 * p.U_b_max, 0.0)  # bounds zero it where unused
    return {"t": t, "states": np.column_stack([omega, V, H, V_b]), "position": s, "controls": controls, "phase": phase}


def get_ocp(braking: str, params: LoaderParams | dict | None = None, settings: OCPSettings | None = None) -> CycleOCP:
    """The NLP for these inputs with the scenario's bounds (the NLP itself is built once per machine and mesh
    and kept for the process, :data:`NLP_CACHE_SIZE`; building takes seconds)."""
    return CycleOCP(braking, resolve(params), settings or OCPSettings())


DEFAULT_STARTS = ((5.0, 0.7), (6.0, 0.75), (4.6, 0.6), (8.0, 0.8))  # (leg time s, accel fraction)
MAX_STARTS = 100  # template starts of one solve at most (each a solve of 1-10 s)


# Re-simulation acceptance (the project's figures): 5 cm in distance, 2 cm in height, 1 % violation.
VERIFY_TOL = {"distance": 0.05, "height": 0.02, "violation": 0.01}


def verification_passed(v: dict[str, Any]) -> bool:
    """True if a re-simulation meets the end targets and holds the constraints (VERIFY_TOL). A value read back as
    null (a NaN, as a cache entry writes it) fails, as the NaN did (it was a TypeError)."""
    def value(key: str) -> Any:
        return math.nan if v[key] is None else v[key]

    return (
        abs(value("reversing_error_m")) <= VERIFY_TOL["distance"]
        and abs(value("final_position_error_m")) <= VERIFY_TOL["distance"]
        and abs(value("final_height_error_m")) <= VERIFY_TOL["height"]
        and value("max_violation") <= VERIFY_TOL["violation"]
    )


def refined_mesh(durations: list[float], base: tuple[int, ...], max_interval: float) -> tuple[int, int, int, int]:
    """Intervals per phase so that no mesh interval is longer than ``max_interval`` seconds."""
    return tuple(max(int(b), int(math.ceil(dur / max_interval))) for dur, b in zip(durations, base, strict=True))  # type: ignore[return-value]


def check_cycle_time(T: Any, name: str = "T") -> float:
    """``T`` as a fixed cycle time in [MIN_CYCLE_TIME, MAX_CYCLE_TIME] s, else ValueError naming ``name``."""
    T = plain(T)  # (a float32 as the number it prints, not its binary value)
    ok = isinstance(T, numbers.Real) and not isinstance(T, (bool, np.bool_)) and is_finite(T)  # numpy scalars too
    if not (ok and MIN_CYCLE_TIME <= T <= MAX_CYCLE_TIME):
        raise ValueError(
            f"{name} must be a finite cycle time in [{MIN_CYCLE_TIME:g}, {MAX_CYCLE_TIME:g}] s, got {shown(T)}"
            + (f": each phase of the OCP is bounded to {MAX_PHASE_DURATION:g} s and the braking phases take "
               f"under a second, so no longer cycle exists in it (the fuel-optimal cycle takes about 21.5 s)"
               if ok and T > MAX_CYCLE_TIME else
               f": each of the {len(cycle.PHASES)} phases lasts at least {cycle.MIN_PHASE_DURATION:g} s (the "
               f"shortest cycle of the scenario ranges takes ~5.7 s)" if ok and T > 0 else ""))
    return float(T)


def with_scenario(braking: str | None, params: LoaderParams | dict | None, scenario: Any) -> tuple[str, LoaderParams]:
    """(braking, parameters) of a call that may name a :class:`wl_env.scenario.Scenario` (its cycle on the
    machine ``params``; ``braking``, if given, must agree with it)."""
    if scenario is None:
        return cycle.check_braking(braking or "service"), resolve(params)
    from wl_env.scenario import resolve_scenario

    s = resolve_scenario(scenario, braking)
    check_no_overridden(params, s)
    return s.braking, s.params(resolve(params))


@in_turn  # (CasADi from one thread at a time: mpc.threads)
def solve_ocp(
    braking: str | None = None,
    objective: str = "time",
    T: float | None = None,
    w_fuel: float | None = None,
    params: LoaderParams | dict | None = None,
    settings: OCPSettings | None = None,
    warm_start: OCPResult | None = None,
    starts: tuple[tuple[float, float], ...] | None = None,
    verify: bool = True,
    refine: bool = True,
    max_interval: float = 0.15,
    max_refinements: int = 3,
    scenario: Any = None,
) -> OCPResult:
    """Solve the cycle OCP and return the best optimum found, re-simulated and refined until it holds.

    The cycle is ``scenario``'s (a :class:`wl_env.scenario.Scenario`: its start state, distances, dump
    height, payload and rolling resistance on the machine ``params``), else that of ``params`` itself. A
    warm start from another scenario's optimum is reshaped to this one's first (:func:`transport`).

    Multi-start: each (leg time, acceleration fraction) in ``starts`` gives a template guess; a
    ``warm_start`` result is tried first. All starts are recorded in ``result.starts``. With ``verify``,
    the best candidate whose re-simulation meets the targets (``VERIFY_TOL``) wins; a better one that
    does not reproduce is a discretization artefact, not an optimum. With ``refine``, if no candidate
    reproduces, the best is solved again on a mesh with at least twice the intervals and none longer than
    ``max_interval`` (halved at each further failure), warm-started from it; ``result.starts`` records
    every mesh tried. A result whose re-simulation still fails has ``success`` False and says so in its status.
    """
    braking, p = with_scenario(braking, params, scenario)
    # (a float32 as the number it prints: np.float32(9.1) was solved for, and recorded as, 9.1000003815 s)
    T, w_fuel = plain(T), plain(w_fuel)
    check_solve_arguments(objective, T, settings, warm_start, starts, max_interval, max_refinements, w_fuel)
    check_flag("verify", verify), check_flag("refine", refine)  # (verify="no" verified, as any string would)
    w_fuel, max_refinements = None if w_fuel is None else float(w_fuel), int(max_refinements)
    settings = settings or OCPSettings()
    try:
        result = _solve_on_mesh(braking, objective, T, w_fuel, p, settings, warm_start, starts, verify)
    except OCPError:
        if objective != "fuel_at_time" or warm_start is not None or starts is not None:
            raise
        # Just above T_min the templates can all fail (a TC scenario at 9.3 s, 0.5 % over its T_min of 9.256 s, was
        # called infeasible): its minimum-time cycle, on the mesh that cycle needed, is a start that solves (as the
        # scoring's direct solves start)
        r_time = solve_ocp(braking, "time", params=p, settings=settings, verify=verify, refine=refine,
                           max_interval=max_interval, max_refinements=max_refinements)
        if T < r_time.T:
            raise
        result = _solve_on_mesh(braking, objective, T, w_fuel, p, replace(settings, intervals=tuple(r_time.mesh)),
                                r_time, (), verify)
    if not verify:
        return result
    history = [_mesh_record(result)]
    for attempt in range(max_refinements if refine else 0):
        if history[-1]["verified"]:
            break
        # at least twice the intervals of the mesh that failed: a few more barely change the error
        mesh = tuple(max(n, 2 * m) for n, m in zip(
            refined_mesh(result.phase_durations, settings.intervals, max_interval / 2**attempt), result.mesh, strict=True))
        if max(mesh) > MAX_PHASE_INTERVALS:  # (the result stands as it is: its check failed, and says so below)
            log.warning("mesh refinement stopped: %s intervals would pass %d per phase", mesh, MAX_PHASE_INTERVALS)
            break
        previous = result
        result = _solve_on_mesh(braking, objective, T, w_fuel, p, replace(settings, intervals=mesh), previous, (), verify)
        result.starts = previous.starts + result.starts
        history.append(_mesh_record(result))
    result.verification["mesh_history"] = history
    if not result.verification["passed"]:  # solved, but its cycle does not reproduce: no optimum to use
        result.success = False
        result.status += " (re-simulation check failed)"
    return result


def check_solve_arguments(objective: Any, T: Any, settings: Any, warm_start: Any, starts: Any, max_interval: Any,
                          max_refinements: Any, w_fuel: Any = None) -> None:
    """:func:`solve_ocp`'s arguments, each refused by name (a string settings was a TypeError from dataclasses, a
    NaN start an error from numpy, T with another objective than fuel_at_time was ignored without a word, as
    w_fuel with another than weighted)."""
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {shown(objective)}")
    if objective == "fuel_at_time":
        check_cycle_time(T)
    elif T is not None:
        raise ValueError(f"T is the cycle time of objective 'fuel_at_time'; objective {objective!r} takes none, got {shown(T)}")
    if objective == "weighted":
        if not (is_real_number(w_fuel) and 0.0 <= w_fuel <= 1.0):
            raise ValueError(f"w_fuel must be a number in [0, 1] for the weighted objective, got {shown(w_fuel)}")
    elif w_fuel is not None:
        raise ValueError(f"w_fuel is the fuel weight of objective 'weighted'; objective {objective!r} takes none, "
                         f"got {shown(w_fuel)}")
    if settings is not None and not isinstance(settings, OCPSettings):
        raise ValueError(f"settings must be an OCPSettings or None, got {type(settings).__name__}")
    if warm_start is not None:
        if not isinstance(warm_start, OCPResult):
            raise ValueError(f"warm_start must be an OCPResult or None, got {type(warm_start).__name__}")
        from mpc.benchmark.pareto import check_result

        problem = check_result(warm_start.to_dict())  # (as a cached result is checked; numpy's numbers too)
        if problem:
            raise ValueError(f"warm_start is no consistent OCPResult: {problem}")
    if starts is not None:
        ok = isinstance(starts, (tuple, list)) and all(
            isinstance(st, (tuple, list)) and len(st) == 2 and all(is_real_number(v) for v in st)
            and 0.1 <= st[0] <= 30.0 and 0.0 < st[1] <= 1.0 for st in starts)
        if not ok:
            raise ValueError("starts must be (leg time in [0.1, 30] s, acceleration fraction in (0, 1]) pairs, got "
                             f"{shown(starts)}")
        if len(starts) > MAX_STARTS:  # (each a solve of seconds: 10**5 of them were taken, days of work)
            raise ValueError(f"starts must be at most {MAX_STARTS} pairs (each one a solve), got {len(starts)}")
    if not (is_real_number(max_interval) and 0.001 <= max_interval <= 10.0):
        raise ValueError(f"max_interval must lie in [0.001, 10] s, got {shown(max_interval)}")
    if not (is_integer(max_refinements) and 0 <= max_refinements <= 20):  # (numpy's integers too: np.int64(3) was refused)
        raise ValueError(f"max_refinements must be an integer in [0, 20], got {shown(max_refinements)}")


def _mesh_record(r: OCPResult) -> dict[str, Any]:
    return {"mesh": list(r.mesh), "T": r.T, "fuel_g": r.fuel_g, "verified": r.verification["passed"]}


def _solve_on_mesh(braking, objective, T, w_fuel, p, settings, warm_start, starts, verify) -> OCPResult:
    ocp = get_ocp(braking, p, settings)
    candidates: list[tuple[str, np.ndarray]] = []
    if warm_start is not None:
        ws = transport(warm_start, p)
        candidates.append(("warm_start", ocp.guess_from_trajectory(
            np.asarray(ws.t), np.asarray(ws.states), np.asarray(ws.position),
            np.asarray(ws.controls), np.asarray(ws.phase))))
    if starts is None:
        starts = DEFAULT_STARTS if warm_start is None else ()
        if objective == "fuel_at_time" and T is not None:
            starts = tuple((T / 2.0, a) for _, a in starts)
    for leg, frac in starts:
        g = template_guess(p, leg, frac)
        candidates.append((f"template(leg={leg:g}s, accel={frac:g})", ocp.guess_from_trajectory(**g)))
    solved, records, errors = [], [], []
    mesh = list(ocp.settings.intervals)
    for name, z0 in candidates:
        try:
            z, info = ocp.solve(z0, objective, T=T, w_fuel=w_fuel)
        except OCPError as exc:
            records.append({"start": name, "mesh": mesh, "status": str(exc)})
            errors.append(str(exc))
            continue
        fuel_g, T_sol = ocp.objective_parts(z)
        value = info["smoothing"][-1]["objective"]
        records.append({"start": name, "mesh": mesh, "status": info["status"], "objective": value, "T": T_sol,
                        "fuel_g": fuel_g, "iterations": info["iterations"], "wall_time": info["wall_time"]})
        solved.append((value, len(records) - 1, z, info))
    if not solved:
        statuses = sorted({e.rsplit("status ", 1)[-1] for e in errors})
        hint = ""
        if objective == "fuel_at_time" and any("Infeasible" in s for s in statuses):
            hint = (f"; no cycle of T = {T:.3f} s exists within the constraints (below the minimum cycle time?"
                    f" see `wl ocp --objective time --braking {braking}`)")
        elif any("Infeasible" in s for s in statuses):
            hint = "; the targets cannot be met within the constraints (e.g. H_T out of the boom's reach)"
        raise OCPError(f"{ocp.settings.solver} found no optimum for the {braking} {objective} problem from "
                       f"{len(errors)} start(s), solver status: {', '.join(statuses)}{hint}")
    # Best objective first; with verify, the first that reproduces in simulation wins (else the best).
    solved.sort(key=lambda c: c[0])
    best = None
    for _value, i, z, info in solved:
        result = _result(ocp, z, info, objective, T, w_fuel, p, records)
        if not verify:
            return result
        from mpc.benchmark.verify import verify_result

        result.verification = verify_result(result, p)
        result.verification["passed"] = records[i]["verified"] = verification_passed(result.verification)
        best = best or result
        if result.verification["passed"]:
            return result
    return best


def _result(ocp: CycleOCP, z: np.ndarray, info: dict[str, Any], objective: str, T: float | None,
            w_fuel: float | None, p: LoaderParams, records: list[dict[str, Any]]) -> OCPResult:
    sol = ocp.unpack(z)
    fuel_g, T_sol = ocp.objective_parts(z)
    return OCPResult(
        braking=ocp.braking, objective=objective, T=T_sol, fuel_g=fuel_g, phase_durations=sol["durations"],
        t=sol["t"].tolist(), states=sol["states"].tolist(), controls=sol["controls"].tolist(),
        phase=[int(v) for v in sol["phase"]], position=sol["position"].tolist(), status=info["status"],
        success=True, iterations=info["iterations"], wall_time=sum(r.get("wall_time", 0.0) for r in records),
        w_fuel=None if w_fuel is None else float(w_fuel), target_T=None if T is None else float(T),  # (numpy's: no JSON)
        params_fingerprint=p.fingerprint(), mesh=list(ocp.settings.intervals),
        degree=ocp.settings.degree, solver=ocp.settings.solver, smoothing=info["smoothing"], starts=records,
        scenario_fields=scenario_fields(p), scenario=scenario_of(p, ocp.braking),
    )


def scenario_of(p: LoaderParams, braking: str) -> dict[str, Any] | None:
    """The scenario a parameter set drives, as a dict (None if a field lies outside the scenario ranges)."""
    from wl_env.scenario import Scenario

    try:
        return Scenario.from_params(p, braking).to_dict()
    except ValueError:
        return None


def scenario_fields(p: LoaderParams) -> dict[str, float]:
    return {f: float(getattr(p, f)) for f in SCENARIO_FIELDS}


def transport(result: OCPResult, params: LoaderParams) -> OCPResult:
    """An optimum of another scenario reshaped as a guess for ``params``' scenario: positions scaled per
    leg to its distances, heights mapped from H_0..H_T onto its own, times kept. (A warm start needs the
    shape, not consistency; without the scenario it was solved for, it is returned as it is.)"""
    src = result.scenario_fields
    if not src:
        return result
    dst = scenario_fields(params)
    x, s_new = transport_states(result.states, result.position, result.phase, src, dst)
    x[0, 0] = dst["omega_0"]
    return replace(result, states=x.tolist(), position=s_new.tolist(), scenario_fields=dst)


def transport_states(states: Any, position: Any, phase: Any, src: dict[str, float],
                     dst: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """States [omega, V, H, V_b, ...] and positions s (m) of a cycle of scenario ``src`` (scenario_fields),
    reshaped for ``dst``: positions scaled per leg (phases 1-2, 3-4) to its distances, heights mapped from
    H_0..H_T onto its own (the bucket speed with them); the engine and the travel speed kept."""
    phase = np.asarray(phase)
    s = np.asarray(position, dtype=float)
    rd, rd_new = src["reverse_distance"], dst["reverse_distance"]
    s_new = np.where(phase <= 2, s * rd_new / rd,
                     -rd_new + (s + rd) * dst["forward_distance"] / src["forward_distance"])
    x = np.array(states, dtype=float)
    lift = (dst["H_T"] - dst["H_0"]) / (src["H_T"] - src["H_0"])
    x[:, 2] = dst["H_0"] + (x[:, 2] - src["H_0"]) * lift
    x[:, 3] *= lift
    return x, s_new
