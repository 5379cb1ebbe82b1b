"""The MPC: its model is the environment's step, it drives the cycle near the optimum within the
constraints, it adapts to a mismatched plant, and it survives solver failures."""

import functools
import json
import math
import types

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import wl_env  # noqa: F401  (registers the env)
from mpc.benchmark.ocp import solve_ocp
from mpc.controller import solver as solver_module
from mpc.controller.grid import NOMINAL_ESTIMATE, StepModel
from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop
from mpc.controller.schedule import apportion, steps_of
from mpc.controller.solver import IpoptSolver, SolverResult
from wl_env.model import estimated_derivatives
from wl_env.params import DEFAULT_PARAMS as P
from wl_env.scenario import Scenario
from wl_env.simulator import Simulator


def sim_step(sim, y, phase, u, dt=0.1):
    """One control step of the environment's simulator (substeps = 1) from y with controls u."""
    ue = sim.effective_controls(y, phase, *u, dt)[:3]
    assert np.allclose(ue, u, rtol=1e-12), "the test's control must lie within the machine's limits"
    y1, phase1, s_rev, _ = sim.substep(y, phase, ue, dt)
    return np.array(y1), phase1, s_rev


# a heavier, rougher cycle: the plant the model's functions take as their parameter, not the one built with
HEAVY = P.replace(M_load=12500.0, c_r=0.045, H_T=4.4, reverse_distance=7.5, forward_distance=5.5)


@pytest.mark.parametrize("braking,plant", [("service", P), ("tc", P), ("service", HEAVY), ("tc", HEAVY)])
def test_grid_step_is_the_environment_step(braking, plant):
    """The MPC's step functions compute what the simulator computes: full steps in every phase, the
    stop step at the reversing point (cut at V = 0, the rest in phase 3) and at the end (standing). Built
    once for the machine, they take the scenario as a parameter: the nominal model's functions with the
    heavy cycle's payload and rolling resistance are the heavy cycle's simulator."""
    model, sim = StepModel(braking, P).with_params(plant), Simulator(plant, braking)
    cases = [  # phase, kind, state (omega, V, H, V_b, s), control
        (1, "full", (180.0, -1.2, 1.5, 0.3, -1.0), (120.0, 0.5, 0.0)),
        (2, "full", (150.0, -1.5, 2.0, 0.3, -5.0), (20.0, 0.0, 30000.0 if braking == "service" else 0.0)),
        (3, "full", (190.0, 0.8, 3.0, 0.4, -5.8), (150.0, 1.0, 0.0)),
        (4, "full", (120.0, 1.5, 4.5, 0.3, -1.5), (10.0, -0.5, 30000.0)),
        (2, "stop", (100.0, -0.1, 2.5, 0.2, -6.59), (5.0, 0.0, 40000.0 if braking == "service" else 0.0)),
        (4, "stop", (80.0, 0.10, 4.99, 0.1, -0.005), (8.0, -1.0, 40000.0)),
    ]
    for phase, kind, x, u in cases:
        fn = (model.full if kind == "full" else model.stop)[phase].fn
        x1, _rows, fuel, s_stop = fn(np.array(x), np.array(u), 0.1, NOMINAL_ESTIMATE, model.step_scenario)
        y1, phase1, s_rev = sim_step(sim, (*x, 0.0), phase, u)
        assert np.allclose(np.array(x1).ravel(), y1[:5], rtol=0, atol=1e-9), (phase, kind)
        assert float(fuel) == pytest.approx(y1[5], abs=1e-12)
        if kind == "stop":
            assert y1[1] == 0.0 or phase == 2  # it stood or turned
            assert phase1 == (3 if phase == 2 else 4)
            if phase == 2:
                assert float(s_stop) == pytest.approx(s_rev, abs=1e-9)


def test_a_plans_fuel_is_its_steps_fuel():
    """A plan's fuel (GridNLP.fuel_g, the objective's fuel term) is its active steps' fuel by the step functions
    (the simulator's, test_grid_step_is_the_environment_step) in slot order, the idle slots burning none; and
    IPOPT's first plan never builds the inlined NLP it does not solve (its build took 0.10-0.15 s a first step)."""
    ctrl = MPCController("tc", config=MPCConfig(mode="target_time", target_time=11.0))
    x = np.array([P.omega_0, 0.0, P.H_0, 0.0, 0.0])
    ctrl._plan_cycle(x, 1, 0)
    sol, nlp = ctrl._sol, ctrl._nlp(1)
    plan = nlp.plan(sol.z, sol.counts, x, ctrl.dt)
    assert len(nlp.active_slots(sol.counts)) < len(nlp.slots)  # (idle slots in the layout)
    fuel_kg = 0.0
    for k, (phase, stop, u) in enumerate(zip(plan["phase"], plan["stop"], plan["controls"], strict=True)):
        fn = (ctrl.model.stop if stop else ctrl.model.full)[int(phase)].fn
        fuel_kg += float(fn(plan["states"][k], u, ctrl.dt, NOMINAL_ESTIMATE, ctrl.model.step_scenario)[2])
    assert sol.fuel_g == pytest.approx(1000.0 * fuel_kg, rel=1e-6)
    assert 40.0 < sol.fuel_g < 90.0  # (57.4 g; the front at 11 s: 57.37 g)
    assert "nlp" not in vars(nlp)


@functools.cache
def _nlp_with_solvers(braking, first_phase, slots, open_phase):
    """A grid NLP and IPOPT on it twice: the derivatives CasADi generates from the whole NLP, and the
    project's (its slot functions', mapped over the slots; compiled where a C compiler is found, as the
    controller's: mpc.controller.codegen)."""
    from mpc.controller.grid import GridNLP
    from mpc.controller.solver import NO_NLP_GRAD

    nlp = GridNLP(StepModel(braking, P), first_phase, dict(slots), open_phase=open_phase)
    quiet = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}
    sqp = {"print_header": False, "print_iteration": False, "print_status": False, "print_time": False}
    return nlp, {"ipopt": (ca.nlpsol("generated", "ipopt", nlp.nlp, quiet),
                           ca.nlpsol("mapped", "ipopt", nlp.mapped_nlp,
                                     {**quiet, **nlp.derivative_functions, **NO_NLP_GRAD})),
                 "sqpmethod": (ca.nlpsol("generated", "sqpmethod", nlp.nlp, sqp),
                               ca.nlpsol("mapped", "sqpmethod", nlp.nlp,
                                         {**sqp, **nlp.sqp_derivative_functions, **NO_NLP_GRAD}))}


LAYOUTS = [("tc", 1, ((1, 3), (2, 2), (3, 3), (4, 2)), None), ("service", 3, ((3, 2), (4, 3)), None),
           ("tc", 1, ((1, 3), (2, 2)), 2), ("service", 2, ((2, 2), (3, 3)), 3), ("tc", 4, ((4, 1),), None)]


@settings(max_examples=10, deadline=None)
@given(layout=st.sampled_from(LAYOUTS), seed=st.integers(0, 2**32 - 1))
def test_mapped_derivatives_are_the_generated_ones(layout, seed):
    """The NLP's objective, rows, gradient, Hessian of the Lagrangian and constraint Jacobian, assembled from
    the slot functions' (where neighbouring slots share the state between them, their blocks sum), and its
    parameter sensitivities (lam_p), equal CasADi's from the whole NLP: every nonzero, with the same
    sparsity, at any point, multipliers and parameters (start, estimate, scenario, step lengths, terminal
    cost)."""
    nlp, solvers = _nlp_with_solvers(*layout)
    rng = np.random.default_rng(seed)
    point = {"x": rng.uniform(-1.5, 1.5, nlp.n_var), "p": rng.uniform(-1.0, 1.0, nlp.n_par)}
    lagrangian = {"lam_f": rng.uniform(0.1, 2.0), "lam_g": rng.normal(0.0, 10.0, nlp.n_con)}
    # IPOPT: the Hessian's upper triangle and the Jacobian; sqpmethod: the whole Hessian, and the objective's
    # gradient beside the Jacobian
    for plugin, name, extra in (("ipopt", "nlp_hess_l", lagrangian), ("ipopt", "nlp_jac_g", {}),
                                ("ipopt", "nlp_f", {}), ("ipopt", "nlp_g", {}), ("ipopt", "nlp_grad_f", {}),
                                ("sqpmethod", "nlp_hess_l", lagrangian), ("sqpmethod", "nlp_jac_fg", {})):
        generated, mapped = (fn.get_function(name) for fn in solvers[plugin])
        # (the solvers read the outputs by position)
        assert (mapped.name_in(), mapped.name_out()) == (generated.name_in(), generated.name_out())
        want, got = (fn.call({**point, **extra}) for fn in (generated, mapped))
        for key, value in want.items():
            assert got[key].sparsity() == value.sparsity(), (plugin, name, key)
            scale = max(1.0, float(ca.norm_inf(value)))
            assert float(ca.norm_inf(got[key] - value)) <= 1e-12 * scale, (plugin, name, key)
    want = -np.array(solvers["ipopt"][0].get_function("nlp_grad").call({**point, **lagrangian})["grad_gamma_p"]).ravel()
    got = nlp.lam_p(point["x"], point["p"], lagrangian["lam_g"] / lagrangian["lam_f"]) * lagrangian["lam_f"]
    assert np.abs(got - want).max() <= 1e-12 * max(1.0, np.abs(want).max())


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_compiled_slot_functions_are_the_interpreted_ones(seed):
    """Compiled (mpc.controller.codegen, from the cache after the first build), each slot function's values
    and derivatives are the interpreted ones' to the last bit, at any point; -ffp-contract=off is what
    keeps the compiler from fusing a multiply-add the interpreter rounds twice."""
    from mpc.controller import codegen
    from mpc.controller.grid import _evaluation_functions

    if codegen.compiler() is None:
        pytest.skip("no C compiler")
    nlp, _ = _nlp_with_solvers(*LAYOUTS[4])
    kinds = list({id(sf): sf for sf in nlp._slot_fns}.values())
    rng = np.random.default_rng(seed)
    codegen.set_mode("on")  # (whatever $WL_CODEGEN says)
    try:
        evaluated = _evaluation_functions(kinds)
    finally:
        codegen.set_mode(None)
    for sf, fns in zip(kinds, evaluated, strict=True):
        assert fns is not sf.functions and set(fns) == set(sf.functions)
        for name, f in sf.functions.items():
            assert fns[name].class_name() == "External"
            args = [rng.uniform(-1.5, 1.5, f.sparsity_in(i).shape) for i in range(f.n_in())]
            for want, got in zip(f.call(args), fns[name].call(args), strict=True):
                assert want.sparsity() == got.sparsity()
                np.testing.assert_array_equal(np.array(got.nonzeros()), np.array(want.nonzeros()), err_msg=name)


