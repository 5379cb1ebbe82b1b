"""Receding (shrinking) horizon MPC that drives ``WheelLoader-v0`` through the cycle.

At every control step the controller reads the state from the observation, solves the cycle OCP of
:mod:`mpc.ocp` from that state over the phases still ahead (the same model and constraints as the
offline benchmark, on a coarser mesh), applies the first control and requests a shift when its plan
says the current phase ends. The NLP of each starting phase is built once; the measured state and the
remaining time enter as parameters, and every solve is warm-started from the previous one (primal and
dual). A failed or over-budget solve applies the previous plan, shifted by the time since it was made,
and says so in ``last_info``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpc.ocp import FUEL_REF_G, TIME_REF, CycleOCP, OCPSettings, estimated_derivatives, nlp_parameters, solve_ocp
from wl_env import cycle
from wl_env.params import LoaderParams, resolve
from wl_env.physics import engine, lift

MODES = ("time", "target_time", "weighted")
# In phase 4 the terminal law (see _terminal) takes over from the NLP once braking at this fraction of
# the deceleration limit stops the machine within one control step (then < 1 cm from where it stands).
TERMINAL_DECEL_FRACTION = 0.9
# m/s: a machine this slow in phase 2 is at its reversing point (it stops within the step, < 0.3 mm on);
# a plan for the rest of phase 2 would be a plan of nothing, which the NLP may call infeasible.
REVERSING_SPEED = 0.01
# Steps ahead of the planned end of phase 1 or 3 from which the MPC puts the gear change on the step grid.
SHIFT_GRID_STEPS = 15
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


@dataclass(frozen=True)
class MPCConfig:
    """MPC settings. ``mode``: minimum time, minimum fuel finishing by ``target_time``, or weighted."""

    mode: str = "time"
    target_time: float | None = None
    w_fuel: float | None = None
    intervals: tuple[int, int, int, int] = (8, 5, 8, 5)
    degree: int = 2
    max_iter: int = 60  # per solve after the first: the deterministic budget
    time_budget: float | None = None  # s of wall time per solve (real-time use; makes runs timing-dependent)
    deadline_weight: float = 10.0  # objective units per second beyond the target time
    # The plan keeps 2 % off the deceleration limit. Measured with 1 %: no faster in min-time mode, fuel
    # gaps +3.6 / +3.7 % (service, 9 / 10 s targets), and a heavy plant's reversing point missed by 10 cm.
    tighten: float = 0.02
    # The least margin: a plan may cut into the margin down to it, at a price (see ocp.DECEL_MARGIN_WEIGHT),
    # where the measured state leaves no plan within the full margin (a gear change a hair late, say).
    min_tighten: float = 0.005
    omega_margin: float = 5.0  # rad/s the plan keeps above omega_min (fuel-optimal plans ride it)
    max_time: float = 40.0  # the env's max_time (to read the elapsed time from the observation)

    def __post_init__(self) -> None:
        object.__setattr__(self, "intervals", tuple(int(n) for n in self.intervals))
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.mode == "target_time" and not (self.target_time and math.isfinite(self.target_time) and self.target_time > 0):
            raise ValueError(f"mode 'target_time' needs a target_time > 0 (s), got {self.target_time!r}")
        if self.mode == "weighted" and (self.w_fuel is None or not 0.0 <= self.w_fuel <= 1.0):
            raise ValueError(f"mode 'weighted' needs w_fuel in [0, 1], got {self.w_fuel!r}")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time_budget must be > 0 s or None, got {self.time_budget!r}")


_SOLVERS: dict[tuple, CycleOCP] = {}


def _mpc_ocp(braking: str, params: LoaderParams, config: MPCConfig, first_phase: int) -> CycleOCP:
    key = (braking, params.fingerprint(), config.intervals, config.degree, config.max_iter, config.tighten,
           config.min_tighten, config.omega_margin, first_phase)
    if key not in _SOLVERS:
        settings = OCPSettings(intervals=config.intervals, degree=config.degree, smoothing=(0.0,),
                               max_iter=config.max_iter, tol=1e-6, tighten=config.tighten,
                               min_tighten=min(config.min_tighten, config.tighten), omega_margin=config.omega_margin)
        _SOLVERS[key] = CycleOCP(braking, params, settings, first_phase=first_phase, parametric_start=True)
    return _SOLVERS[key]


class MPCController:
    """Shrinking-horizon MPC for ``WheelLoader-v0`` (controller protocol: ``reset()``, ``act(obs)``)."""

    def __init__(self, braking: str = "service", params: LoaderParams | dict | None = None,
                 config: MPCConfig | None = None, dt: float = 0.1) -> None:
        self.braking = cycle.check_braking(braking)
        self.params = resolve(params)
        self.config = config or MPCConfig()
        self.dt = dt
        self.solve_times: list[float] = []
        self.fallbacks = 0
        self.last_info: dict[str, Any] = {}
        self._force_failure = False  # test hook: the solves of the next step count as failed
        self._reference = None
        self._sim = None
        self.reset()

    # ------------------------------------------------------------------ protocol
    def reset(self) -> None:
        self._plan: dict[str, Any] | None = None  # last good plan, with the time it was made
        self._last: tuple | None = None  # (state, phase, control) of the previous step
        self._shift_at: tuple[int, float] | None = None  # (phase, time) the controller committed to end it
        # estimate of the plant's dV/dt = gain * model + d * offset: [gain, offset (m/s^2)], and its covariance
        self._theta = THETA_PRIOR.copy()
        self._theta_cov = np.diag(THETA_PRIOR_STD**2)
        self._lift_gain, self._lift_gain_var = LIFT_GAIN_PRIOR, LIFT_GAIN_PRIOR_STD**2
        self._warm: dict[int, tuple] = {}  # per first phase: (z, lam_x, lam_g)
        self.solve_times = []
        self.fallbacks = 0
        self.last_info = {}

    def act(self, obs: np.ndarray) -> np.ndarray:
        x, t, phase = self.state_from_obs(obs)
        self._estimate_model_error(x, phase)
        u, shift, info = self.control(x, t, phase)
        self._last = (x, phase + 1 if shift else phase, u)
        info["accel_gain"], info["accel_offset"] = float(self._theta[0]), float(self._theta[1])
        info["lift_gain"] = float(self._lift_gain)
        p = self.params
        lo, hi = p.U_ab_bounds
        action = np.array([
            2.0 * u[0] / p.U_mf_max - 1.0,
            2.0 * (u[1] - lo) / (hi - lo) - 1.0,
            2.0 * u[2] / p.U_b_max - 1.0,
            1.0 if shift else -1.0,
        ])
        action = np.clip(np.nan_to_num(action, nan=-1.0), -1.0, 1.0).astype(np.float32)
        self.last_info = info
        return action

    def state_from_obs(self, obs: np.ndarray) -> tuple[np.ndarray, float, int]:
        """[omega, V, H, V_b, s], elapsed time and phase from a WheelLoader-v0 observation."""
        p = self.params
        o = np.asarray(obs, dtype=np.float64)
        x = np.array([o[0] * p.omega_max, o[1] * p.V_max, o[2] * p.H_T, o[3], o[4] * p.distance])
        return x, float(o[6] * self.config.max_time), int(np.argmax(o[8:12])) + 1

    # ------------------------------------------------------------------ one step
    def control(self, x: np.ndarray, t: float, phase: int) -> tuple[np.ndarray, bool, dict[str, Any]]:
        """The control [U_mf, U_ab, U_b], the shift request and diagnostics for state x at time t."""
        if phase == 2 and abs(x[1]) < REVERSING_SPEED:
            phase = 3  # at the reversing point (the env switches there by itself): plan the way forward
        # the speed that braking at TERMINAL_DECEL_FRACTION of the limit takes away within one step
        v_step = TERMINAL_DECEL_FRACTION * self.params.decel_max * self.params.g * self.dt
        if phase == 2 and self._last is not None and -x[1] < v_step:
            # The machine reaches the reversing point within this step, and the plan's first interval
            # (a whole step in phase 2) would run past it: hold the braking of the previous step.
            return self._stopping(x), False, {"solve_time": 0.0, "status": "stopping", "fallback": False,
                                              "over_budget": False, "planned_T_remaining": math.nan}
        if phase == 4 and x[1] < v_step:
            return self._terminal(x), False, {"solve_time": 0.0, "status": "terminal", "fallback": False,
                                               "over_budget": False, "planned_T_remaining": 0.0}
        best, solve_time, statuses = None, 0.0, []
        for tier in self._shift_options(t, phase):  # the next tier only if no plan of this one succeeds
            for first, rest_bounds in tier:
                cand = self._replan(x, t, first, rest_bounds)
                solve_time += cand["solve_time"]
                statuses.append(cand["status"])
                if cand["ok"] and (best is None or cand["f"] < best["f"]):
                    best = cand
            if best is not None:
                break
        self._force_failure = False  # (the test hook fails every solve of one step)
        self.solve_times.append(solve_time)  # per control step: the solves it took (1, or 2 at a gear-change decision)
        over_budget = self.config.time_budget is not None and self._plan is not None and solve_time > self.config.time_budget
        ok = best is not None and not over_budget
        if ok:
            self._plan = best["plan"]
            self._warm[best["plan"]["phases"][0]] = best["warm"]
            shift = best["plan"]["phases"][0] != phase
            fixed = best["rest_bounds"] is not None and best["rest_bounds"][0] == best["rest_bounds"][1]
            self._shift_at = (phase, t + self.dt + best["rest_bounds"][0]) if fixed and not shift else None
            u, _ = self._from_plan(t, best["plan"]["phases"][0])
        else:
            self.fallbacks += 1
            u, shift = self._from_plan(t, phase)  # the old plan, shifted by its age (gear change included)
        info = {"solve_time": solve_time, "status": "; ".join(statuses), "fallback": not ok,
                "over_budget": over_budget,
                "planned_T_remaining": float(self._plan["sol"]["t"][-1] - (t - self._plan["t_made"])) if self._plan else math.nan}
        return u, shift, info

    def _shift_options(self, t: float, phase: int) -> list[list[tuple[int, tuple[float, float] | None]]]:
        """The plans to solve this step, in tiers: (first phase, bounds on the rest of the current phase
        after this step); a tier is tried only if no plan of the tiers before succeeded.

        The env shifts only at the start of a step, so once the planned end of phase 1 or 3 is less than
        SHIFT_GRID_STEPS steps ahead, the controller puts it on the step grid: it plans with the phase
        ending at the grid point before and at the one after the planned end, and commits to the cheaper.
        A committed end is kept (one solve per step), and moved a step later only if it has become
        infeasible. Deciding early leaves the plan time to prepare the shift: with TC braking the engine
        must slow down before the converter takes the drag, at the fuel cut's pace (~1 s from full speed).
        """
        dt = self.dt
        plan = self._plan
        if phase not in (1, 3) or plan is None or plan["phases"][0] != phase:
            return [[(phase, None)]]
        if self._shift_at is not None and self._shift_at[0] == phase:
            k = round((self._shift_at[1] - t) / dt) - 1  # the phase ends k steps after this one
            if k < 0:
                return [[(phase + 1, None)], [(phase, (0.0, 0.0))]]
            return [[(phase, (k * dt, k * dt))], [(phase, ((k + 1) * dt, (k + 1) * dt))], [(phase, None)]]
        rest = plan["sol"]["durations"][0] - (t - plan["t_made"])  # planned time in phase after this step
        if rest >= SHIFT_GRID_STEPS * dt:
            return [[(phase, None)]]
        k = math.floor(rest / dt + 1e-6)
        if k < 0:  # planned to end before this step is over: shift now, or at the next step
            return [[(phase + 1, None), (phase, (0.0, 0.0))]]
        return [[(phase, (k * dt, k * dt)), (phase, ((k + 1) * dt, (k + 1) * dt))], [(phase, None)]]

    def _replan(self, x: np.ndarray, t: float, phase: int, rest_bounds: tuple[float, float] | None = None) -> dict[str, Any]:
        """Solve from state x at time t for the phases from ``phase`` on (no side effects but timing).

        ``rest_bounds`` bounds how long the current phase lasts after this step's execution interval.
        """
        x = self.project_state(x, phase)
        ocp = _mpc_ocp(self.braking, self.params, self.config, phase)
        t0 = time.perf_counter()
        out: dict[str, Any] = {"ok": False, "status": "not solved", "f": math.inf, "rest_bounds": rest_bounds}
        try:
            if self._force_failure:
                raise RuntimeError("forced failure (test hook)")
            z, lam_x, lam_g, status, ok, f = self._solve(ocp, x, t, phase, rest_bounds)
            out.update(status=status, ok=ok, f=f)
            if ok:
                out["plan"] = {"t_made": t, "sol": ocp.unpack(z, x_start=x), "phases": ocp.phases}
                out["warm"] = (z, lam_x, lam_g)
        except RuntimeError as exc:
            out["status"] = f"error: {exc}"
        if not out["ok"]:
            self._warm.pop(phase, None)
        out["solve_time"] = time.perf_counter() - t0
        return out

    def _solve(self, ocp: CycleOCP, x: np.ndarray, t: float, phase: int,
               rest_bounds: tuple[float, float] | None = None):
        cfg = self.config
        if cfg.mode == "time":
            w_f, w_t = 0.0, 1.0
        elif cfg.mode == "target_time":
            w_f, w_t = 1.0, 0.0
        else:
            w_f, w_t = cfg.w_fuel / FUEL_REF_G, (1.0 - cfg.w_fuel) / TIME_REF
        lbg, ubg = ocp._lbg.copy(), ocp._ubg.copy()
        if cfg.mode == "target_time":
            # half a control step early: the plant stops on the step grid, a plan ending on the deadline
            # to the millisecond leaves a few mm/s for one more step
            ubg[ocp._g_deadline_index] = max(cfg.target_time - t - 0.5 * self.dt, 0.0)
        par = nlp_parameters(w_f, w_t, 0.0, cfg.deadline_weight * (1.0 if cfg.mode == "target_time" else 0.0), x,
                             accel_offset=float(self._theta[1]), accel_gain=float(self._theta[0]),
                             lift_gain=float(self._lift_gain))
        warm = self._warm.get(phase)
        if warm is not None:
            z0, lam_x, lam_g = warm
        else:
            z0, lam_x, lam_g = self._guess(ocp, x, t), None, None
        lbx, ubx = ocp._lbw, ocp._ubw
        if rest_bounds is not None:
            lbx, ubx = lbx.copy(), ubx.copy()
            i = ocp._index["dur"][0]
            lbx[i], ubx[i] = rest_bounds[0], min(rest_bounds[1], ubx[i])
            z0 = np.array(z0, dtype=float)
            z0[i] = min(max(z0[i], lbx[i]), ubx[i])
        args = dict(x0=z0, p=par, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        if warm is not None:
            args.update(lam_x0=lam_x, lam_g0=lam_g)
        # Only the very first solve of a cycle may take long (no plan to fall back on yet).
        solver = self._solver_for(ocp, warm=warm is not None, budget=self._plan is not None)
        sol = solver(**args)
        stats = solver.stats()
        status = str(stats.get("return_status", "unknown"))
        ok = bool(stats.get("success")) or status in ("Solved_To_Acceptable_Level",)
        return np.array(sol["x"]).ravel(), sol["lam_x"], sol["lam_g"], status, ok, float(sol["f"])

    _ipopt: dict[tuple, Any] = {}

    def _solver_for(self, ocp: CycleOCP, warm: bool, budget: bool):
        import casadi as ca

        key = (id(ocp), warm, budget, self.config.time_budget, self.config.max_iter)
        if key not in self._ipopt:
            opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                    "ipopt.max_iter": self.config.max_iter if budget else 3000, "ipopt.tol": 1e-6,
                    "ipopt.acceptable_tol": 1e-4, "ipopt.acceptable_iter": 3,
                    "ipopt.max_wall_time": (self.config.time_budget or 60.0) if budget else 60.0,
                    "ipopt.mu_strategy": "adaptive"}
            if warm:
                opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-4,
                             "ipopt.warm_start_bound_push": 1e-6, "ipopt.warm_start_mult_bound_push": 1e-6})
            self._ipopt[key] = ca.nlpsol("mpc", "ipopt", ocp._nlp, opts)
        return self._ipopt[key]

    def _guess(self, ocp: CycleOCP, x: np.ndarray, t: float) -> np.ndarray:
        """Initial guess: the previous plan shifted to now, else the offline optimum of the mode."""
        if self._plan is not None:
            sol = self._plan["sol"]
            shift = t - self._plan["t_made"]
            ts = sol["t"] - shift
            keep = ts >= 0.0
            if keep.sum() >= 2:
                first = np.flatnonzero(keep)[0]
                return ocp.guess_from_trajectory(ts[first:], sol["states"][first:], sol["position"][first:],
                                                 sol["controls"][first:] if first < len(sol["controls"]) else sol["controls"][-1:],
                                                 sol["phase"][first:])
        ref = self.reference()
        ts = np.asarray(ref.t) - t
        first = int(np.clip(np.searchsorted(ts, 0.0), 0, len(ts) - 2))
        return ocp.guess_from_trajectory(ts[first:], np.asarray(ref.states)[first:], np.asarray(ref.position)[first:],
                                         np.asarray(ref.controls)[first:], np.asarray(ref.phase)[first:])

    def reference(self):
        """The offline optimum of this mode (the cold-start guess), solved once."""
        if self._reference is None:
            cfg = self.config
            if cfg.mode == "time":
                self._reference = solve_ocp(self.braking, "time", params=self.params, verify=False)
            elif cfg.mode == "target_time":
                try:
                    self._reference = solve_ocp(self.braking, "fuel_at_time", T=cfg.target_time, params=self.params, verify=False)
                except RuntimeError:
                    self._reference = solve_ocp(self.braking, "time", params=self.params, verify=False)
            else:
                self._reference = solve_ocp(self.braking, "weighted", w_fuel=cfg.w_fuel, params=self.params, verify=False)
        return self._reference

    def _from_plan(self, t: float, phase: int) -> tuple[np.ndarray, bool]:
        """Control and shift request now, from the last good plan (shifted by its age)."""
        if self._plan is None:
            ref = self.reference()
            i = int(np.clip(np.searchsorted(ref.t, t, side="right") - 1, 0, len(ref.controls) - 1))
            return np.asarray(ref.controls[i], dtype=float), int(ref.phase[i]) > phase
        sol = self._plan["sol"]
        age = t - self._plan["t_made"]
        ts, ph = sol["t"], sol["phase"]
        if age >= ts[-1]:  # the plan is used up: hold still (brakes where allowed, bucket stopped)
            return self._terminal(None), False
        # the planned end of the current phase, relative to now
        in_phase = np.flatnonzero(ph[:-1] == phase)
        end_of_phase = ts[in_phase[-1] + 1] - age if in_phase.size else -math.inf
        # Shift in this step if the plan ends the phase before the next step: early is always feasible
        # (brake a little less), late may not be (at 2.5 m/s a step costs 25 cm of stopping distance).
        shift = phase in (1, 3) and end_of_phase < self.dt
        if shift:
            nxt = np.flatnonzero(ph[:-1] == phase + 1)
            i = int(nxt[0]) if nxt.size else len(sol["controls"]) - 1
            i = max(i, int(np.clip(np.searchsorted(ts, age, side="right") - 1, 0, len(sol["controls"]) - 1)))
        else:
            i = int(np.clip(np.searchsorted(ts, age, side="right") - 1, 0, len(sol["controls"]) - 1))
        return np.asarray(sol["controls"][i], dtype=float), bool(shift)

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
        """(omega, V) one control step after x0 under the effective controls u: the model (one RK4 step,
        as the simulator's), its lift drawing lift_gain times the model's power from the engine, its
        dV/dt = accel[0] * model + d * accel[1]."""
        p = self.params
        gear, direction, _ = cycle.phase_tables(self.braking, p)
        gear, direction = float(gear[phase]), float(direction[phase])

        def f(y: np.ndarray) -> np.ndarray:
            return np.array(estimated_derivatives(y, u, gear, direction, p, accel[1], accel[0], lift_gain)[:4])

        h = self.dt
        y = np.asarray(x0[:4], dtype=float)
        k1 = f(y)
        k2 = f(y + 0.5 * h * k1)
        k3 = f(y + 0.5 * h * k2)
        k4 = f(y + h * k3)
        y1 = y + h / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)
        return float(y1[0]), float(y1[1])

    def project_state(self, x: np.ndarray, phase: int) -> np.ndarray:
        """The measurement moved onto the constraints it may graze (by a hair, through the simulator's
        per-substep saturation): a plan must start from a state its constraints admit."""
        p = self.params
        x = np.array(x, dtype=float)
        x[0] = min(max(x[0], p.omega_min), p.omega_max)
        d = -1.0 if phase <= 2 else 1.0
        x[1] = d * min(max(d * x[1], 0.0), p.V_max)
        x[2] = min(max(x[2], p.H_0), lift.max_bucket_height(p))
        x[3] = min(max(x[3], 0.0), (1.0 - 1e-6) * float(lift.max_lift_speed(x[2], x[0], p)))
        return x

    def _stopping(self, x: np.ndarray) -> np.ndarray:
        """The last part-step of phase 2: the previous step's controls; with service brakes the brake
        torque that decelerates at the limit (as the terminal law brakes)."""
        u = np.array(self._last[2], dtype=float)
        if self.braking == "service":
            u[2] = self._terminal(None)[2]
        return u

    def _terminal(self, x: np.ndarray | None) -> np.ndarray:
        """End of the cycle, the vehicle (nearly) standing: brake, bring the bucket to H_T and hold it.

        The OCP has no stiction (a standing machine would roll back under the brake torque), so the
        last tenths of a second are a simple feedback law rather than an NLP.
        """
        p = self.params
        # the brake torque that decelerates at the 0.18 g limit with rolling resistance helping, in the plant
        # as estimated: deceleration = gain * (U_b / r_w + F_roll) / M_tot - offset
        gain, offset = self._theta
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
        st = np.asarray(self.solve_times) if self.solve_times else np.zeros(1)
        return {"median_s": float(np.median(st)), "p95_s": float(np.percentile(st, 95)), "max_s": float(st.max()),
                "n": int(len(self.solve_times)), "fallbacks": int(self.fallbacks)}


def run_closed_loop(braking: str = "service", config: MPCConfig | None = None,
                    params: LoaderParams | dict | None = None, plant_params: LoaderParams | dict | None = None,
                    score: bool = True, seed: int = 0, controller: MPCController | None = None) -> dict[str, Any]:
    """One cycle of ``WheelLoader-v0`` under the MPC; returns the trajectory, the result and its score.

    ``params`` is the controller's model, ``plant_params`` the simulated machine (default: the same);
    they differ in a model-mismatch study. ``controller`` (default: built from ``config``) lets a caller
    inspect the controller afterwards.
    """
    import gymnasium as gym

    import wl_env  # noqa: F401  (registers the env)
    from wl_env.rollout import run_episode

    config = config or MPCConfig()
    model = resolve(params)
    plant = resolve(plant_params) if plant_params is not None else model
    env = gym.make("WheelLoader-v0", braking=braking, params=plant, max_time=config.max_time)
    ctrl = controller or MPCController(braking, model, config, dt=env.unwrapped.core.dt)
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
        from mpc.scoring import score_run

        s = score_run(ep["T"], ep["fuel_g"], braking, success=ep["success"], max_violation=ep["max_excess"],
                      params=model)
        result["score"] = s.to_dict()
    return result
