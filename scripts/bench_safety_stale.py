"""The safety filter against stale plans, deterministically: the synchronous MPC (minimum-time mode) solves only
every N-th step and applies the previous plan, shifted, on the others (a failed solve's fallback: a plan up to
N - 1 steps old, as the real-time controller applies them), on plants whose payload and rolling resistance
differ from the model's. The real-time controller's plan ages depend on the machine's load from run to run; these
do not, so the filter's changes can be compared run for run. Usage::

    python scripts/bench_safety_stale.py [--every 3 6 12 25] [--braking tc] [--safety-filter both] [--json PATH]

Per run: the cycle time, whether it completed, on its marks, stalled, the largest violation (the environment's
own check), and the controls the filter changed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import gymnasium as gym  # noqa: E402

import wl_env  # noqa: E402,F401  (registers the envs)
from agents.train_cli import refuse_repeated_values  # noqa: E402
from mpc.controller.mpc import MPCConfig, MPCController  # noqa: E402
from mpc.controller.solver import IpoptSolver, SolverResult  # noqa: E402
from wl_env.atomic_io import check_output_option, write_json_atomic  # noqa: E402
from wl_env.logs import run_script  # noqa: E402
from wl_env.params import DEFAULT_PARAMS  # noqa: E402

PLANTS = [(p, r) for p in (0.8, 1.0, 1.2) for r in (0.7, 1.0, 1.3) if (p, r) != (1.0, 1.0)]  # (payload, rolling) x


class EveryNthSolver(IpoptSolver):
    """IPOPT on every ``every``-th step (the caller sets ``step``); the other steps' solves fail, so the controller
    applies its last plan shifted. (tests/fakes.FailingSolver is the tests' own; a script does not import tests.)"""

    def __init__(self, every: int) -> None:
        super().__init__()
        self.every, self.step = every, 0

    def solve(self, *args, **kwargs) -> SolverResult:
        if self.step % self.every:
            return SolverResult(ok=False, status=f"skipped (a solve every {self.every} steps)", iterations=0)
        return super().solve(*args, **kwargs)


def run(braking: str, every: int, payload: float, rolling: float, safety_filter: bool) -> dict:
    plant = DEFAULT_PARAMS.variant(payload_scale=payload, rolling_scale=rolling)
    env = gym.make("WheelLoader-v2", braking=braking, params=plant)
    solver = EveryNthSolver(every)
    ctrl = MPCController(braking, config=MPCConfig(safety_filter=safety_filter, horizon_steps=None), solver=solver)
    obs, _ = env.reset(seed=0)
    t0 = time.perf_counter()
    for k in range(400):
        solver.step = k
        obs, _, terminated, truncated, info = env.step(ctrl.act(obs))
        if terminated or truncated:
            break
    ctrl.end_episode()
    return {"braking": braking, "every": every, "payload_scale": payload, "rolling_scale": rolling,
            "safety_filter": safety_filter, "T": float(info["t"]), "completed": bool(info["completed"]),
            "success": bool(info["is_success"]), "stalled": bool(info["stalled"]),
            "max_violation": float(info["violations"]["max_excess"]), "eased": int(ctrl.safety_eased),
            "wall_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--every", type=int, nargs="+", default=[3, 6, 12, 25], metavar="N")
    ap.add_argument("--braking", choices=("service", "tc"), nargs="+", default=["tc"])
    ap.add_argument("--safety-filter", choices=("on", "off", "both"), default="both")
    ap.add_argument("--json", metavar="PATH")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    check_output_option(ap, args.json, "--json")
    if not all(1 <= n <= 100 for n in args.every):
        ap.error(f"--every must be integers in [1, 100], got {args.every}")
    try:  # (each run twice, and counted twice in the summaries)
        refuse_repeated_values("--every", args.every)
        refuse_repeated_values("--braking", args.braking, "a braking alternative")
    except ValueError as exc:
        ap.error(str(exc))
    filters = {"on": [True], "off": [False], "both": [True, False]}[args.safety_filter]
    rows = []
    for braking in args.braking:
        for safety_filter in filters:
            for every in args.every:
                for payload, rolling in PLANTS:
                    row = run(braking, every, payload, rolling, safety_filter)
                    rows.append(row)
                    print(f"{braking} filter {'on ' if safety_filter else 'off'} every {every:3d} payload x{payload} "
                          f"rolling x{rolling}: T {row['T']:.1f} s, completed {row['completed']}, on the marks "
                          f"{row['success']}, stalled {row['stalled']}, max violation {100 * row['max_violation']:.2f} %, "
                          f"eased {row['eased']}", flush=True)
            mine = [r for r in rows if r["braking"] == braking and r["safety_filter"] == safety_filter]
            over = [r for r in mine if r["max_violation"] > 0.0]
            print(f"[{braking}, filter {'on' if safety_filter else 'off'}] {len(mine)} cycles: {len(over)} over the limit "
                  f"(max {100 * max([r['max_violation'] for r in mine]):.2f} %), "
                  f"{sum(r['success'] for r in mine)} on their marks, {sum(r['stalled'] for r in mine)} stalled", flush=True)
    if args.json:
        write_json_atomic(args.json, {"command": " ".join(sys.argv), "rows": rows})


if __name__ == "__main__":
    run_script("bench_safety_stale", main)  # (Ctrl-C: exit 130; the JSON is written only at the end, nothing partial is left)
