"""Reproduce Section IV of Nezhadali & Eriksson with this project's model: Figs. 6-9 and a comparison table.

The optima come from the Pareto cache of :func:`mpc.benchmark.pareto.pareto_front` (``min_time.json``,
``min_fuel.json`` and the front's points, per braking alternative), polished and completed by
:mod:`mpc.benchmark.optima` (its results cached beside the Pareto cache, in ``<cache>/paper/``). A
second run only reads the cache and redraws.

Outputs (each written atomically through :mod:`wl_env.atomic_io`):

* ``fig6.png``: time-optimal (left) and fuel-optimal (right) controls and states of both alternatives;
* ``fig7.png``: engine operating points of the four optima on the engine map (torque limit lines,
  constant power in grey, constant brake efficiency in blue);
* ``fig8.png``: the Pareto fronts and the extra fuel of TC braking at equal cycle time;
* ``fig9.png``: the fuel-optimal 10 s cycles;
* ``table.md`` / ``results.json``: each quantitative statement of Section IV beside our number.

Our parameters are the specification's re-implementation values, not the paper's (unpublished) ones, so
agreement is expected in the shape of the results, not in every digit.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.train_cli import add_dataclass_args, config_from_args
from mpc.benchmark.optima import fixed_time_optimum, front_optima, lean_time_optimum, polish_front
from mpc.benchmark.pareto import cache_dir
from wl.paper.figures import cycles_figure, engine_map_figure, pareto_figure
from wl.paper.table import FIXED_T, build_table_markdown, compute_results, statement_rows
from wl_env.atomic_io import save_figure, write_atomic, write_json_atomic
from wl_env.cycle import BRAKING_MODES
from wl_env.params import resolve

log = logging.getLogger(__name__)


@dataclass
class PaperOptions:
    """What :func:`reproduce` writes where; each field is a command-line flag of the same name."""

    out: str = field(default="docs/paper", metadata={"help": "output folder for the figures, table.md and results.json"})
    cache: str | None = field(default=None, metadata={
        "help": "cache folder of solved optima (none: $WL_CACHE_DIR or ~/.cache/wheel-loader-gym)"})
    points: int = field(default=8, metadata={"help": "cycle times on each Pareto front, 3 to 100"})

    def __post_init__(self) -> None:
        if not 3 <= self.points <= 100:
            raise ValueError(f"--points must lie in [3, 100], got {self.points}")


def parse_args(argv: list[str] | None = None, description: str | None = None) -> PaperOptions:
    """The options of ``argv`` (default: the command line); exits with a usage message on a bad one."""
    parser = argparse.ArgumentParser(description=description or __doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataclass_args(parser, PaperOptions)
    try:
        return config_from_args(PaperOptions, parser.parse_args(argv))[0]
    except ValueError as exc:
        parser.error(str(exc))


def main(argv: list[str] | None = None, description: str | None = None) -> int:
    """The command line: :func:`parse_args` then :func:`reproduce`; returns the exit code (2: a bad option,
    one line naming it; 130: interrupted, nothing partial written)."""
    options = parse_args(argv, description)
    try:
        reproduce(options)
    except ValueError as exc:
        print(f"reproduce_paper: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        from mpc import interrupt

        print("reproduce_paper: interrupted", file=sys.stderr)
        return interrupt.exit_code() if interrupt.interrupted() else 130  # (SIGTERM: 143, as everywhere else)
    return 0


def reproduce(options: PaperOptions) -> dict[str, Any]:
    """Solve (or read from the cache) every optimum, draw Figs. 6-9, write table.md and results.json into
    ``options.out``; returns the results."""
    from wl_env.atomic_io import check_output_folder

    p = resolve(None)
    out, cache = Path(options.out), options.cache
    if cache is not None:  # (an empty one wrote pareto/ into the working folder; `wl` refuses it)
        check_output_folder(cache, f"--cache {cache}")
    check_output_folder(out, f"--out {out}")  # (before the solves, ~minutes; not when the figures are saved)
    t0 = time.perf_counter()
    log.info(f"parameters {p.fingerprint()}, cache {cache_dir(cache)}, {options.points} points per front -> {out}")
    alts = {b: front_optima(b, options.points, p, cache) for b in BRAKING_MODES}
    for b in BRAKING_MODES:
        alts[b] = polish_front(b, alts[b], p, cache)
        alts[b].lean = lean_time_optimum(b, alts[b].time, p, cache, first_point=alts[b].first_point)
    fixed = {b: fixed_time_optimum(b, FIXED_T, p, cache, alts[b].front.mesh, alts[b].points) for b in BRAKING_MODES}
    times = {b: alts[b].time for b in BRAKING_MODES}
    fuels = {b: alts[b].fuel for b in BRAKING_MODES}
    figs = []
    log.info("drawing fig6 (time- and fuel-optimal transients)")
    fig = cycles_figure([("time-optimal", times), ("fuel-optimal", fuels)], p,
                        "Time-optimal (left) and fuel-optimal (right) cycles; dashed: phase boundaries")
    figs.append(save_figure(fig, out / "fig6.png").name)
    log.info("drawing fig7 (engine operating points)")
    fig = engine_map_figure([("time-optimal cycles", times), ("fuel-optimal cycles", fuels)], p)
    figs.append(save_figure(fig, out / "fig7.png").name)
    log.info("drawing fig8 (Pareto fronts)")
    lean = {b: a.lean for b, a in alts.items() if a.lean is not None}
    cache_fronts = {b: a.front_cache for b, a in alts.items() if a.front_cache is not None}
    fig = pareto_figure({b: a.front for b, a in alts.items()}, fixed, lean, cache_fronts)
    figs.append(save_figure(fig, out / "fig8.png").name)
    log.info(f"drawing fig9 (fuel-optimal {FIXED_T:g} s cycles)")
    fig = cycles_figure([(f"fuel-optimal {FIXED_T:g} s cycle", fixed)], p,
                        f"Minimum fuel at T = {FIXED_T:g} s; dashed: phase boundaries")
    figs.append(save_figure(fig, out / "fig9.png").name)
    log.info("computing the table")
    res = compute_results(alts, fixed, p)
    rows = statement_rows(res)
    res["statements"] = rows
    write_atomic(out / "table.md", build_table_markdown(res, rows, figs))
    write_json_atomic(out / "results.json", res, nan_as_null=True)  # strict JSON, as it always was
    log.info(f"wrote {', '.join(figs)}, table.md, results.json to {out} in {time.perf_counter() - t0:.1f} s")
    return res
