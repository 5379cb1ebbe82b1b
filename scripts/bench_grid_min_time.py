"""Is there a cycle one step shorter than the MPC's minimum-time plan on the environment's 0.1 s grid?

Plans the nominal cycle in minimum-time mode, then solves every schedule with one step fewer within +-R
steps per phase of the plan's (warm from the plan, then cold if that fails) and prints each one's target
misses (relative: the reversing point's and the end position's to the reverse distance, the height's to
H_T) and whether it meets the MPC's tolerance (``mpc.controller.solver.MISS_TOL``).

Usage::

    python scripts/bench_grid_min_time.py {service,tc} [R]
"""

from __future__ import annotations

import itertools
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import wl_env  # noqa: E402, F401  (registers the envs)
from mpc.controller import mpc as M  # noqa: E402
from mpc.controller.schedule import steps_of  # noqa: E402
from mpc.controller.solver import MISS_TOL, Solve  # noqa: E402


def main() -> None:
    braking = sys.argv[1] if len(sys.argv) > 1 else "tc"
    reach = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    env = gym.make("WheelLoader-v2", braking=braking)
    core = env.unwrapped.core
    ctrl = M.MPCController(braking, config=M.MPCConfig(mode="time"), dt=core.dt, substeps=core.substeps)
    obs, _ = env.reset(seed=0)
    ctrl.reset()
    ctrl.act(obs)  # plans the cycle
    x, _, phase = ctrl.state_from_obs(obs)
    sol, x = ctrl._sol, ctrl.project_state(x, phase)  # (the start state the plan was made from)
    n0 = steps_of(sol.counts)
    print(f"{braking}: the plan's schedule {sol.counts} = {n0} steps ({n0 * ctrl.dt:.1f} s), feasible {sol.feasible}, "
          f"fuel {sol.fuel_g:.3f} g; the MPC's target tolerance {MISS_TOL:g} (relative)", flush=True)
    nlp = ctrl._nlp(1)
    phases = sorted(sol.counts)
    t0, tried, feasible, closest = time.perf_counter(), 0, 0, None
    for d in itertools.product(range(-reach, reach + 1), repeat=len(phases)):
        new = {q: sol.counts[q] + dq for q, dq in zip(phases, d, strict=True)}
        if sum(d) != -1 or any(not (0 if q in (2, 4) else 1) <= new[q] <= nlp.slots_per_phase[q] for q in phases):
            continue
        tried += 1
        z, lam_x, lam_g = nlp.resample(sol.z, sol.lam_x, sol.lam_g, sol.counts, new)
        alt = ctrl._solve(1, new, x, warm=Solve(counts=new, first_phase=1, ok=True, status="", z=z, lam_x=lam_x, lam_g=lam_g))
        if not alt.feasible:
            cold = ctrl._solve(1, new, x, warm=None)
            alt = cold if cold.feasible or not alt.ok else alt
        feasible += alt.feasible
        worst = max(map(abs, alt.misses.values()), default=np.inf) if alt.ok else np.inf
        if closest is None or worst < closest[0]:
            closest = (worst, new)
        print(f"  {new}: ok {alt.ok}, feasible {alt.feasible}, misses {({k: round(v, 4) for k, v in alt.misses.items()})}, "
              f"deceleration excess {alt.excess:.1e}", flush=True)
    print(f"{braking}: {tried} schedules of {n0 - 1} steps solved in {time.perf_counter() - t0:.0f} s, {feasible} meet the "
          "targets" + (f"; the closest {closest[1]} misses by {closest[0]:.4f} (relative)" if closest else ""))


if __name__ == "__main__":
    main()
