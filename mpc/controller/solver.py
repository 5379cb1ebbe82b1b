"""The MPC's solver: the grid NLPs, built once per model and slot layout, and IPOPT on them.

Built models, NLPs and IPOPT instances are shared by every controller of a process (building one takes a
second or two), through ``functools.lru_cache`` on their defining arguments. The controller takes any
object with :meth:`IpoptSolver.solve`'s signature, so a test can inject a failing or slow solver.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import dataclasses
import functools
import gc
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import casadi as ca
import numpy as np

from mpc import interrupt
from mpc.controller.grid import N_XR, GridNLP, StepModel, model_structure, slot_function
from mpc.threads import exclusive
from wl_env.episode import DISTANCE_TOL, HEIGHT_TOL
from wl_env.params import LoaderParams, check_flag, is_integer, is_real_number, plain, shown

log = logging.getLogger(__name__)

# A schedule meets the targets if it misses none by more than this (m): a quarter of the episode's own success
# tolerance (wl_env.episode: 5 cm in position, 2 cm in height), the rest the closed loop's margin for model error.
# (In metres, not relative to the leg: the episode's check is. Until stop 44 it was 1e-3 of the leg and of H_T,
# 4-10 mm over the scenarios' legs; that kept TC's nominal minimum time a step over T_min, see docs/benchmarks.md.)
MISS_TOL_M = {"reversing point": DISTANCE_TOL / 4, "end position": DISTANCE_TOL / 4, "end height": HEIGHT_TOL / 4}
EXCESS_TOL = 1e-4  # ... and no planned deceleration exceeds the limit by more than this (relative)
# A solve stopped at its deadline (solve_until) is a plan if its iterate meets the rows to this (IPOPT's
# primal infeasibility, max norm): feasible, if not yet optimal, as a real-time iteration's.
DEADLINE_FEASIBLE_TOL = 1e-4  # (the acceptable level the solves here stop at, ipopt.acceptable_tol)


@dataclass
class Solve:
    """One NLP solve: the schedule it was for and what came of it."""

    counts: dict[int, int]
    first_phase: int
    ok: bool
    status: str
    J: float = math.inf  # the NLP objective: fuel (g) plus the target and deceleration penalties
    fuel_g: float = math.nan
    misses_m: dict[str, float] = field(default_factory=dict)  # the signed target misses (m)
    excess: float = 0.0  # the largest relative excess over the deceleration limit the plan has
    z: np.ndarray | None = None
    lam_x: np.ndarray | None = None
    lam_g: np.ndarray | None = None
    lam_p_source: Callable[[], np.ndarray] | None = field(default=None, repr=False)  # lam_p, evaluated on demand
    iterations: int = 0
    wall: float = 0.0

    @functools.cached_property
    def lam_p(self) -> np.ndarray | None:
        """CasADi's lam_p at the plan (minus dJ/dp: the schedule search's step sensitivities), evaluated at its
        first use: only a full plan's schedule search reads it, and a short horizon's real-time iteration spent
        0.24 ms of its ~4 ms step on it (measured, stop 47). None where the solve gave no plan."""
        return None if self.lam_p_source is None else self.lam_p_source()

    def keep_lam_p(self) -> None:
        """Evaluate lam_p now and drop its source (which holds the NLP): for a plan kept beyond its solvers."""
        _ = self.lam_p
        self.lam_p_source = None

    @property
    def feasible(self) -> bool:
        return self.ok and self.within()

    def within(self, factor: float = 1.0) -> bool:
        """The plan misses no target by more than ``factor`` times its MISS_TOL_M and keeps the deceleration
        limit."""
        return not self.missed(factor) and self.excess <= EXCESS_TOL

    def missed(self, factor: float = 1.0) -> list[str]:
        """The targets the plan misses by more than ``factor`` times their MISS_TOL_M."""
        return [name for name, v in self.misses_m.items() if abs(v) > factor * MISS_TOL_M[name]]


@dataclass(frozen=True)
class SolverResult:
    """What a solver returns for one NLP solve (z, lam_x, lam_g, lam_p_source None where it failed to produce them;
    ``lam_p_source()``: CasADi's lam_p at z, on demand)."""

    ok: bool
    status: str
    iterations: int
    z: np.ndarray | None = None
    lam_x: np.ndarray | None = None
    lam_g: np.ndarray | None = None
    lam_p_source: Callable[[], np.ndarray] | None = None
    f: float = math.inf


class GridSolver(Protocol):
    def solve(self, nlp: GridNLP, args: dict[str, Any], x0: np.ndarray, lam_x0: np.ndarray | None = None,
              lam_g0: np.ndarray | None = None) -> SolverResult: ...

    def prepare(self, nlp: GridNLP) -> None: ...


# The step models built, per machine (StepModel.key). A dict, not an lru_cache: that would key on the
# whole params, and build again for each scenario.
_MODELS: dict[tuple, StepModel] = {}
MODELS_KEPT = 16


def step_model(braking: str, params: LoaderParams, dt: float, substeps: int, omega_margin: float) -> StepModel:
    """The model of ``params``'s scenario, on the functions built once for its machine (and on its NLPs,
    :func:`grid_nlp`: the models of one machine are equal)."""
    key = model_structure(braking, params, dt, substeps, omega_margin)
    built = _MODELS.get(key)
    if built is None:
        built = _MODELS[key] = StepModel(braking, params, dt, substeps, omega_margin)
        while len(_MODELS) > MODELS_KEPT:
            del _MODELS[next(iter(_MODELS))]
    return built.with_params(params)


# The NLPs one controller plans with (one per first phase; the MX twin of the first where a cycle's first
# solve fails on the warm solver) and their solvers: a suite run moves on to other slot layouts. Each NLP
# with its IPOPT holds a few MB beside its machine's slot functions (measured at stop 45: a layout's four
# +41 MB in a fresh process, the next layout's +7 MB; 50-200 MB each before).
NLP_CACHE = 8
# The short horizons' NLPs and solvers: those along a schedule and along each schedule a move away from it (
# MPCController._prepare_horizons), 9-12 a cycle, and their machine's other layouts' (slots under a horizon's).
HORIZON_CACHE = 16


CacheInfo = collections.namedtuple("CacheInfo", "hits misses maxsize currsize")


class _NLPCache:
    """The grid NLPs built, least recently used out first (functools.lru_cache's interface): a cache that
    can also say what it holds (``holds``), which lru_cache cannot, so that a first plan picks a layout
    whose NLPs are built."""

    def __init__(self, maxsize: int) -> None:
        self.maxsize, self._nlps, self._hits, self._misses = maxsize, collections.OrderedDict(), 0, 0

    def __call__(self, model: StepModel, first_phase: int, slots: tuple[tuple[int, int], ...],
                 symbolic: str = "SX") -> GridNLP:
        """The NLP of a model from ``first_phase`` on with ``slots`` ((phase, slots), ...)."""
        key = (model, first_phase, slots, symbolic)
        nlp = self._nlps.pop(key, None)
        if nlp is None:
            self._misses += 1
            nlp = GridNLP(model, first_phase, dict(slots), symbolic)
        else:
            self._hits += 1
        self._nlps[key] = nlp
        while len(self._nlps) > self.maxsize:
            self._nlps.popitem(last=False)
        return nlp

    def holds(self, model: StepModel, first_phase: int, slots: tuple[tuple[int, int], ...], symbolic: str = "SX") -> bool:
        return (model, first_phase, slots, symbolic) in self._nlps

    def cache_info(self) -> CacheInfo:
        return CacheInfo(self._hits, self._misses, self.maxsize, len(self._nlps))

    def cache_clear(self) -> None:
        self._nlps.clear()
        self._hits = self._misses = 0


grid_nlp = _NLPCache(NLP_CACHE)


@functools.lru_cache(maxsize=HORIZON_CACHE)
def horizon_nlp(model: StepModel, first_phase: int, slots: tuple[tuple[int, int], ...], open_phase: int | None) -> GridNLP:
    """A short horizon's NLP, ending open in ``open_phase`` (None: at the cycle's end). A cache of its own
    (with its solvers): a cycle prepares 9-12 of them, which would push the full layouts out of theirs."""
    return GridNLP(model, first_phase, dict(slots), "SX", open_phase, short=True)


# A wall-clock deadline per solve call (time.perf_counter() s), per thread: IPOPT's own max_wall_time is
# fixed when its solver is built, and a real-time controller's solves each have their own.
_CALL = threading.local()


@contextlib.contextmanager
def _per_call(name: str, value: Any, default: Any) -> Iterator[None]:
    """``_CALL.<name>`` = ``value`` in this thread within the block, restored after it."""
    before = getattr(_CALL, name, default)
    setattr(_CALL, name, value)
    try:
        yield
    finally:
        setattr(_CALL, name, before)


def solve_until(deadline: float | None) -> contextlib.AbstractContextManager[None]:
    """Warm IPOPT solves in this thread, within the block, stop at ``deadline`` (time.perf_counter()
    seconds; None: no limit) with the iterate so far (status ``Deadline_Exceeded``; ok if the iterate is
    feasible, DEADLINE_FEASIBLE_TOL)."""
    return _per_call("deadline", deadline, None)


def unbudgeted() -> contextlib.AbstractContextManager[None]:
    """Warm IPOPT solves in this thread, within the block, run without the solver's ``time_budget`` (a first plan:
    the budget and ``deadline_ms`` bound the steps after it)."""
    return _per_call("unbudgeted", True, False)


def far_starts(far: bool = True) -> contextlib.AbstractContextManager[None]:
    """Warm IPOPT solves in this thread, within the block, start far from their solution (``far``): pushed
    off their bounds by WARM_START_PUSH_FAR, not WARM_START_PUSH_NEAR."""
    return _per_call("far", far, False)


class _DeadlineCallback(ca.Callback):
    """IPOPT's intermediate callback: stop once the calling thread's deadline (:func:`solve_until`) passed.
    It takes the objective only (empty inputs otherwise: no copy of the iterate per iteration)."""

    def __init__(self) -> None:
        ca.Callback.__init__(self)
        self.construct("deadline", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "stop"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.scalar() if ca.nlpsol_out(i) == "f" else ca.Sparsity(0, 0)

    def eval(self, arg: Any) -> list[int]:
        deadline = getattr(_CALL, "deadline", None)
        stop = deadline is not None and time.perf_counter() > deadline
        if stop:
            _CALL.stopped = True
        return [int(stop)]


_DEADLINE_CALLBACK: _DeadlineCallback | None = None  # one for every solver (built on first use)


# No derivatives of the NLP's own: its values may be compiled functions, which have none
# (mpc.controller.codegen); lam_p comes from GridNLP.lam_p, f, g and lam_x from the solver itself.
NO_NLP_GRAD = {"no_nlp_grad": True, "calc_lam_p": False, "calc_lam_x": False, "calc_f": False, "calc_g": False}


# How far a warm start's variables, slacks and bound multipliers are pushed off their bounds (solver
# options, so one IPOPT function per value). Near: a solve from a plan for the same plant estimate (a full
# horizon's step, a target-time first plan's schedule search, a re-plan where a horizon missed a target). Far
# (:func:`far_starts`): a short horizon's re-plan for a plant estimate that moved, and its schedule move (stop
# 50); a minimum-time first plan's schedule moves (stop 51). At 1e-6 the fraction-to-the-boundary rule cut such
# a re-plan's first 20-30 steps to 2-20 % of their length; 1e-3 took 14-23 iterations where 1e-6 took 20-48 (a
# mismatch corner's 10 re-plans, replayed). Near starts are slower at 1e-3: a target-time first plan's search
# took longer on 4 of 7 `test` cycles (stop 50), 2.4x as long on 10 (stop 51).
WARM_START_PUSH_NEAR, WARM_START_PUSH_FAR = 1e-6, 1e-3

# MUMPS's fill-reducing ordering of the KKT matrix: 2 (approximate minimum fill). Its automatic choice (7)
# took a slower one for the longer cycles' layouts: on 20 `test` cycles at 1.15 T_min the first plans' 76
# solves took 1.36x as long in all (32 of them over 1.2x; the same iterates), the mismatch corners the same
# (scripts/bench_mumps_ordering.py, stop 51).
MUMPS_PIVOT_ORDER = 2


def _build_ipopt(nlp: GridNLP, warm: bool, max_iter: int, max_wall_time: float | None,
                 push: float = WARM_START_PUSH_NEAR, pivot_order: int = MUMPS_PIVOT_ORDER) -> ca.Function:
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.tol": 1e-6,
            "ipopt.acceptable_tol": 1e-4, "ipopt.acceptable_iter": 2, "ipopt.mu_strategy": "adaptive",
            "ipopt.max_iter": max_iter,
            # MUMPS without its permuting scaling (a maximum transversal, for unsymmetric matrices): the same
            # iterates, 30-38 % less time per solve on the full plans' KKT systems (measured, stop 49)
            "ipopt.mumps_permuting_scaling": 0, "ipopt.mumps_pivot_order": pivot_order}
    if warm:
        opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-5,
                     "ipopt.warm_start_bound_push": push, "ipopt.warm_start_mult_bound_push": push,
                     "ipopt.warm_start_slack_bound_push": push})
        if max_wall_time is not None:
            opts["ipopt.max_wall_time"] = max_wall_time
        global _DEADLINE_CALLBACK
        _DEADLINE_CALLBACK = _DEADLINE_CALLBACK or _DeadlineCallback()
        opts.update({"iteration_callback": _DEADLINE_CALLBACK, "iteration_callback_ignore_errors": False})
    # the NLP and its derivatives from its slots' (built once per machine): ~0.1 s to build against ~1.8 s
    opts.update(nlp.derivative_functions, **NO_NLP_GRAD)
    return ca.nlpsol("mpc", "ipopt", nlp.mapped_nlp, opts)


