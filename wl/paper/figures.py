"""Figs. 6-9 of the paper from our optima: cycle transients, engine operating points, Pareto fronts.

Each figure is a :class:`matplotlib.figure.Figure` (no pyplot state); :func:`wl_env.atomic_io.save_figure` writes it
through :func:`wl_env.atomic_io.atomic_path`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from mpc.benchmark.ocp import OCPResult
from mpc.benchmark.optima import LEAN_FACTOR
from mpc.benchmark.pareto import ParetoFront, pchip
from wl.paper.analysis import RAD_S_TO_RPM, cycle_signals, extra_fuel_points, phase_boundaries
from wl_env.params import LoaderParams
from wl_env.physics import engine

DPI = 150
COLORS = {"service": "tab:blue", "tc": "tab:red"}
LABELS = {"service": "service brakes", "tc": "TC braking"}
MARKERS = {"service": "o", "tc": "^"}


PANELS = (
    ("U_mf", "$U_{mf}$ (mg/cycle)"),
    ("U_ab", "$U_{ab}$ (m/s²)"),
    ("U_b", "$U_b$ (kN m)"),
    ("omega", "ω (rpm)"),
    ("V", "V (m/s)"),
    ("H", "H (m)"),
    ("V_b", "$V_b$ (m/s)"),
    ("phi", "φ (–)"),
)
MODE_BANDS = (("I", -math.inf, 0.0, "#f4cccc"), ("II", 0.0, 1.0, "#d9ead3"), ("III", 1.0, math.inf, "#fff2cc"))


def draw_cycle_column(axes: Sequence[Any], results: Mapping[str, OCPResult], params: LoaderParams,
                      title: str | None = None, ylabels: bool = True) -> None:
    """The eight panels of one column of Fig. 6 (controls as steps, states at the mesh points, phi with
    the TC mode bands), one colour per braking alternative, dashed phase boundaries in that colour."""
    phi_lo, phi_hi = -0.5, 1.5
    t_end = 0.0
    for braking, r in results.items():
        col = COLORS.get(braking, "k")
        sig = cycle_signals(r, params)
        t, x, u = sig["t"], sig["states"], sig["controls"]
        t_end = max(t_end, float(t[-1]))
        label = f"{LABELS.get(braking, braking)}: T = {r.T:.2f} s, {r.fuel_g:.1f} g"
        axes[0].stairs(u[:, 0], t, color=col, baseline=None, lw=1.4, label=label)
        axes[1].stairs(u[:, 1], t, color=col, baseline=None, lw=1.4)
        axes[2].stairs(u[:, 2] / 1000.0, t, color=col, baseline=None, lw=1.4)
        axes[3].plot(t, x[:, 0] * RAD_S_TO_RPM, color=col, lw=1.4)
        axes[4].plot(t, x[:, 1], color=col, lw=1.4)
        axes[5].plot(t, x[:, 2], color=col, lw=1.4)
        axes[6].plot(t, x[:, 3], color=col, lw=1.4)
        for seg in sig["segments"]:
            if seg["gear"] == 0:
                continue
            axes[7].plot(seg["t"], seg["phi"], color=col, lw=1.4)
            phi_lo = min(phi_lo, float(np.nanmin(seg["phi"])))
            phi_hi = max(phi_hi, float(np.nanmax(seg["phi"])))
        for tb in phase_boundaries(r):
            for ax in axes:
                ax.axvline(tb, color=col, ls="--", lw=0.9, alpha=0.7)
    lo, hi = phi_lo - 0.15 * (phi_hi - phi_lo), phi_hi + 0.15 * (phi_hi - phi_lo)
    for name, a, b, colour in MODE_BANDS:
        a, b = max(a, lo), min(b, hi)
        if b > a:
            axes[7].axhspan(a, b, color=colour, zorder=0, lw=0)
            axes[7].text(1.005, (a + b) / 2, name, transform=axes[7].get_yaxis_transform(), va="center",
                         ha="left", fontsize=8, fontweight="bold", color="0.3")
    axes[7].set_ylim(lo, hi)
    axes[7].text(0.01, 0.04, "mode I: φ<0, II: 0–1, III: φ>1; not drawn in neutral", transform=axes[7].transAxes,
                 fontsize=7, color="0.3")
    for ax, (_, lab) in zip(axes, PANELS, strict=True):
        ax.set_xlim(0.0, t_end)
        ax.grid(True, lw=0.4, alpha=0.5)
        if ylabels:
            ax.set_ylabel(lab, fontsize=9)
        ax.tick_params(labelsize=8)
    for ax in axes[:-1]:
        ax.tick_params(labelbottom=False)
    axes[-1].set_xlabel("time (s)", fontsize=9)
    # legend above the column, under the column's title, so it hides no curve
    axes[0].legend(title=title, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, fontsize=8,
                   title_fontsize=10, frameon=False, borderaxespad=0.2)


def cycles_figure(columns: Sequence[tuple[str, Mapping[str, OCPResult]]], params: LoaderParams,
                  suptitle: str = "") -> Figure:
    """Fig. 6 / Fig. 9 layout: one column of eight panels per (title, {braking: result})."""
    n = len(columns)
    fig = Figure(figsize=(6.2 * n + 0.6, 15.5), layout="constrained")
    axes = fig.subplots(len(PANELS), n, squeeze=False)
    for j, (title, results) in enumerate(columns):
        draw_cycle_column(axes[:, j], results, params, title=title, ylabels=True)
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    return fig


def engine_map_grid(params: LoaderParams, n_rpm: int = 160, n_torque: int = 160,
                    torque_range: tuple[float, float] = (20.0, 2400.0)) -> dict[str, np.ndarray]:
    """Brake power (kW) and brake efficiency P / (m_f q_hv) of our engine model on an (N, T) grid.

    Points above the torque limit or needing more than U_mf,max are NaN.
    """
    p = params
    N = np.linspace(p.omega_min * RAD_S_TO_RPM, p.omega_max * RAD_S_TO_RPM, n_rpm)
    T = np.linspace(*torque_range, n_torque)
    NN, TT = np.meshgrid(N, T)
    omega = NN / RAD_S_TO_RPM
    u_mf = (TT + engine.friction_torque(omega, p)) / p.T_ig_per_mg
    fuel = engine.fuel_mass_rate(omega, u_mf, p)  # kg/s
    power = TT * omega  # W
    eff = power / (fuel * p.q_hv)
    feasible = (TT <= engine.max_engine_torque(omega, p)) & (u_mf <= p.U_mf_max)
    return {"N": NN, "T": TT, "P_kW": np.where(feasible, power / 1000.0, np.nan),
            "eff": np.where(feasible, eff, np.nan)}


def operating_points(result: OCPResult, params: LoaderParams) -> tuple[np.ndarray, np.ndarray]:
    """(N rpm, T_ice N m) at every sample with the control applied there."""
    sig = cycle_signals(result, params)
    N = np.concatenate([s["N_rpm"][:-1] for s in sig["segments"]] + [sig["segments"][-1]["N_rpm"][-1:]])
    T = np.concatenate([s["T_ice"][:-1] for s in sig["segments"]] + [sig["segments"][-1]["T_ice"][-1:]])
    return N, T


def engine_map_figure(panels: Sequence[tuple[str, Mapping[str, OCPResult]]], params: LoaderParams) -> Figure:
    """Fig. 7: operating points over the torque-limit lines, constant power (grey) and efficiency (blue)."""
    p = params
    grid = engine_map_grid(p)
    N_line = np.linspace(p.omega_min * RAD_S_TO_RPM, p.omega_max * RAD_S_TO_RPM, 300)
    lines = [a + b * N_line for a, b in p.T_max_lines]
    envelope = np.minimum.reduce(lines)
    t_lo = min(min(float(np.min(operating_points(r, p)[1])) for r in res.values()) for _, res in panels)
    y_lo = min(0.0, t_lo) - 100.0
    y_hi = float(envelope.max()) * 1.12
    fig = Figure(figsize=(6.3 * len(panels), 5.6), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    eff_levels = [0.25, 0.30, 0.34, 0.37, 0.39, 0.40, 0.41, 0.42]
    p_levels = [25, 50, 100, 150, 200, 250]
    for ax, (title, results) in zip(axes, panels, strict=True):
        cp = ax.contour(grid["N"], grid["T"], grid["P_kW"], levels=p_levels, colors="0.55", linewidths=0.8)
        ax.clabel(cp, fmt="%d kW", fontsize=7)
        ce = ax.contour(grid["N"], grid["T"], grid["eff"], levels=eff_levels, colors="tab:blue", linewidths=0.8,
                        linestyles="-", alpha=0.8)
        ax.clabel(ce, fmt=lambda v: f"{100 * v:.0f} %", fontsize=7)
        for ln in lines:
            ax.plot(N_line, ln, color="k", lw=0.8, ls=":", alpha=0.7)
        ax.plot(N_line, envelope, color="k", lw=2.0)
        ax.axhline(0.0, color="0.3", lw=0.6)
        for braking, r in results.items():
            N, T = operating_points(r, p)
            ax.plot(N, T, color=COLORS[braking], lw=0.5, alpha=0.5)
            ax.scatter(N, T, s=14, color=COLORS[braking], marker=MARKERS[braking], edgecolors="none", zorder=3,
                       alpha=0.85)
        ax.set_xlim(N_line[0] - 20, N_line[-1] + 20)
        ax.set_ylim(y_lo, y_hi)
        ax.set_xlabel("engine speed N (rpm)")
        ax.set_ylabel("engine torque $T_{ice}$ (N m)")
        ax.set_title(title, fontsize=10)
        ax.grid(True, lw=0.3, alpha=0.4)
        handles = [Line2D([], [], color=COLORS[b], marker=MARKERS[b], ls="", label=LABELS[b]) for b in results]
        handles += [Line2D([], [], color="k", lw=2, label="torque limit (min of 3 lines)"),
                    Line2D([], [], color="k", lw=0.8, ls=":", label="the 3 lines $a_i + b_i N$"),
                    Line2D([], [], color="0.55", lw=0.8, label="constant power (kW)"),
                    Line2D([], [], color="tab:blue", lw=0.8, label="constant brake efficiency")]
        ax.legend(handles=handles, fontsize=7, loc="upper right", framealpha=0.9)
    return fig



def pareto_figure(fronts: Mapping[str, ParetoFront], fixed: Mapping[str, OCPResult] | None = None,
                  lean: Mapping[str, OCPResult] | None = None,
                  cache_fronts: Mapping[str, ParetoFront] | None = None) -> Figure:
    """Fig. 8: fuel against cycle time for both alternatives (top) and TC braking's extra fuel (bottom)."""
    fig = Figure(figsize=(7.5, 8.0), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    for b, fr in fronts.items():
        T, F = np.asarray(fr.T), np.asarray(fr.fuel_g)
        Td = np.linspace(T[0], T[-1], 300)
        ax1.plot(Td, [pchip(T, F, v) for v in Td], color=COLORS[b], lw=1.3)
        ax1.plot(T, F, MARKERS[b], color=COLORS[b], ms=6, label=f"{LABELS[b]} ({len(T)} optima)")
        if lean and b in lean:
            ax1.plot([lean[b].T], [lean[b].fuel_g], MARKERS[b], color=COLORS[b], ms=9, mfc="none", mew=1.4,
                     label=f"{LABELS[b]}: leanest at {LEAN_FACTOR:g} × T_min")
        if fixed and b in fixed:
            ax1.plot([fixed[b].T], [fixed[b].fuel_g], "*", color=COLORS[b], ms=12, mec="k", mew=0.6,
                     label=f"{LABELS[b]}: solved at {fixed[b].T:g} s")
    labelled = False
    for b, fr0 in (cache_fronts or {}).items():
        fr = fronts.get(b)
        bad = [(T, f0) for T, f0, f in zip(fr0.T, fr0.fuel_g, fr.fuel_g if fr else fr0.fuel_g, strict=True) if f < f0 * (1 - 1e-6)]
        if bad:
            ax1.plot([q[0] for q in bad], [q[1] for q in bad], "x", color="0.35", ms=8, mew=1.5,
                     label=None if labelled else "Pareto cache point bettered by a re-solve")
            labelled = True
    ax1.set_ylabel("fuel per cycle (g)")
    ax1.set_title("Pareto fronts: minimum fuel at fixed cycle time", fontsize=10)
    ax1.grid(True, lw=0.4, alpha=0.5)
    ax1.legend(fontsize=8)
    if "service" in fronts and "tc" in fronts:
        pts = extra_fuel_points(fronts["service"], fronts["tc"])
        s, c = fronts["service"], fronts["tc"]
        lo, hi = max(s.T_min, c.T_min), min(s.T_fuel_opt, c.T_fuel_opt)
        Td = np.linspace(lo, hi - 1e-6, 300)
        dense = [100.0 * (c.fuel_at(v) - s.fuel_at(v)) / s.fuel_at(v) for v in Td]
        ax2.plot(Td, dense, color="0.5", lw=1.0, ls="--", label="both fronts interpolated")
        if pts:
            ax2.plot([q[0] for q in pts], [q[3] for q in pts], "o-", color="tab:purple", ms=6,
                     label="at the service front's cycle times")
        ax2.axhline(0.0, color="k", lw=0.6)
    ax2.set_xlabel("cycle time T (s)")
    ax2.set_ylabel("extra fuel with TC braking (%)")
    ax2.grid(True, lw=0.4, alpha=0.5)
    ax2.legend(fontsize=8)
    return fig