def test_estimated_derivatives_follow_the_estimate():
    x, u = (180.0, -1.0, 2.0, 0.4), (100.0, 1.0, 0.0)
    gear, d = -P.gear_ratio, -1.0
    base = estimated_derivatives(x, u, gear, d, P)
    scaled = estimated_derivatives(x, u, gear, d, P, offset=0.1, gain=0.9, lift_gain=1.2)
    assert scaled[1] == pytest.approx(0.9 * base[1] - 0.1)
    heavier = P.variant(payload_scale=1.2)
    # a 20 % heavier payload draws 20 % more lift power: what lift_gain = 1.2 says
    assert scaled[0] == pytest.approx(estimated_derivatives(x, u, gear, d, heavier)[0], rel=1e-9)


def test_apportion_keeps_the_steps_and_the_shape():
    counts = apportion({1: 3.197, 2: 1.035, 3: 2.668, 4: 1.512}, 84, 0.1)
    assert steps_of(counts) == 84
    assert counts == {1: 32, 2: 9, 3: 27, 4: 14}  # 32, 10, 27, 15 steps: the stop steps of phases 2, 4 apart
    assert min(apportion({1: 0.01, 2: 0.01, 3: 5.0, 4: 0.01}, 20, 0.1).values()) >= 0


@functools.cache  # several tests check one run (a cycle takes 10-15 s)
def closed_loop(braking, mode, **kw):
    config = MPCConfig(mode=mode, target_time=11.0 if mode == "target_time" else None, **kw)
    ctrl = MPCController(braking, config=config)
    return run_closed_loop(braking, config, score=False, controller=ctrl), ctrl


@pytest.mark.parametrize("braking, mode, horizon", [  # (the default run keeps the TC runs, which other tests reuse)
    pytest.param("service", "time", "auto", marks=pytest.mark.slow), ("tc", "time", "auto"),
    pytest.param("service", "target_time", "auto", marks=pytest.mark.slow), ("tc", "target_time", "auto"),
    ("tc", "target_time", None)])  # (the full horizon every step: real time's and the deadline's controller)
def test_closed_loop_cycle_near_the_optimum(braking, mode, horizon):
    r, ctrl = closed_loop(braking, mode) if horizon == "auto" else closed_loop(braking, mode, horizon_steps=horizon)
    assert r.episode.completed and r.episode.success
    written = json.loads(json.dumps(r.to_dict()))  # (the result file says how the controller ran)
    assert (written["horizon_steps"], written["horizon_solver"], written["replan_lag_steps"]) == (
        (10, "sqp-rti", 5) if horizon == "auto" else (None, None, None))
    assert abs(r.episode.reversing_error_m) <= 0.05 and abs(r.episode.final_position_error_m) <= 0.05
    assert abs(r.episode.final_height_error_m) <= 0.02
    # deceleration and speed limits held at every step (the RTI's plans too: grid.DECEL_FLOOR)
    assert r.episode.max_violation == 0.0
    assert (np.asarray(r.episode.trajectory.states)[:, 0] > P.omega_min).all()
    # Warm-started: 2 IPOPT iterations a step in the median (measured, both modes). Iterations, not wall
    # time, are the bound: a 2-core machine shared with another pytest worker ran the same solves at
    # 65-115 ms. The wall-time bound only catches work per step (an NLP build takes > 1 s) that counts none.
    assert ctrl.fallbacks == 0 and np.median(ctrl.step_iterations[1:]) <= 5
    assert r.solve_time["median_s"] < 0.5
    if mode == "time":  # #13's 1 %: measured +0.4 % (service), +0.25 % (tc; +1.44 % while the plans aimed within
        # 6.6 mm of the reversing point, where no 8.4 s grid cycle came closer than 8.6 mm: solver.MISS_TOL_M)
        assert r.episode.T <= 1.01 * solve_ocp(braking, "time", verify=False).T
    else:  # on time, and within 3 % of the least fuel of any cycle that long (measured +0.1 %, -0.03 %)
        assert r.episode.T <= 11.0 + 1e-9
        assert r.episode.fuel_g <= 1.03 * solve_ocp(braking, "fuel_at_time", T=r.episode.T, verify=False).fuel_g


@pytest.mark.slow  # 33 s; the default run has the minimum-time and target-time modes
def test_weighted_mode_trades_fuel_for_time():
    """w_fuel = 0.5 weighs 1 g against 0.1 s x 0.5: the cycle lands between the fastest and a slow one."""
    r, _ = closed_loop("service", "weighted", w_fuel=0.5)
    assert r.episode.success and r.episode.max_violation == 0.0
    assert 8.5 <= r.episode.T <= 10.5  # measured 9.0 s, 67.0 g (min time 8.2 s / 85.5 g; 11 s: 54.7 g)
    assert r.episode.fuel_g <= 1.03 * solve_ocp("service", "fuel_at_time", T=r.episode.T, verify=False).fuel_g


def test_weighted_mode_without_fuel_plans_as_minimum_time_does(monkeypatch):
    """w_fuel 0 ranks schedules as minimum time does, so its first plan's schedule moves start far as minimum
    time's (stop 52: near, its search took 1.2-1.6x as long on 5 TC draws, for the same cycles)."""
    from mpc.controller import mpc as mpc_module

    assert MPCConfig().fastest and MPCConfig(mode="weighted", w_fuel=0.0).fastest
    assert not (MPCConfig(mode="weighted", w_fuel=0.5).fastest or MPCConfig(mode="target_time", target_time=11.0).fastest)
    far, starts = [], mpc_module.far_starts
    monkeypatch.setattr(mpc_module, "far_starts", lambda on=True: far.append(on) or starts(on))
    ctrl = MPCController("service", config=MPCConfig(mode="weighted", w_fuel=0.0))
    obs, _ = gym.make("WheelLoader-v2", braking="service").reset(seed=0)
    ctrl.act(obs)  # (the first step: the plan and its schedule search)
    assert far and all(far)


def test_plans_predict_the_plant_step_by_step():
    """Without model error a plan is what the environment does: each step's measurement is the plan's
    prediction, to the solver's tolerance (a plan 'solved to acceptable level' keeps defects of ~1e-5
    of the state's scale) and the float32 of the observation."""
    env = gym.make("WheelLoader-v1", braking="tc")
    ctrl = MPCController("tc", config=MPCConfig(mode="target_time", target_time=11.0))
    obs, _ = env.reset(seed=0)
    errors = []
    while True:
        a = ctrl.act(obs)
        plan, k = ctrl._plan, round(ctrl.state_from_obs(obs)[1] / 0.1)
        predicted = plan["states"][k - plan["k_made"] + 1]
        obs, _, term, trunc, info = env.step(a)
        if info["phase"] == 4 and info["completed"]:
            break
        errors.append(np.abs(ctrl.state_from_obs(obs)[0] - predicted))
        assert not trunc
    errors = np.array(errors)
    assert errors[:, 0].max() < 0.02 and errors[:, 1].max() < 1e-4 and errors[:, 4].max() < 1e-4


def test_tc_braking_holds_the_deceleration_limit_within_the_steps():
    """With TC braking the converter's drag rises within a step; a plan checked at step starts only
    exceeded the limit by 22 % in between. The environment checks every RK4 stage and the step's end,
    and so does the plan."""
    r, _ = closed_loop("tc", "time")
    assert r.episode.max_violation == 0.0


@pytest.mark.parametrize("braking, payload, rolling", [  # (the default run keeps one corner: 20 s each)
    pytest.param("service", 0.8, 1.3, marks=pytest.mark.slow), pytest.param("tc", 0.8, 0.7, marks=pytest.mark.slow),
    ("tc", 1.2, 1.3)])
def test_model_mismatch_case_completes(braking, payload, rolling, monkeypatch):
    plant = P.variant(payload_scale=payload, rolling_scale=rolling)
    # the nominal model; its re-plans in their steps, where the steps' iterations show their starts (the default's
    # run on the worker: tests/test_mpc_horizon.py::test_the_default_re_plans_a_mismatched_plant_beside_the_horizon_not_in_a_step)
    config = MPCConfig(mode="time", replan_lag_steps=None)
    ctrl = MPCController(braking, config=config)
    starts = []  # (the first step?, full NLP?, far start?) of each warm IPOPT solve
    solve = IpoptSolver.solve

    def recorded(self, nlp, args, x0, lam_x0=None, lam_g0=None):
        if lam_x0 is not None:
            starts.append((not ctrl.solve_times, not nlp.short, getattr(solver_module._CALL, "far", False)))
        return solve(self, nlp, args, x0, lam_x0, lam_g0)

    monkeypatch.setattr(IpoptSolver, "solve", recorded)
    r = run_closed_loop(braking, config, plant_params=plant, score=False, controller=ctrl)
    assert r.episode.completed and r.episode.success
    assert abs(r.episode.reversing_error_m) <= 0.05
    assert r.episode.max_violation == 0.0
    # the estimates: gain = model mass / plant mass, offset = the rolling-resistance error (m/s^2),
    # lift gain = plant payload / model payload
    gain, offset = ctrl.estimator.theta
    assert gain == pytest.approx(P.M_tot / plant.M_tot, abs=0.01)
    assert offset == pytest.approx((P.F_roll - plant.F_roll) / plant.M_tot, abs=0.03)
    assert ctrl.estimator.lift_gain == pytest.approx(payload, abs=0.03)
    # the minimum-time first plan: its first solve near, its schedule search's moves far (the plan has no slack)
    first = [is_far for planning, _, is_far in starts if planning]
    assert first and not first[0] and all(first[1:])
    # later, only the whole-cycle re-plans for the moved estimate start far (a plan and a schedule move per
    # re-plan at most), no short horizon
    far = [full for planning, full, is_far in starts if is_far and not planning]
    assert all(far) and 1 <= len(far) <= 2 * ctrl.replans
    if (braking, payload, rolling) == ("tc", 1.2, 1.3):
        # its re-plans start far from their optimum (a plan for another estimate): pushed off the bounds by
        # solver.WARM_START_PUSH_FAR they took <= 30 iterations a step, by the near push 38-71 (stop 50); 50 at most
        # since the synchronous controller plans every cycle afresh (stop 64: <= 45 held only in a process where an
        # earlier test had planned this cycle, its plan solved again from the stored one; a fresh process gave 50)
        assert max(ctrl.step_iterations[1:]) <= 55


