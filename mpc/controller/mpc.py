"""Shrinking-horizon MPC that drives ``WheelLoader-v0`` through the cycle, on the environment's own grid.

At every control step the controller reads the state from the observation and solves the rest of the
cycle as the environment will run it (:mod:`mpc.controller.grid`: the plant's RK4 step, its saturations and its
cut at V = 0, the driver's limits where the environment checks them), from the measured state, with the
plant as its model-error estimate has it. It applies the plan's first control and requests the gear
change when the plan's next step belongs to the next phase. Without model error the plan is what
happens, so the closed loop is the optimum on the grid.

The cycle time is the *schedule*: whole steps per phase. The first step plans it (rounded from the
continuous optimum of :mod:`mpc.benchmark.ocp`, then improved by moves of single steps between phases); later
steps keep it, and try the move that the parametric sensitivities of the step lengths predict to pay
(one extra solve, at most, per step). The mode decides what pays: the fewest steps (minimum time),
the least fuel in the steps until the target time (target time), or fuel and time weighed.

The NLPs (one per first phase) are built once and reused; each solve is warm-started from the
previous one (primal and dual; the plan one step later is the same vector). A failed or over-budget
solve applies the previous plan's next step and says so in ``last_info``.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mpc import interrupt
from mpc.controller.grid import MIN_STOP_SPEED, N_X, U_SCALE, X_SCALE, GridNLP, StepModel, apportion, steps_of
from wl_env import cycle
from wl_env.params import LoaderParams, resolve
from wl_env.physics import engine, lift

MODES = ("time", "target_time", "weighted")
FUEL_REF_G, TIME_REF = 100.0, 10.0  # the weighted mode's normalization (as the OCP's weighted objective)
# A schedule meets the targets if no relative miss exceeds this (6.6 mm at the reversing point, 5 mm in height).
MISS_TOL = 1e-3
EXCESS_TOL = 1e-4  # ... and no planned deceleration exceeds the limit by more than this (relative)
# Objective (g) per step in minimum-time mode and per step late in target-time mode: a step outweighs
# any fuel, not a target miss (MISS_TOL decides that first).
STEP_PRICE = 1.0e3
# g: the least predicted improvement worth a solve, when the first step plans the cycle and during it
# (a schedule move takes 10-30 iterations, 0.2-0.5 s: during the cycle only for a clear gain)
MIN_GAIN = 0.05
MIN_GAIN_ONLINE = 0.2
SEARCH_SOLVES = 12  # solves the first step may spend on the schedule
SEARCH_FAILURES = 2  # moves in a row that do not pay end the first step's search
RETRY_AFTER = 10  # steps before a move that did not pay is tried again (twice as many after each failure)
SLOT_ROUNDING = 4  # slots per phase are a multiple of this (NLPs are shared between nearby schedules)
# Model-error estimate [gain, offset m/s^2] (see MPCController._estimate_model_error): prior, its spread
# (a payload or mass error of ~20 %, a rolling-resistance error of ~0.3 m/s^2), bounds, forgetting.
THETA_PRIOR = np.array([1.0, 0.0])
THETA_PRIOR_STD = np.array([0.2, 0.3])
THETA_MIN, THETA_MAX = np.array([0.5, -1.0]), np.array([1.5, 1.0])
RLS_FORGETTING = 0.98
ACCEL_NOISE_STD = 0.01  # m/s^2: how well one step of the model predicts the measured acceleration
# Lift-load gain (plant payload / model payload, as the lift's power drawn from the engine shows it):
# prior, spread, bounds, and how well one step of the model predicts the engine's acceleration.
LIFT_GAIN_PRIOR, LIFT_GAIN_PRIOR_STD = 1.0, 0.2
LIFT_GAIN_MIN, LIFT_GAIN_MAX = 0.5, 1.5
ENGINE_ACCEL_NOISE_STD = 1.0  # rad/s^2
PREDICTION_ERROR_DECAY = 0.9  # per step, of the moving mean square of the one-step prediction error


@dataclass(frozen=True)
class MPCConfig:
    """MPC settings. ``mode``: minimum time, minimum fuel finishing by ``target_time`` (s), or
    ``w_fuel`` * fuel / 100 g + (1 - ``w_fuel``) * time / 10 s (weighted)."""

    mode: str = "time"
    target_time: float | None = None
    w_fuel: float | None = None
    # IPOPT iterations per solve after the first (the deterministic budget): a warm start takes 2-5; a
    # model estimate that jumps (a heavier plant seen) can take ~90, from a plan the new estimate
    # cannot keep to the least-miss one. A real-time controller bounds it with time_budget.
    max_iter: int = 100
    time_budget: float | None = None  # s of wall time per step (real-time use; makes runs timing-dependent)
    # Fraction of the deceleration limit a plan keeps free (it may use the margin at a price, see
    # grid.DECEL_MARGIN_WEIGHT). The plan is the plant's own step, so a nominal plant needs only the
    # solver's tolerance; after the first step the margin grows as the plans mispredict the engine speed
    # (MARGIN_PER_RAD_S): a plant unlike the model.
    tighten: float = 0.005
    omega_margin: float = 1.0  # rad/s the plan keeps above omega_min (fuel-optimal plans ride it)
    spare_steps: int = 3  # slots per phase beyond the first schedule's steps (room for schedule moves)
    max_time: float = 40.0  # the env's max_time (to read the elapsed time from the observation)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.mode == "target_time" and not (
                isinstance(self.target_time, (int, float)) and math.isfinite(self.target_time) and self.target_time > 0):
            raise ValueError(f"mode 'target_time' needs a target_time > 0 (s), got {self.target_time!r}")
        if self.mode == "weighted" and (self.w_fuel is None or not 0.0 <= self.w_fuel <= 1.0):
            raise ValueError(f"mode 'weighted' needs w_fuel in [0, 1], got {self.w_fuel!r}")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time_budget must be > 0 s or None, got {self.time_budget!r}")
        if not (isinstance(self.max_iter, int) and self.max_iter >= 1):
            raise ValueError(f"max_iter must be an integer >= 1, got {self.max_iter!r}")
        if not (isinstance(self.spare_steps, int) and self.spare_steps >= 1):
            raise ValueError(f"spare_steps must be an integer >= 1, got {self.spare_steps!r}")
        if not 0.0 <= self.tighten < 0.5:
            raise ValueError(f"tighten must lie in [0, 0.5), got {self.tighten!r}")


@dataclass
class Solve:
    """One NLP solve: the schedule it was for and what came of it."""

    counts: dict[int, int]
    first_phase: int
    ok: bool
    status: str
    J: float = math.inf  # the NLP objective: fuel (g) plus the target and deceleration penalties
    fuel_g: float = math.nan
    misses: dict[str, float] = field(default_factory=dict)
    excess: float = 0.0  # the largest relative excess over the deceleration limit the plan has
    z: np.ndarray | None = None
    lam_x: np.ndarray | None = None
    lam_g: np.ndarray | None = None
    lam_p: np.ndarray | None = None
    iterations: int = 0
    wall: float = 0.0

    @property
    def feasible(self) -> bool:
        return self.ok and all(abs(v) <= MISS_TOL for v in self.misses.values()) and self.excess <= EXCESS_TOL


# Built NLPs and their solvers, shared by the controllers of a process (building takes a second or two).
_NLPS: dict[tuple, GridNLP] = {}
_SOLVERS: dict[tuple, Any] = {}
_MODELS: dict[tuple, StepModel] = {}
_REFERENCES: dict[tuple, Any] = {}
# The margin kept below the deceleration limit after a plan's first step grows with the plans' one-step
# engine-speed error (see MPCController._later_margin): per rad/s of RMS error, and at most.
# Measured on the TC cycle, payload x1.2 and rolling resistance x1.3: 0.08 missed the reversing
# point by 9.9 cm, 0.16 met it (and every other corner); a nominal plant keeps MPCConfig.tighten.
MARGIN_PER_RAD_S = 0.16
MAX_MARGIN = 0.03

REFERENCE_MESH = (12, 8, 12, 8)  # the continuous reference only sets the first schedule and guess


class MPCController:
    """Shrinking-horizon MPC for ``WheelLoader-v0`` (controller protocol: ``reset()``, ``act(obs)``).

    ``dt`` and ``substeps`` must be the environment's (``run_closed_loop`` reads them from it).
    """

    def __init__(self, braking: str = "service", params: LoaderParams | dict | None = None,
                 config: MPCConfig | None = None, dt: float = 0.1, substeps: int = 1) -> None:
        self.braking = cycle.check_braking(braking)
        self.params = resolve(params)
        self.config = config or MPCConfig()
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise ValueError(f"dt (the control interval) must lie in (0, 1] s, got {dt!r}")
        self.dt, self.substeps = float(dt), int(substeps)
        key = (self.braking, self.params.fingerprint(), self.dt, self.substeps, self.config.omega_margin)
        if key not in _MODELS:
            _MODELS[key] = StepModel(self.braking, self.params, self.dt, self.substeps, self.config.omega_margin)
        self.model = _MODELS[key]
        self._sim = None
        self._force_failure = False  # test hook: the solves of the next step count as failed
        self.reset()

    # ------------------------------------------------------------------ protocol
    def reset(self) -> None:
        self._sol: Solve | None = None  # the last good solve (its z is the plan, shifted by the counts)
        self._iterate: Solve | None = None  # the last solve's iterate, converged or not: the next warm start
        self._counts: dict[int, int] | None = None  # full steps left per phase after the last applied step
        self._plan: dict[str, Any] | None = None  # the last good plan's steps, and the step it was made at
        self._last: tuple | None = None  # (state, phase, control) of the previous step
        self._tried: dict[tuple, tuple[int, int]] = {}  # schedule move -> (step it last failed to pay, failures)
        self._last_failure = -10**9  # the step a schedule move last failed to pay
        self._failures = 0  # schedule moves in a row that did not pay (each doubles the wait for the next)
        self._theta = THETA_PRIOR.copy()
        self._theta_cov = np.diag(THETA_PRIOR_STD**2)
        self._lift_gain, self._lift_gain_var = LIFT_GAIN_PRIOR, LIFT_GAIN_PRIOR_STD**2
        self._omega_err2 = 0.0  # moving mean square of the plans' one-step engine-speed error (rad/s)^2
        self.solve_times: list[float] = []
        self.step_solves: list[int] = []  # solves per step (1, or 2 with a schedule move)
        self.fallbacks = 0
        self.planning_time = 0.0
        self.last_info: dict[str, Any] = {}

    def act(self, obs: np.ndarray) -> np.ndarray:
        x, t, phase = self.state_from_obs(obs)
        self._estimate_model_error(x, phase)
        self._track_prediction_error(x, t)
        u, shift, info = self.control(x, t, phase)
        self._last = (x, phase + 1 if shift else phase, u)
        info["accel_gain"], info["accel_offset"] = float(self._theta[0]), float(self._theta[1])
        info["lift_gain"] = float(self._lift_gain)
        self.last_info = info
        return self.action(u, shift)

    def action(self, u: np.ndarray, shift: bool) -> np.ndarray:
        """The env's normalized action for the control [U_mf, U_ab, U_b] and a shift request."""
        p = self.params
        lo, hi = p.U_ab_bounds
        a = np.array([2.0 * u[0] / p.U_mf_max - 1.0, 2.0 * (u[1] - lo) / (hi - lo) - 1.0,
                      2.0 * u[2] / p.U_b_max - 1.0, 1.0 if shift else -1.0])
        return np.clip(np.nan_to_num(a, nan=-1.0), -1.0, 1.0).astype(np.float32)

    def state_from_obs(self, obs: np.ndarray) -> tuple[np.ndarray, float, int]:
        """[omega, V, H, V_b, s], elapsed time and phase from a WheelLoader-v0 observation."""
        p = self.params
        o = np.asarray(obs, dtype=np.float64)
        if o.shape != (12,) or not np.isfinite(o).all():
            raise ValueError(f"obs must be a finite WheelLoader-v0 observation of shape (12,), got {o!r}")
        x = np.array([o[0] * p.omega_max, o[1] * p.V_max, o[2] * p.H_T, o[3], o[4] * p.distance])
        return x, float(o[6] * self.config.max_time), int(np.argmax(o[8:12])) + 1

    # ------------------------------------------------------------------ one step
    def control(self, x: np.ndarray, t: float, phase: int) -> tuple[np.ndarray, bool, dict[str, Any]]:
        """The control [U_mf, U_ab, U_b], the shift request and diagnostics for state x at time t."""
        k = int(round(t / self.dt))
        if phase == 2 and -x[1] < MIN_STOP_SPEED:
            phase = 3  # at the reversing point (the env switches within this step): plan the way forward
        if phase == 4 and x[1] < MIN_STOP_SPEED:
            # standing at the truck and not done (a plant the plan misjudged): bring the bucket to rest
            info = {"solve_time": 0.0, "status": "terminal", "fallback": False, "over_budget": False,
                    "solves": 0, "iterations": 0, "schedule": dict(self._counts or {}), "planned_T_remaining": self.dt}
            return self._terminal(x), False, info
        t0 = time.perf_counter()
        x_plan = self.project_state(x, phase)
        if self._counts is None:  # the first step plans the cycle (a real controller would before it starts)
            self._plan_cycle(x_plan, phase, k)
            solves, ok, over_budget = [self._sol], True, False
            solve_time = self.planning_time = time.perf_counter() - t0
        else:
            self._enter_phase(phase)
            sol = self._solve(phase, self._counts, x_plan, warm=self._iterate)
            solves, over_budget = [sol], self._over_budget(t0)
            ok = sol.ok and not over_budget
            if sol.z is not None:  # the next solve goes on from here, converged or not
                self._iterate = sol
            if ok:
                self._sol = sol
                extra = self._try_better_schedule(x_plan, phase, k, budget_left=not self._over_budget(t0, 0.5))
                if extra is not None:
                    solves.append(extra)
            solve_time = sum(s.wall for s in solves)
        self._force_failure = False  # (the test hook fails every solve of one step)
        if ok:
            self._plan = self._make_plan(self._sol, x_plan, k)
            self._iterate = self._sol
        else:
            self.fallbacks += 1
        u, shift = self._from_plan(k, phase)
        self.solve_times.append(solve_time)
        self.step_solves.append(len(solves))
        info = {"solve_time": solve_time, "status": "; ".join(s.status for s in solves), "fallback": not ok,
                "over_budget": over_budget, "solves": len(solves), "iterations": sum(s.iterations for s in solves),
                "schedule": dict(self._counts), "planned_T_remaining": self._planned_remaining()}
        return u, shift, info

    def _over_budget(self, t0: float, fraction: float = 1.0) -> bool:
        b = self.config.time_budget
        return b is not None and time.perf_counter() - t0 > fraction * b

    # ------------------------------------------------------------------ the plan
    def _make_plan(self, sol: Solve, x: np.ndarray, k: int) -> dict[str, Any]:
        nlp = self._nlp(sol.first_phase)
        plan = nlp.plan(sol.z, sol.counts, x, self.dt)
        plan["k_made"] = k
        return plan

    def _from_plan(self, k: int, phase: int) -> tuple[np.ndarray, bool]:
        """Control and shift request now, from the last good plan (its step ``k - k_made``), and the
        schedule advanced past the step applied."""
        plan = self._plan
        i = k - plan["k_made"]
        if i >= len(plan["phase"]):  # the plan is used up: hold still (brakes where allowed, bucket stopped)
            return self._terminal(None), False
        step_phase, stop = int(plan["phase"][i]), bool(plan["stop"][i])
        if step_phase < phase:  # the plant is ahead of the plan (a phase ended early): its first step there
            later = np.flatnonzero(plan["phase"][i:] >= phase)
            i = i + int(later[0]) if later.size else len(plan["phase"]) - 1
            step_phase, stop = int(plan["phase"][i]), bool(plan["stop"][i])
        u = np.array(plan["controls"][i], dtype=float)
        if stop and step_phase == 4:
            u[1] = self.params.U_ab_bounds[0]  # the simulator lands the bucket speed on 0 exactly (V_b >= 0)
        if not stop and self._counts.get(step_phase, 0) > 0:
            self._counts[step_phase] -= 1
        for q in range(phase, step_phase):
            self._counts[q] = 0
        shift = phase in (1, 3) and step_phase > phase
        return u, shift

    def _planned_remaining(self) -> float:
        return float(steps_of(self._counts) * self.dt) if self._counts else math.nan

    def _enter_phase(self, phase: int) -> None:
        """The plant is in ``phase``: drop what the schedule had left of the phases before (the plant
        ended them early) and cut the warm starts to the NLP from ``phase`` on (it is the tail)."""
        for q in [q for q in self._counts if q < phase]:
            del self._counts[q]
        self._sol, self._iterate = self._tail(self._sol, phase), self._tail(self._iterate, phase)

    def _tail(self, sol: Solve | None, phase: int) -> Solve | None:
        if sol is None or sol.first_phase >= phase:
            return sol
        zo, go = self._nlp(sol.first_phase).segment_offsets(phase)
        return Solve(counts={q: n for q, n in sol.counts.items() if q >= phase}, first_phase=phase, ok=sol.ok,
                     status=sol.status, J=sol.J, misses=sol.misses, excess=sol.excess, z=sol.z[zo:], lam_x=sol.lam_x[zo:],
                     lam_g=sol.lam_g[go:], lam_p=None)

    # ------------------------------------------------------------------ schedule
    def _cost(self, sol: Solve, k: int) -> tuple:
        """How a mode ranks a solved schedule: targets met first, then steps and fuel as the mode weighs them."""
        if not sol.ok:
            return (2, math.inf)
        if not sol.feasible:
            return (1, sol.J)
        return (0, self._scalar_cost(sol.J, steps_of(sol.counts), k))

    def _scalar_cost(self, J: float, n_steps: int, k: int) -> float:
        cfg = self.config
        if cfg.mode == "time":
            return J + STEP_PRICE * n_steps
        if cfg.mode == "target_time":
            return J + STEP_PRICE * max(k + n_steps - self._n_target, 0)
        if cfg.w_fuel == 0.0:
            return J + STEP_PRICE * n_steps
        # weighted: grams of fuel per step of time at the mode's exchange rate
        return J + (1.0 - cfg.w_fuel) / TIME_REF * self.dt / (cfg.w_fuel / FUEL_REF_G) * n_steps

    def _moves(self, sol: Solve, phase: int, k: int) -> list[tuple[float, tuple]]:
        """Schedule moves of one step, with the change the sensitivities predict, best first.

        A move (i, j) takes a step from phase i and gives it to phase j; i or j None adds or removes one.
        Phases 1 and 3 keep a step until they are under way (each phase lasts >= 0.1 s), and a phase in
        its last step keeps its end (the plan shifts now; one step more at a time runs away past the
        reversing point when the targets are out of reach). The prediction is the mode's cost while the
        schedule meets the targets, else the objective alone (the misses first, whatever the steps).
        """
        nlp = self._nlp(sol.first_phase)
        sens = nlp.sensitivities(sol.lam_p, sol.counts, self.dt)
        counts, n = sol.counts, steps_of(sol.counts)
        base = self._scalar_cost(sol.J, n, k)
        phases = list(counts)

        def removable(q: int) -> bool:
            return counts[q] > (0 if q in (2, 4) or q == phase else 1)

        def fits(q: int) -> bool:
            return counts[q] < nlp.slots_per_phase[q] and not (q == phase and q in (1, 3) and counts[q] == 0)

        out = []
        for i in [None, *phases]:
            for j in [None, *phases]:
                if i == j or (i is not None and not removable(i)) or (j is not None and not fits(j)):
                    continue
                dJ = (sens[j] if j is not None else 0.0) - (sens[i] if i is not None else 0.0)
                dn = (j is not None) - (i is not None)
                out.append((self._scalar_cost(sol.J + dJ, n + dn, k) - base if sol.feasible else dJ, (i, j)))
        return sorted(out)

    def _moved(self, counts: dict[int, int], move: tuple) -> dict[int, int]:
        c = dict(counts)
        i, j = move
        if i is not None:
            c[i] -= 1
        if j is not None:
            c[j] += 1
        return c

    def _candidate(self, sol: Solve, phase: int, k: int, failed: set, removals: bool = True,
                   min_gain: float = MIN_GAIN) -> tuple | None:
        """The move to try: the best predicted one not tried in vain (``failed``, or within RETRY_AFTER
        steps); while the targets are missed, the one predicted to cut the misses most, never a removal."""
        for gain, move in self._moves(sol, phase, k):
            last, failures = self._tried.get(move, (-10**9, 0))
            if move in failed or k - last < RETRY_AFTER * 2 ** max(failures - 1, 0):
                continue
            if move[1] is None and (not removals or not sol.feasible):
                continue
            return move if gain < -min_gain else None
        return None

    def _try_move(self, sol: Solve, move: tuple, phase: int, x: np.ndarray) -> Solve:
        """Solve a schedule move, warm-started from ``sol`` stretched onto the new schedule."""
        counts = self._moved(sol.counts, move)
        nlp = self._nlp(sol.first_phase)
        z, lam_x, lam_g = nlp.resample(sol.z, sol.lam_x, sol.lam_g, sol.counts, counts)
        warm = Solve(counts=counts, first_phase=sol.first_phase, ok=True, status="", z=z, lam_x=lam_x, lam_g=lam_g)
        return self._solve(phase, counts, x, warm=warm)

    def _try_better_schedule(self, x: np.ndarray, phase: int, k: int, budget_left: bool) -> Solve | None:
        """One step's schedule move: solve the predicted best one and keep it if it ranks better.

        Steps are dropped where the mode prices time (minimum time, weighted) or the cycle runs late
        (target time), and added in any mode when the targets are missed. A move that did not pay waits
        RETRY_AFTER steps, twice as long after each such move in a row (a schedule too short fails
        slowly: 0.2-0.6 s), so a nominal cycle tries 3-4.
        """
        if not budget_left or self._sol.lam_p is None:
            return None
        if self._sol.feasible and k - self._last_failure < RETRY_AFTER * 2 ** max(self._failures - 1, 0):
            return None
        late = self.config.mode == "target_time" and k + steps_of(self._sol.counts) > self._n_target
        move = self._candidate(self._sol, phase, k, failed=set(), removals=self.config.mode != "target_time" or late,
                               min_gain=MIN_GAIN_ONLINE)
        if move is None:
            return None
        alt = self._try_move(self._sol, move, phase, x)
        if self._cost(alt, k) < self._cost(self._sol, k):
            self._sol = alt
            self._counts = dict(alt.counts)
            self._failures = 0
        else:
            self._tried[move] = (k, self._tried.get(move, (0, 0))[1] + 1)
            self._last_failure, self._failures = k, self._failures + 1
        return alt

    def _plan_cycle(self, x: np.ndarray, phase: int, k: int) -> None:
        """The first step: the schedule from the continuous optimum, then improved by single-step moves
        (the predicted best first; it ends after SEARCH_FAILURES moves in a row that did not pay)."""
        ref = self.reference()
        cfg = self.config
        durations = dict(zip(range(1, 5), ref.phase_durations, strict=True))
        if phase > 1:  # a controller started mid-cycle: the reference's later phases, in the time left
            durations = {q: d for q, d in durations.items() if q >= phase}
        if cfg.mode == "target_time":
            self._n_target = int(math.floor(cfg.target_time / self.dt + 1e-6))
            n = max(self._n_target - k, len(durations))
        else:
            self._n_target = 0
            n = max(int(round(sum(durations.values()) / self.dt)), len(durations))
        counts = apportion(durations, n, self.dt)
        self._slots = {q: SLOT_ROUNDING * math.ceil((c + cfg.spare_steps) / SLOT_ROUNDING) for q, c in counts.items()}
        for q in range(phase, 5):  # build them all now, not in the middle of the cycle
            self._solver(self._nlp(q), warm=True)
        sol = self._solve(phase, counts, x, warm=None, guess=self._guess(phase, counts, ref, x))
        failed: set = set()
        for _ in range(SEARCH_SOLVES):
            # a step fewer that did not hold the targets will not from another phase either
            removals = sum(1 for m in failed if m[1] is None) < 1
            move = self._candidate(sol, phase, k, failed, removals=removals) if sol.ok else None
            if move is None or len(failed) >= SEARCH_FAILURES:
                break
            alt = self._try_move(sol, move, phase, x)
            if self._cost(alt, k) < self._cost(sol, k):
                sol, failed = alt, set()
            else:
                failed.add(move)
        if not sol.ok:
            raise RuntimeError(f"MPC: no plan for the {self.braking} cycle from the start state: IPOPT status {sol.status}")
        self._sol, self._iterate, self._counts = sol, sol, dict(sol.counts)

    def reference(self):
        """The continuous optimum of this mode on a coarse mesh (the first plan's schedule and guess)."""
        key = (self.braking, self.params.fingerprint(), self.config.mode, self.config.target_time,
               self.config.w_fuel, self.dt)
        if key not in _REFERENCES:
            _REFERENCES[key] = self._solve_reference()
        return _REFERENCES[key]

    def _solve_reference(self):
        from mpc.benchmark.ocp import OCPError, OCPSettings, solve_ocp

        cfg, b, p = self.config, self.braking, self.params
        settings = OCPSettings(intervals=REFERENCE_MESH, smoothing=(0.0,))
        opts = dict(params=p, verify=False, settings=settings)
        if cfg.mode == "target_time":
            T = math.floor(cfg.target_time / self.dt + 1e-6) * self.dt
            try:  # the split of the time between the phases has local optima: start from several
                return solve_ocp(b, "fuel_at_time", T=T, starts=tuple((T / 2.0, a) for a in (0.3, 0.5, 0.7)), **opts)
            except OCPError:
                fastest = solve_ocp(b, "time", params=p)  # as the benchmark solves it: T_min itself
                if cfg.target_time < fastest.T:
                    raise ValueError(
                        f"target_time {cfg.target_time:g} s is impossible: the minimum cycle time with {b} braking is "
                        f"{fastest.T:.3f} s (MPCConfig.target_time must be at least that)") from None
                return fastest  # feasible, but not on the control grid: the cycle ends a step late
        if cfg.mode == "time" or cfg.w_fuel == 0.0:
            return solve_ocp(b, "time", starts=((4.2, 0.6), (4.2, 0.8)), **opts)
        return solve_ocp(b, "weighted", w_fuel=cfg.w_fuel, **opts)

    def _guess(self, phase: int, counts: dict[int, int], ref: Any, x: np.ndarray) -> np.ndarray:
        """A decision vector from the continuous optimum: each phase's steps at phase-normalized times."""
        nlp = self._nlp(phase)
        rt, rph = np.asarray(ref.t), np.asarray(ref.phase)
        rx = np.column_stack([np.asarray(ref.states), np.asarray(ref.position)])
        ru = np.asarray(ref.controls)
        starts = np.concatenate([[0.0], np.cumsum(ref.phase_durations)])
        z = np.zeros(nlp.n_var)
        active = nlp.active_slots(counts)
        x_prev = np.asarray(x, dtype=float)
        per_phase = {q: [k for k in active if nlp.slots[k].phase == q] for q in nlp.phases}
        for k_slot, s in enumerate(nlp.slots):
            if k_slot in active:
                ks = per_phase[s.phase]
                frac = (ks.index(k_slot) + 1) / len(ks)
                tr = starts[s.phase - 1] + frac * ref.phase_durations[s.phase - 1]
                x_prev = np.array([np.interp(tr, rt, rx[:, m]) for m in range(N_X)])
                i = int(np.clip(np.searchsorted(rt, tr - 0.5 * self.dt) - 1, 0, len(ru) - 1))
                if rph[i] != s.phase:
                    i = int(np.flatnonzero(rph[:-1] == s.phase)[-1]) if (rph[:-1] == s.phase).any() else i
                z[s.u:s.u + 3] = ru[i] / U_SCALE
            z[s.x:s.x + N_X] = x_prev / X_SCALE
        return z

    # ------------------------------------------------------------------ NLP solves
    def _nlp(self, first_phase: int, symbolic: str = "SX") -> GridNLP:
        slots = {q: self._slots[q] for q in range(first_phase, 5)}
        key = (id(self.model), first_phase, tuple(sorted(slots.items())), symbolic)
        if key not in _NLPS:
            _NLPS[key] = GridNLP(self.model, first_phase, slots, symbolic)
        return _NLPS[key]

    def _solver(self, nlp: GridNLP, warm: bool) -> Any:
        import casadi as ca

        cfg = self.config
        key = (id(nlp), warm, cfg.max_iter, cfg.time_budget)
        if key not in _SOLVERS:
            opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.tol": 1e-6,
                    "ipopt.acceptable_tol": 1e-4, "ipopt.acceptable_iter": 2, "ipopt.mu_strategy": "adaptive",
                    "ipopt.max_iter": cfg.max_iter if warm else 500}
            if warm:
                opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-5,
                             "ipopt.warm_start_bound_push": 1e-6, "ipopt.warm_start_mult_bound_push": 1e-6,
                             "ipopt.warm_start_slack_bound_push": 1e-6})
                if cfg.time_budget is not None:
                    opts["ipopt.max_wall_time"] = cfg.time_budget
            _SOLVERS[key] = ca.nlpsol("mpc", "ipopt", nlp.nlp, opts)
        return _SOLVERS[key]

    def _estimate(self) -> np.ndarray:
        return np.array([self._theta[1], self._theta[0], self._lift_gain])

    def _solve(self, first_phase: int, counts: dict[int, int], x: np.ndarray, warm: Solve | None,
               guess: np.ndarray | None = None) -> Solve:
        """Solve the schedule ``counts`` from state x (no side effects but timing)."""
        t0 = time.perf_counter()
        out = Solve(counts=dict(counts), first_phase=first_phase, ok=False, status="not solved")
        try:
            if self._force_failure:
                raise RuntimeError("forced failure (test hook)")
            nlp = self._nlp(first_phase)
            args = nlp.arguments(counts, x, self._estimate(), self.dt, tighten=(self.config.tighten, self._later_margin()))
            if warm is not None and warm.first_phase == first_phase and warm.z is not None:
                solver = self._solver(nlp, warm=True)
                sol = solver(x0=np.clip(warm.z, args["lbx"], args["ubx"]), lam_x0=warm.lam_x, lam_g0=warm.lam_g, **args)
            else:  # a cold solve (the first of a cycle): on the MX twin, which builds in a tenth of the time
                z0 = guess if guess is not None else (nlp.lbw + nlp.ubw) / 2
                solver = self._solver(self._nlp(first_phase, "MX"), warm=False)
                sol = solver(x0=np.clip(z0, args["lbx"], args["ubx"]), **args)
            stats = solver.stats()
            out.status = str(stats.get("return_status", "unknown"))
            interrupt.check(out.status)  # Ctrl-C inside IPOPT stops the run, not just this plan
            out.iterations = int(stats.get("iter_count", 0))
            out.ok = bool(stats.get("success")) or out.status == "Solved_To_Acceptable_Level"
            out.z = np.array(sol["x"]).ravel()
            out.lam_x, out.lam_g = np.array(sol["lam_x"]).ravel(), np.array(sol["lam_g"]).ravel()
            out.lam_p = np.array(sol["lam_p"]).ravel()
            out.J = float(sol["f"])
            out.fuel_g = float(nlp.fuel_g(out.z, args["p"]))
            out.misses = nlp.misses(out.z)
            out.excess = nlp.excess(out.z)
            if not np.isfinite(out.z).all():
                out.ok, out.status = False, out.status + " (non-finite iterate)"
        except (RuntimeError, ValueError) as exc:
            out.status = f"error: {exc}"
        out.wall = time.perf_counter() - t0
        return out

    def _track_prediction_error(self, x: np.ndarray, t: float) -> None:
        """How far the last plan's next state was off the measurement in engine speed (moving RMS)."""
        plan, k = self._plan, int(round(t / self.dt))
        if plan is None or k - plan["k_made"] != 1 or len(plan["states"]) < 2:
            return
        e = float(x[0] - plan["states"][1][0])
        self._omega_err2 = PREDICTION_ERROR_DECAY * self._omega_err2 + (1.0 - PREDICTION_ERROR_DECAY) * e * e

    def _later_margin(self) -> float:
        """The margin below the deceleration limit the plan keeps after its first step: the configured
        one, and more as the plans mispredict the engine speed. With TC braking the converter's drag at
        the shift follows the engine speed, which a fuel cut sets about a second before, with no way to
        slow the engine further: the errors of that second add up (1.6 % of the limit per rad/s)."""
        return min(self.config.tighten + MARGIN_PER_RAD_S * math.sqrt(self._omega_err2), MAX_MARGIN)

    # ------------------------------------------------------------------ model-error estimate
    def _estimate_model_error(self, x: np.ndarray, phase: int) -> None:
        """Adaptive MPC: fit the plant's deviation from the model by recursive least squares over the
        steps so far, from the one-step prediction error of the previous step.

        * dV/dt = gain * (model's dV/dt) + d * offset: a payload error scales the acceleration of every
          force (gain = model mass / plant mass); a rolling-resistance error is an acceleration against
          the travel direction (offset). Phase 1 varies the model's acceleration enough to tell them
          apart, so the braking phases start with the plant's deceleration per unit of brake or converter
          torque, not the nominal one. Steps that stop, reverse or change phase say nothing about it.
        * The lift's power drawn from the engine is proportional to the payload (eq. (10)), so a payload
          error also shows in the engine's acceleration: d omega/dt = model - (lift_gain - 1) P_lift /
          (omega J_ice). With TC braking the engine speed at the shift sets the converter's drag, so a
          plan must predict it to the rad/s.
        """
        if self._last is None:
            return
        x0, ph0, u = self._last
        if ph0 != phase:
            return
        if self._sim is None:
            from wl_env.simulator import Simulator

            self._sim = Simulator(self.params, self.braking)
        p, dt = self.params, self.dt
        y = (float(x0[0]), float(x0[1]), float(x0[2]), float(x0[3]), 0.0, 0.0)
        ue = self._sim.effective_controls(y, ph0, float(u[0]), float(u[1]), float(u[2]), dt)[:3]
        if max(x0[0], x[0]) < 0.99 * p.omega_max:  # at the governor's cap the fuel, not the load, sets omega
            # the predicted omega is (nearly) linear in the gain: omega(g) = omega(1) + (g - 1) r dt
            omega1, _ = self._predict(x0, ph0, ue, 1.0, self._theta)
            r = (omega1 - self._predict(x0, ph0, ue, 0.0, self._theta)[0]) / dt
            residual = (x[0] - omega1) / dt  # measured minus modelled d omega/dt
            var = self._lift_gain_var
            k = var * r / (RLS_FORGETTING * ENGINE_ACCEL_NOISE_STD**2 + r * var * r)
            self._lift_gain += k * (residual - (self._lift_gain - 1.0) * r)
            self._lift_gain_var = (var - k * r * var) / RLS_FORGETTING
            self._lift_gain = min(max(self._lift_gain, LIFT_GAIN_MIN), LIFT_GAIN_MAX)
        if abs(x0[1]) >= 0.2 and abs(x[1]) >= 0.2:
            # the model's mean dV/dt over the step, its engine speed as the lift-load estimate has it
            _, v1 = self._predict(x0, ph0, ue, self._lift_gain, THETA_PRIOR)
            d = -1.0 if ph0 <= 2 else 1.0
            regressor = np.array([(v1 - x0[1]) / dt, d])
            measured = (x[1] - x0[1]) / dt
            P = self._theta_cov
            k = P @ regressor / (RLS_FORGETTING * ACCEL_NOISE_STD**2 + regressor @ P @ regressor)
            self._theta = self._theta + k * (measured - regressor @ self._theta)
            self._theta_cov = (P - np.outer(k, regressor @ P)) / RLS_FORGETTING
            self._theta = np.clip(self._theta, THETA_MIN, THETA_MAX)

    def _predict(self, x0: np.ndarray, phase: int, u: tuple, lift_gain: float, accel: np.ndarray) -> tuple[float, float]:
        """(omega, V) one control step after x0 under the effective controls u, by the plan's own step
        (:class:`mpc.controller.grid.StepModel`) with the lift drawing lift_gain times the model's power from the
        engine and dV/dt = accel[0] * model + d * accel[1]."""
        x1 = self.model.full[phase].fn(np.asarray(x0, dtype=float)[:5], np.asarray(u, dtype=float), self.dt,
                                       np.array([accel[1], accel[0], lift_gain]))[0]
        return float(x1[0]), float(x1[1])

    # ------------------------------------------------------------------ helpers
    def project_state(self, x: np.ndarray, phase: int) -> np.ndarray:
        """The measurement moved onto the constraints it may graze (by a hair, through the simulator's
        saturation and the observation's float32): a plan must start from a state its constraints admit."""
        p = self.params
        x = np.array(x, dtype=float)
        x[0] = min(max(x[0], p.omega_min), p.omega_max)
        d = -1.0 if phase <= 2 else 1.0
        x[1] = d * min(max(d * x[1], 0.0), p.V_max)
        x[2] = min(max(x[2], p.H_0), lift.max_bucket_height(p))
        x[3] = max(x[3], 0.0)
        return x

    def _terminal(self, x: np.ndarray | None) -> np.ndarray:
        """The machine standing at the truck: brake, bring the bucket to H_T and hold it (a plan needs a
        moving machine for its stop step; this serves a plant that stopped before the plan said)."""
        p = self.params
        gain, offset = self._theta
        # the brake torque that decelerates at the limit with rolling resistance helping, in the plant as estimated
        a_stop = (1.0 - self.config.tighten) * p.decel_max * p.g + offset
        u_b = min(max((a_stop * p.M_tot / gain - p.F_roll) * p.r_w, 0.0), p.U_b_max)
        if x is None:
            return np.array([0.0, p.U_ab_bounds[0], u_b])
        omega, _, H, V_b = x[0], x[1], x[2], x[3]
        lo, hi = p.U_ab_bounds
        # Approach H_T on the speed that stops there with 80 % of the lowest deceleration; a bucket
        # already too fast for that brakes with what stops it exactly at H_T (as much as it can).
        gap = p.H_T - H
        v_ref = math.copysign(math.sqrt(2.0 * 0.8 * -lo * abs(gap)), gap)
        u_ab = min(max((max(v_ref, 0.0) - V_b) / self.dt, lo), hi)
        if V_b > 0.0:
            decel_to_stop = V_b**2 / (2.0 * gap) if gap > 0.0 else math.inf
            if decel_to_stop > 0.8 * -lo:
                u_ab = max(-decel_to_stop, lo)
        load = self._lift_gain * lift.lift_power(max(V_b, 0.0), u_ab, p) / max(omega, 1.0)
        u_mf = (engine.friction_torque(omega, p) + load) / p.T_ig_per_mg  # hold the engine speed
        return np.array([min(max(u_mf, 0.0), p.U_mf_max), u_ab, u_b])

    def stats(self) -> dict[str, float]:
        """Per-step solve times (s; the first step's planning apart) and the fallback count."""
        st = np.asarray(self.solve_times[1:] or self.solve_times or [0.0])
        return {"median_s": float(np.median(st)), "p95_s": float(np.percentile(st, 95)), "max_s": float(st.max()),
                "n": int(len(self.solve_times)), "fallbacks": int(self.fallbacks), "planning_s": float(self.planning_time)}


