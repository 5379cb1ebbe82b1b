"""The QP of one real-time iteration of the MPC's grid NLP, measured alone (issue #13).

    python scripts/bench_rti_qp.py --braking tc --target 11 --solves 20

Runs one closed-loop MPC cycle with IPOPT, keeps its warm-started solves of the NLP from phase 1, then
builds at each kept start the QP an SQP step solves (the exact Hessian of the Lagrangian at the start's
multipliers, the rows' Jacobian, the rows and the gradient) and solves it with each QP solver CasADi
ships (``casadi.conic``; hpipm with the NLP's stage structure). Prints per solver the time to evaluate
the QP's data, the QP solve's median and max, the iterations and the return statuses.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from agents.train_cli import refuse_repeated_values  # noqa: E402


def capture(braking: str, target: float, n: int) -> list[tuple[Any, dict[str, Any], np.ndarray, np.ndarray]]:
    """(nlp, args, start, lam_g) of up to n warm-started IPOPT solves from phase 1 in one closed-loop cycle."""
    from mpc.controller.mpc import MPCConfig, run_closed_loop
    from mpc.controller.solver import IpoptSolver

    kept = []

    class Recording(IpoptSolver):
        def solve(self, nlp, args, x0, lam_x0=None, lam_g0=None):  # type: ignore[no-untyped-def]
            if lam_g0 is not None and nlp.first_phase == 1 and len(kept) < n:
                kept.append((nlp, args, np.clip(x0, args["lbx"], args["ubx"]), np.asarray(lam_g0)))
            return super().solve(nlp, args, x0, lam_x0, lam_g0)

    run_closed_loop(braking, MPCConfig(mode="target_time", target_time=target, horizon_steps=None), solver=Recording(), score=False)
    return kept


def main() -> None:
    import casadi as ca

    from mpc.controller.solver import stage_structure

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--braking", default="tc", choices=("service", "tc"))
    ap.add_argument("--target", type=float, default=11.0, help="target cycle time (s)")
    ap.add_argument("--solves", type=int, default=20, help="warm starts to build QPs at")
    ap.add_argument("--solvers", nargs="+", default=["hpipm", "hpipm-speed", "osqp", "qrqp"],
                    choices=["hpipm", "hpipm-speed", "osqp", "qrqp"])
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    try:  # (each QP solver timed twice)
        refuse_repeated_values("--solvers", args.solvers, "a QP solver")
    except ValueError as exc:
        ap.error(str(exc))
    if not 1 <= args.solves <= 1000:  # (0 ran the whole cycle, then "no warm-started solve captured", exit 1)
        ap.error(f"--solves must be an integer in [1, 1000], got {args.solves}")
    from wl_env.env import check_target_time

    try:
        check_target_time(args.target, "--target")
    except ValueError as exc:
        ap.error(str(exc))
    kept = capture(args.braking, args.target, args.solves)
    if not kept:
        sys.exit("no warm-started solve from phase 1 was captured")
    nlp = kept[0][0]
    x, p, f, g = nlp.nlp["x"], nlp.nlp["p"], nlp.nlp["f"], nlp.nlp["g"]
    lam = ca.SX.sym("lam", g.numel())
    H = ca.hessian(f + ca.dot(lam, g), x)[0]
    J = ca.jacobian(g, x)
    qp_data = ca.Function("qp_data", [x, p, lam], [H, ca.gradient(f, x), g, J])
    st = stage_structure(nlp)
    print(f"NLP: {x.numel()} variables, {g.numel()} rows, {st['N']} stages; Hessian nnz {H.nnz()}, Jacobian nnz {J.nnz()}; "
          f"{len(kept)} warm starts")
    options = {"hpipm": ("hpipm", {**st, "hpipm": {"iter_max": 100}}),
               "hpipm-speed": ("hpipm", {**st, "hpipm": {"mode": "speed", "iter_max": 100}}),
               "osqp": ("osqp", {"osqp": {"verbose": False}}),
               "qrqp": ("qrqp", {"print_iter": False, "print_header": False})}
    print("| QP solver | QP data median | QP solve median / max | iterations | statuses |\n|---|---:|---:|---|---|")
    for name in args.solvers:
        plugin, opts = options[name]
        qp = ca.conic("rti_qp", plugin, {"h": H.sparsity(), "a": J.sparsity()}, {**opts, "error_on_fail": False})
        t_data, t_qp, iters, statuses = [], [], [], collections.Counter()
        for nlp_k, a, z, lam_g in kept:
            if nlp_k is not nlp:  # (a new layout: another NLP; the first one's QPs only)
                continue
            t0 = time.perf_counter()
            Hv, grad, gv, Jv = qp_data(z, a["p"], lam_g)
            t1 = time.perf_counter()
            qp(h=Hv, g=grad, a=Jv, lba=a["lbg"] - gv, uba=a["ubg"] - gv, lbx=a["lbx"] - z, ubx=a["ubx"] - z)
            t2 = time.perf_counter()
            stats = qp.stats()
            t_data.append(t1 - t0)
            t_qp.append(t2 - t1)
            iters.append(stats.get("iter_count", -1))
            statuses[str(stats.get("return_status", stats.get("success")))] += 1
        print(f"| {name} | {1e3 * np.median(t_data):.1f} ms | {1e3 * np.median(t_qp):.1f} / {1e3 * np.max(t_qp):.1f} ms | "
              f"{min(iters)}-{max(iters)} | {dict(statuses)} |")


if __name__ == "__main__":
    from wl_env.logs import run_script

    run_script("bench_rti_qp", main)  # (Ctrl-C: exit 130, no traceback; a ValueError: one line, exit 2)