@functools.cache
def tc_model() -> StepModel:
    return StepModel("tc", P)


@settings(max_examples=6, deadline=None)
@given(payload=st.floats(0.8, 1.2))
def test_the_lift_gain_settles_on_the_plants_payload_and_predicts_the_engine(payload):
    """The estimator's lift gain is the plant's payload over the model's (eq. (10): the lift's power is proportional
    to it), and with it the model predicts the engine step by step. Its regression is linearized at the estimate:
    the secant from gain 0 to 1 it used before settled a x1.2 plant at 1.22, and the engine then ran 0.1-0.4 rad/s
    per step faster than predicted (the TC shift's converter drag follows that speed)."""
    from mpc.controller.estimator import ModelErrorEstimator

    plant = P.variant(payload_scale=payload)
    sim, est = Simulator(plant, "tc"), ModelErrorEstimator(tc_model(), 0.1)
    y, phase = (P.omega_0, 0.0, P.H_0, 0.0, 0.0, 0.0), 1
    errors = []
    for k in range(24):  # reversing from the pile while lifting, then off the fuel, braking the bucket (the
        # engine below its cap and the bucket within the pump's flow, where the plans keep them)
        u = (130.0, 0.8, 0.0) if k < 12 else (130.0, 0.0, 0.0) if k < 17 else (20.0, -0.9, 0.0)
        ue = sim.effective_controls(y, phase, *u, 0.1)[:3]
        predicted, _ = est.predict(np.array(y[:5]), phase, ue, est.lift_gain, est.theta)
        y1, phase1, _, _ = sim.substep(y, phase, ue, 0.1)
        if k >= 10:  # (once the lift has run a second)
            errors.append(abs(y1[0] - predicted))
        est.update(np.array(y[:5]), phase, np.array(u), np.array(y1[:5]), int(phase1))
        y, phase = tuple(float(v) for v in y1), int(phase1)
    assert phase == 1
    assert est.lift_gain == pytest.approx(payload, abs=0.005)
    assert max(errors) < 0.02  # rad/s per 0.1 s step


@settings(max_examples=6, deadline=None)
@given(payload=st.floats(0.8, 1.2), rolling=st.floats(0.7, 1.3))
def test_before_the_lift_the_lift_gain_is_the_payload_the_mass_error_implies(payload, rolling):
    """Driving with the bucket held, the lift says nothing of the payload; the acceleration gain does (model mass
    / plant mass, the payload the whole difference). A TC plan for the nominal lift from there brought the engine
    too high to come down by the shift: a draw at payload x0.81 ended 0.21 m past its reversing point (stop 57)."""
    from mpc.controller.estimator import LIFT_GAIN_PRIOR, ModelErrorEstimator

    plant = P.variant(payload_scale=payload, rolling_scale=rolling)
    sim, est = Simulator(plant, "tc"), ModelErrorEstimator(tc_model(), 0.1)
    y, phase = (P.omega_0, 0.0, P.H_0, 0.0, 0.0, 0.0), 1
    for k in range(20):  # reversing, the fuel varied (so gain and offset part), the bucket held still
        u = (130.0 if k % 6 < 3 else 60.0, 0.0, 0.0)
        ue = sim.effective_controls(y, phase, *u, 0.1)[:3]
        y1, phase1, _, _ = sim.substep(y, phase, ue, 0.1)
        est.update(np.array(y[:5]), phase, np.array(u), np.array(y1[:5]), int(phase1))
        y, phase = tuple(float(v) for v in y1), int(phase1)
        if k == 0:  # (standing still: no acceleration data yet, the prior)
            assert est.lift_gain == LIFT_GAIN_PRIOR
    assert phase == 1 and y[3] == 0.0  # (the bucket never moved)
    assert est.theta[0] == pytest.approx(P.M_tot / plant.M_tot, abs=0.01)
    assert est.lift_gain == pytest.approx(payload, abs=0.05)


@pytest.mark.slow  # 25 s (five tight solves); the closed-loop tests exercise the moves these sensitivities rank
def test_schedule_sensitivities_predict_a_stretched_phase():
    """One solve's parametric sensitivities give the fuel of a step more in each phase (the schedule
    search rests on them): against re-solves with the phase's steps stretched (a tight solver, so the
    difference is the optimum's and not the tolerance's; measured within 0.3 %)."""
    import casadi as ca

    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0))
    x = np.array([P.omega_0, 0.0, P.H_0, 0.0, 0.0])
    ctrl._plan_cycle(x, 1, 0)
    sol, nlp = ctrl._sol, ctrl._nlp(1)
    tight = ca.nlpsol("tight", "ipopt", nlp.nlp, {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                                                   "ipopt.tol": 1e-10})
    args = nlp.arguments(sol.counts, x, NOMINAL_ESTIMATE, 0.1, tighten=(ctrl.config.tighten, ctrl.config.tighten),
                         params=ctrl.params)
    base = tight(x0=sol.z, **args)
    # the method, on a converged optimum; the controller's own solves (tol 1e-6, acceptable 1e-4) rank
    # the moves with multipliers that err by up to 5 % (measured), each move then verified by a solve
    sens = nlp.sensitivities(np.array(base["lam_p"]).ravel(), sol.counts, 0.1)
    loose = nlp.sensitivities(sol.lam_p, sol.counts, 0.1)
    active = nlp.active_slots(sol.counts)
    for phase in (1, 2, 3, 4):
        ks = [k for k in active if nlp.slots[k].phase == phase]
        p = args["p"].copy()
        p[nlp.h_offset + np.array(ks)] *= 1.0 + 1e-3  # each step 0.1 ms longer
        stretched = tight(x0=base["x"], **{**args, "p": p})
        per_step = (float(stretched["f"]) - float(base["f"])) / (1e-3 * len(ks))
        assert loose[phase] == pytest.approx(per_step, rel=0.1)
        assert sens[phase] < 0 and per_step == pytest.approx(sens[phase], rel=0.02)


def test_terminal_law_stops_a_fast_bucket_at_the_target_height():
    ctrl = MPCController("service")
    # the vehicle standing, the bucket 3.3 cm below H_T still rising at 0.41 m/s: braking at the
    # lowest bucket acceleration stops it in 3.3 cm
    H, V_b = P.H_T - 0.033, 0.406
    for _ in range(5):
        u_ab = ctrl._terminal(np.array([170.0, 0.0, H, V_b]))[1]
        u_ab = max(u_ab, -V_b / 0.1)  # the simulator does not lower the bucket
        H, V_b = H + V_b * 0.1 + 0.5 * u_ab * 0.01, V_b + u_ab * 0.1
    assert V_b == pytest.approx(0.0, abs=1e-9)
    assert abs(H - P.H_T) < 0.005


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="mode"):
        MPCConfig(mode="fast")
    with pytest.raises(ValueError, match="target_time"):
        MPCConfig(mode="target_time")
    with pytest.raises(ValueError, match="w_fuel"):
        MPCConfig(mode="weighted", w_fuel=1.5)
    with pytest.raises(ValueError, match="realtime and deadline_ms"):
        MPCConfig(realtime=True, deadline_ms=50.0)
    with pytest.raises(ValueError, match="w_fuel is mode 'weighted''s; mode 'time' takes none"):  # (was ignored)
        MPCConfig(mode="time", w_fuel=0.5)
    with pytest.raises(ValueError, match="target_time is mode 'target_time''s; mode 'weighted' takes none"):
        MPCConfig(mode="weighted", w_fuel=0.5, target_time=11.0)
    for kw, name in ((dict(mode="target_time", target_time=1e9), "target_time must lie in \\[1, 40\\) s"),
                     (dict(mode="weighted", w_fuel="0.5"), "w_fuel"), (dict(time_budget="1"), "time_budget"),
                     (dict(max_iter=True), "max_iter"), (dict(rate_weight=5), "rate_weight"),
                     (dict(omega_margin=math.nan), "omega_margin"), (dict(deadline_ms=True), "deadline_ms"),
                     (dict(parallel_search=1), "parallel_search must be True or False")):
        with pytest.raises(ValueError, match=name):  # (bare TypeErrors, or accepted, before)
            MPCConfig(**kw)
    with pytest.raises(ValueError, match="braking"):
        MPCController("engine")
    heavy = Scenario(payload=12000.0, braking="tc")
    with pytest.raises(ValueError, match="mismatch run must be built with the run's model"):  # (it planned the plant's)
        run_closed_loop("tc", controller=MPCController("tc", heavy.params()), scenario=heavy, mismatch=True, score=False)
    with pytest.raises(ValueError, match="dt"):
        MPCController("tc", dt=math.nan)
    with pytest.raises(ValueError, match="obs"):
        MPCController("tc").act(np.full(12, np.nan))


def test_impossible_target_time_is_a_clear_error():
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=6.0))
    env = gym.make("WheelLoader-v1", braking="service")
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"target_time 6 s is impossible: the minimum cycle time .* is 8\.\d+ s"):
        ctrl.act(obs)