# the full layouts' solvers, and the short horizons' (each a cache of its own, as their NLPs)
_ipopt = functools.lru_cache(maxsize=NLP_CACHE)(_build_ipopt)
_ipopt_horizon = functools.lru_cache(maxsize=HORIZON_CACHE)(_build_ipopt)


def checked_max_iter(max_iter: Any) -> int:
    """A solver's iteration limit: an integer in [1, 100000] (MPCConfig.max_iter's range; numpy's integers as the
    ints they hold), else a ValueError naming ``max_iter``."""
    max_iter = plain(max_iter)
    if not (is_integer(max_iter) and 1 <= max_iter <= 100_000):
        raise ValueError(f"max_iter must be an integer in [1, 100000], got {shown(max_iter)}")
    return max_iter


def checked_time_budget(time_budget: Any) -> float | None:
    """A solve's wall-time budget: > 0 s or None (MPCConfig.time_budget's range), else a ValueError naming
    ``time_budget`` (0 was IPOPT's "Invalid options" at the first plan, NaN no budget at all)."""
    time_budget = plain(time_budget)
    if time_budget is not None and not (is_real_number(time_budget) and time_budget > 0):
        raise ValueError(f"time_budget must be > 0 s or None, got {shown(time_budget)}")
    return time_budget


class IpoptSolver:
    """IPOPT on a grid NLP: warm-started solves at ``max_iter`` iterations and ``time_budget`` seconds of
    wall time at most (pushed off their bounds as :func:`far_starts` says); a cold solve (no multipliers
    given) at up to 500 iterations."""

    COLD_MAX_ITER = 500

    def __init__(self, max_iter: int = 100, time_budget: float | None = None) -> None:
        # (checked as MPCConfig checks them: max_iter 2.5 or True was taken as 2 or 1)
        self.max_iter, self.time_budget = checked_max_iter(max_iter), checked_time_budget(time_budget)

    def _function(self, nlp: GridNLP, warm: bool, far: bool = False) -> ca.Function:
        build = _ipopt_horizon if nlp.short else _ipopt
        budget = self.time_budget if warm and not getattr(_CALL, "unbudgeted", False) else None
        return build(nlp, warm, self.max_iter if warm else self.COLD_MAX_ITER, budget,
                     WARM_START_PUSH_FAR if far else WARM_START_PUSH_NEAR)

    def prepare(self, nlp: GridNLP) -> None:
        """Build the warm solver of an NLP now (not in the middle of a cycle; a far start's at its first use)."""
        self._function(nlp, warm=True)

    def solve(self, nlp: GridNLP, args: dict[str, Any], x0: np.ndarray, lam_x0: np.ndarray | None = None,
              lam_g0: np.ndarray | None = None) -> SolverResult:
        warm = lam_x0 is not None and lam_g0 is not None
        fn = self._function(nlp, warm, getattr(_CALL, "far", False))
        args = nlp.fix_leading_idle(args)
        extra = {"lam_x0": lam_x0, "lam_g0": lam_g0} if warm else {}
        log.debug("IPOPT: a %s grid NLP solve from phase %d", "warm" if warm else "cold", nlp.first_phase)
        _CALL.stopped = False
        with exclusive(fn):  # (one thread at a time in a solver: mpc.threads)
            sol = fn(x0=np.clip(x0, args["lbx"], args["ubx"]), **extra, **args)
            stats = fn.stats()
        status = str(stats.get("return_status", "unknown"))
        if status == "User_Requested_Stop" and getattr(_CALL, "stopped", False):
            status = "Deadline_Exceeded"  # (solve_until's, not an interrupt)
        interrupt.check(status)  # Ctrl-C inside IPOPT stops the run, not just this plan
        z = np.array(sol["x"]).ravel()
        ok = bool(stats.get("success")) or status == "Solved_To_Acceptable_Level"
        if status == "Deadline_Exceeded":
            inf_pr = stats.get("iterations", {}).get("inf_pr") or [math.inf]
            ok = inf_pr[-1] <= DEADLINE_FEASIBLE_TOL
            status += f" ({'a feasible' if ok else 'an infeasible'} iterate, {int(stats.get('iter_count', 0))} iterations)"
        ok = ok and bool(np.isfinite(z).all())
        if not np.isfinite(z).all():
            status += " (non-finite iterate)"
        lam_g = np.array(sol["lam_g"]).ravel()
        return SolverResult(ok=ok, status=status, iterations=int(stats.get("iter_count", 0)), z=z,
                            lam_x=np.array(sol["lam_x"]).ravel(), lam_g=lam_g,
                            lam_p_source=functools.partial(nlp.lam_p, z, np.array(args["p"]), lam_g), f=float(sol["f"]))


