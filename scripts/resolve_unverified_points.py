"""Re-solve the front points a shipped suite file left out as unverified, and splice in those that now pass.

    python scripts/resolve_unverified_points.py --suite test                    # report only
    python scripts/resolve_unverified_points.py --suite test --write            # and rewrite the shipped file

A point fails its re-simulation check under one version of the check and may pass a later one (stop 37 fixed
the check's lift loop, CHECK_VERSION 2: the 7 points the `test` fronts left out all failed by their final
height). The shipped file keeps no trajectories to re-check, so each such point is solved again at its cycle
time on its own mesh (``solve_ocp``, template starts, one refinement as the front's solves). It is spliced in
only if it passes the check and lands on the optimum first found (fuel within ``--fuel-tol`` of the recorded
unverified solve's): another local optimum would change the front, not complete it. The front's fuel stays
non-increasing in T (the same cap as :func:`mpc.benchmark.pareto.pareto_front`'s). The file is written
atomically and checked as it is read (:mod:`mpc.benchmark.store`).
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)

from agents.train_cli import tyro_options  # noqa: E402
from mpc.benchmark import store  # noqa: E402
from mpc.benchmark.ocp import OCPError, OCPSettings, solve_ocp  # noqa: E402
from mpc.benchmark.reference import REFERENCE_DIR, SUITE_KIND, check_suite_file  # noqa: E402
from wl_env.logs import run_script  # noqa: E402
from wl_env.scenario import Scenario  # noqa: E402
from wl_env.suites import SUITES  # noqa: E402

log = logging.getLogger("resolve_unverified_points")


@dataclass
class Options:
    suite: str = "test"  # the shipped file mpc/benchmark/references/<suite>.json
    write: bool = False  # rewrite the shipped file with the points that now pass
    fuel_tol: float = 0.005  # relative: the re-solve must land within this of the recorded fuel


def splice(entry: dict[str, Any], point: dict[str, Any]) -> dict[str, Any]:
    """``entry`` with ``point`` (verified) in place of the unverified point at the same cycle time, its front
    (T, fuel_g) rebuilt from every verified point, fuel capped to be non-increasing in T."""
    points = [point if abs(p["T"] - point["T"]) <= 1e-9 and not p.get("verified") else p for p in entry["points"]]
    good = sorted((p for p in points if p.get("verified") and p.get("fuel_g") is not None), key=lambda p: p["T"])
    return {**entry, "points": points, "T": [float(p["T"]) for p in good],
            "fuel_g": np.minimum.accumulate([p["fuel_g"] for p in good]).tolist()}


def shipped_suite_file(suite: str) -> Path:
    """The shipped file of the suite so named, ``mpc/benchmark/references/<suite>.json``; ValueError naming --suite
    unless it is a suite's name with a shipped file (``--suite ../../x --write`` read and rewrote ``x.json`` outside
    the references, any file that passed the suite file's check)."""
    shipped = sorted(p.stem for p in REFERENCE_DIR.glob("*.json") if p.stem in SUITES)
    if suite not in shipped:
        raise ValueError(f"--suite must name a suite with a shipped file ({', '.join(shipped)}), got {suite!r}")
    return REFERENCE_DIR / f"{suite}.json"


def run(o: Options) -> list[dict[str, Any]]:
    if not 0.0 < o.fuel_tol <= 0.1:
        raise ValueError(f"--fuel-tol must lie in (0, 0.1], got {o.fuel_tol}")
    path = shipped_suite_file(o.suite)
    data = store.read_entry(path, SUITE_KIND, check_suite_file)
    entries, outcomes = data["entries"], []
    for key, e in sorted(entries.items()):
        scenario = Scenario.from_dict(e["scenario"])
        for p in [p for p in e["points"] if not p.get("verified") and p.get("fuel_g") is not None]:
            t0 = time.perf_counter()
            out: dict[str, Any] = {"entry": key, "T": p["T"], "recorded_fuel_g": p["fuel_g"]}
            try:
                r = solve_ocp(scenario=scenario, objective="fuel_at_time", T=float(p["T"]),
                              settings=OCPSettings(intervals=tuple(p["mesh"])), max_refinements=1)
                v = r.verification
                out.update(fuel_g=r.fuel_g, passed=bool(v.get("passed")), status=r.status,
                           final_height_error_m=v.get("final_height_error_m"))
                same = abs(r.fuel_g / p["fuel_g"] - 1.0) <= o.fuel_tol
                out["spliced"] = out["passed"] and same
                if out["spliced"]:
                    entries[key] = splice(entries[key], {
                        "T": r.T, "fuel_g": r.fuel_g, "mesh": r.mesh, "verified": True,
                        "final_position_error_m": v.get("final_position_error_m"),
                        "final_height_error_m": v.get("final_height_error_m"), "max_violation": v.get("max_violation")})
            except OCPError as exc:
                out.update(passed=False, spliced=False, status=str(exc))
            out["solve_s"] = time.perf_counter() - t0
            log.info("%s at T = %.3f s: %s", key, p["T"], {k: v for k, v in out.items() if k not in ("entry", "T")})
            outcomes.append(out)
    n = sum(o_["spliced"] for o_ in outcomes)
    print(f"{o.suite}: {len(outcomes)} unverified point(s); {n} re-solved, passed and on the recorded optimum")
    for o_ in outcomes:
        fuel = f"{o_['fuel_g']:.3f}" if "fuel_g" in o_ else "-"
        print(f"  {o_['entry']} T {o_['T']:.3f} s: fuel {fuel} g (recorded {o_['recorded_fuel_g']:.3f}), "
              f"check {'passed' if o_['passed'] else 'failed'}, {'spliced' if o_['spliced'] else 'left out'}"
              f" ({o_['solve_s']:.0f} s)")
    if o.write and n:
        store.write_entry(path, SUITE_KIND, data, check_suite_file)
        print(f"rewrote {path}")
    return outcomes


if __name__ == "__main__":
    run_script("resolve_unverified_points", lambda: run(tyro_options(Options)))