@pytest.mark.parametrize("fields, target, objective, solves", [
    # the target rounds down to 8.7 s, 0.008 s above the coarse mesh's T_min: warm-started from it
    (dict(payload=12260.0, reverse_distance=7.44, forward_distance=6.34, rolling_resistance=0.0274, dump_height=4.54,
          start_engine_speed=1216.0, start_bucket_height=0.86), 8.79, "fuel_at_time", 3),
    # ... to 9.8 s, under its 9.804 s (the target, 9.89 s, above): the minimum-time reference itself
    (dict(payload=9290.0, reverse_distance=7.11, forward_distance=9.41, rolling_resistance=0.04, dump_height=4.14,
          start_engine_speed=1354.0, start_bucket_height=0.56), 9.89, "time", 2)])
def test_a_target_near_t_min_is_planned_from_the_coarse_minimum_time(monkeypatch, fields, target, objective, solves):
    """TC draws whose target is so near T_min that the reference's template start finds no cycle on the coarse
    mesh. The reference comes from that mesh's minimum-time one, not from the benchmark's T_min solve that
    followed until stop 52 (5-16 s of the first step); no fixed-time solve under that mesh's T_min (1.7-3.6 s
    to fail)."""
    import mpc.benchmark.ocp as ocp
    from mpc.controller.mpc import REFERENCE_MESH

    near = Scenario(**fields, braking="tc")
    meshes = []
    solve = ocp.solve_ocp

    def spy(*args, **kwargs):
        meshes.append(tuple(kwargs["settings"].intervals) if kwargs.get("settings") else None)
        return solve(*args, **kwargs)

    monkeypatch.setattr(ocp, "solve_ocp", spy)
    ref = MPCController("tc", near.params(), MPCConfig(mode="target_time", target_time=target)).reference()
    assert ref.objective == objective and ref.T <= math.floor(target * 10 + 1e-6) / 10 + 0.1
    assert meshes == [REFERENCE_MESH] * solves


def test_controls_move_no_more_than_the_optimums():
    """The control-rate penalty: on the TC cycle at 11 s (whose bucket speed zig-zagged between 0 and
    0.6 m/s without it) U_mf and U_ab move at most 1.5x the optimum's total variation at the same cycle
    time, at a fuel within 0.5 % of that optimum."""
    from mpc.benchmark.scoring import smoothness

    r, _ = closed_loop("tc", "target_time")
    ep = r.episode
    assert ep.success and ep.max_violation == 0.0
    s = smoothness(ep.trajectory.controls, ep.T, "tc")
    assert s.ratio_fuel_injection <= 1.5 and s.ratio_bucket_acceleration <= 1.5
    assert ep.fuel_g == pytest.approx(solve_ocp("tc", "fuel_at_time", T=ep.T, verify=False).fuel_g, rel=0.005)


@pytest.mark.slow  # 12 s: a penalty that does nothing would pass the bound above; it does not pass this one
def test_without_the_rate_penalty_the_bucket_acceleration_chatters():
    """On the full horizon (where #13 saw the zig-zag) the bucket acceleration moves several times as much
    without the penalty. Measured at stop 47: 1.43x the optimum's total variation against 0.12x with it (1.73x
    when the penalty came, stop 18); the default 10-step RTI moves 0.74x even without it."""
    from mpc.benchmark.scoring import smoothness

    tv = {}
    for w in (0.0, 0.1):
        r = run_closed_loop("tc", MPCConfig(mode="target_time", target_time=11.0, rate_weight=(w, w), horizon_steps=None),
                            score=False)
        tv[w] = smoothness(r.episode.trajectory.controls, r.episode.T, "tc").ratio_bucket_acceleration
    assert tv[0.0] > 1.0 and tv[0.0] > 4.0 * tv[0.1], tv


def test_the_minimum_time_search_tries_a_step_fewer_from_the_other_leg():
    """TC ``test`` scenario (T_min 9.867 s): the first plan's search removed a step from phase 2 (the reversing
    point missed by 0.18 m), then ruled out every removal and ended at 10.0 s; phase 4's step fewer holds every
    mark, so the cycle takes 9.9 s (measured)."""
    from mpc.benchmark.reference import reference_at
    from wl_env.suites import load_suite

    sc = load_suite("test").spread("tc", 8)[4]
    T_min = reference_at(10.0, "tc", sc.params())["T_min"]
    r = run_closed_loop("tc", MPCConfig(mode="time"), scenario=sc, score=False)
    assert r.episode.success and r.episode.max_violation == 0.0
    assert T_min <= r.episode.T <= T_min + 0.1  # (the grid's best: T_min rounded up to a step)


def test_the_search_keeps_the_better_of_a_rounds_two_moves_forked_or_not(monkeypatch):
    """TC ``test`` cycle 2 at minimum time: its first schedule (99 steps) misses the reversing point. The search's
    first round solves the step added to phase 2 (100 steps) and, as the move it would try next, the step moved
    there from phase 3 (99 steps, on its marks), and keeps the latter (measured: one move at a time took 7 solves to
    the same 99 steps). The second move of each round is solved in a forked copy of the process where it can be,
    else here: the same plan to the bit either way."""
    from mpc.controller import forked
    from mpc.controller.mpc import forget_plans
    from wl_env.suites import load_suite

    sc = load_suite("test").of("tc")[2]
    forks = []
    monkeypatch.setattr(forked, "ForkedCall", functools.partial(_counted, forks, forked.ForkedCall))
    plans = {}
    for parallel in (True, False):
        forget_plans()  # (the second controller would start from the first's stored plan)
        ctrl = MPCController("tc", sc.params(), MPCConfig(parallel_search=parallel))
        env = gym.make("WheelLoader-v2", braking="tc", params=sc.params())
        obs, _ = env.reset(seed=0, options={"scenario": sc})
        ctrl.reset(sc)
        ctrl.act(obs)
        plans[parallel] = ctrl._sol
    assert bool(forks) == forked.available()  # (2 CPUs on Linux: the first run forked its second moves)
    assert steps_of(plans[True].counts) == 99 and plans[True].feasible
    assert plans[True].counts == plans[False].counts and plans[True].J == plans[False].J
    assert np.array_equal(plans[True].z, plans[False].z)


def test_the_minimum_time_search_tries_no_schedule_shorter_than_the_references_t_min_allows(monkeypatch):
    """TC ``test`` cycle 2 at minimum time: the coarse reference's T_min is 9.920 s and the grid's best 9.9 s (99
    steps). Every step fewer from 99 misses a target (measured: two of the search's seven solves, 0.2-0.3 s each);
    the search no longer tries a schedule under the reference's T_min less REFERENCE_T_MARGIN_S, and ends at the
    same 99 steps. A perturbed start (init noise) is not the reference's: no bound there."""
    from mpc.controller.mpc import REFERENCE_T_MARGIN_S

    ctrl, obs, solved = _first_plan(monkeypatch, 2)
    tried = [(move, steps_of(alt.counts), alt.feasible) for move, alt in solved]
    bound = math.ceil((ctrl.reference().T - REFERENCE_T_MARGIN_S) / ctrl.dt - 1e-6)
    assert bound == 99 and steps_of(ctrl._sol.counts) == 99 and ctrl._sol.feasible
    assert tried and all(n >= bound for _, n, _ in tried), tried  # (the old search solved two of 98 steps)
    assert ctrl.schedule.min_steps == 0  # (the bound holds for the first plan's search only)
    x = ctrl.project_state(ctrl.state_from_obs(obs)[0], 1)
    assert ctrl._at_reference_start(x, 1, 0)
    assert not ctrl._at_reference_start(x + np.array([1.0, 0, 0, 0, 0]), 1, 0) and not ctrl._at_reference_start(x, 1, 3)


@pytest.mark.parametrize("index, steps", [(12, 74), (17, 92)])
def test_a_tc_forward_step_fewer_is_also_solved_as_phase_3s_with_the_reversing_drive_giving_its_stop_a_step(
        monkeypatch, index, steps):
    """TC ``test`` cycles 12 and 17 at minimum time: the search ended a step above the grid's best (75 and 93 steps),
    every step fewer alone missing a target (phase 4's and phase 3's the reversing point by 3.1 and 1.6 cm), where 74
    {1: 25, 2: 10, 3: 24, 4: 13} and 92 {1: 32, 2: 9, 3: 34, 4: 15} hold every mark (bench_grid_min_time). A round of
    one step fewer from the forward leg now also solves phase 3's step fewer with a step moved from phase 1 to phase 2
    beside it (a compound move, in the round's free fork), which gives those schedules."""
    from mpc.controller.schedule import moved

    assert moved({1: 3, 2: 2, 3: 4, 4: 1}, ((3, None), (1, 2))) == {1: 2, 2: 3, 3: 3, 4: 1}
    ctrl, _, solved = _first_plan(monkeypatch, index)
    paid = [move for move, alt in solved if isinstance(move[0], tuple) and alt.feasible]
    assert paid == [((3, None), (1, 2))]
    assert steps_of(ctrl._sol.counts) == steps and ctrl._sol.feasible  # (a step more before)
    assert ctrl._compound(ctrl._sol, (1, 2)) is None and ctrl._compound(ctrl._sol, (1, None)) is None
    # (a plan from phase 4 on, a controller started there: no phase 1 to give a step)
    assert ctrl._compound(types.SimpleNamespace(counts={4: 10}, first_phase=4), (4, None)) is None


def test_a_real_time_first_plan_that_misses_a_target_searches_in_the_first_step_until_it_holds_them(monkeypatch):
    """TC ``test`` cycle 14 at minimum time in real time: the first solve, on the reference's schedule, missed the
    reversing point by 6.7 cm, and real time left the whole search to the worker, whose moves added steps to the
    forward leg: the cycle ended 6.7 cm off its mark (success False, 2 of 20 TC `test` cycles). The first step now
    searches while the plan misses a target, and leaves the rest to the worker once it holds them."""
    ctrl, _, solved = _first_plan(monkeypatch, 14, MPCConfig(realtime=True))
    try:
        assert solved and ctrl._sol.feasible and ctrl.first_plan_from == "reference"
        assert any(alt.feasible for _, alt in solved[-2:]) and not any(alt.feasible for _, alt in solved[:-2])
        assert steps_of(ctrl._sol.counts) == 73  # (7.3 s, as before: a shift holds every mark)
    finally:
        ctrl.end_episode()


