"""Is there a cycle one step shorter than the MPC's minimum-time plan on the environment's 0.1 s grid (or,
``--same-length``, one as short on less fuel)?

Plans the nominal cycle in minimum-time mode, then solves every schedule with one step fewer within +-R
steps per phase of the plan's (warm from the plan, then cold if that fails) and prints each one's target
misses (m) and whether it meets the MPC's tolerance (``mpc.controller.solver.MISS_TOL_M``).

``--same-length``: instead, every schedule with as many steps as the plan's within +-R per phase, each
solved for the least fuel (the target-time mode's NLP at the plan's cycle time, no control-rate penalty),
and the least fuel of those that meet the targets against the continuous optimum's at the same cycle time
(:func:`mpc.benchmark.scoring.score_run`): what the grid itself allows a minimum-time cycle.

``--suite NAME --scenario I``: the suite's I-th cycle of the braking instead of the nominal one.

Usage::

    python scripts/bench_grid_min_time.py {service,tc} [R] [--same-length] [--suite test --scenario I]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import wl_env  # noqa: E402, F401  (registers the envs)
from mpc.benchmark.scoring import score_run  # noqa: E402
from mpc.controller import mpc as M  # noqa: E402
from mpc.controller.schedule import steps_of  # noqa: E402
from mpc.controller.solver import MISS_TOL_M, Solve  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("braking", nargs="?", default="tc", choices=("service", "tc"))
    ap.add_argument("reach", nargs="?", type=int, default=2, help="R: steps per phase around the plan's schedule")
    ap.add_argument("--same-length", action="store_true", help="schedules as long as the plan's, for the least fuel")
    ap.add_argument("--suite", default=None, help="a suite (wl_env.suites.SUITES) whose cycle --scenario to plan")
    ap.add_argument("--scenario", type=int, default=None, help="I: the suite's I-th cycle of the braking")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    a = ap.parse_args()
    if not 1 <= a.reach <= 8:  # ((2R + 1)^4 schedules: R = 1000 looped for hours over slots a phase does not have)
        ap.error(f"R (reach) must be an integer in [1, 8], got {a.reach}")
    braking, reach, same_length = a.braking, a.reach, a.same_length
    scenario = None
    if (a.suite is None) != (a.scenario is None):
        ap.error("--suite and --scenario go together (the suite's I-th cycle of the braking)")
    if a.suite is not None:
        from wl_env.suites import load_suite

        cycles = load_suite(a.suite).of(braking)  # (ValueError naming the suites, or a sampler)
        if not 0 <= a.scenario < len(cycles):
            ap.error(f"--scenario must be an integer in [0, {len(cycles) - 1}] (the {a.suite} suite's {braking} "
                     f"cycles), got {a.scenario}")
        scenario = cycles[a.scenario]
    params = None if scenario is None else scenario.params()
    env = gym.make("WheelLoader-v2", braking=braking, params=params)
    core = env.unwrapped.core
    obs, _ = env.reset(seed=0, options=None if scenario is None else {"scenario": scenario})

    def planned(config: M.MPCConfig) -> M.MPCController:
        ctrl = M.MPCController(braking, params, config=config, dt=core.dt, substeps=core.substeps)
        ctrl.reset(scenario)
        ctrl.act(obs)  # plans the cycle
        return ctrl

    ctrl = planned(M.MPCConfig(mode="time", horizon_steps=None))
    if same_length:
        T = steps_of(ctrl._sol.counts) * ctrl.dt
        ctrl = planned(M.MPCConfig(mode="target_time", target_time=T, rate_weight=(0.0, 0.0), horizon_steps=None))
    x, _, phase = ctrl.state_from_obs(obs)
    sol, x = ctrl._sol, ctrl.project_state(x, phase)  # (the start state the plan was made from)
    n0 = steps_of(sol.counts)
    print(f"{braking}: the plan's schedule {sol.counts} = {n0} steps ({n0 * ctrl.dt:.1f} s), feasible {sol.feasible}, "
          f"fuel {sol.fuel_g:.3f} g; the MPC's target tolerance {MISS_TOL_M} (m)", flush=True)
    nlp = ctrl._nlp(1)
    phases = sorted(sol.counts)
    t0, tried, feasible, closest, cheapest = time.perf_counter(), 0, 0, None, None
    for d in itertools.product(range(-reach, reach + 1), repeat=len(phases)):
        new = {q: sol.counts[q] + dq for q, dq in zip(phases, d, strict=True)}
        if sum(d) != (0 if same_length else -1) or any(not (0 if q in (2, 4) else 1) <= new[q] <= nlp.slots_per_phase[q] for q in phases):
            continue
        tried += 1
        z, lam_x, lam_g = nlp.resample(sol.z, sol.lam_x, sol.lam_g, sol.counts, new)
        alt = ctrl._solve(1, new, x, warm=Solve(counts=new, first_phase=1, ok=True, status="", z=z, lam_x=lam_x, lam_g=lam_g))
        if not alt.feasible:
            cold = ctrl._solve(1, new, x, warm=None)
            alt = cold if cold.feasible or not alt.ok else alt
        feasible += alt.feasible
        worst = max((abs(v) / MISS_TOL_M[k] for k, v in alt.misses_m.items()), default=np.inf) if alt.ok else np.inf
        if closest is None or worst < closest[0]:
            closest = (worst, new)
        if alt.feasible and (cheapest is None or alt.fuel_g < cheapest[0]):
            cheapest = (alt.fuel_g, new)
        print(f"  {new}: ok {alt.ok}, feasible {alt.feasible}, fuel {alt.fuel_g:.3f} g, misses "
              f"(m) {({k: round(v, 4) for k, v in alt.misses_m.items()})}, deceleration excess {alt.excess:.1e}", flush=True)
    n = n0 if same_length else n0 - 1
    print(f"{braking}: {tried} schedules of {n} steps solved in {time.perf_counter() - t0:.0f} s, {feasible} meet the "
          "targets" + (f"; the closest {closest[1]} misses by {closest[0]:.2f} times the tolerance" if closest else ""))
    if same_length and cheapest is not None:
        fuel_opt = score_run(n * ctrl.dt, cheapest[0], braking, params).fuel_opt_g
        print(f"{braking}: the least fuel on the grid at {n * ctrl.dt:.1f} s: {cheapest[0]:.3f} g ({cheapest[1]}), "
              f"{100 * (cheapest[0] / fuel_opt - 1):+.2f} % against the continuous optimum's {fuel_opt:.3f} g")


if __name__ == "__main__":
    from wl_env.logs import run_script

    run_script("bench_grid_min_time", main)  # (Ctrl-C: exit 130, no traceback; a ValueError: one line, exit 2)
