"""MUMPS's fill-reducing orderings on the MPC's whole-cycle IPOPT solves, replayed in one process.

    python scripts/bench_mumps_ordering.py --scenarios 10 --out docs/bench_mumps_ordering_stop51.json

Each of the first ``--scenarios`` cycles of ``--suite`` per braking (at ``--target-ratio`` times the scenario's
estimated T_min), and with ``--corners`` ``bench_mpc.py``'s mismatch corners (minimum time), runs under the
default MPC; every whole-cycle IPOPT solve it makes (the first step's plan and schedule moves, the later
re-plans; not the short horizons') is recorded with its arguments and warm start. Each is then solved again
under each of ``--orders`` (``ipopt.mumps_pivot_order``: 0 AMD, 2 AMF, 4 PORD, 5 METIS, 6 QAMD, 7 MUMPS's
automatic choice), ``--repeats`` times, the orders interleaved: per solve the median time, the iterations and
the objective of each. The stored plans are forgotten before each cycle (each plans as a fresh process would).
"""

from __future__ import annotations

import logging
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)
from agents.train_cli import refuse_repeated_values, tyro_options  # noqa: E402
from wl_env.atomic_io import check_output_file  # noqa: E402
from wl_env.cycle import check_braking  # noqa: E402
from wl_env.logs import run_script  # noqa: E402

log = logging.getLogger("bench_mumps_ordering")

PIVOT_ORDERS = (0, 2, 4, 5, 6, 7)  # IPOPT's mumps_pivot_order values (1, an order given by the caller, aside)


@dataclass
class Options:
    brakings: tuple[str, ...] = ("service", "tc")
    suite: str = "test"
    scenarios: int = 10  # the suite's first N cycles of each braking
    target_ratio: float = 1.15  # the target, times the scenario's estimated T_min; 0: minimum time
    corners: bool = False  # the mismatch corners too (nominal model, the plant's payload and rolling scaled)
    orders: tuple[int, ...] = (2, 7)  # the orderings compared; the first is the one the ratios are of
    repeats: int = 3  # solves per ordering and recorded solve (the median is taken)
    out: str | None = None  # JSON of the per-solve records and the summary


def check(o: Options) -> None:
    for b in o.brakings:
        check_braking(b)
    refuse_repeated_values("--brakings", o.brakings, "a braking alternative")  # (each run twice, counted twice)
    if not 0 <= o.scenarios <= 1000:
        raise ValueError(f"--scenarios must be an integer in [0, 1000], got {o.scenarios}")
    if o.target_ratio != 0 and not 1.0 <= o.target_ratio <= 3.0:
        raise ValueError(f"--target-ratio must be 0 (minimum time) or lie in [1, 3], got {o.target_ratio}")
    if len(o.orders) < 2 or len(set(o.orders)) != len(o.orders) or not set(o.orders) <= set(PIVOT_ORDERS):
        raise ValueError(f"--orders must be two or more distinct values of {list(PIVOT_ORDERS)}, got {list(o.orders)}")
    if not 1 <= o.repeats <= 100:
        raise ValueError(f"--repeats must be an integer in [1, 100], got {o.repeats}")
    if o.scenarios == 0 and not o.corners:
        raise ValueError("nothing to run: --scenarios 0 without --corners")
    if o.out is not None:
        check_output_file(o.out, "--out")


