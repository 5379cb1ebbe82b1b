"""Fast stand-ins for the expensive work, shared by the tests (and the subprocesses some of them start)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

from mpc.benchmark.ocp import OCPResult
from mpc.controller.solver import IpoptSolver, SolverResult
from wl_env.params import resolve


class FailingSolver(IpoptSolver):
    """IPOPT, except that every solve of the steps in ``failing`` fails (an injected solver;
    the test sets ``step`` before each step's act)."""

    def __init__(self, failing: set[int]) -> None:
        super().__init__()
        self.failing, self.step = failing, -1

    def solve(self, *args, **kwargs) -> SolverResult:
        if self.step in self.failing:
            return SolverResult(ok=False, status="forced failure (injected solver)", iterations=0)
        return super().solve(*args, **kwargs)


def tiny_ppo_config(tmp_path, **changes):
    """A PPOConfig that trains in seconds (8 loaders, a 16x16 network, no scoring) in ``tmp_path``."""
    from agents.ppo_config import PPOConfig

    base = dict(total_timesteps=4096, num_envs=8, n_steps=64, batch_size=256, n_epochs=2, eval_freq=1024,
                eval_episodes=2, checkpoint_freq=1024, score=False, progress_bar=False, log_dir=str(tmp_path),
                run_name="tiny", net_arch=(16, 16))
    return PPOConfig(**{**base, **changes})


def fake_solve(braking: str = "service", objective: str = "time", T: float | None = None, w_fuel=None,
               params=None, settings=None, **_: object) -> OCPResult:
    """A stand-in for ``solve_ocp``: T_min 7 s, the fuel optimum 47 g at 21 s, a convex front between.
    Each call is recorded in ``fake_solve.calls`` as (braking, objective, T)."""
    fake_solve.calls.append((braking, objective, T))
    T_sol = {"time": 7.0, "fuel": 21.0}.get(objective, T)
    fuel = 47.0 + 63.0 * ((21.0 - T_sol) / 14.0) ** 2
    t = np.linspace(0.0, T_sol, 5)
    return OCPResult(braking, objective, float(T_sol), float(fuel), [T_sol / 4] * 4, t.tolist(),
                     np.zeros((5, 4)).tolist(), np.zeros((4, 3)).tolist(), [1, 2, 3, 4, 4], np.zeros(5).tolist(),
                     "Solve_Succeeded", True, 10, 0.01, target_T=T, params_fingerprint=resolve(params).fingerprint(),
                     mesh=list(settings.intervals) if settings else [20, 12, 20, 12], verification={"passed": True})


fake_solve.calls = []


def fake_front_job(scenario, cache, n_points):
    """A stand-in for ``mpc.benchmark.suite.solve_one`` (a suite's per-scenario solve): a made-up front whose
    minimum time grows with the scenario's distances, so that each scenario's entry is its own (three verified points,
    the other ``n_points - 3`` failed: one record per point, as the suite's n<N> folder holds)."""
    import os

    from mpc.benchmark.pareto import ParetoFront

    p = scenario.params()
    T_min = 4.0 + 0.5 * (p.reverse_distance + p.forward_distance)
    T = [T_min * 1.001, T_min * 1.2, T_min * 2.5]
    front = ParetoFront(scenario.braking, T, [90.0, 60.0, 45.0], p.fingerprint(), T_min, T[-1], 45.0, [20, 12, 20, 12],
                        points=[{"T": t, "fuel_g": f, "verified": True} for t, f in zip(T, [90.0, 60.0, 45.0], strict=True)]
                        + [{"T": T_min * (1.3 + 0.1 * k), "fuel_g": None, "verified": False} for k in range(n_points - 3)])
    return {**front.__dict__, "scenario": scenario.to_dict(), "solve_s": 0.0, "pid": os.getpid()}


def in_thread(fn, timeout: float = 20.0):
    """``fn()``'s result or exception, or a failure if it has not returned within ``timeout`` s (a hang, e.g. a FIFO
    read)."""
    import threading

    out: dict = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except Exception as exc:  # noqa: BLE001
            out["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"{fn} hung (a FIFO read)"
    if "error" in out:
        raise out["error"]
    return out.get("value")


SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(name: str, prefix: str) -> ModuleType:
    """The script ``scripts/<name>`` as a module named ``<prefix><stem>``, registered in ``sys.modules`` (its
    dataclasses look their module up there; a prefix per test file keeps one file's copy from replacing another's)."""
    module_name = prefix + name.removesuffix(".py")
    spec = importlib.util.spec_from_file_location(module_name, SCRIPTS / name)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    return module
