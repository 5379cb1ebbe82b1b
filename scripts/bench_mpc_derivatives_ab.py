"""Per-step solve times of the synchronous MPC under different builds of the NLP's functions, alternating
in one process (the order turned each round, the solvers released and built again per variant): a paired
comparison on a noisy machine. The variants:

* "compiled": the slot functions' values and derivatives compiled (:mod:`mpc.controller.codegen`; the
  default where a C compiler is found, since stop 46; built before the first round, from the cache after);
* "mapped": the same functions interpreted by CasADi (``$WL_CODEGEN=off``; the default of stop 45);
* "generated": IPOPT on the whole SX NLP with CasADi's own derivatives (stop 44's build).

Per round and variant, the nominal cycle at an 11 s target and at minimum time; ``--rti`` adds both on the
10-step horizon under the real-time iteration. Usage::

    python scripts/bench_mpc_derivatives_ab.py [--braking tc] [--rounds 3] [--variants compiled mapped] [--rti]
        [--json PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import numpy as np  # noqa: E402

from agents.train_cli import refuse_repeated_values  # noqa: E402
from mpc.controller import codegen, solver  # noqa: E402
from mpc.controller.grid import GridNLP  # noqa: E402
from mpc.controller.mpc import MPCConfig, run_closed_loop  # noqa: E402
from wl_env.atomic_io import check_output_option, write_json_atomic  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

MAPPED = (GridNLP.mapped_nlp, GridNLP.derivative_functions)
VARIANTS = ("compiled", "mapped", "generated")


def use(variant: str) -> None:
    """The NLP's functions for the next solvers built: one of :data:`VARIANTS` (see above)."""
    solver.release_solvers()
    codegen.set_mode("on" if variant == "compiled" else "off")
    if variant == "generated":
        GridNLP.mapped_nlp = property(lambda self: self.nlp)
        GridNLP.derivative_functions = property(lambda self: {})
    else:
        GridNLP.mapped_nlp, GridNLP.derivative_functions = MAPPED


def label(cfg: MPCConfig) -> str:
    return "full" if cfg.horizon is None else f"h{cfg.horizon} {cfg.short_horizon_solver}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--braking", choices=("service", "tc"), default="tc")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the variants (1..20)")
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=["compiled", "mapped"])
    ap.add_argument("--rti", action="store_true", help="also the 10-step horizon under the real-time iteration")
    ap.add_argument("--json", metavar="PATH")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    if not 1 <= args.rounds <= 20:
        raise ValueError(f"--rounds must be an integer in [1, 20], got {args.rounds}")
    check_output_option(ap, args.json, "--json")
    refuse_repeated_values("--variants", args.variants, "a variant")  # (as every script's lists; was dropped silently)
    configs = [MPCConfig(mode="target_time", target_time=11.0, horizon_steps=None), MPCConfig(mode="time", horizon_steps=None)]
    if args.rti:
        configs += [dataclasses.replace(c, horizon_steps=10, horizon_solver="sqp-rti") for c in configs]
    variants = list(args.variants)
    steps: dict[str, list[float]] = {f"{v} {label(c)}": [] for v in variants for c in configs}
    rows = []
    if "compiled" in variants:  # the libraries built before the rounds time anything
        use("compiled")
        for c in configs:
            run_closed_loop(args.braking, dataclasses.replace(c, mode="target_time", target_time=11.0), score=False)
    for rnd in range(args.rounds):
        for variant in variants[rnd % len(variants):] + variants[:rnd % len(variants)]:
            use(variant)
            for cfg in configs:
                r = run_closed_loop(args.braking, cfg, score=False)
                times = r.solve_times_s[1:]
                steps[f"{variant} {label(cfg)}"] += times
                rows.append({"round": rnd, "variant": variant, "mode": cfg.mode, "horizon": label(cfg), "T": r.episode.T,
                             "fuel_g": r.episode.fuel_g, "planning_s": r.solve_time["planning_s"], "solve_times_s": times})
                print(f"round {rnd} {variant} {cfg.mode} {label(cfg)}: T {r.episode.T:.1f} s, fuel {r.episode.fuel_g:.4f} g, step median "
                      f"{1e3 * statistics.median(times):.1f} ms, planning {r.solve_time['planning_s']:.2f} s", flush=True)
    for variant, times in steps.items():
        print(f"{variant}: all steps median {1e3 * np.median(times):.1f} ms, p90 {1e3 * np.percentile(times, 90):.1f} ms, "
              f"p99 {1e3 * np.percentile(times, 99):.1f} ms ({len(times)} steps)", flush=True)
    use("mapped")
    codegen.set_mode(None)
    if args.json:
        write_json_atomic(args.json, {"command": " ".join(sys.argv), "rows": rows})


if __name__ == "__main__":
    run_script("bench_mpc_derivatives_ab", main)