def run(o: Options) -> dict[str, Any]:
    check(o)
    from bench_mpc import MISMATCH, summary_line, write_with_speed

    from mpc.controller import mpc, solver
    from mpc.controller.mpc import MPCConfig, MPCController, run_closed_loop
    from wl_env.params import DEFAULT_PARAMS
    from wl_env.suites import load_suite
    from wl_env.suites.min_time import estimate_min_time

    class Recording(solver.IpoptSolver):
        """IPOPT as the controller's, recording each whole-cycle solve (its step: 0 is the first plan)."""

        def __init__(self) -> None:
            super().__init__()
            self.step_of: Any = lambda: 0
            self.solves: list[dict[str, Any]] = []

        def solve(self, nlp, args, x0, lam_x0=None, lam_g0=None):  # noqa: ANN001, ANN201 (IpoptSolver's)
            if not nlp.short:
                self.solves.append({"nlp": nlp, "args": args, "x0": x0, "lam_x0": lam_x0, "lam_g0": lam_g0,
                                    "far": bool(getattr(solver._CALL, "far", False)), "step": self.step_of()})
            return super().solve(nlp, args, x0, lam_x0, lam_g0)

    runs = []
    for b in o.brakings:
        for i, sc in enumerate(load_suite(o.suite).of(b)[:o.scenarios]):
            cfg = (MPCConfig() if o.target_ratio == 0 else
                   MPCConfig(mode="target_time", target_time=round(o.target_ratio * estimate_min_time(sc), 1)))
            runs.append((b, f"{o.suite}[{i}]", sc, None, cfg))
        if o.corners:
            runs += [(b, f"x{p}/x{r}", None, DEFAULT_PARAMS.variant(payload_scale=p, rolling_scale=r), MPCConfig(mode="time"))
                     for p, r in MISMATCH]
    records = []
    for b, label, scenario, plant, cfg in runs:
        mpc.forget_plans()
        ipopt = Recording()
        ctrl = MPCController(b, scenario.params() if scenario else None, cfg, solver=solver.rti_on_short_horizons(ipopt))
        ipopt.step_of = lambda c=ctrl: len(c.solve_times)
        ep = run_closed_loop(b, cfg, scenario=scenario, plant_params=plant, score=False, controller=ctrl).episode
        for s in ipopt.solves:
            nlp, warm = s["nlp"], s["lam_x0"] is not None and s["lam_g0"] is not None
            args = nlp.fix_leading_idle(s["args"])
            x0 = np.clip(s["x0"], args["lbx"], args["ubx"])
            extra = {"lam_x0": s["lam_x0"], "lam_g0": s["lam_g0"]} if warm else {}
            push = solver.WARM_START_PUSH_FAR if s["far"] else solver.WARM_START_PUSH_NEAR
            max_iter = ipopt.max_iter if warm else ipopt.COLD_MAX_ITER
            # (the solver module's cache of IPOPT functions: recorded solves on one slot layout share theirs)
            fns = {order: solver._ipopt(nlp, warm, max_iter, None, push, order) for order in o.orders}
            times: dict[int, list[float]] = {order: [] for order in o.orders}
            outcome: dict[int, tuple[int, float, str]] = {}
            for _ in range(o.repeats):
                for order, fn in fns.items():
                    t = time.perf_counter()
                    sol = fn(x0=x0, **extra, **args)
                    times[order].append(time.perf_counter() - t)
                    stats = fn.stats()
                    outcome[order] = (int(stats["iter_count"]), float(sol["f"]), str(stats["return_status"]))
            rec = {"braking": b, "run": label, "step": s["step"], "far": s["far"], "warm": warm,
                   **{f"order{order}": {"median_s": statistics.median(times[order]), "iterations": outcome[order][0],
                                        "objective": outcome[order][1], "status": outcome[order][2]}
                      for order in o.orders}}
            records.append(rec)
        log.info("%s %s: T %.1f s, fuel %.3f g, success %s; %d whole-cycle solves: %s", b, label, ep.T, ep.fuel_g,
                 ep.success, len(ipopt.solves), ", ".join(
                     f"order {order} {sum(r[f'order{order}']['median_s'] for r in records[-len(ipopt.solves):]):.2f} s"
                     for order in o.orders))
    first = o.orders[0]
    summary = {}
    for group, keep in (("first_step", lambda r: r["step"] == 0), ("later", lambda r: r["step"] > 0)):
        rows = [r for r in records if keep(r)]
        if not rows:
            continue
        total = {order: sum(r[f"order{order}"]["median_s"] for r in rows) for order in o.orders}
        summary[group] = {
            "solves": len(rows), **{f"order{order}_s": total[order] for order in o.orders},
            **{f"order{order}_over_order{first}": total[order] / total[first] for order in o.orders[1:]},
            # solves where another ordering took 20 % longer than the first's, or ran other iterations
            **{f"order{order}_slower_20pct": sum(r[f"order{order}"]["median_s"] > 1.2 * r[f"order{first}"]["median_s"]
                                                 for r in rows) for order in o.orders[1:]},
            **{f"order{order}_other_iterations": sum(r[f"order{order}"]["iterations"] != r[f"order{first}"]["iterations"]
                                                     for r in rows) for order in o.orders[1:]},
            "max_objective_difference": max(abs(r[f"order{order}"]["objective"] - r[f"order{first}"]["objective"])
                                            / max(1.0, abs(r[f"order{first}"]["objective"]))
                                            for r in rows for order in o.orders[1:]),
        }
        print(f"{group}: {summary_line(summary[group], 4)}")
    write_with_speed(o.out, o, summary, records)
    return summary


if __name__ == "__main__":
    run_script("bench_mumps_ordering", lambda: run(tyro_options(Options)))
