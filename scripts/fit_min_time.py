"""Fit the minimum-cycle-time model (:mod:`wl_env.suites.min_time`) on ``train`` draws, per braking alternative.

    python scripts/fit_min_time.py --draws 80

Solves the minimum-time OCP of ``--draws`` scenarios of the ``train`` sampler per braking alternative
(seed ``--seed`` of its stream; one worker process per braking alternative; each solve cached, so a
killed run resumes), fits T_min over the quadratic terms of the scenario features by least squares,
measures the fit's leave-one-out error and its error on the shipped ``test`` optima (never fitted on),
and writes ``wl_env/suites/min_time_model.json`` atomically with the coefficients and that provenance.
"""

from __future__ import annotations

import logging
import platform
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)

from agents.train_cli import tyro_options  # noqa: E402
from wl_env.atomic_io import write_json_atomic  # noqa: E402
from wl_env.logs import PACKAGES, run_script  # noqa: E402

log = logging.getLogger("fit_min_time")


@dataclass
class Options:
    draws: int = 80  # train scenarios per braking alternative
    seed: int = 7  # the train stream's seed (the suite's own draws use seed 0)
    cache: str | None = None  # the optima cache (default $WL_CACHE_DIR or ~/.cache/wheel-loader-gym)
    out: str = "wl_env/suites/min_time_model.json"


def solve_min_times(braking: str, draws: int, seed: int, cache: str | None) -> list[tuple[list[float], float]]:
    """(features, T_min) of ``draws`` train scenarios (a worker's job)."""
    from mpc.benchmark.ocp import OCPError
    from mpc.benchmark.reference import direct_min_time
    from wl_env.suites import TRAIN_STREAM, draw, stream

    rng = stream(TRAIN_STREAM, seed)
    out = []
    for i in range(draws):
        sc = draw(rng, braking)
        try:
            T = direct_min_time(braking, sc.params(), cache).T
        except OCPError as exc:  # left out, and said
            log.warning(f"[{braking}] draw {i} ({sc.label()}): no minimum-time optimum: {exc}")
            continue
        out.append((sc.features().tolist(), float(T)))
        log.info(f"[{braking}] {i + 1}/{draws}: T_min {T:.3f} s")
    return out


def loo_errors(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Leave-one-out relative errors of the least-squares fit (the hat-matrix identity)."""
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    H = X @ np.linalg.pinv(X)
    return (y - X @ coef) / (1.0 - np.diag(H)) / y


def main(o: Options) -> None:
    from mpc.benchmark.reference import shipped_fronts
    from mpc.workers import run_in_workers
    from wl.cli import _out_file  # (the command line's check of an output file: before the solves, not after)
    from wl_env.suites import load_suite
    from wl_env.suites.min_time import N_FEATURES, quadratic_terms

    n_terms = quadratic_terms([[0.0] * N_FEATURES]).shape[1]
    if not 2 * n_terms <= o.draws <= 10_000:
        raise ValueError(f"--draws must be an integer in [{2 * n_terms}, 10000] (twice the model's {n_terms} terms), "
                         f"got {o.draws}")
    if not 0 <= o.seed < 2**32:  # (numpy's "expected non-negative integer" named no flag)
        raise ValueError(f"--seed must be an integer in [0, 2**32), got {o.seed}")
    if o.cache is not None:  # (--cache X --out X: every solve, then "X is a folder"; the cache checked before them)
        from wl_env.atomic_io import check_output_folder, refuse_one_path_twice

        refuse_one_path_twice([("--cache", o.cache), ("--out", o.out)])
    _out_file(o.out)
    if o.cache is not None:
        check_output_folder(o.cache, f"--cache {o.cache}")
    jobs = {b: ("fit_min_time:solve_min_times", (b, o.draws, o.seed, o.cache)) for b in ("service", "tc")}
    results = run_in_workers(jobs, log_level=logging.INFO)
    shipped = shipped_fronts()
    model = {"description": "T_min (s) ~ quadratic terms of Scenario.features(), least squares per braking",
             "command": f"python scripts/fit_min_time.py --draws {o.draws} --seed {o.seed}",
             "python": platform.python_version(), "braking": {}}
    for b, rows in results.items():
        X = quadratic_terms([f for f, _ in rows])
        y = np.array([T for _, T in rows])
        if len(rows) < 2 * X.shape[1]:
            raise SystemExit(f"[{b}] {len(rows)} solved draws cannot fit {X.shape[1]} terms well: give --draws >= "
                             f"{2 * X.shape[1]}")
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        loo = np.abs(loo_errors(X, y))
        test = []
        for sc in load_suite("test").of(b):
            front = shipped.get(f"{b}_{sc.params().fingerprint()}")
            if front is not None:
                test.append(abs(float((quadratic_terms(sc.features()) @ coef)[0]) / front.T_min - 1.0))
        test = np.array(test)
        model["braking"][b] = {
            "coefficients": coef.tolist(), "n_fit": len(rows), "T_min_range_s": [float(y.min()), float(y.max())],
            "loo_rel_error_median": float(np.median(loo)), "loo_rel_error_max": float(loo.max()),
            "test_rel_error_median": float(np.median(test)) if len(test) else None,
            "test_rel_error_max": float(test.max()) if len(test) else None, "n_test": len(test)}
        log.info(f"[{b}] {len(rows)} fitted; leave-one-out error median {100 * np.median(loo):.2f} %, max "
                 f"{100 * loo.max():.2f} %; on {len(test)} test optima median {100 * np.median(test):.2f} %, "
                 f"max {100 * test.max():.2f} %")
    write_json_atomic(o.out, model)
    print(f"-> {o.out}")


if __name__ == "__main__":
    # bad options one line, exit 2; Ctrl-C or SIGTERM during the solves exit 130 / 143 (was a traceback)
    run_script("fit_min_time", lambda: main(tyro_options(Options)), PACKAGES)