@pytest.mark.parametrize("config", [MPCConfig(deadline_ms=100.0), MPCConfig(time_budget=0.05)], ids=["deadline", "budget"])
def test_the_first_plan_is_not_held_to_a_steps_deadline_or_time_budget(monkeypatch, config):
    """TC ``test`` cycle 22 at minimum time with ``deadline_ms`` 100: every warm solve of the first plan's search
    stopped at 0.1 s (IPOPT's Maximum_WallTime_Exceeded), so the first solve stood, 6.4 cm short of the reversing
    point, and the cycle failed. The deadline and the time budget bound the steps after the first."""
    ctrl, _, solved = _first_plan(monkeypatch, 22, config)
    try:
        assert solved and all(alt.ok for _, alt in solved), [alt.status for _, alt in solved]
        assert ctrl._sol.feasible and ctrl._sol.counts == {1: 39, 2: 10, 3: 22, 4: 15}  # (the default's plan)
    finally:
        ctrl.end_episode()


def test_a_target_time_first_plan_that_ends_late_is_planned_again_from_the_minimum_time_references_shares(monkeypatch):
    """Service ``test`` cycle 21 at 9.0 s (1.02 T_min; minimum time takes 8.9 s): the fuel-optimal reference split the
    90 steps {1: 21, 2: 23, 3: 21, 4: 23}, 2.9 cm short of the reversing point, and the search's single moves ended at
    91 steps: the cycle took 9.1 s, late. A late first plan is now planned again from the minimum-time reference's
    shares of the target's steps."""
    cfg = MPCConfig(mode="target_time", target_time=9.0)
    ctrl, _, _ = _first_plan(monkeypatch, 21, cfg, braking="service")
    try:
        assert ctrl._sol.feasible and steps_of(ctrl._sol.counts) == 90, ctrl._sol.counts
        assert ctrl._plan_reference.objective == "time"  # (the retry's reference, for the re-plans' guesses)
    finally:
        ctrl.end_episode()


def test_a_horizon_that_misses_a_target_no_more_than_its_whole_rest_plan_is_applied_not_re_planned_in_the_step():
    """A fresh TC mismatch draw (seed 6801, draw 7, within #13's ranges): the reversing point 3.6 cm off in every plan
    from step 44 on, its five steps before the reversing point each solved the whole rest again in the step (60-134
    ms, over the 100 ms interval twice) to the same 3.64 cm. A horizon that misses a target by no more than the
    whole-rest plan it follows (within half the target's tolerance, that plan within three) is applied."""
    from mpc.controller.mpc import NEAR_PLAN_MAX_MISS, NEAR_PLAN_MISS
    from mpc.controller.solver import MISS_TOL_M, Solve

    def solve(miss_m: float, excess: float = 0.0, ok: bool = True) -> Solve:
        return Solve(counts={2: 3}, first_phase=2, ok=ok, status="", misses_m={"reversing point": miss_m,
                     "end position": 0.0, "end height": 0.0}, excess=excess)

    def near(horizon: Solve, plan: Solve | None) -> bool:
        return MPCController._as_near_as_the_plan(types.SimpleNamespace(_sol=plan), horizon)

    tol = NEAR_PLAN_MISS * MISS_TOL_M["reversing point"]
    assert near(solve(-0.0381), solve(-0.0364)) and near(solve(0.0364 + 0.99 * tol), solve(-0.0364))
    assert not near(solve(-0.0364 - 1.01 * tol), solve(-0.0364))  # (farther off than the plan found possible)
    assert not near(solve(-0.03), solve(0.0))  # (a plan on its marks: the step re-plans, as before)
    far = 1.01 * NEAR_PLAN_MAX_MISS * MISS_TOL_M["reversing point"]  # (service corner 7 at 1.15 T_min: a re-plan 16 cm
    assert not near(solve(-far), solve(-far))                        # short, which the step's whole-rest solve mended)
    assert not near(solve(-0.0364, excess=0.01), solve(-0.0364))  # (the deceleration limit broken)
    assert not near(solve(-0.0364), solve(-0.0364, ok=False)) and not near(solve(-0.0364), None)


def _first_plan(monkeypatch, index: int, config: MPCConfig | None = None, braking: str = "tc") -> tuple:
    """The MPC's first plan (default: the default MPC's) of ``test`` cycle ``index`` of the braking in a fresh
    controller: (controller, the first observation, the search's (move, solve) pairs)."""
    from mpc.controller import mpc as mpc_module
    from mpc.controller.mpc import forget_plans
    from wl_env.suites import load_suite

    sc = load_suite("test").of(braking)[index]
    solved = []
    move_solves = MPCController._move_solves

    def logged(self, sol, moves, phase, x):
        alts = move_solves(self, sol, moves, phase, x)
        solved.extend(zip(moves, alts, strict=True))
        return alts

    monkeypatch.setattr(mpc_module.MPCController, "_move_solves", logged)
    forget_plans()
    ctrl = MPCController(braking, sc.params(), config or MPCConfig())
    env = gym.make("WheelLoader-v2", braking=braking, params=sc.params())
    obs, _ = env.reset(seed=0, options={"scenario": sc})
    ctrl.reset(sc)
    ctrl.act(obs)
    return ctrl, obs, solved


def _counted(calls: list, cls: type, fn):
    calls.append(fn)
    return cls(fn)


def test_a_mismatched_draw_in_range_keeps_the_limit_at_its_last_stop():
    """A fresh TC draw in mismatch mode, its plant within #13's ranges (payload x0.85, rolling resistance x0.83):
    the last stop's plan was 1.9e-6 over the limit under the estimate. Eased just inside it (SOLVED_EASE_MARGIN),
    the plant still broke it by 5.3e-5: the easing now keeps the filter's own prediction error as its margin
    (stop 52)."""
    draw = Scenario(payload=8460.0, reverse_distance=4.92, forward_distance=8.75, rolling_resistance=0.0249,
                    dump_height=3.83, start_engine_speed=1806.0, start_bucket_height=0.97, braking="tc")
    ep = run_closed_loop("tc", MPCConfig(), scenario=draw, mismatch=True, score=False).episode
    assert ep.success and ep.max_violation == 0.0


@pytest.mark.slow  # 15 s; the default run has the mismatch corners of test_model_mismatch_case_completes
def test_a_corner_scenario_in_mismatch_mode_completes_within_the_limits():
    """The corners suite's heaviest, slowest-rolling TC cycle, the MPC keeping the nominal payload and
    rolling resistance (it knows the distances, the truck and the start) and learning the rest."""
    from wl_env.suites import load_suite

    corners = load_suite("corners").of("tc")
    sc = max(corners, key=lambda s: (s.payload, s.rolling_resistance))
    r = run_closed_loop(config=MPCConfig(mode="time"), scenario=sc, mismatch=True, score=False)
    assert r.episode.completed and r.episode.success and r.episode.max_violation == 0.0
    assert r.scenario["payload"] == sc.payload


@pytest.mark.slow  # 20 s: the RTI fails every schedule move of the first plan
def test_a_candidate_that_fails_hands_the_solve_to_its_fallback():
    """The solver candidates of bench_mpc run with IPOPT behind them: a failed solve (the RTI's cold start
    here: it has no previous plan; or a step whose rows it leaves unmet) is IPOPT's, both statuses kept."""
    from mpc.controller.solver import FallbackSolver, SqpRtiSolver

    ctrl = MPCController("tc", config=MPCConfig(mode="target_time", target_time=11.0),
                         solver=FallbackSolver(SqpRtiSolver("hpipm"), IpoptSolver()))
    x = np.array([P.omega_0, 0.0, P.H_0, 0.0, 0.0])
    ctrl._plan_cycle(x, 1, 0)  # cold: the RTI refuses, IPOPT plans (and takes the moves the RTI fails)
    # (the last plan may be a move the RTI met itself: on compiled functions it meets more of them, stop 47)
    assert ctrl._sol.ok and ctrl.solver.handed_over >= 1
    cold = ctrl._solve(1, ctrl._sol.counts, x, warm=None, guess=ctrl._sol.z)  # no multipliers: the RTI refuses
    assert cold.ok and cold.status.startswith("sqp-rti (hpipm): no previous plan, then "), cold.status
    # (the bench reads the hand-overs from the controller's stats: this cycle's, where the solver counts over its life)
    assert ctrl.stats()["handed_over"] == ctrl.solver.handed_over
    ctrl.reset()
    assert ctrl.stats()["handed_over"] == 0


