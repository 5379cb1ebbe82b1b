"""The paper's reproduction (wl.paper, mpc.benchmark.optima, scripts/reproduce_paper.py): figure and table
helpers on a small case (two minimum-time optima).

The full reproduction (Pareto fronts, polishing, 10 s cycles) is marked slow.
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpc.benchmark.ocp import solve_ocp
from mpc.benchmark.optima import FrontOptima
from mpc.benchmark.pareto import ParetoFront
from wl.paper.analysis import (
    cycle_facts,
    cycle_signals,
    extra_fuel_points,
    mode_summary,
    phase_boundaries,
    pressure_summary,
    tc_mode,
)
from wl.paper.figures import (
    cycles_figure,
    engine_map_figure,
    engine_map_grid,
    operating_points,
    pareto_figure,
)
from wl.paper.run import main, parse_args
from wl.paper.table import build_table_markdown, compute_results, fmt_num, fmt_pct, markdown_table, statement_rows
from wl_env.atomic_io import save_figure, write_atomic, write_json_atomic
from wl_env.params import DEFAULT_PARAMS

ROOT = Path(__file__).resolve().parents[1]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def optima():
    # no re-simulation: the helpers only need the trajectories
    return {b: solve_ocp(b, "time", verify=False) for b in ("service", "tc")}


def _front(braking, T, fuel):
    return ParetoFront(braking=braking, T=T, fuel_g=fuel, params_fingerprint=DEFAULT_PARAMS.fingerprint(),
                       T_min=T[0], T_fuel_opt=T[-1], fuel_min_g=fuel[-1], mesh=[20, 12, 20, 12])


FRONTS = {
    "service": _front("service", [8.0, 10.0, 14.0, 20.0], [90.0, 60.0, 50.0, 47.0]),
    "tc": _front("tc", [8.2, 10.2, 14.2, 20.4], [88.0, 62.0, 51.5, 47.5]),
}


def _assert_png(path: Path):
    assert path.exists() and path.stat().st_size > 10_000
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert not [p for p in path.parent.iterdir() if ".tmp" in p.name]  # atomic write left nothing behind


def test_cycle_figure_from_a_minimum_time_optimum(optima, tmp_path):
    fig = cycles_figure([("time-optimal", optima), ("again", {"service": optima["service"]})], DEFAULT_PARAMS,
                        "test")
    axes = fig.get_axes()
    assert len(axes) == 16  # eight panels per column
    assert axes[0].get_legend() is not None
    out = save_figure(fig, tmp_path / "sub" / "fig6.png")
    _assert_png(out)


def test_signals_modes_and_pressure(optima):
    p = DEFAULT_PARAMS
    for b, r in optima.items():
        sig = cycle_signals(r, p)
        assert [s["phase"] for s in sig["segments"]] == [1, 2, 3, 4]
        assert sig["segments"][-1]["i1"] == len(r.t) - 1
        m = mode_summary(r, p)
        assert sum(m["counts"].values()) == len(r.controls)  # every control interval has one mode
        assert m["counts"]["N"] == r.mesh[3] + (r.mesh[1] if b == "service" else 0)  # neutral phases
        pr = pressure_summary(r, p)
        assert 0.0 < pr["max_ratio"] < 1.5 and 0.0 <= pr["t_at_max"] <= r.T
        assert phase_boundaries(r) == pytest.approx(np.cumsum(r.phase_durations)[:3])
        facts = cycle_facts(r, p)
        assert facts["reversing_leg_s"] + facts["forwarding_leg_s"] == pytest.approx(r.T)
    # converter braking is mode I, and the time-optimal TC cycle reaches mode III before reversing
    assert optima["tc"].braking == "tc" and mode_summary(optima["tc"], p)["counts"]["I"] > 0


def test_tc_mode_classification():
    phi = np.array([-0.5, -1e-4, 0.0, 0.5, 1.0, 1.0005, 1.2])
    assert list(tc_mode(phi, 60.0)) == ["I", "II", "II", "II", "II", "II", "III"]
    assert list(tc_mode(phi, 0.0)) == ["N"] * len(phi)


def test_engine_map_grid_and_figure(optima, tmp_path):
    p = DEFAULT_PARAMS
    g = engine_map_grid(p, n_rpm=40, n_torque=40)
    eff = g["eff"][np.isfinite(g["eff"])]
    assert eff.size and 0.0 < eff.min() and eff.max() < p.eta_ig  # brake efficiency below indicated
    assert np.nanmax(g["P_kW"]) == pytest.approx(278.0, rel=0.05)  # the spec's peak power
    N, T = operating_points(optima["service"], p)
    assert len(N) == len(T) == len(optima["service"].t)
    _assert_png(save_figure(engine_map_figure([("time-optimal", optima)], p), tmp_path / "fig7.png"))


def test_pareto_figure_and_extra_fuel(optima, tmp_path):
    pts = extra_fuel_points(FRONTS["service"], FRONTS["tc"])
    assert [q[0] for q in pts] == [10.0, 14.0, 20.0]  # 8 s lies below the TC front's T_min
    for T, f_s, f_tc, extra in pts:
        assert f_tc == pytest.approx(FRONTS["tc"].fuel_at(T))
        assert extra == pytest.approx(100.0 * (f_tc - f_s) / f_s)
    cache = {"service": _front("service", [8.0, 10.0, 14.0, 20.0], [90.0, 61.0, 50.0, 47.0])}
    fig = pareto_figure(FRONTS, fixed={"service": optima["service"]}, lean=None, cache_fronts=cache)
    _assert_png(save_figure(fig, tmp_path / "fig8.png"))


def test_number_formatting():
    assert fmt_pct(2.634) == "+2.63 %"
    assert fmt_pct(-35.0, 1) == "-35.0 %"
    assert fmt_pct(2.8, 1, signed=False) == "2.8 %"
    assert fmt_num(8.16657, 3, "s") == "8.167 s"
    assert fmt_num(None) == "–" and fmt_num(math.nan) == "–" and fmt_pct(math.inf) == "–"
    md = markdown_table(["a", "b|c"], [[1, "x|y"]])
    assert md.splitlines() == ["| a | b\\|c |", "|---|---|", "| 1 | x\\|y |"]


def test_table_and_results_from_a_small_case(optima, tmp_path):
    p = DEFAULT_PARAMS
    alts = {b: FrontOptima(front=FRONTS[b], time=r, fuel=r, points=[], lean=r) for b, r in optima.items()}
    res = compute_results(alts, dict(optima), p)
    S = res["summary"]["service"]
    assert S["T_min_s"] == 8.0 and S["fuel_min_g"] == 47.0
    assert res["dT_time_pct"] == pytest.approx(2.5)  # 8.0 -> 8.2 s
    assert res["dT_fuel_pct"] == pytest.approx(2.0)  # 20.0 -> 20.4 s
    assert S["half_fuel_opt_extra_fuel_pct"] == pytest.approx(100.0 * (60.0 / 47.0 - 1.0))
    rows = statement_rows(res)
    ids = [r["id"] for r in rows]
    assert ids[:5] == ["dT_time", "dT_fuel", "half_fuel_opt", "plus10_time", "fuel_10s"]
    assert {"pressure", "tc_modes", "smoothing"} <= set(ids)
    assert all(r["note"] for r in rows)
    text = build_table_markdown(res, rows, ["fig6.png"])
    assert "| TC braking lengthens the time-optimal cycle by 1.58 % | +1.58 % | +2.50 % (8.000 → 8.200 s) |" in text
    assert "| minimum cycle time T_min | 8.000 s | 8.200 s |" in text
    assert "![fig6.png](fig6.png)" in text
    res["statements"] = rows
    write_atomic(tmp_path / "table.md", text)
    data = json.loads(write_json_atomic(tmp_path / "results.json", res, nan_as_null=True).read_text())
    assert data["dT_time_pct"] == pytest.approx(2.5)
    assert data["statements"][0]["id"] == "dT_time"


def test_arguments():
    args = parse_args([])
    assert args.out == "docs/paper" and args.points == 8 and args.cache is None
    with pytest.raises(SystemExit):
        parse_args(["--points", "2"])


def test_script_help_runs_as_a_subprocess():
    done = subprocess.run([sys.executable, "scripts/reproduce_paper.py", "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: reproduce_paper.py") and "--points" in done.stdout


@pytest.mark.slow
def test_full_reproduction_small_fronts(tmp_path):
    out, cache = tmp_path / "paper", tmp_path / "cache"
    assert main(["--out", str(out), "--cache", str(cache), "--points", "3"]) == 0
    for name in ("fig6.png", "fig7.png", "fig8.png", "fig9.png"):
        _assert_png(out / name)
    data = json.loads((out / "results.json").read_text())
    assert data["summary"]["service"]["T_min_s"] < data["summary"]["tc"]["T_min_s"]
    assert (out / "table.md").read_text().startswith("# Nezhadali & Eriksson")
