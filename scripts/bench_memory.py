"""Peak memory of the main job: ``wl run`` with an empty optimum cache, its whole process tree.

Runs ``wl run --out OUT --cache CACHE`` (fresh temporary folders unless given) and samples, every
``--period`` seconds, the resident memory (VmRSS) of the ``wl`` process and all its descendants (the
worker processes each controller runs in), summed. Prints the peak of that sum, the largest single
process's peak (``getrusage(RUSAGE_CHILDREN)``: exact, not sampled), the wall time and the exit code.
Linux only (/proc). Issue #13 asks <= 600 MB.

Usage::

    python scripts/bench_memory.py [--out DIR] [--cache DIR] [--period 0.5] [--json PATH]
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from wl_env.atomic_io import write_json_atomic  # noqa: E402


def tree(pid: int) -> list[int]:
    """pid and every descendant of it (from /proc/<pid>/task/<tid>/children)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                todo += [int(c) for c in Path(f"/proc/{p}/task/{task}/children").read_text().split()]
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
    return out


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError):
        pass
    return 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="wl run's output folder (default: a temporary one)")
    ap.add_argument("--cache", help="the optimum cache (default: an empty temporary one)")
    ap.add_argument("--period", type=float, default=0.5, help="seconds between samples")
    ap.add_argument("--json", metavar="PATH", help="also write the figures")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    from wl_env.atomic_io import check_output_option

    check_output_option(ap, args.json, "--json")  # (now: it was written only at the end, after the work)
    if not (math.isfinite(args.period) and 0.01 <= args.period <= 60):  # (nan failed after wl run had started)
        ap.error(f"--period must be a number of seconds in [0.01, 60], got {args.period:g}")
    if not Path("/proc/self/status").exists():
        sys.exit("bench_memory needs Linux's /proc")
    with tempfile.TemporaryDirectory(prefix="wl_bench_memory_") as tmp:
        out, cache = args.out or f"{tmp}/results", args.cache or f"{tmp}/cache"
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "wl", "run", "--out", out, "--cache", cache])
        peak, peak_at = 0.0, 0.0
        try:
            while proc.poll() is None:
                total = sum(rss_mb(p) for p in tree(proc.pid))
                if total > peak:
                    peak, peak_at = total, time.perf_counter() - t0
                time.sleep(args.period)
        except KeyboardInterrupt:
            proc.wait()
            sys.exit(130)
        except BaseException:  # (the run is this script's child: it does not outlive a failure here)
            proc.kill()
            proc.wait()
            raise
        wall = time.perf_counter() - t0
    if proc.returncode != 0:  # (a failed run's figures were written as a measurement, exit 0)
        sys.exit(f"bench_memory: wl run failed (exit {proc.returncode}): no figures")
    largest = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0  # KiB on Linux
    figures = {"exit_code": proc.returncode, "wall_s": round(wall, 1), "peak_tree_mb": round(peak),
               "peak_at_s": round(peak_at), "largest_process_mb": round(largest), "period_s": args.period}
    print(f"wl run: exit {proc.returncode}, {wall:.0f} s; peak of the process tree {peak:.0f} MB (at {peak_at:.0f} s, "
          f"sampled every {args.period:g} s); largest single process {largest:.0f} MB")
    if args.json:
        write_json_atomic(Path(args.json), figures)


if __name__ == "__main__":
    main()