def test_scenarios_of_one_machine_share_its_nlps_and_another_structure_releases_them():
    """Planning time and memory: a grid NLP and its solver take the scenario as a parameter. A controller
    moved to another scenario of its machine plans on the ones built (real time or synchronous), with that
    scenario's values in their parameters; a scenario whose dump height brings the boom's end stop within
    reach (its rows: another structure) releases them all, and release_solvers leaves nothing built."""
    from mpc.controller import solver
    from mpc.controller.grid import GRID_SCENARIO
    from wl_env.scenario import Scenario

    ctrl = MPCController("service", config=MPCConfig(realtime=True))
    nlp = solver.grid_nlp(ctrl.model, 4, ((4, 4),))  # a small NLP
    ctrl.reset(scenario=Scenario(payload=12000.0, reverse_distance=7.0, dump_height=4.5, braking="service"))
    assert ctrl.model.params.M_tot > P.M_tot and ctrl.model.params.M_load == 12000.0
    assert solver.grid_nlp(ctrl.model, 4, ((4, 4),)) is nlp  # the same NLP, not a new one
    x = np.array([150.0, 1.0, 4.0, 0.2, -0.6])
    par = nlp.arguments({4: 3}, x, NOMINAL_ESTIMATE, 0.1, params=ctrl.params)["p"]
    assert dict(zip(GRID_SCENARIO, par[nlp.scenario_offset:nlp.h_offset], strict=True)) == {
        "M_load": 12000.0, "c_r": P.c_r, "H_T": 4.5, "reverse_distance": 7.0, "forward_distance": P.forward_distance}
    with pytest.raises(ValueError, match="another machine"):
        nlp.arguments({4: 3}, x, NOMINAL_ESTIMATE, 0.1, params=P.replace(gear_ratio=1.1 * P.gear_ratio))
    with pytest.raises(ValueError, match="another machine"):
        StepModel("service", P).with_params(P.replace(U_mf_max=0.9 * P.U_mf_max))
    ctrl.reset(scenario=Scenario(dump_height=5.1, braking="service"))  # the end stop within a step's lift
    assert ctrl.model.end_stop and solver.grid_nlp.cache_info().currsize == 0
    synchronous = MPCController("service")
    mine = solver.grid_nlp(synchronous.model, 4, ((4, 4),))
    synchronous.reset(scenario=Scenario(payload=9000.0, braking="service"))  # the same machine
    assert solver.grid_nlp(synchronous.model, 4, ((4, 4),)) is mine
    synchronous.reset(scenario=Scenario(dump_height=5.1, braking="service"))
    assert solver.grid_nlp.cache_info().currsize == 0
    solver.grid_nlp(ctrl.model, 4, ((4, 4),))
    solver.release_solvers()
    assert solver.grid_nlp.cache_info().currsize == 0 and not solver._MODELS


class CountingSolver(IpoptSolver):
    """IPOPT that records how each solve was started, and fails the ones from zero multipliers if told."""

    def __init__(self, fail_from_zero: bool) -> None:
        super().__init__()
        self.fail_from_zero, self.starts = fail_from_zero, []

    def solve(self, nlp, args, x0, lam_x0=None, lam_g0=None):
        start = "cold" if lam_x0 is None else "zero" if not (np.any(lam_x0) or np.any(lam_g0)) else "warm"
        self.starts.append((start, nlp.symbolic is ca.MX))
        if start == "zero" and self.fail_from_zero:
            return SolverResult(ok=False, status="forced failure (injected solver)", iterations=0)
        return super().solve(nlp, args, x0, lam_x0, lam_g0)


@pytest.mark.parametrize("fail_from_zero", [pytest.param(False, marks=pytest.mark.slow), True])  # (15-20 s each)
def test_the_first_solve_runs_on_the_warm_solver_and_falls_back_to_the_cold_one(fail_from_zero):
    """A cycle's first solve starts the layout's warm (SX) solver from the reference's guess with zero
    multipliers, and builds no MX twin; if that fails, the cold solve on the MX twin plans the cycle."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    solver = CountingSolver(fail_from_zero)
    target = 11.3 if fail_from_zero else 11.7  # (targets no other test plans: no stored first plan)
    ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=target), solver=solver)
    ctrl.act(obs)
    assert ctrl.first_plan_from == "reference" and ctrl._sol.ok and ctrl._sol.feasible
    assert solver.starts[0] == ("zero", False)
    # (where the planning went: its four parts, in order, within the first step's time)
    parts = ctrl.planning_parts
    assert list(parts) == ["reference", "layout", "first_solve", "search"] and min(parts.values()) >= 0.0
    assert 0.5 * ctrl.planning_time < sum(parts.values()) <= ctrl.planning_time
    cold = [s for s in solver.starts if s[0] == "cold"]
    assert cold == ([("cold", True)] if fail_from_zero else [])


@settings(max_examples=60, deadline=None)
@given(src=st.builds(dict, reverse_distance=st.floats(4.0, 10.0), forward_distance=st.floats(4.0, 10.0),
                     H_0=st.floats(0.5, 1.2), H_T=st.floats(3.5, 5.1)),
       dst=st.builds(dict, reverse_distance=st.floats(4.0, 10.0), forward_distance=st.floats(4.0, 10.0),
                     H_0=st.floats(0.5, 1.2), H_T=st.floats(3.5, 5.1)))
def test_a_plan_reshaped_for_another_scenario_keeps_its_marks_on_the_new_ones(src, dst):
    """The warm start of a first plan from another scenario (GridNLP.transport, and the OCP's transport):
    the start, the reversing point and the truck of the old legs land on the new ones, the bucket's start
    and dump heights on the new ones; the engine and the travel speed are kept."""
    from mpc.benchmark.ocp import transport_states

    rd, fd = src["reverse_distance"], src["forward_distance"]
    position = np.array([0.0, -0.5 * rd, -rd, -rd, -rd + 0.5 * fd, fd - rd])
    phase = np.array([1, 1, 2, 3, 3, 4])
    states = np.column_stack([np.full(6, 150.0), np.linspace(-1.0, 1.0, 6),
                              np.linspace(src["H_0"], src["H_T"], 6), np.full(6, 0.3)])
    x, s = transport_states(states, position, phase, src, dst)
    rd2, fd2 = dst["reverse_distance"], dst["forward_distance"]
    assert np.allclose(s[[0, 2, 3, 5]], [0.0, -rd2, -rd2, fd2 - rd2], atol=1e-9)
    assert np.allclose(x[[0, -1], 2], [dst["H_0"], dst["H_T"]], atol=1e-9)
    assert np.array_equal(x[:, :2], states[:, :2])
    lift = (dst["H_T"] - dst["H_0"]) / (src["H_T"] - src["H_0"])
    assert np.allclose(x[:, 3], 0.3 * lift)


# ------------------------------------------------------------------ hostile settings (second audit)
@pytest.mark.parametrize("kwargs", [
    {"horizon_steps": np.int64(20)}, {"max_iter": np.int64(5)}, {"spare_steps": np.int32(3)},
    {"tighten": np.float32(0.01)}, {"mode": "target_time", "target_time": np.float32(12.0)},
    {"horizon_steps": 20, "replan_lag_steps": np.int64(2)}, {"rate_weight": (np.float32(0.1), np.int64(1))},
])
def test_mpc_config_takes_numpy_scalars_as_the_numbers_they_hold(kwargs):
    cfg = MPCConfig(**kwargs)  # (np.int64(20) steps was "must be an integer in [2, 1000]")
    for name in kwargs:
        v = getattr(cfg, name)
        assert all(type(x) in (int, float) for x in v) if isinstance(v, tuple) else type(v) in (int, float, str)


@pytest.mark.parametrize("value", [True, 10**400, float("nan"), -1.0, "5"])
def test_mpc_config_refuses_a_bad_terminal_weight_by_name(value):
    with pytest.raises(ValueError, match="terminal_weight must be a finite number >= 0"):
        MPCConfig(terminal_weight=value)  # (True was taken as 1.0; 10**400 raised OverflowError)


@pytest.mark.parametrize("kwargs, match", [
    ({"substeps": 0}, r"substeps must be an integer in \[1, 1000\]"),  # (ZeroDivisionError)
    ({"substeps": 1.7}, r"substeps must be an integer in \[1, 1000\]"),  # (taken as 1)
    ({"substeps": True}, r"substeps must be an integer in \[1, 1000\]"),
    ({"substeps": 10**9}, r"substeps must be an integer in \[1, 1000\]"),  # (built its steps for hours)
    ({"substeps": "x"}, r"substeps must be an integer in \[1, 1000\]"),
    ({"dt": True}, r"dt \(the control interval\) must lie in \[0.001, 1\] s"),  # (taken as 1 s)
    ({"dt": 10**400}, r"dt \(the control interval\) must lie in \[0.001, 1\] s"),  # (OverflowError)
    ({"config": {"mode": "time"}}, "config must be an MPCConfig or None, got dict"),  # (AttributeError)
    ({"solver": "ipopt"}, "solver must be a GridSolver"),
])
def test_mpc_controller_refuses_bad_arguments_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MPCController("service", **kwargs)


def test_mpc_controller_takes_numpy_scalar_dt_and_substeps():
    ctrl = MPCController("service", dt=np.float64(0.1), substeps=np.int64(1))
    assert (type(ctrl.dt), type(ctrl.substeps)) == (float, int)


@pytest.mark.parametrize("kwargs, match", [
    ({"config": "time"}, "config must be an MPCConfig or None, got str"),
    ({"scenario": {"braking": "tc"}}, "scenario must be a wl_env.scenario.Scenario or None, got dict"),
    ({"mismatch": "yes"}, "mismatch must be True or False"),
    ({"mismatch": True}, "mismatch plans a scenario's cycle .*give a scenario"),  # (was ignored: a nominal run)
    ({"controller": "mpc"}, "controller must be an MPCController or None, got str"),
    ({"cache": 5}, "cache must be a folder path or None, got int"),  # (TypeError after the whole cycle)
])
def test_run_closed_loop_refuses_bad_arguments_before_the_cycle(kwargs, match):
    with pytest.raises(ValueError, match=match):
        run_closed_loop("service", **kwargs)


def test_run_closed_loop_refuses_a_controller_of_the_other_braking():
    ctrl = MPCController("service")  # (the tc env ran under the service plan without a word)
    with pytest.raises(ValueError, match="the controller plans service braking; the run has braking='tc'"):
        run_closed_loop("tc", controller=ctrl, score=False)


def test_a_refused_reset_leaves_the_controller_as_it_was():
    """A scenario of the other braking with a target time was refused after the target had been taken: the next
    cycle ran in target-time mode (12 s where minimum time is ~8.2 s)."""
    from wl_env.scenario import Scenario

    ctrl = MPCController("service")
    with pytest.raises(ValueError, match="plans service braking"):
        ctrl.reset(scenario=Scenario(braking="tc"), target_time=12.0)
    assert ctrl.config.mode == "time" and ctrl.config.target_time is None
    with pytest.raises(ValueError, match="no file 'abc'"):  # (JSON or a dict, as the env takes them; was an AttributeError)
        ctrl.reset(scenario="abc")
    ctrl.reset(scenario={"payload": 9000.0})
    assert ctrl.params.M_load == pytest.approx(9000.0)


# ------------------------------------------------------------------ hostile inputs (stop 60's library round)
def test_a_tighten_over_the_later_margins_cap_still_brakes_in_time():
    """tighten 0.2 (in its range): the later steps' margin was capped at MAX_MARGIN (0.03), under the first step's,
    so every plan braked harder later and the braking moved back a step each step: 0.22 m past the reversing
    point, a failed cycle with no error."""
    r = run_closed_loop("service", MPCConfig(tighten=0.2), score=False)
    assert r.episode.success and r.episode.max_violation == 0.0


def test_a_target_past_the_fuel_optimal_cycle_ends_with_it():
    """A 30 s target on the nominal service cycle (its fuel-optimal cycle takes 21.3 s): the MPC stretched the cycle
    to 30 s on 49.25 g where the fuel-optimal one takes 47.69 g; "the least fuel finishing by then" is that cycle."""
    r = run_closed_loop("service", MPCConfig(mode="target_time", target_time=30.0), score=False)
    assert r.episode.success and 20.5 < r.episode.T < 22.5 and r.episode.fuel_g < 47.9


def test_the_mpc_refuses_what_would_drive_another_cycle_or_divide_by_nothing():
    """A controller planned for 5 m legs on the run's 6.6 m cycle (1.6 m past the reversing point, reported as no
    mismatch); a new episode's observation without reset() (an IndexError in the plan); a weighted mode of w_fuel
    5e-324 (a ZeroDivisionError in the schedule's ranking after 2 s of planning)."""
    short = Scenario(reverse_distance=5.0, forward_distance=5.0)
    with pytest.raises(ValueError, match="the controller plans another machine or cycle than the run's model"):
        run_closed_loop("service", controller=MPCController("service", short.params()), score=False)
    with pytest.raises(ValueError, match=r"w_fuel 0 \(minimum time\) or in \[1e-06, 1\]"):
        MPCConfig(mode="weighted", w_fuel=5e-324)
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service")
    later = obs.copy()
    ctrl._last, ctrl._last_t = (None, 1, None), 3.0  # (as after a step at t = 3 s)
    with pytest.raises(ValueError, match="a new cycle starts with the controller's reset"):
        ctrl.act(later)


# ------------------------------------------------------------------ hostile inputs (the MPC's API, another round)
@pytest.mark.parametrize("kwargs, match", [
    ({"rate_weight": (1e308, 1e308)}, r"rate_weight must be two weights in \[0, 1e\+06\]"),  # (Invalid_Number_Detected)
    ({"rate_weight": (0.1, 1e7)}, r"rate_weight must be two weights in \[0, 1e\+06\]"),
    ({"terminal_weight": 1e308}, r"terminal_weight must be a finite number >= 0, at most 1e\+06"),  # (inf derivatives)
    ({"deadline_ms": 5e-324}, r"deadline_ms must be >= 0.001 ms"),  # (0 s: IPOPT's "Invalid options" traceback)
])
def test_mpc_config_refuses_weights_that_overflow_the_nlp(kwargs, match):
    """rate_weight 1e308 failed the first plan after 2 s of planning ("no plan ... Invalid_Number_Detected");
    terminal_weight 1e308 made the RTI's Hessian inf. `wl mpc --rate-weight` takes [0, 1e6]. deadline_ms 5e-324 is 0 s,
    which IPOPT refused as its time limit at the first plan (a CasADi RuntimeError)."""
    with pytest.raises(ValueError, match=match):
        MPCConfig(**kwargs)
    MPCConfig(rate_weight=(1e6, 0.0), terminal_weight=1e6)


def test_the_mpc_refuses_an_observation_that_is_no_array_of_numbers_or_of_another_cycle():
    """A dict was a bare TypeError; a boolean or complex observation was cast without a word (True as 1.0, a full
    engine speed); a v2 observation of a 5 m cycle was planned as the controller's 6.6 m one."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service")
    for bad in ({"a": 1}, obs.astype(bool), obs.astype(complex), np.array([str(v) for v in obs]), None):
        with pytest.raises(ValueError, match=r"obs must be WheelLoader observations \(arrays of real numbers\)"):
            ctrl.act(bad)
    short = Scenario(reverse_distance=5.0)
    obs5, _ = gym.make("WheelLoader-v2", braking="service", scenario=short).reset(seed=0)
    with pytest.raises(ValueError, match=r"a cycle of reverse_distance 5 m; this MPC plans 6.6 m: .*reset\(scenario="):
        ctrl.act(obs5)
    ctrl.reset(scenario=short)
    ctrl.state_from_obs(obs5)  # (told, it plans that cycle; a float16 copy is the same one)
    ctrl.state_from_obs(obs5.astype(np.float16))
    with pytest.raises(ValueError, match="plant_params moves the cycle's marks off the model's"):  # (before the env)
        run_closed_loop("service", plant_params={"reverse_distance": 7.0}, score=False)


def test_act_takes_one_observation_per_step_and_applied_checks_the_action():
    """The same observation twice moved a nominal plant's estimate to gain 1.08 and dropped a step from the schedule; a
    skipped one was learnt from as one step. applied() took NaN as the previous control, [5, ...] as 780 mg where the
    env applies 260 mg, and a short action was an IndexError."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service", config=MPCConfig(parallel_search=False))
    a = ctrl.act(obs)
    for bad in (np.array([np.nan, 0.0, 0.0, 0.0]), np.zeros(1), 0.5, np.zeros((2, 4)), np.zeros(5), "x"):
        with pytest.raises(ValueError, match="action must be"):
            ctrl.applied(bad)
    ctrl.applied(np.array([5.0, 0.0, -1.0, -1.0]))
    assert ctrl._last[2][0] == pytest.approx(P.U_mf_max)  # (clipped as the env's step clips it)
    ctrl.applied(a)
    with pytest.raises(ValueError, match="act\\(\\) takes one observation per control step of 0.1 s"):
        ctrl.act(obs)  # (the same one again)
    obs1, *_ = env.step(a)
    obs2, *_ = env.step(a)
    with pytest.raises(ValueError, match="a repeated or skipped observation"):
        ctrl.act(obs2)
    counts = dict(ctrl._counts)
    ctrl.act(obs1)  # (the refused ones changed nothing: one step further on the schedule)
    assert sum(counts.values()) - sum(ctrl._counts.values()) == 1


