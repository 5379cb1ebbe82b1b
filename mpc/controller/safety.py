"""The MPC's last guard on the control it applies: a one-step safety filter on the driver's limits.

A plan keeps the deceleration and speed limits as its model predicted them when it was solved. The control a
step applies may come from an older plan: a real-time step applies the plan the worker solved while the steps
before it ran, a deadline step the previous plan shifted, a failed solve the last good one. Under model
error that plan was made for a state and an estimate the plant has since left: a TC-braking cycle on a light,
hard-rolling machine (payload x0.8, rolling resistance x1.3) applied a 28-step-old plan into the shift and
ended 74 % over the deceleration limit (docs/benchmarks.md section 3).

The filter predicts the coming step from the measured state, under the current plant estimate, with the
simulator's own step (:meth:`wl_env.simulator.Simulator.substep`: the environment's check at every RK4 stage
and the step's end, the stop cut at V = 0). Where the step would break the deceleration or speed limit (a control
from a plan older than the state: where it comes within ``STALE_MARGIN`` of them; the cycle's last stop, within the
margin the filter's own predictions have missed by), it eases the control that
causes it: the service brake's torque where the brakes act, then the injection (with a gear in, the engine's speed
sets the converter's drag, and it drives the machine). Each is bisected to the largest value that keeps the limit
``EASE_MARGIN`` inside it (the estimate mispredicts); a fresh plan's excess under ``FILTER_TOL``, which its NLP
traded against a target (the limit is elastic there), only ``SOLVED_EASE_MARGIN`` inside.

An engine the step would bring within ``STALL_GUARD`` of omega_min (a plan made for a lighter machine: TC x1.2 /
x1.3 in real time stalled in phase 1 on a 28-step-old plan) gets the least injection that keeps it
``STALL_MARGIN`` above, and keeps it whatever the limits (a stall ends the cycle); no eased injection goes below
that either.

With TC braking the converter brakes the shift into forward gear by the engine's speed at the shift: an engine
left too fast cannot be slowed within that step, so the filter also looks ahead along the plan. Where the plan's
controls up to its shift (at most ``SHIFT_LOOKAHEAD`` steps away) would bring the machine there with an engine
at which even an unfuelled shift breaks the limit, this step's injection is cut to the least that keeps the
engine running, and where that is not enough the bucket is lifted at full acceleration (up to the curve that
stops it at the dump height): the pump's load brings the engine down. The look-ahead adds, per step predicted,
the engine speed's one-step bias the filter has measured (a mismatched engine drifted 0.1-0.3 rad/s per step
from the prediction while the estimator settled the lift's load 2 % high, fixed at stop 44; the bias stays as a
guard against what the estimate does not model).

A control that keeps the limits passes unchanged (a fresh plan keeps them under the same estimate, bar its
elastic excess), and an easing that would not help (less injection in a driven phase can let the converter brake
harder) is not applied.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from wl_env import step
from wl_env.assist import bucket_command
from wl_env.params import LoaderParams
from wl_env.simulator import Simulator

# Relative excess a plan may carry as its own (the solver's tolerance, its elastic limit): a fresh plan's is eased only
# SOLVED_EASE_MARGIN inside the limit, not EASE_MARGIN, and the shift look-ahead leaves a shift predicted within it.
FILTER_TOL = 1e-3
# A plan's excess is elastic (grid.DECEL_EXCESS_WEIGHT): a TC minimum-time plan rode 1.9e-5 over the limit in its
# last stop rather than miss the truck by a centimetre (a fresh draw, stop 52; the environment counts any excess).
# Below FILTER_TOL such a control is eased to this fraction inside the limit, which moves the stop by ~0.1 mm, or
# to MARGIN_SIGMAS times the filter's moving RMS prediction error if that is more (a mismatched TC draw within #13's
# ranges, eased to 1e-5 at its last stop, broke the limit by 5.3e-5: the estimate's error; stop 52).
SOLVED_EASE_MARGIN = 1e-5
# An eased control aims this fraction inside the limits (MPCConfig.tighten's default, what a plan keeps free): the
# estimate mispredicts the plant's step (TC x0.8 / x1.3 in real time: controls eased to the limit +0.1 % gave +0.27 %)
EASE_MARGIN = 0.005
# A control from a plan older than the state is eased where the step is predicted above this fraction inside the
# limits (a fresh plan keeps EASE_MARGIN), or, where the filter's own predictions of the speed have missed by more,
# MARGIN_SIGMAS times their moving RMS (as a fraction of the deceleration limit): service x0.8 / x1.3 in real time
# braked 0.2 % over the limit on plans the estimate put 0.25 % inside it (measured)
STALE_MARGIN = 0.0025
MARGIN_SIGMAS = 3.0
MARGIN_STEP = 0.0025  # (the margins are rounded up to it: one simulator per margin)
# The most a margin takes off the limits: a plant far outside the model (rolling resistance x10) mispredicted by
# more than the limit itself, and a margin over 1 made the limits negative (`wl mpc --rolling-scale 10` stopped on
# "V_max must lie in [0.1, 20] m/s")
MAX_MARGIN = 0.2
PREDICTION_ERROR_DECAY = 0.9  # per step, of the moving means of the filter's one-step prediction errors
STALL_MARGIN = 2.0  # rad/s above omega_min an eased injection keeps the engine at the step's end (a stall ends the cycle)
# rad/s above omega_min under which the filter raises the injection (plans keep MPCConfig.omega_margin, 1 rad/s)
STALL_GUARD = 0.5
BISECTIONS = 12  # per eased control: its range to 1/4096
SHIFT_LOOKAHEAD = 20  # steps (2 s at 0.1 s: an unfuelled engine comes down by 40-80 rad/s in them)


@dataclass(frozen=True)
class Filtered:
    """The control to apply, [U_mf (mg), U_ab (m/s^2), U_b (N m)], and what the filter did: the predicted
    relative excess over the driver's limits before and after, and which controls it eased ('' none)."""

    control: np.ndarray
    excess_before: float
    excess_after: float
    eased: str


