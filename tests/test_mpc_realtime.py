"""The MPC in time: a forced solver failure falls back on the shifted plan, a hard deadline per step
(deadline_ms) never returns a late control, the real-time mode (realtime) returns its control at once,
and a time budget overrun falls back without crashing. Slow and failing solvers are injected."""

import time

import gymnasium as gym
import numpy as np
import pytest
from fakes import FailingSolver

import wl_env  # noqa: F401  (registers the env)
from mpc.benchmark.ocp import solve_ocp
from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop
from mpc.controller.solver import IpoptSolver, solve_until
from wl_env.scenario import Scenario


def test_fallback_applies_the_shifted_plan_on_a_forced_failure():
    env = gym.make("WheelLoader-v1", braking="service")
    solver = FailingSolver({10, 11, 12, 30})
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0), solver=solver)
    obs, _ = env.reset(seed=0)
    flagged = 0
    for k in range(200):
        solver.step = k
        a = ctrl.act(obs)
        assert np.isfinite(a).all() and a.shape == (4,)
        if ctrl.last_info["fallback"]:
            flagged += 1
            assert "forced failure" in ctrl.last_info["status"]
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    assert flagged == 4 and ctrl.fallbacks == 4
    assert info["completed"] and info["is_success"] and info["violations"]["max_excess"] == 0.0


# A timed step's slack for the scheduler: the 2 CI cores also run another pytest worker (a step there returned
# 24 ms past its bound once). The solves the tests slow down take 250-500 ms: a step that waited for one is
# late by far more.
TIMING_SLACK_S = 0.05


def _act_timed(ctrl: MPCController, obs: np.ndarray) -> tuple[np.ndarray, float]:
    """The control and how long after the step's real-time start it came: a simulation faster than real
    time may wait until one interval after the step before began (:meth:`MPCController._collect_ahead`,
    :meth:`MPCController._step_outcome`), never longer."""
    before = getattr(ctrl, "_step_start", None)
    t_call = time.perf_counter()
    a = ctrl.act(obs)
    begins = t_call if before is None else max(t_call, before + ctrl.dt)
    return a, time.perf_counter() - begins


class SlowSolver(IpoptSolver):
    """IPOPT that takes ``delay`` s more at the control steps in ``slow`` (a slower CPU, a hard solve);
    with ``once``, only on the first solve that starts at one of them (recorded in ``slowed_at``)."""

    def __init__(self, slow: set[int], delay: float, once: bool = False) -> None:
        super().__init__()
        self.slow, self.delay, self.once, self.step = slow, delay, once, -1
        self.slowed_at: list[int] = []

    def solve(self, *args, **kwargs):
        step = self.step
        if step in self.slow and not (self.once and self.slowed_at):
            self.slowed_at.append(step)
            time.sleep(self.delay)
        return super().solve(*args, **kwargs)