def stage_structure(nlp: GridNLP) -> dict[str, Any]:
    """GridNLP's stage-wise layout as fatrop's and hpipm's structure options state it (N stages, the states,
    controls and non-gap rows of each; the last stage is the end state alone)."""
    n = len(nlp.slots)
    return {"N": n, "nx": [N_XR] * (n + 1), "nu": [*nlp.stage_controls, 0], "ng": [*nlp.stage_rows, 0]}


@functools.lru_cache(maxsize=NLP_CACHE)
def _fatrop(nlp: GridNLP, max_iter: int) -> ca.Function:
    opts = {"structure_detection": "manual", **stage_structure(nlp), "print_time": False,
            "fatrop": {"print_level": 0, "max_iter": max_iter}}
    return ca.nlpsol("mpc_fatrop", "fatrop", nlp.nlp, opts)


class FatropSolver:
    """fatrop (a structure-exploiting interior point method: a Riccati recursion over the stages) on a
    grid NLP. Its CasADi interface takes a primal start only (no multipliers, no warm-started barrier), so
    each solve runs the barrier down from its default."""

    def __init__(self, max_iter: int = 300) -> None:
        # (checked as IpoptSolver's: 2.5 or True reached fatrop's options, "0" its solver's build at the first plan)
        self.max_iter = checked_max_iter(max_iter)

    def prepare(self, nlp: GridNLP) -> None:
        _fatrop(nlp, self.max_iter)

    def solve(self, nlp: GridNLP, args: dict[str, Any], x0: np.ndarray, lam_x0: np.ndarray | None = None,
              lam_g0: np.ndarray | None = None) -> SolverResult:
        fn = _fatrop(nlp, self.max_iter)
        with exclusive(fn):
            sol = fn(x0=np.clip(x0, args["lbx"], args["ubx"]), **args)
            stats = fn.stats()
        status = str(stats.get("return_status", "unknown"))
        interrupt.check(status)
        z = np.array(sol["x"]).ravel()
        ok = bool(stats.get("success")) and bool(np.isfinite(z).all())
        return SolverResult(ok=ok, status=f"fatrop: {status}", iterations=int(stats.get("iter_count", 0)), z=z,
                            lam_x=np.array(sol["lam_x"]).ravel(), lam_g=np.array(sol["lam_g"]).ravel(),
                            lam_p_source=functools.partial(np.ravel, np.array(sol["lam_p"])), f=float(sol["f"]))