class SafetyFilter:
    """Eases a control whose next step the model predicts over the deceleration or speed limit."""

    def __init__(self, params: LoaderParams, braking: str, dt: float) -> None:
        self.sim, self.dt, self.braking = Simulator(params, braking), float(dt), braking
        # (the same machine with its limits a fraction inside: what an eased or a stale control is checked against)
        self._inside: dict[float, Simulator] = {}
        self.reset()

    def reset(self) -> None:
        """A new cycle: no prediction to learn from yet."""
        # (phase, omega, V) the last filtered step was predicted to end at
        self._predicted: tuple[int, float, float] | None = None
        self._until: float | None = None  # the current call's deadline (time.perf_counter() s)
        self._accel_err2 = 0.0
        self.engine_speed_bias = 0.0  # rad/s per step: the moving mean of (measured - predicted) omega, same phase

    def forget_prediction(self) -> None:
        """The last filtered control was not the one applied (a shadow expert's): nothing to learn from it."""
        self._predicted = None

    def observe(self, x: np.ndarray, phase: int) -> None:
        """The state the last filtered step ended at: the moving RMS of the predicted acceleration's error and the
        moving mean of the engine speed's (with a 20 % heavier payload the engine ran 0.15-0.29 rad/s per step
        faster than predicted late in phase 1, while the estimator settled the lift gain at 1.22: measured at stop
        43, the estimator fixed at stop 44; what the estimate does not model still shows here)."""
        if self._predicted is not None and self._predicted[0] == phase:
            decay = PREDICTION_ERROR_DECAY
            self.engine_speed_bias = decay * self.engine_speed_bias + (1.0 - decay) * (float(x[0]) - self._predicted[1])
            if abs(x[1]) > 0.05:
                a_limit = self.sim.params.decel_max * self.sim.params.g
                e = (float(x[1]) - self._predicted[2]) / self.dt / a_limit
                self._accel_err2 = decay * self._accel_err2 + (1.0 - decay) * e * e
        self._predicted = None

    @property
    def prediction_margin(self) -> float:
        """MARGIN_SIGMAS times the moving RMS of the filter's one-step acceleration errors (a fraction of the limit)."""
        return min(MARGIN_SIGMAS * float(np.sqrt(self._accel_err2)), MAX_MARGIN)

    @property
    def stale_margin(self) -> float:
        """The fraction inside the limits a stale plan's control is eased at (module constants)."""
        m = max(STALE_MARGIN, self.prediction_margin)
        return min(MARGIN_STEP * np.ceil(m / MARGIN_STEP - 1e-9), MAX_MARGIN)

    def _within(self, margin: float) -> Simulator:
        # (sums of MARGIN_STEP, or a fresh plan's prediction margin, rare: one simulator each, 0.14 ms to build)
        margin = round(margin, 6)
        sim = self._inside.get(margin)
        if sim is None:
            p, inside = self.sim.params, 1.0 - margin
            sim = self._inside[margin] = Simulator(p.replace(decel_max=inside * p.decel_max, V_max=inside * p.V_max),
                                                   self.braking)
        return sim

    def _step(self, x: np.ndarray, phase: int, u: np.ndarray, est: np.ndarray,
              margin: float = 0.0) -> tuple[tuple, int, float]:
        """One control step from x = [omega, V, H, V_b, s] in ``phase`` under the commanded control u, the plant
        estimate ``est`` ([accel offset, accel gain, lift gain]) on the model: the end state, its phase and the
        relative excess (0: within) over the deceleration and speed limits (``margin``: that fraction inside)."""
        sim = self._within(margin) if margin else self.sim
        y = (float(x[0]), float(x[1]), float(x[2]), float(x[3]), float(x[4]), 0.0)
        gear, _, brake = sim.phase_constants(phase)
        # (wl_env.step's effective controls, not the simulator's flattened copy: a new scenario builds that first,
        # 20-90 ms, measured)
        applied = step.effective_controls(y, gear, brake, float(u[0]), float(u[1]), float(u[2]), self.dt, sim.params)[:3]
        y1, after, _, ex = sim.substep(y, phase, applied, self.dt, est=np.asarray(est, dtype=float))
        return y1, int(after), float(max(ex["deceleration"], ex["speed"]))

    def excess(self, x: np.ndarray, phase: int, u: np.ndarray, est: np.ndarray, margin: float = 0.0) -> float:
        """The relative excess (0: within) over the deceleration and speed limits of the step (:meth:`_step`)."""
        return self._step(x, phase, u, est, margin)[2]

    def _in_time(self) -> bool:
        return self._until is None or time.perf_counter() < self._until

    def _boundary(self, good: float, bad: float, ok: Callable[[float], bool]) -> float:
        """Bisect between a value where ``ok`` holds and one where it does not (BISECTIONS times, or until the
        call's deadline): the value nearest the boundary on the side that holds."""
        for _ in range(BISECTIONS):
            if not self._in_time():
                break
            mid = 0.5 * (good + bad)
            good, bad = (mid, bad) if ok(mid) else (good, mid)
        return good

    def _least_injection(self, x: np.ndarray, phase: int, u: np.ndarray, est: np.ndarray,
                         most: float | None = None) -> float:
        """The least U_mf up to ``most`` (default u's) that keeps the engine STALL_MARGIN above omega_min at the
        step's end (``most`` if none does; out of time, the least found so far that does)."""
        floor = self.sim.params.omega_min + STALL_MARGIN
        lo, hi = 0.0, float(u[0] if most is None else most)
        trial = u.copy()

        def runs(u_mf: float) -> bool:
            trial[0] = u_mf
            return self._step(x, phase, trial, est)[0][0] >= floor

        if runs(lo):
            return lo
        return hi if not runs(hi) else self._boundary(hi, lo, runs)

    def shift_excess(self, x: np.ndarray, phase: int, controls: np.ndarray, at_shift: np.ndarray,
                     est: np.ndarray) -> float:
        """The least relative excess the shift out of ``phase`` can have when it comes: ``controls`` (one row
        per step before the shift) applied from x, then the shift's step ``at_shift`` with no injection. Each
        predicted step adds the engine speed's one-step bias where it runs the engine faster (a faster engine
        brakes harder at the shift; over 5-15 steps the bias was the excess the look-ahead missed: 2-7.5 %)."""
        y = np.asarray(x, dtype=float)
        drift = max(self.engine_speed_bias, 0.0)
        for u in controls:
            y1, after, _ = self._step(y, phase, u, est)
            if after != phase:  # (the leg ended on its own: no shift to come)
                return 0.0
            y = np.array(y1[:5])
            y[0] += drift
        return self.excess(y, phase + 1, np.array([0.0, at_shift[1], at_shift[2]]), est)

    def __call__(self, x: np.ndarray, phase: int, u: np.ndarray, est: np.ndarray,
                 ahead: tuple[np.ndarray, np.ndarray] | None = None, stale: bool = False,
                 until: float | None = None) -> Filtered:
        """The control u for the step in ``phase`` (the phase after a shift) from state x, eased where it
        would break a limit (module doc). ``ahead``: the plan's controls after this step up to a shift into a
        phase braked by the converter, and the shift's own; where that shift would break the limit even
        unfuelled, this step's injection is cut and the bucket lifted (module doc). ``stale``: u comes from a plan
        made before this state (real time, a fallback): eased where it comes within ``stale_margin`` of the limits.
        ``until`` (``time.perf_counter()`` s): the step's deadline; past it the bisections stop on the safe side of
        what they found and the look-ahead is skipped (a control is never late for the filter)."""
        self._until = until
        original = np.array(u, dtype=float)
        u = original.copy()
        y1, after, before = self._step(x, phase, u, est)
        if y1[0] < self.sim.params.omega_min + STALL_GUARD:
            # an engine about to stall (a plan for a lighter machine): the least injection that keeps it running;
            # a stall ends the cycle, so this fuel is not eased for the limits
            least = self._least_injection(x, phase, u, est, most=self.sim.params.U_mf_max)
            if least > u[0]:
                u[0] = least
                return self._keep(u, before, "U_mf up (stall)", self._step(x, phase, u, est))
        if ahead is not None and self._in_time():
            guarded = self._shift_guard(x, phase, u, est, ahead)
            if guarded is not None:
                u, later, eased = guarded
                return self._keep(u, later, eased, self._step(x, phase, u, est))
        # The cycle's last stop (at the truck, the step predicted to end standing): a fresh plan's brake there is eased
        # by the prediction margin even within the limit (an acceleration gain 0.06-0.2 % off put three mismatched draws'
        # last stops 1e-5..1.6e-4 over it; no later step makes good a miss of the mark). Every fresh braking step so
        # eased cost service draws in-step re-plans and 0.4 s; the injection too, 4 of 16 TC draws their marks (stop 57).
        last_stop = not stale and after == 4 and y1[1] == 0.0 and before <= 0.0 and u[2] > 0.0
        decide = self.stale_margin if stale else self.prediction_margin if last_stop else 0.0
        if stale:
            ease = decide + EASE_MARGIN - STALE_MARGIN
        elif before > FILTER_TOL:
            ease = EASE_MARGIN
        else:  # (a fresh plan's own elastic excess: just inside the limit, by the estimate's error if that is more)
            ease = max(SOLVED_EASE_MARGIN, self.prediction_margin)
        if not (self.excess(x, phase, u, est, decide) > 0.0 if decide else before > 0.0):
            return self._keep(u, before, "", (y1, after, before))
        _, _, brake_allowed = self.sim.phase_constants(phase)
        eased, inside = [], self.excess(x, phase, u, est, ease)
        inside_before = inside
        for i, name in ((2, "U_b"), (0, "U_mf")):
            if inside <= 0.0 or (i == 0 and last_stop):  # (the last stop's: the brake alone)
                break
            if u[i] <= 0.0 or (i == 2 and not brake_allowed):
                continue
            lo, hi = (0.0 if i == 2 else self._least_injection(x, phase, u, est)), float(u[i])
            if lo >= hi:
                continue
            u[i] = lo
            eased.append(name)
            inside = self.excess(x, phase, u, est, ease)
            if inside > 0.0:  # not enough alone: this one off, the next one too
                continue

            def keeps(value: float, i: int = i) -> bool:
                u[i] = value
                return self.excess(x, phase, u, est, ease) <= 0.0

            u[i] = self._boundary(lo, hi, keeps)  # the largest value that keeps the limits ``ease`` inside
            inside = self.excess(x, phase, u, est, ease)
        step_after = self._step(x, phase, u, est)
        if step_after[2] > before or inside >= inside_before:  # (easing did not help: the control as it came)
            return self._keep(original, before, "", (y1, after, before))
        return self._keep(u, before, "+".join(eased), step_after)

    def _shift_guard(self, x: np.ndarray, phase: int, u: np.ndarray, est: np.ndarray,
                     ahead: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, float, str] | None:
        """The look-ahead to a TC shift (module doc): None where the plan's controls bring the machine there within
        the limit (or nothing this step can do helps); else the control with the injection cut to the least that
        keeps the engine running, where that is not enough the bucket lifted at full acceleration too (the pump's
        load brings the engine down: a re-plan that lifted less met the shift 4 rad/s faster and 3.6 % over the
        limit, measured), the shift's excess predicted before, and what was changed."""
        later = self.shift_excess(x, phase, np.vstack([u, ahead[0]]), ahead[1], est)
        if later <= FILTER_TOL:
            return None
        guarded, changed, excess = u.copy(), [], later
        if u[0] > 0.0:
            guarded[0] = self._least_injection(x, phase, u, est)
            if guarded[0] < u[0]:
                changed.append("U_mf")
                excess = self.shift_excess(x, phase, np.vstack([guarded, ahead[0]]), ahead[1], est)
        if excess > FILTER_TOL and self._in_time():
            p = self.sim.params
            lifted = guarded.copy()
            lifted[1] = float(bucket_command(x[2], x[3], p.U_ab_bounds[1], p, self.dt))  # (stops at the dump height)
            if lifted[1] > guarded[1]:
                lifted[0] = self._least_injection(x, phase, lifted, est, most=p.U_mf_max)  # (the lift loads the engine)
                if self.shift_excess(x, phase, np.vstack([lifted, ahead[0]]), ahead[1], est) < excess:
                    guarded = lifted
                    changed.append("U_ab up")
        return (guarded, later, "+".join(changed) + " (the shift ahead)") if changed else None

    def _keep(self, u: np.ndarray, before: float, eased: str, stepped: tuple[tuple, int, float]) -> Filtered:
        """The filtered control u and its step (:meth:`_step`), whose end state is kept for :meth:`observe`."""
        y1, after, excess = stepped
        self._predicted = (after, float(y1[0]), float(y1[1]))
        return Filtered(u, before, excess, eased)