def test_deadline_returns_the_shifted_plan_in_time_and_flags_it():
    """With deadline_ms, a step whose solve would pass the deadline returns an earlier step's plan's
    control by the deadline (flagged), while the solve runs on; the step after, with the solver still busy,
    does too; the late plan is then the one in use, and the cycle stays within the limits. It completes
    where the solves mostly keep their deadline. (Measured: where every solve ran 100-160 ms, all of steps
    1-60 late, it still completed in 11.0 s; with three more busy processes on the 2 cores, 2 of 3 runs
    stalled at 2.4-3.1 s: plans 3-4 steps old drive the machine open loop.)"""
    env = gym.make("WheelLoader-v2", braking="service")
    deadline_ms, delay = 100.0, 0.5
    # (the first solve that starts at step 20 or later: on a slow machine step 20 may still wait for step 19's)
    solver = SlowSolver(set(range(20, 200)), delay, once=True)
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0, deadline_ms=deadline_ms),
                         solver=solver)
    obs, _ = env.reset(seed=0)
    missed = []
    for k in range(200):
        solver.step = k
        a, late = _act_timed(ctrl, obs)
        if k > 0:  # (a simulation faster than real time waits a late solve's control interval, see _step_outcome)
            assert late < 1e-3 * deadline_ms + TIMING_SLACK_S, f"step {k}: a control {1e3 * late:.0f} ms after it began"
            assert ctrl.solve_times[-1] < 1e-3 * deadline_ms + TIMING_SLACK_S
        if ctrl.last_info["deadline_missed"]:
            missed.append(k)
            assert ctrl.last_info["fallback"] and "deadline" in ctrl.last_info["status"]
            # an earlier step's plan's control for this step (shifted), not a new one
            # (its step k - k_made, or later where the plant ended a phase ahead of the plan)
            assert ctrl._plan_index >= k - ctrl._plan["k_made"] >= 1
            step = {key: v[0] for key, v in ctrl.planned_steps().items()}
            expected = np.array(step["controls"][:2])
            if step["stop"] and step["phase"] == 4:  # (a standing stop at the truck lands the bucket)
                expected[1] = ctrl.params.U_ab_bounds[0]
            assert np.allclose(ctrl.codec.decode_action(*a[:3])[:2], expected, rtol=1e-4, atol=1e-3)
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    # the late solve (0.5 s and its own) spans two deadlines in a row: its step's and the next, or, where it
    # waited on the worker behind an earlier late solve and began only after its step returned, the next two
    # (other steps may miss too on a slow machine: a solve here takes 10-150 ms; CI once had 22 on time
    # after a 0.25 s delay that began at 21)
    slow = solver.slowed_at[0]
    assert 20 <= slow <= 30 and any({j, j + 1} <= set(missed) for j in (slow, slow + 1))
    assert ctrl.deadline_misses == len(missed) == ctrl.stats()["deadline_misses"]
    assert info["violations"]["max_excess"] == 0.0
    if len(missed) <= 0.25 * (k + 1):
        assert info["completed"] and info["is_success"]


def test_realtime_controls_come_at_once_and_keep_the_optimum():
    """MPCConfig.realtime: each step applies the plan solved while the step before ran (from the state
    measured then, its control fixed) and hands its own solve to the worker. Without model error the
    cycle is the optimum's on the grid (measured: fuel +0.05 % over the OCP at 11 s), within the limits,
    and a control takes a fraction of a millisecond (measured: 0.1 ms median, 0.3 ms max). Another
    scenario at another target next plans on the same NLPs and solvers (the scenario is their parameter):
    its own continuous reference warm-started from the first cycle's, and the first plan reshaped to its
    legs and heights as the warm start (measured: 0.46-1.23 s on five `test` scenarios at 12 s after the
    nominal one, +0.23..+0.43 % fuel, as from the continuous reference, which took 8-16 s with new NLPs)."""
    from mpc.controller.solver import grid_nlp

    other = Scenario(payload=11000.0, reverse_distance=7.2, forward_distance=6.0, rolling_resistance=0.035,
                     dump_height=4.6, start_engine_speed=1400.0, start_bucket_height=0.8, braking="tc")
    for target, scenario in ((11.0, None), (11.4, other)):
        config = MPCConfig(mode="target_time", target_time=target, realtime=True)
        params = None if scenario is None else scenario.params()
        ctrl = MPCController("tc", params, config=config)
        builds = grid_nlp.cache_info().misses
        r = run_closed_loop("tc", config, score=False, controller=ctrl, scenario=scenario)
        ep = r.episode
        assert ep.completed and ep.success and ep.max_violation == 0.0
        assert ep.T <= target + 1e-9
        assert ep.fuel_g <= 1.01 * solve_ocp("tc", "fuel_at_time", T=ep.T, params=params, verify=False).fuel_g
        assert r.solve_time["p99_s"] < 0.03 and r.solve_time["max_s"] < TIMING_SLACK_S + ctrl.dt / 2  # (0.3 ms measured)
        # the worker's solves kept up: most steps applied the plan due for them
        assert len(r.worker_solve_times_s) > 0.5 * len(r.solve_times_s)
        assert ctrl.fallbacks < 0.5 * len(r.solve_times_s)
        assert ctrl._ahead is None  # the worker's last solve ended with the episode (run_episode -> end_episode)
    # (the reference's path takes 6-23 s: the continuous OCP and a cold solve, new NLPs if the layout is new;
    # this one 0.5-1.2 s alone, 2.7 s beside two other jobs on the 2 cores)
    assert ctrl.first_plan_from == "neighbour" and ctrl.planning_time < 4.0
    assert grid_nlp.cache_info().misses == builds  # no NLP built for the other scenario