@functools.lru_cache(maxsize=HORIZON_CACHE)  # (the real-time iteration runs on the short horizons)
def _sqp_rti(nlp: GridNLP, qpsol: str) -> ca.Function:
    qp_opts = {"hpipm": {**stage_structure(nlp), "hpipm": {"warm_start": True}}, "osqp": {"osqp": {"verbose": False}}}.get(qpsol, {})
    # The Lagrangian's Hessian is indefinite (the dynamics' curvature under the multipliers), which an
    # interior-point QP does not converge on: regularized to positive definite (measured on the 10-step
    # horizons: rows met to 1e-10 after one step; eigen-clip left 5e-6 and fell back to IPOPT 5x as often).
    # The full step, as a real-time iteration takes it: no line search (its merit evaluations cost 0.25 ms of a
    # 3.1 ms step and left the TC 11 s cycle the same to 0.1 mg; measured, stop 40).
    opts = {"qpsol": qpsol, "qpsol_options": {**qp_opts, "error_on_fail": False}, "max_iter": 1, "print_header": False,
            "print_iteration": False, "print_status": False, "print_time": False, "error_on_fail": False,
            "convexify_strategy": "regularize", "convexify_margin": 1e-6, "max_iter_ls": 0}
    return ca.nlpsol("mpc_rti", "sqpmethod", nlp.nlp, {**opts, **nlp.sqp_derivative_functions, **NO_NLP_GRAD})