@pytest.mark.parametrize("kwargs, match", [
    ({"score": "no"}, "score must be True or False, got 'no'"),  # (scored the run)
    ({"score": None}, "score must be True or False, got None"),
    ({"plant_params": "abc"}, "plant_params: params must be a LoaderParams"),  # (named params)
])
def test_run_closed_loop_names_score_and_plant_params(kwargs, match):
    with pytest.raises(ValueError, match=match):
        run_closed_loop("service", **kwargs)


# ------------------------------------------------------------------ hostile inputs (the controller's failure modes, stop 62)
def test_a_solver_that_says_ok_of_a_non_finite_plan_is_a_fallback_with_its_status():
    """Any GridSolver may be injected: one that said ok of a NaN iterate made a NaN plan, whose control the codec
    encoded as [-1, -1, -1, -1] (no fuel, bucket down, no brake), flagged as no fallback, status "Solve_Succeeded"."""
    import dataclasses

    class NaNSolver(IpoptSolver):
        armed = False

        def solve(self, nlp, args, x0, lam_x0=None, lam_g0=None):
            r = super().solve(nlp, args, x0, lam_x0, lam_g0)
            return dataclasses.replace(r, z=np.full_like(r.z, np.nan)) if self.armed else r

    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    solver = NaNSolver()
    ctrl = MPCController("service", config=MPCConfig(parallel_search=False, horizon_steps=None), solver=solver)
    a = ctrl.act(obs)
    planned = ctrl.planned_steps()["controls"][1]
    solver.armed = True
    obs, *_ = env.step(a)
    a = ctrl.act(obs)
    info = ctrl.last_info
    assert info["fallback"] and "non-finite iterate" in info["status"] and ctrl.fallbacks == 1
    assert np.isfinite(a).all() and a[0] > -1.0  # (the previous plan's next step: fuel, not the encoded NaN)
    assert np.allclose(ctrl.planned_steps()["controls"][0], planned)