def test_realtime_never_waits_for_a_slow_solver():
    """With solves slower than the interval (steps 1-29), a real-time step still returns its control at
    once: the current plan's, shifted, flagged as overdue, until the solves plan far enough ahead (the
    lead doubles) to be in time again; the cycle completes within the limits."""
    env = gym.make("WheelLoader-v2", braking="service")
    solver = SlowSolver(set(range(1, 30)), 0.25)  # (read on the worker: a solve may take the next step's number)
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0, realtime=True),
                         solver=solver)
    obs, _ = env.reset(seed=0)
    overdue, leads = [], []
    for k in range(200):
        solver.step = k
        plan_before = ctrl._plan
        a, late = _act_timed(ctrl, obs)
        if k > 0:  # (a step waits for the worker at most the interval real time would give it; twice the slack: the
            # worker's Python work beside it holds the GIL, a step came 56 ms late once in CI at stop 44, and a wait
            # for one of these 250 ms solves is later still)
            assert late < 2 * TIMING_SLACK_S, f"step {k}: a control {1e3 * late:.0f} ms after it began"
        leads.append(ctrl.last_info.get("lead", 0))
        if ctrl.last_info["fallback"]:
            overdue.append(k)
            assert "overdue" in ctrl.last_info["status"]
            i = k - plan_before["k_made"]
            if ctrl._plan is plan_before and i < len(plan_before["stop"]) and not plan_before["stop"][i]:
                # the plan in use, one step further on (a stop step at the truck brakes the bucket instead)
                assert np.allclose(ctrl.codec.decode_action(*a[:3])[:2], plan_before["controls"][i][:2],
                                   rtol=1e-4, atol=1e-3)
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    assert any(k < 30 for k in overdue) and max(leads[:30]) >= 4
    assert np.median(ctrl.solve_times[1:]) < 0.005  # (no solve on the step's own thread: measured 0.1 ms)
    assert info["completed"] and info["is_success"] and info["violations"]["max_excess"] == 0.0


def test_fixed_first_controls_and_a_solve_deadline():
    """A plan solved with its first control fixed at the plan's own is that plan (the principle of
    optimality), with another first control it keeps that control and costs no less (to the solver's
    tolerance); a solve past its
    deadline (solve_until) returns a failed solve with its iterate, not an interrupt."""
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0))
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl.act(obs)
    sol, x = ctrl._sol, ctrl.project_state(ctrl.state_from_obs(obs)[0], 1)
    u0 = ctrl._plan["controls"][0]
    same = ctrl._solve(1, sol.counts, x, sol, u_fixed=u0[None, :])
    assert same.ok and abs(same.J - sol.J) <= 1e-3 * abs(sol.J)
    other = u0 + np.array([20.0, 0.0, 0.0])  # 20 mg more fuel in the first step
    moved = ctrl._solve(1, sol.counts, x, sol, u_fixed=other[None, :])
    first = ctrl._nlp(1).plan(moved.z, moved.counts, x, ctrl.dt)["controls"][0]
    assert moved.ok and np.allclose(first, other, rtol=1e-9, atol=1e-12)
    assert moved.J >= sol.J - 1e-3 * abs(sol.J)  # (IPOPT's acceptable tolerance; the first step's rows are relaxed)
    with solve_until(time.perf_counter() - 1.0):  # stopped at once: the warm start, with another first step
        late = ctrl._solve(1, sol.counts, x, sol, u_fixed=other[None, :])
    assert late.status.startswith("Deadline_Exceeded (an infeasible iterate") and not late.ok and late.z is not None
    with solve_until(time.perf_counter() - 1.0):  # ... with the same: the plan, feasible
        again = ctrl._solve(1, sol.counts, x, sol)
    assert again.status.startswith("Deadline_Exceeded (a feasible iterate") and again.ok


