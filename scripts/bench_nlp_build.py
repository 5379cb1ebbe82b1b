"""What a slot layout of the MPC's grid NLP costs to build, to hold and to evaluate: IPOPT on the NLP and its
derivatives mapped from the slot functions (``GridNLP.mapped_nlp``, ``GridNLP.derivative_functions``: the
default) against IPOPT on the whole NLP and the derivatives CasADi generates from it (before stop 45). Each
variant runs in a fresh process (its memory its own): it builds the NLPs and warm IPOPT solvers of
``--layouts`` slot layouts (the 4 NLPs from each first phase, as a cycle's planning does), then evaluates the
largest NLP's Hessian of the Lagrangian and constraint Jacobian. Usage::

    python scripts/bench_nlp_build.py [--braking tc] [--layouts 2] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from wl_env.atomic_io import check_output_option, write_json_atomic  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

VARIANTS = ("mapped", "generated")
# the nominal TC cycle's first-plan layout at minimum time, then one slot layout per step more in phase 1
BASE_SLOTS = {1: 24, 2: 16, 3: 28, 4: 20}


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024.0


def measure(variant: str, braking: str, layouts: int) -> dict:
    """One variant in this process (see the module doc)."""
    import numpy as np
    from bench_mpc_derivatives_ab import use  # (this folder is the script's first sys.path entry)

    from mpc.controller import solver
    from mpc.controller.grid import StepModel

    use(variant)  # "generated": IPOPT as it was built before stop 45, the whole NLP and CasADi's derivatives of it
    model = StepModel(braking)
    ipopt = solver.IpoptSolver()
    before = rss_mb()
    builds, rss = [], []
    for i in range(layouts):
        slots = {**BASE_SLOTS, 1: BASE_SLOTS[1] + 4 * i}
        for q in range(1, 5):
            t0 = time.perf_counter()
            ipopt.prepare(solver.grid_nlp(model, q, tuple((p, slots[p]) for p in range(q, 5))))
            builds.append(time.perf_counter() - t0)
        rss.append(rss_mb() - before)
    nlp = solver.grid_nlp(model, 1, tuple(BASE_SLOTS.items()))
    fn = ipopt._function(nlp, warm=True)
    rng = np.random.default_rng(0)
    point = {"x": rng.uniform(-1.0, 1.0, nlp.n_var), "p": rng.uniform(0.1, 1.0, nlp.n_par)}
    evals = {}
    for name, extra in (("nlp_hess_l", {"lam_f": 1.0, "lam_g": rng.normal(0.0, 1.0, nlp.n_con)}), ("nlp_jac_g", {})):
        f = fn.get_function(name)
        times = []
        for _ in range(30):
            t0 = time.perf_counter()
            f.call({**point, **extra})
            times.append(time.perf_counter() - t0)
        evals[f"{name}_ms"] = 1e3 * statistics.median(times)
    return {"variant": variant, "braking": braking, "build_s": builds, "build_median_s": statistics.median(builds),
            "rss_growth_mb": rss, **evals}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--braking", choices=("service", "tc"), default="tc")
    ap.add_argument("--layouts", type=int, default=2, help="slot layouts to build (1..8)")
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument("--variant", choices=VARIANTS, help=argparse.SUPPRESS)  # (the child process's)
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    if not 1 <= args.layouts <= 8:
        raise ValueError(f"--layouts must be an integer in [1, 8], got {args.layouts}")
    check_output_option(ap, args.json, "--json")
    if args.variant:  # a child: one variant, its row on stdout
        print(json.dumps(measure(args.variant, args.braking, args.layouts)))
        return
    rows = []
    for variant in VARIANTS:
        out = subprocess.run([sys.executable, __file__, "--variant", variant, "--braking", args.braking,
                              "--layouts", str(args.layouts)], capture_output=True, text=True)
        if out.returncode == 130:
            raise KeyboardInterrupt
        if out.returncode != 0:  # (its own error, not this process's traceback)
            sys.exit(f"bench_nlp_build: the {variant} variant failed (exit {out.returncode}):\n{out.stderr[-2000:]}")
        r = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(r)
        print(f"{variant}: build per NLP with its IPOPT median {r['build_median_s']:.2f} s (max "
              f"{max(r['build_s']):.2f}); memory after each layout +{' / +'.join(f'{m:.0f}' for m in r['rss_growth_mb'])} MB; "
              f"Hessian {r['nlp_hess_l_ms']:.2f} ms, Jacobian {r['nlp_jac_g_ms']:.2f} ms (median of 30)", flush=True)
    if args.json:
        write_json_atomic(args.json, {"command": " ".join(sys.argv), "rows": rows})


if __name__ == "__main__":
    run_script("bench_nlp_build", main)