def test_act_refuses_an_observation_of_an_earlier_phase_and_changes_nothing():
    """A phase-2 observation after a phase-3 one was planned from on the phase-3 schedule (a cold solve from a NaN
    start, "Invalid_Number_Detected") and applied as a fallback, without an error: the phases only go forward."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service", config=MPCConfig(parallel_search=False))
    x, _, _ = ctrl.state_from_obs(obs)
    ctrl._last, ctrl._last_t, ctrl._obs_phase = (x, 2, np.zeros(3)), 0.0, 2  # (as after a step in phase 2 at t = 0)
    later = obs.copy()
    later[6] = obs[6] + 0.1 / 40.0  # (one step later; the observation's time is scaled by 40 s)
    assert ctrl.state_from_obs(later)[1] == pytest.approx(0.1, abs=1e-6)
    with pytest.raises(ValueError, match="the observation is in phase 1, the last step's was in phase 2"):
        ctrl.act(later)
    assert ctrl._last_t == 0.0 and ctrl._counts is None and ctrl.estimator.theta.tolist() == [1.0, 0.0]


def test_a_damaged_codegen_cache_is_built_again_never_a_traceback_or_a_hang(tmp_path, caplog):
    """The compiled libraries' folder: a record that parses as no JSON object ([], 5, null) was an AttributeError's
    traceback; a FIFO as the record hung the first plan in its read; a dangling link as a library was a
    FileNotFoundError in the folder's privacy check; another library of other input shapes under the key, its record
    matching, was CasADi's "mismatching shape" RuntimeError. Each is now a library built again (or, in a FIFO's
    place, interpreted functions), with a warning."""
    import logging
    import os
    import threading

    from mpc.controller import codegen

    if codegen.compiler() is None:
        pytest.skip("no C compiler")
    x, p = ca.SX.sym("x", 3), ca.SX.sym("p", 2)
    f = ca.Function("tiny_f", [x, p], [ca.sin(x[0]) * p[0] + x[1] * x[2] / p[1]])
    group = {"f": f, "grad": ca.Function("tiny_grad", [x, p], [ca.gradient(f(x, p), x)])}

    def values(fns):
        return [float(v) for fn in fns.values() for v in np.array(fn([0.3, -0.7, 1.1], [2.0, 0.5])).ravel()]

    def compiled(cache):
        done = []
        worker = threading.Thread(target=lambda: done.append(codegen.compiled([group], [f], cache=cache)[0]), daemon=True)
        worker.start()
        worker.join(30)
        assert done, "codegen.compiled hung"
        return done[0]

    os.chmod(tmp_path, 0o700)
    assert values(compiled(tmp_path)) == values(group)
    (lib,) = (tmp_path / "codegen").glob("*.so")
    record = lib.with_suffix(".json")
    good = record.read_text()
    with caplog.at_level(logging.WARNING, logger="mpc.controller.codegen"):
        for text in ("[]", "5", "null"):
            record.unlink()
            record.write_text(text)
            assert values(compiled(tmp_path)) == values(group)
        assert "the record is no JSON object (list)" in caplog.text
        (tmp_path / "codegen" / "gone.so").symlink_to(tmp_path / "nowhere")
        assert values(compiled(tmp_path)) == values(group)
        record.unlink()
        os.mkfifo(record)
        assert compiled(tmp_path) is None  # (a pipe in the record's place is not replaced: interpreted)
        assert "is not a regular file" in caplog.text
        # another library of other input shapes under the key, its record made to match it
        x4 = ca.SX.sym("x", 4)
        other = {"f": ca.Function("tiny_f", [x4, p], [ca.cos(x4[0]) * p[0]]),
                 "grad": ca.Function("tiny_grad", [x4, p], [ca.vertcat(x4, p)])}
        codegen.compiled([other], [other["f"]], cache=tmp_path / "other")
        (lib_other,) = (tmp_path / "other" / "codegen").glob("*.so")
        fresh = tmp_path / "fresh" / "codegen"
        fresh.mkdir(parents=True)
        (fresh / lib.name).write_bytes(lib_other.read_bytes())
        (fresh / record.name).write_text(json.dumps({**json.loads(good), "sha256": codegen._sha256(lib_other)}))
        caplog.clear()
        assert values(compiled(tmp_path / "fresh")) == values(group)
        assert "does not give its functions' values" in caplog.text


@pytest.mark.parametrize("make, match", [
    (lambda: IpoptSolver(time_budget=0.0), r"time_budget must be > 0 s or None, got 0.0"),  # (IPOPT's "Invalid options")
    (lambda: IpoptSolver(time_budget=math.nan), r"time_budget must be > 0 s or None, got nan"),  # (no budget at all)
    (lambda: IpoptSolver(max_iter=2.5), r"max_iter must be an integer in \[1, 100000\], got 2.5"),  # (taken as 2)
    (lambda: IpoptSolver(max_iter=True), r"max_iter must be an integer in \[1, 100000\], got True"),
    (lambda: solver_module.SqpRtiSolver("hpipm", extra_steps=True), r"extra_steps must be an integer >= 0, got True"),
    (lambda: solver_module.SqpRtiSolver("nope"), r"qpsol must name a QP solver of CasADi's"),  # (failed at the first plan)
])
def test_the_injectable_solvers_refuse_their_settings_by_name(make, match):
    """IpoptSolver(time_budget=0) failed at the first plan with IPOPT's "Invalid options were detected" (a CasADi
    traceback); nan ran without a budget and 2.5 iterations as 2; the RTI took extra_steps=True as 1 and an unknown QP
    solver until its first solve."""
    with pytest.raises(ValueError, match=match):
        make()
    IpoptSolver(np.int64(50), np.float32(0.05))  # (numpy's numbers are numbers)


def test_act_never_returns_a_non_finite_control_as_an_action(monkeypatch):
    """A NaN control was encoded as the action [-1, -1, -1, -1] (no fuel, bucket down, no brake) without a word: it is
    an error naming the step's status."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service", config=MPCConfig(safety_filter=False))
    info = {"solve_time": 0.0, "status": "a solver of NaN", "fallback": False}
    monkeypatch.setattr(ctrl, "control", lambda x, t, phase: (np.array([np.nan, 0.0, 0.0]), False, dict(info)))
    with pytest.raises(RuntimeError, match="no finite control at t = 0.00 s .*'a solver of NaN'"):
        ctrl.act(obs)


# ------------------------------------------------------------------ the controller's review (stop 63): cold starts, mixed loaders,
# solver names and settings
def test_a_plant_back_in_phase_2_after_the_reversing_point_is_planned_from_the_reference():
    """A phase-2 observation standing at the reversing point (under 1 mm/s) is planned from phase 3; the next one, still
    in phase 2 and moving back at 2 cm/s, has no warm start of phase 2. That solve started from the middle of the
    bounds, NaN for every variable without bounds: "Invalid_Number_Detected" every time, a fallback. It starts from the
    continuous reference's guess; with none, it fails with a status that says so, without a solve."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service", config=MPCConfig(horizon_steps=None, parallel_search=False))
    v_max, p = ctrl.params.V_max, ctrl.params
    one_step = p.decel_max * p.g * ctrl.dt + 0.01  # m/s: the last phase-2 step before the stop is slower than this
    while not (obs[9] == 1.0 and obs[1] * v_max > -one_step):
        assert obs[10] != 1.0, "phase 3 reached without a phase-2 step one step from the stop"
        obs, *_ = env.step(ctrl.act(obs))
    standing = obs.copy()
    standing[1] = -0.0005 / v_max
    ctrl.act(standing)
    assert ctrl._iterate.first_phase == 3
    back = standing.copy()
    back[1], back[6] = -0.02 / v_max, standing[6] + ctrl.dt / 40.0  # (one step later, still in phase 2)
    a = ctrl.act(back)
    info = ctrl.last_info
    assert not info["fallback"] and "Invalid_Number" not in info["status"], info["status"]
    assert ctrl._sol.first_phase == 2 and np.isfinite(a).all() and a[2] > -1.0  # (it brakes to the stop)
    x = ctrl.project_state(ctrl.state_from_obs(back)[0], 2)
    ctrl._plan_reference = None  # (no reference: a clear status, no NaN start)
    sol = ctrl._solve(2, dict(ctrl._counts), x, warm=None)
    assert not sol.ok and sol.status.startswith("no start for a solve from phase 2") and sol.z is None


def test_act_refuses_an_observation_whose_episode_features_change_within_the_episode():
    """Observations of two loaders on the same marks, interleaved, passed: a payload, rolling resistance or start that
    changed between two steps was taken as the plant's and fed to the estimator. The features fixed for an episode
    (the scenario's, and a target env's target) must stay as first observed; a refused observation changes nothing;
    the next episode (reset()) may have others."""
    env = gym.make("WheelLoader-v2", braking="service")
    obs, _ = env.reset(seed=0)
    ctrl = MPCController("service", config=MPCConfig(parallel_search=False))
    obs1, *_ = env.step(ctrl.act(obs))
    other = gym.make("WheelLoader-v2", braking="service", scenario=Scenario(payload=12000.0, rolling_resistance=0.04))
    obs_other, _ = other.reset(seed=0)
    mixed = obs1.copy()
    mixed[12:] = obs_other[12:]  # (the same marks, another loader's payload and rolling resistance)
    start = obs1.copy()
    start[12 + 5] = 0.5  # (scenario.start_engine_speed)
    before = (ctrl._last_t, dict(ctrl._counts), ctrl.estimator.theta.tolist(), ctrl._obs_phase)
    for bad, match in ((mixed, r"scenario\.payload .*scenario\.rolling_resistance"), (start, r"scenario\.start_engine_speed"),
                       (np.concatenate([obs1, [0.3, 0.2]]).astype(np.float32), r"the observation has 21 entries, the episode's first had 19"),
                       (obs1[:12], r"the observation has 12 entries, the episode's first had 19")):
        with pytest.raises(ValueError, match=match):
            ctrl.act(bad)
        assert (ctrl._last_t, dict(ctrl._counts), ctrl.estimator.theta.tolist(), ctrl._obs_phase) == before
    ctrl.act(obs1)  # (this loader's next step)
    ctrl.reset()
    ctrl.act(obs_other)  # (a new episode: another loader on the same marks)
    assert ctrl._features is not None and np.allclose(ctrl._features, obs_other[12:])


def test_a_first_plan_that_fails_names_the_solver_it_ran():
    """The first plan's failure said "IPOPT status ..." whatever solver was injected."""

    class Refusing:
        def prepare(self, nlp):
            pass

        def solve(self, nlp, args, x0, lam_x0=None, lam_g0=None):
            return SolverResult(ok=False, status="refused (injected)", iterations=0)

    obs, _ = gym.make("WheelLoader-v2", braking="service").reset(seed=0)
    with pytest.raises(RuntimeError, match=r"from the start state: Refusing status refused \(injected\)"):
        MPCController("service", config=MPCConfig(parallel_search=False), solver=Refusing()).act(obs)
    fatrop = solver_module.FallbackSolver(solver_module.FatropSolver(), IpoptSolver())
    assert solver_module.solver_name(fatrop) == "fatrop, then IPOPT"
    assert solver_module.solver_name(IpoptSolver()) == "IPOPT"


@pytest.mark.parametrize("max_iter", [2.5, True, 0, 100_001, "50", None, math.nan])
def test_fatrop_refuses_its_settings_as_ipopt_does(max_iter):
    """FatropSolver(max_iter=...) took anything (2.5, True, "50") until fatrop's build at the first plan."""
    with pytest.raises(ValueError, match=r"max_iter must be an integer in \[1, 100000\]"):
        solver_module.FatropSolver(max_iter)
    assert solver_module.FatropSolver(np.int64(50)).max_iter == 50