def test_the_same_cycle_again_plans_within_a_second_and_alike():
    """A cycle planned before in the process (same model, mode and start) starts from its first plan:
    under a second (measured 0.13-0.16 s against 13-17 s with the NLP builds), the same schedule and
    controls to the solver's tolerance."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    plans = []
    for _ in range(2):
        ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0))
        ctrl.act(obs)
        plans.append((ctrl.planning_time, ctrl._counts, np.asarray(ctrl._plan["controls"])))
    (_, counts_1, u_1), (t_2, counts_2, u_2) = plans
    assert t_2 < 1.0 and counts_2 == counts_1
    assert np.allclose(u_2, u_1, rtol=1e-3, atol=1e-3 * np.abs(u_1).max(axis=0))


def test_bad_deadline_is_refused():
    for bad in (0.0, -5.0, float("nan"), "10"):
        with pytest.raises(ValueError, match="deadline_ms"):
            MPCConfig(deadline_ms=bad)
    with pytest.raises(ValueError, match="longer than the control interval"):
        MPCController("service", config=MPCConfig(deadline_ms=150.0))


def test_time_budget_overrun_falls_back_without_crashing():
    env = gym.make("WheelLoader-v1", braking="service")
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0, time_budget=1e-4))
    obs, _ = env.reset(seed=0)
    for _ in range(15):
        a = ctrl.act(obs)
        assert np.isfinite(a).all()
        obs, *_ = env.step(a)
    assert ctrl.fallbacks == 14 and ctrl.last_info["over_budget"] and ctrl.last_info["fallback"]


# ------------------------------------------------------------------ the controller's review (stop 63): a worker's error at reset
class WorkerBug(Exception):
    """An error no solver failure is (timed_solve turns RuntimeError and ValueError into failed solves)."""


class LateFailingSolver(IpoptSolver):
    """IPOPT, except that the first solve that starts at step ``at`` or later takes 0.3 s (longer than any wait of a
    100 ms step), then raises WorkerBug; ``started`` is set as it begins."""

    def __init__(self, at: int) -> None:
        import threading

        super().__init__()
        self.at, self.step, self.started = at, -1, threading.Event()

    def solve(self, *args, **kwargs):
        if self.step >= self.at and not self.started.is_set():
            self.started.set()
            time.sleep(0.3)
            raise WorkerBug("a bug in the solve on the worker")
        return super().solve(*args, **kwargs)


def test_a_worker_error_raised_at_reset_leaves_the_controller_reset():
    """With deadline_ms a late solve runs on the worker; one that raised re-raised in reset() (end_episode) part-way:
    the new target taken, the old episode's plan, schedule and model kept, the new scenario not. The reset now ends
    first, then raises the worker's error (with a note); the next reset raises nothing."""
    env = gym.make("WheelLoader-v2", braking="service")
    solver = LateFailingSolver(at=3)
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0, deadline_ms=100.0),
                         solver=solver)
    obs, _ = env.reset(seed=0)
    for k in range(40):  # (on a loaded machine step 3 may still wait for step 2's solve: the first one from step 3 on)
        solver.step = k
        obs, *_ = env.step(ctrl.act(obs))
        if solver.started.is_set():
            break
    assert ctrl._pending is not None  # (the failing solve runs on)
    with pytest.raises(WorkerBug) as raised:
        ctrl.reset(scenario={"payload": 9000.0}, target_time=12.0)
    assert ctrl.config.target_time == 12.0 and ctrl.params.M_load == pytest.approx(9000.0)
    assert ctrl.codec.params is ctrl.params and ctrl.model.params == ctrl.params
    assert ctrl._counts is None and ctrl._sol is None and ctrl._plan is None and ctrl._last is None
    assert ctrl._pending is None and ctrl.solve_times == [] and ctrl.deadline_misses == 0 and ctrl.last_info == {}
    assert "the controller was reset" in "".join(getattr(raised.value, "__notes__", []))
    ctrl.reset()  # (the error was raised once)
    assert ctrl.config.target_time == 11.0