MAX_EXTRA_STEPS = 100  # SqpRtiSolver's extra SQP steps at most (it takes 2; each a QP solve)


class SqpRtiSolver:
    """The real-time iteration: one SQP step per control step (CasADi's ``sqpmethod``, exact Hessian
    regularized to positive definite) from the previous plan, its QP solved by ``qpsol`` (hpipm: a Riccati
    interior point on the stage structure; osqp: sparse, structure-blind). A step that leaves the NLP's
    rows unmet by more than ``FEAS_TOL`` (a new phase's first horizon, a stop step coming into view) takes
    up to ``extra_steps`` more SQP steps from where it ended; a plan still unmet counts as failed (a
    fallback solver takes it)."""

    # (IPOPT's default constr_viol_tol, and a deadline-stopped IPOPT plan's: at 1e-5, 1.1e-5..3.4e-5 after three
    # steps handed 1-2 horizons per mismatch corner to IPOPT, 0.1-0.4 s each)
    FEAS_TOL = DEADLINE_FEASIBLE_TOL

    def __init__(self, qpsol: str = "hpipm", extra_steps: int = 2) -> None:
        extra_steps = plain(extra_steps)  # (True was taken as 1 step; a QP solver CasADi lacks failed at the first plan)
        if not (is_integer(extra_steps) and extra_steps >= 0):
            raise ValueError(f"extra_steps must be an integer >= 0, got {shown(extra_steps)}")
        if extra_steps > MAX_EXTRA_STEPS:  # (10**9: a plan whose rows stay unmet took SQP steps for hours)
            raise ValueError(f"extra_steps must be at most {MAX_EXTRA_STEPS}, got {shown(extra_steps)}")
        if not (isinstance(qpsol, str) and ca.has_conic(qpsol)):
            raise ValueError(f"qpsol must name a QP solver of CasADi's (hpipm, osqp, ...), got {shown(qpsol)}")
        self.qpsol, self.extra_steps = qpsol, extra_steps

    def prepare(self, nlp: GridNLP) -> None:
        _sqp_rti(nlp, self.qpsol)

    def solve(self, nlp: GridNLP, args: dict[str, Any], x0: np.ndarray, lam_x0: np.ndarray | None = None,
              lam_g0: np.ndarray | None = None) -> SolverResult:
        # a cold start is not a real-time iteration's: no multipliers, or the zeros of a first solve's guess (from
        # those an SQP iterate met the rows and became the cycle's first plan, unconverged)
        if lam_x0 is None or lam_g0 is None or not (np.any(lam_x0) or np.any(lam_g0)):
            return SolverResult(ok=False, status=f"sqp-rti ({self.qpsol}): no previous plan", iterations=0)
        fn = _sqp_rti(nlp, self.qpsol)  # (the bounds as they are: hpipm keeps the start's equalities)
        z, lam_x, lam_g = np.clip(x0, args["lbx"], args["ubx"]), lam_x0, lam_g0
        steps = 0
        while True:
            steps += 1
            with interrupt.guarded(), exclusive(fn):  # (sqpmethod swallows a KeyboardInterrupt: only the flag tells)
                sol = fn(x0=z, lam_x0=lam_x, lam_g0=lam_g, **args)
                interrupt.check("")
            z, lam_x, lam_g = (np.array(sol[key]).ravel() for key in ("x", "lam_x", "lam_g"))
            g = np.array(sol["g"]).ravel()
            infeas = float(np.max(np.maximum(args["lbg"] - g, 0.0) + np.maximum(g - args["ubg"], 0.0), initial=0.0))
            ok = bool(np.isfinite(z).all()) and infeas <= self.FEAS_TOL
            if ok or not np.isfinite(infeas) or steps > self.extra_steps:
                break
        return SolverResult(ok=ok, status=f"sqp-rti ({self.qpsol}): row residual {infeas:.1e} after {steps} steps",
                            iterations=steps, z=z, lam_x=lam_x, lam_g=lam_g,
                            lam_p_source=functools.partial(nlp.lam_p, z, np.array(args["p"]), lam_g),
                            f=float(sol["f"]))


