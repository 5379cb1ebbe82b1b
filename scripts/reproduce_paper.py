#!/usr/bin/env python
"""Reproduce Section IV of Nezhadali & Eriksson with this project's model: Figs. 6-9 and a comparison table.

    python scripts/reproduce_paper.py                      # writes docs/paper/{fig6..fig9.png, table.md, results.json}
    python scripts/reproduce_paper.py --out /tmp/paper --cache /tmp/wlcache --points 8

The optima are solved once and cached (the Pareto fronts by mpc.benchmark.pareto, the polished points,
the leanest time-optimal cycles and the 10 s cycles by mpc.benchmark.optima); a second run only reads
the cache and redraws. The analysis, figures and table are wl.paper; this script only drives it.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repo, if not installed

from agents.train_cli import refuse_repeated_argv  # noqa: E402
from wl.paper.run import main  # noqa: E402
from wl_env.logs import PACKAGES, run_script  # noqa: E402


def run() -> None:
    refuse_repeated_argv(sys.argv[1:])  # (wl.paper.run's parser kept the last of an option given twice, without a word)
    sys.exit(main(description=__doc__))


if __name__ == "__main__":
    # the library's progress on stderr; Ctrl-C or SIGTERM anywhere (also what CasADi made of it) exit 130 / 143
    run_script("reproduce_paper", run, PACKAGES)
