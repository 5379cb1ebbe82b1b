"""Per-step solve times of the synchronous MPC with IPOPT on the mapped NLP (``GridNLP.mapped_nlp`` and the
slot functions' derivatives, the default since stop 45) against IPOPT on the whole SX NLP with CasADi's own
derivatives (stop 44's build), alternating in one process (the order turned each round, the solvers released
and built again per variant): a paired comparison on a noisy machine. Per round and variant, the nominal
cycle at an 11 s target and at minimum time. Usage::

    python scripts/bench_mpc_derivatives_ab.py [--braking tc] [--rounds 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from mpc.controller import solver  # noqa: E402
from mpc.controller.grid import GridNLP  # noqa: E402
from mpc.controller.mpc import MPCConfig, run_closed_loop  # noqa: E402
from wl_env.atomic_io import check_output_option, write_json_atomic  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

MAPPED = (GridNLP.mapped_nlp, GridNLP.derivative_functions)


def use(variant: str) -> None:
    """IPOPT's NLP and derivatives for the next solvers built: "mapped" (now) or "generated" (stop 44's)."""
    solver.release_solvers()
    if variant == "generated":
        GridNLP.mapped_nlp = property(lambda self: self.nlp)
        GridNLP.derivative_functions = property(lambda self: {})
    else:
        GridNLP.mapped_nlp, GridNLP.derivative_functions = MAPPED


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--braking", choices=("service", "tc"), default="tc")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of both variants (1..20)")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args()
    if not 1 <= args.rounds <= 20:
        raise ValueError(f"--rounds must be an integer in [1, 20], got {args.rounds}")
    check_output_option(ap, args.json, "--json")
    rows, steps = [], {"mapped": [], "generated": []}
    for rnd in range(args.rounds):
        for variant in ("mapped", "generated") if rnd % 2 == 0 else ("generated", "mapped"):
            use(variant)
            for cfg in (MPCConfig(mode="target_time", target_time=11.0), MPCConfig(mode="time")):
                r = run_closed_loop(args.braking, cfg, score=False)
                times = r.solve_times_s[1:]
                steps[variant] += times
                rows.append({"round": rnd, "variant": variant, "mode": cfg.mode, "T": r.episode.T,
                             "fuel_g": r.episode.fuel_g, "planning_s": r.solve_time["planning_s"], "solve_times_s": times})
                print(f"round {rnd} {variant} {cfg.mode}: T {r.episode.T:.1f} s, fuel {r.episode.fuel_g:.4f} g, step median "
                      f"{1e3 * statistics.median(times):.1f} ms, planning {r.solve_time['planning_s']:.2f} s", flush=True)
    for variant, times in steps.items():
        print(f"{variant}: all steps median {1e3 * np.median(times):.1f} ms, p90 {1e3 * np.percentile(times, 90):.1f} ms, "
              f"p99 {1e3 * np.percentile(times, 99):.1f} ms ({len(times)} steps)", flush=True)
    use("mapped")
    if args.json:
        write_json_atomic(args.json, {"command": " ".join(sys.argv), "rows": rows})


if __name__ == "__main__":
    run_script("bench_mpc_derivatives_ab", main)