class FallbackSolver:
    """A solver, and another for the solves it fails (their statuses both kept). ``short_only``: the
    first solver takes only the short horizons' NLPs (``GridNLP.short``), the fallback the full plans.
    ``lazy_fallback``: :meth:`prepare` builds the fallback only for the NLPs it solves itself; for the
    first solver's it is built at its first hand-over (the short horizons' IPOPT: 19-36 MB and 0.3-0.8 s
    per layout, half their solvers' memory and build time, for solves that fail rarely: none in the
    bench's nominal and test runs, docs/benchmarks.md section 3)."""

    def __init__(self, primary: GridSolver, fallback: GridSolver, short_only: bool = False,
                 lazy_fallback: bool = False) -> None:
        # (checked here: a primary that is no solver was an AttributeError at the controller's first plan, and
        # short_only="no" gave the RTI the full plans)
        for name, solver in (("primary", primary), ("fallback", fallback)):
            if not all(callable(getattr(solver, m, None)) for m in ("solve", "prepare")):
                raise ValueError(f"{name} must be a GridSolver (solve() and prepare()), got {type(solver).__name__}")
        self.primary, self.fallback, self.short_only = primary, fallback, check_flag("short_only", short_only)
        self.lazy_fallback = check_flag("lazy_fallback", lazy_fallback)
        self.handed_over = 0  # solves the first solver failed and the fallback took

    def primary_takes(self, nlp: GridNLP) -> bool:
        return nlp.short or not self.short_only

    def prepare(self, nlp: GridNLP) -> None:
        primary = self.primary_takes(nlp)
        if primary:
            self.primary.prepare(nlp)
        if not (primary and self.lazy_fallback):
            self.fallback.prepare(nlp)

    def solve(self, nlp: GridNLP, args: dict[str, Any], x0: np.ndarray, lam_x0: np.ndarray | None = None,
              lam_g0: np.ndarray | None = None) -> SolverResult:
        if not self.primary_takes(nlp):
            return self.fallback.solve(nlp, args, x0, lam_x0, lam_g0)
        first = self.primary.solve(nlp, args, x0, lam_x0, lam_g0)
        if first.ok:
            return first
        self.handed_over += 1
        r = self.fallback.solve(nlp, args, x0, lam_x0, lam_g0)
        return dataclasses.replace(r, status=f"{first.status}, then {r.status}", iterations=first.iterations + r.iterations)


