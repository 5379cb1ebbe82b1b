"""How fast can a driver of the stopping assist (``WheelLoaderTarget-v3`` to ``-v7``) go? A scheduled all-out driver at T_min.

    python scripts/bench_assist_floor.py --braking service --scenarios 20 --phases

Not a learned driver: a rule that drives as the minimum-time optimum does, to measure what the assist's laws
(braking point, braking, TC lift-off, bucket stopping curve) and the 0.1 s step leave of T_min, whatever the
driver. Each step it asks the engine's top speed, the strongest braking fraction and no coasting, and it
schedules the bucket as the optimum does: held still (the lift takes engine power) in phases 1 and 3 until
the engine runs at ``engine_fraction`` of omega_max or faster, there lifted at full acceleration (the assist's stopping
curve ends the lift at the dump height), and lifted in phases 2 and 4, where the wheels ask no engine power.
The driver reads the plant's state (an oracle, for measuring; a policy reads its observation).

Per scenario of the suite (``--scenarios`` spread over it, each at its shipped T_min, from its nominal start):
the cycle time, the lateness against T_min, success and the largest violation; with ``--phases`` also the
time per phase against each scenario's minimum-time OCP (solved here, ~3-6 s a scenario).
"""

from __future__ import annotations

import logging
import statistics
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)

import wl_env  # noqa: E402, F401  (registers the envs)
import wl_env.assist as assist  # noqa: E402
from agents.ppo_config import COAST_ENV_IDS  # noqa: E402  (the assists with the coasting fraction, its 4th action)
from agents.train_cli import tyro_options  # noqa: E402
from mpc.benchmark.reference import min_time_of  # noqa: E402
from wl_env.atomic_io import check_output_file, write_json_atomic  # noqa: E402
from wl_env.logs import run_script  # noqa: E402
from wl_env.suites import load_suite  # noqa: E402

log = logging.getLogger("bench_assist_floor")


@dataclass
class Options:
    braking: str = "service"
    env_id: str = "WheelLoaderTarget-v3"  # the assist driven (v3-v6 brake alike under this driver; v7 on the step grid)
    scenarios: int = 20  # spread over the suite
    suite: str = "test"
    engine_fraction: float = 0.97  # of omega_max, where the bucket starts lifting in phases 1 and 3
    braking_cap: float | None = None  # the braking fraction at action +1 (None: the env's, 0.95); 0.98 at most
    phases: bool = False  # also each phase's time against the minimum-time OCP's
    out: str | None = None  # JSON of the per-cycle records and the summary


class ScheduledDriver:
    """The all-out driver of the module docstring, reading ``env``'s plant state."""

    def __init__(self, env: gym.Env, engine_fraction: float) -> None:
        self.env, self.engine_fraction = env.unwrapped, engine_fraction

    def act(self, obs: np.ndarray) -> np.ndarray:
        omega, _, _, bucket_speed = self.env.state[:4]
        phase, p = self.env.phase, self.env.episode_params
        lift = phase in (2, 4) or omega >= self.engine_fraction * p.omega_max
        lo, hi = p.U_ab_bounds
        u_ab = hi if lift else np.clip(-bucket_speed / self.env.core.dt, lo, hi)
        return np.array([1.0, (u_ab - 0.5 * (hi + lo)) / (0.5 * (hi - lo)), 1.0, 1.0], dtype=np.float32)


def run(o: Options) -> dict[str, Any]:
    if not 1 <= o.scenarios <= 1000:
        raise ValueError(f"--scenarios must be an integer in [1, 1000], got {o.scenarios}")
    if o.env_id not in COAST_ENV_IDS:
        raise ValueError(f"--env-id must be one of {', '.join(COAST_ENV_IDS)}, got {o.env_id!r}")
    if not 0.0 < o.engine_fraction <= 1.0:
        raise ValueError(f"--engine-fraction must be in (0, 1], got {o.engine_fraction}")
    if o.out is not None:  # (written at the end: checked before the cycles)
        check_output_file(o.out, "--out")
    if o.braking_cap is not None:
        if not assist.BRAKING_FRACTION[0] < o.braking_cap <= assist.MAX_BRAKING_FRACTION:
            raise ValueError(f"--braking-cap must be in ({assist.BRAKING_FRACTION[0]}, {assist.MAX_BRAKING_FRACTION}], "
                             f"got {o.braking_cap}")
        assist.BRAKING_FRACTION = (assist.BRAKING_FRACTION[0], o.braking_cap)  # (this process only: a measurement)
    env = gym.make(o.env_id, braking=o.braking)
    driver = ScheduledDriver(env, o.engine_fraction)
    records = []
    for i, sc in enumerate(load_suite(o.suite).spread(o.braking, o.scenarios)):
        env.reset(seed=i, options={"scenario": sc})
        T_min = min_time_of(o.braking, env.unwrapped.episode_params, solve=True)
        obs, _ = env.reset(seed=i, options={"scenario": sc, "target_time": T_min})
        steps = dict.fromkeys((1, 2, 3, 4), 0)
        done = False
        while not done:
            steps[env.unwrapped.phase] += 1
            obs, _, terminated, truncated, info = env.step(driver.act(obs))
            done = terminated or truncated
        rec = {"scenario": sc.label(), "T": info["t"], "T_min": T_min, "lateness": info["t"] / T_min - 1.0,
               "success": info["is_success"], "max_violation": info["violations"]["max_excess"],
               "phase_s": [steps[q] * env.unwrapped.core.dt for q in (1, 2, 3, 4)]}
        if o.phases:
            from mpc.benchmark.ocp import solve_ocp

            opt = solve_ocp(o.braking, "time", scenario=sc)
            rec["phase_excess_s"] = [a - b for a, b in zip(rec["phase_s"], opt.phase_durations, strict=True)]
        records.append(rec)
        log.info("%s: T %.2f s, T_min %.2f s, late %.1f %%, success %s, violation %.3g", rec["scenario"], rec["T"],
                 T_min, 100 * rec["lateness"], rec["success"], rec["max_violation"])
    late = [r["lateness"] for r in records]
    summary = {"lateness_median": statistics.median(late), "lateness_p10": float(np.percentile(late, 10)),
               "lateness_p90": float(np.percentile(late, 90)), "success_rate": float(np.mean([r["success"] for r in records])),
               "max_violation": max(r["max_violation"] for r in records)}
    if o.phases:
        excess = np.array([r["phase_excess_s"] for r in records])
        summary["phase_excess_median_s"] = np.median(excess, axis=0).round(3).tolist()
        summary["phase_excess_mean_s"] = excess.mean(axis=0).round(3).tolist()
    print(f"{o.braking}, {len(records)} {o.suite} cycles at T_min: lateness median {100 * summary['lateness_median']:.2f} % "
          f"(p10 {100 * summary['lateness_p10']:.2f}, p90 {100 * summary['lateness_p90']:.2f}), success "
          f"{100 * summary['success_rate']:.0f} %, max violation {summary['max_violation']:.3g}"
          + (f"; per phase over the OCP: median {summary['phase_excess_median_s']} s, mean {summary['phase_excess_mean_s']} s"
             if o.phases else ""))
    if o.out:
        write_json_atomic(o.out, {"options": asdict(o), "summary": summary, "records": records})
    return summary


if __name__ == "__main__":
    run_script("bench_assist_floor", lambda: run(tyro_options(Options)))
