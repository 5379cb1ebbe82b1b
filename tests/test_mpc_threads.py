"""The MPC and the OCP from several threads of one process: they take turns (mpc.threads), and give what one thread
gives. Each case runs in a process of its own: CasADi, entered by two threads at once, died of a segmentation fault
(stop 65), which would take the test run with it."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str) -> dict:
    env = {**os.environ, "WL_CODEGEN": "off"}  # (no C build in the process: the threads' turns are the same)
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=env)
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])  # (-11: a segmentation fault)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_two_threads_take_turns_in_one_solver_and_in_the_ocp():
    """Two threads solving on one grid NLP's IPOPT (10 warm solves each) died of "double free or corruption" or a
    segmentation fault in 3 of 3 runs; two threads solving the continuous OCP at once, in its nlpsol build. Now every
    solve gives the single thread's result."""
    out = _run("""
        import json, threading
        import numpy as np
        from mpc.benchmark.ocp import OCPSettings, solve_ocp
        from mpc.controller.grid import NOMINAL_ESTIMATE
        from mpc.controller.mpc import MPCConfig, MPCController
        from wl_env.params import DEFAULT_PARAMS as P

        ctrl = MPCController("service", config=MPCConfig(mode="target_time", target_time=11.0))
        x = np.array([P.omega_0, 0.0, P.H_0, 0.0, 0.0])
        ctrl._plan_cycle(x, 1, 0)
        sol, nlp = ctrl._sol, ctrl._nlp(1)
        args = nlp.arguments(sol.counts, x, NOMINAL_ESTIMATE, 0.1, params=ctrl.params)
        alone = ctrl.solver.solve(nlp, args, sol.z, sol.lam_x, sol.lam_g)
        grid, ocp = [], []

        def solves():
            for _ in range(10):
                r = ctrl.solver.solve(nlp, args, sol.z, sol.lam_x, sol.lam_g)
                grid.append([r.ok, r.iterations, float(r.f)])
            r = solve_ocp("tc", "time", settings=OCPSettings(intervals=(12, 8, 12, 8), smoothing=(0.0,)), starts=((4.2, 0.8),),
                          verify=False)
            ocp.append([r.success, r.T])

        threads = [threading.Thread(target=solves) for _ in range(2)]
        [t.start() for t in threads]
        [t.join() for t in threads]
        print(json.dumps({"alone": [alone.ok, alone.iterations, float(alone.f)], "grid": grid, "ocp": ocp}))
    """)
    assert len(out["grid"]) == 20 and all(r == out["alone"] for r in out["grid"]) and out["alone"][0]
    assert len(out["ocp"]) == 2 and out["ocp"][0] == out["ocp"][1] and out["ocp"][0][0]