def solver_name(solver: Any, nlp: GridNLP | None = None) -> str:
    """What solves ``nlp`` (any NLP if None) with ``solver``, for a message: "IPOPT", "fatrop", "SQP-RTI (hpipm)" (a
    subclass's name after it), a FallbackSolver's "<first>, then <fallback>" (its fallback alone where the first takes
    no such NLP), else the solver's class name."""
    if isinstance(solver, FallbackSolver):
        if nlp is not None and not solver.primary_takes(nlp):
            return solver_name(solver.fallback, nlp)
        return f"{solver_name(solver.primary, nlp)}, then {solver_name(solver.fallback, nlp)}"
    for kind, name in ((IpoptSolver, "IPOPT"), (FatropSolver, "fatrop"), (SqpRtiSolver, "SQP-RTI")):
        if isinstance(solver, kind):
            name += f" ({solver.qpsol})" if kind is SqpRtiSolver else ""
            # (an injected subclass by its own name too: it may change what the solver does)
            return name if type(solver) is kind else f"{name} ({type(solver).__name__})"
    return type(solver).__name__


def rti_on_short_horizons(ipopt: GridSolver) -> FallbackSolver:
    """The short horizons (``MPCConfig.horizon_steps``) by the real-time iteration (hpipm), ``ipopt`` for the
    full plans and where the iteration fails (``MPCConfig.horizon_solver`` "sqp-rti"; there built at its first
    failure, ``lazy_fallback``)."""
    return FallbackSolver(SqpRtiSolver("hpipm"), ipopt, short_only=True, lazy_fallback=True)