def run_closed_loop(braking: str = "service", config: MPCConfig | None = None,
                    params: LoaderParams | dict | None = None, plant_params: LoaderParams | dict | None = None,
                    score: bool = True, seed: int = 0, controller: MPCController | None = None,
                    cache: str | os.PathLike | None = None) -> dict[str, Any]:
    """One cycle of ``WheelLoader-v0`` under the MPC; returns the trajectory, the result and its score.

    ``params`` is the controller's model, ``plant_params`` the simulated machine (default: the same);
    they differ in a model-mismatch study. ``controller`` (default: built from ``config``) lets a caller
    inspect the controller afterwards. ``cache`` is the folder of the Pareto fronts the score reads
    (default: :func:`mpc.benchmark.pareto.cache_dir`).
    """
    import gymnasium as gym

    import wl_env  # noqa: F401  (registers the env)
    from wl_env.rollout import run_episode

    config = config or MPCConfig()
    model = resolve(params)
    plant = resolve(plant_params) if plant_params is not None else model
    env = gym.make("WheelLoader-v0", braking=braking, params=plant, max_time=config.max_time)
    core = env.unwrapped.core
    ctrl = controller or MPCController(braking, model, config, dt=core.dt, substeps=core.substeps)
    ep = run_episode(env, ctrl, seed=seed)
    result = {
        "controller": "mpc", "braking": braking, "mode": config.mode, "target_time": config.target_time,
        "T": ep["T"], "fuel_g": ep["fuel_g"], "success": ep["success"], "completed": ep["completed"],
        "reversing_error_m": ep["reversing_error"], "final_position_error_m": ep["final_s"],
        "final_height_error_m": ep["final_H"] - plant.H_T, "max_violation": ep["max_excess"],
        "t": ep["t"], "states": ep["states"], "controls": ep["controls"], "phase": ep["phase"],
        "solve_time": ctrl.stats(), "solve_times_s": list(ctrl.solve_times),
        "plant_params": plant.to_dict() if plant is not model else None,
    }
    if score and ep["completed"]:
        from mpc.benchmark.scoring import score_run

        s = score_run(ep["T"], ep["fuel_g"], braking, success=ep["success"], max_violation=ep["max_excess"],
                      params=model, cache=cache)
        result["score"] = s.to_dict()
    return result