def release_solvers() -> None:
    """Drop every grid NLP and solver this process has built, and hand the freed heap back to the OS.

    For a long run that moves on to another model or slot layout (another scenario, another mode), whose
    NLPs it cannot reuse: glibc keeps freed pages otherwise, and the process held its peak (measured:
    440 MB after one cycle, 110 MB after this)."""
    from mpc.benchmark import ocp  # (the MPC's reference and the scoring build OCP NLPs too)

    _MODELS.clear()
    for cache in (grid_nlp, horizon_nlp, _ipopt, _ipopt_horizon, _fatrop, _sqp_rti, slot_function):
        cache.cache_clear()
    ocp.release_nlps()
    gc.collect()
    try:  # glibc only (elsewhere the memory is still freed, just not returned at once)
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass


# The candidates scripts/bench_mpc.py compares (each a factory of a fresh solver)
SOLVERS = {"ipopt": IpoptSolver, "fatrop": lambda: FallbackSolver(FatropSolver(), IpoptSolver()),
           "sqp-rti-hpipm": lambda: FallbackSolver(SqpRtiSolver("hpipm"), IpoptSolver()),
           "sqp-rti-osqp": lambda: FallbackSolver(SqpRtiSolver("osqp"), IpoptSolver()),
           "ipopt+sqp-rti": lambda: rti_on_short_horizons(IpoptSolver())}


def timed_solve(solver: GridSolver, nlp: GridNLP, counts: dict[int, int], first_phase: int, args: dict[str, Any],
                x0: np.ndarray, warm: Solve | None = None) -> Solve:
    """A :class:`Solve` of ``nlp`` for the schedule ``counts`` (warm-started from ``warm``'s multipliers if
    given): the solver's result with the plan's fuel, target misses and deceleration excess, and its wall
    time. A solver error is a failed solve with its message as the status, never an exception."""
    t0 = time.perf_counter()
    out = Solve(counts=dict(counts), first_phase=first_phase, ok=False, status="not solved")
    try:
        r = solver.solve(nlp, args, x0, *((warm.lam_x, warm.lam_g) if warm is not None else ()))
        out.ok, out.status, out.iterations = r.ok, r.status, r.iterations
        # (any GridSolver: one that said ok of a non-finite iterate made a NaN plan, whose controls the codec's
        # encoding turned into "no fuel, no brake, bucket down" without a word, the step flagged as no fallback)
        if r.ok and (r.z is None or not np.isfinite(r.z).all()):
            out.ok, out.status = False, f"{r.status} (non-finite iterate)" if r.z is not None else f"{r.status} (no iterate)"
        if r.z is not None:
            out.z, out.lam_x, out.lam_g, out.lam_p_source, out.J = r.z, r.lam_x, r.lam_g, r.lam_p_source, r.f
            out.fuel_g = float(nlp.fuel_g(r.z, args["p"]))
            out.misses_m = nlp.misses_m(r.z, args["p"])
            out.excess = nlp.excess(r.z)
    except (RuntimeError, ValueError) as exc:
        out.ok, out.status = False, f"error: {exc}"
    out.wall = time.perf_counter() - t0
    return out
