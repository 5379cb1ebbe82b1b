"""Side-view rendering of ``WheelLoader-v1``: RGB frames (matplotlib, Agg) and a window for ``"human"``.

``render_frame(env)`` draws the loader at its position ``s`` on the track between the reversing point
(s = -6.6 m) and the pile/truck (s = 0), with the boom and bucket at the bucket height H, and a panel
with time, phase, gear, speed, engine speed, bucket height, fuel and braking mode. Each environment
gets its own off-screen figure (built on first use, kept in a weak-keyed cache, freed with the env);
later frames only move artists, so no figure is created per frame and no display is needed.

``show(frame, handle)`` puts a frame in a matplotlib window (``render_mode="human"``); without a display
it warns once and keeps drawing into an off-screen figure instead.

World coordinates are metres: x = s + (offset on the machine), the loader faces +x (forward), y = height.
The loader's reference point (the position s) is the boom pivot, at height ``params.G``. The pile and the
truck both sit at the end of the track (the short loading cycle's V-pattern seen from the side): the one
the current phase drives to is drawn solid, the other faded.
"""

from __future__ import annotations

import math
import os
import time
import warnings
import weakref
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from wl_env.atomic_io import atomic_path
from wl_env.params import is_finite, is_integer, plain, shown

WIDTH, HEIGHT = 600, 400  # pixels of a frame
_DPI = 100

# Colours
_SKY = "#eef4fa"
_GROUND = "#b9a88f"
_GROUND_LINE = "#6b5a45"
_BODY = "#f2b705"
_BODY_DARK = "#c98f00"
_OUTLINE = "#3a3020"
_TYRE = "#262626"
_HUB = "#9a9a9a"
_GLASS = "#9cc7e6"
_LOAD = "#8b6b4a"
_PILE = "#9c7b57"
_TRUCK = "#4f79a6"
_TRUCK_DARK = "#2f4f73"
_REV = "#c0392b"
_TARGET = "#1e8449"

# Shapes in the loader's frame: x relative to the boom pivot (the position s), y absolute height (m).
_FRONT_FRAME = [(-1.8, 0.95), (0.15, 0.95), (0.35, 1.6), (0.3, 2.65), (-0.45, 2.65), (-0.95, 1.95), (-1.8, 1.95)]
_REAR_FRAME = [(-2.15, 0.95), (-5.55, 0.95), (-6.0, 1.3), (-6.0, 2.35), (-5.75, 2.8), (-3.45, 2.8), (-3.45, 2.55),
               (-2.15, 2.55)]
_JOINT = [(-2.25, 1.25), (-1.7, 1.25), (-1.7, 1.75), (-2.25, 1.75)]
_CAB = [(-3.45, 2.55), (-1.95, 2.55), (-1.85, 3.95), (-3.4, 4.05)]
_WINDOW = [(-3.2, 2.95), (-2.1, 2.95), (-2.03, 3.8), (-3.17, 3.86)]
_EXHAUST = [(-4.75, 2.8), (-4.6, 2.8), (-4.6, 3.35), (-4.75, 3.35)]
_AXLES = (-0.9, -4.3)  # wheel centres' x
# Bucket (carry position) relative to its hinge at the boom tip (x, H); the load heaped on top.
_BUCKET = [(-0.1, 0.32), (-0.18, -0.22), (0.05, -0.38), (1.1, -0.38), (1.38, 0.12), (1.2, 0.12), (1.0, -0.2),
           (0.15, -0.2), (0.1, 0.32)]
_BUCKET_LOAD = [(0.1, 0.3), (0.1, -0.2), (1.0, -0.2), (1.2, 0.12), (0.95, 0.42), (0.55, 0.55), (0.25, 0.48)]

_PHASE_TEXT = {
    1: "reverse out of the pile",
    2: {"service": "brake to the reversing point (service brakes)", "tc": "brake to the reversing point (TC, fwd gear)"},
    3: "drive forward to the truck",
    4: "brake, stop at the truck",
}
_BRAKING_TEXT = {"service": "service brakes", "tc": "torque converter"}

_cache: weakref.WeakKeyDictionary[Any, _Scene] = weakref.WeakKeyDictionary()
_warned_headless = False


# --------------------------------------------------------------------------- state snapshot
def _snapshot(env: Any) -> dict[str, Any]:
    """The numbers a frame shows; before the first reset, the cycle's starting state."""
    p = env.params
    try:
        omega, V, H, _ = (float(v) for v in env.state[:4])
        s = float(env.position)
        fuel = float(env.fuel_g)
    except (IndexError, ValueError, TypeError):  # not reset yet: no state
        omega, V, H, s, fuel = p.omega_0, 0.0, p.H_0, 0.0, 0.0
    phase = int(env.phase)
    gear = float(env.core.sim.phase_constants(phase)[0])
    return {"t": float(env.time), "phase": phase, "gear": gear, "V": V, "rpm": omega * 30.0 / math.pi, "H": H,
            "s": s, "fuel_g": fuel, "braking": env.braking}


# --------------------------------------------------------------------------- the scene
class _Scene:
    """One environment's off-screen figure and the artists that move."""

    def __init__(self, env: Any, size: tuple[int, int]) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle, Polygon, Rectangle
        from matplotlib.transforms import Affine2D

        self.params = p = env.params
        self.braking = env.braking
        self.size = size
        w, h = size
        # Text and line widths are in points: scale the dpi with the frame so other sizes look the same.
        scale = min(w / WIDTH, h / HEIGHT)
        dpi = _DPI * scale
        fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(fig)
        self.fig = fig
        panel_h = 118.0 * scale / h  # the text panel's height (figure fraction)
        ax = fig.add_axes((0.0, panel_h, 1.0, 1.0 - panel_h))
        self.ax = ax
        # The view must show x in [-distance - 6.3, 8.4] and y in [-0.9, 7.3]; equal scale in x and y, the
        # spare room of other aspect ratios goes to the sides or to the sky.
        x_min, x_max, y_min = -p.reverse_distance - 6.3, 8.4 + max(p.final_position, 0.0), -0.9
        scene_w, scene_h = w, (1.0 - panel_h) * h  # pixels
        m_per_px = max((x_max - x_min) / scene_w, (7.3 - y_min) / scene_h)
        spare = m_per_px * scene_w - (x_max - x_min)
        x_min, x_max = x_min - 0.5 * spare, x_max + 0.5 * spare
        y_max = y_min + m_per_px * scene_h
        ax.set_xlim(x_min, x_max)
        ax.set_ylim(y_min, y_max)
        ax.set_axis_off()
        ax.add_patch(Rectangle((x_min, 0.0), x_max - x_min, y_max, color=_SKY, zorder=0))
        ax.add_patch(Rectangle((x_min, y_min), x_max - x_min, -y_min, color=_GROUND, zorder=1))
        ax.plot([x_min, x_max], [0, 0], color=_GROUND_LINE, lw=1.5, zorder=2)
        for x in range(math.ceil(x_min), math.floor(x_max) + 1):
            ax.plot([x, x], [0, -0.12 if x % 2 else -0.22], color=_GROUND_LINE, lw=0.8, zorder=2)
            if x % 2 == 0 and x < x_max - 1.0:
                ax.text(x, -0.3, f"{x:d}", ha="center", va="top", fontsize=6.5, color=_GROUND_LINE, zorder=2)
        ax.text(x_max - 0.15, -0.3, "s (m)", ha="right", va="top", fontsize=6.5, color=_GROUND_LINE, zorder=2)

        # Marks: the reversing point and the end (s = 0), where the pivot must stop.
        rev = -p.reverse_distance
        ax.plot([rev, rev], [0, 6.3], color=_REV, lw=1.4, ls=(0, (4, 2)), zorder=3)
        ax.add_patch(Polygon([(rev, 6.3), (rev + 0.9, 6.05), (rev, 5.8)], color=_REV, zorder=3))
        ax.text(rev - 0.2, 6.05, f"reversing point\ns = {rev:g} m", ha="right", va="center", fontsize=7,
                color=_REV, zorder=3, linespacing=1.1)
        end = p.final_position  # (the truck is drawn at s = 0; with unequal legs the end mark moves)
        ax.plot([end, end], [0, 1.0], color=_TARGET, lw=1.4, ls=(0, (4, 2)), zorder=3)
        ax.text(end, -0.62, f"s = {end:g}", ha="center", va="top", fontsize=7, color=_TARGET, fontweight="bold",
                zorder=3)

        # The pile (start) and the truck (end); their emphasis follows the phase.
        pile = Polygon([(2.75, 0.0), (3.15, 0.75), (3.45, 0.9), (4.3, 1.55), (5.4, 2.15), (6.6, 2.45), (x_max, 2.55),
                        (x_max, 0.0)], facecolor=_PILE, edgecolor="#6e5236", lw=1.0, zorder=4)
        ax.add_patch(pile)
        pile_label = ax.text(6.4, 1.2, "pile", ha="center", va="center", fontsize=8, color="white",
                             fontweight="bold", zorder=4.1)
        edge = 4.5  # the truck's loading edge (m)
        truck = [
            Polygon([(1.05, 2.35), (6.2, 2.35), (6.2, edge), (1.2, edge)], facecolor=_TRUCK, edgecolor=_TRUCK_DARK,
                    lw=1.2),
            Rectangle((0.9, 1.55), 7.3, 0.8, facecolor=_TRUCK_DARK, edgecolor=_TRUCK_DARK),
            Polygon([(6.4, 2.35), (8.2, 2.35), (8.2, 3.2), (7.7, 4.1), (6.4, 4.1)], facecolor=_TRUCK,
                    edgecolor=_TRUCK_DARK, lw=1.2),
            Polygon([(6.65, 3.05), (7.8, 3.05), (7.55, 3.85), (6.65, 3.85)], facecolor=_GLASS, edgecolor=_TRUCK_DARK,
                    lw=0.8),
        ]
        for x in (1.9, 5.2, 7.3):
            truck.append(Circle((x, 0.8), 0.8, facecolor=_TYRE, edgecolor="black", lw=0.8))
            truck.append(Circle((x, 0.8), 0.3, facecolor=_HUB, edgecolor="black", lw=0.6))
        for a in truck:
            ax.add_patch(a)
        truck_label = ax.text(3.7, 3.4, "truck", ha="center", va="center", fontsize=8, color="white",
                              fontweight="bold")
        edge_line, = ax.plot([0.95, 6.4], [edge, edge], color=_TRUCK_DARK, lw=2.0)
        truck.extend([truck_label, edge_line])
        self.pile = [pile, pile_label]
        self.truck = truck
        ax.plot([0.2, 3.0], [p.H_T, p.H_T], color=_TARGET, lw=1.0, ls=(0, (3, 2)), zorder=9)
        ax.text(3.1, p.H_T, f"H_T = {p.H_T:g} m", ha="left", va="center", fontsize=7, color=_TARGET, zorder=9)

        # The loader: the body moves as a group through one translation. Everything that changes between
        # frames is "animated": drawn over a cached background (blitting) instead of redrawing the figure.
        dynamic: list[Any] = []
        self.shift = Affine2D()
        body_tf = self.shift + ax.transData
        z = 10
        for pts, fc in ((_REAR_FRAME, _BODY), (_FRONT_FRAME, _BODY), (_JOINT, _BODY_DARK), (_CAB, _BODY),
                        (_WINDOW, _GLASS), (_EXHAUST, "#555555")):
            dynamic.append(ax.add_patch(Polygon(pts, closed=True, facecolor=fc, edgecolor=_OUTLINE, lw=1.0, zorder=z,
                                                transform=body_tf)))
        r_w = p.r_w
        for xa in _AXLES:
            dynamic.append(ax.add_patch(Circle((xa, r_w), r_w, facecolor=_TYRE, edgecolor="black", lw=1.0,
                                               zorder=z + 1, transform=body_tf)))
            dynamic.append(ax.add_patch(Circle((xa, r_w), 0.42 * r_w, facecolor=_HUB, edgecolor="black", lw=0.8,
                                               zorder=z + 1, transform=body_tf)))
        self.spokes = [ax.plot([], [], color="#333333", lw=1.6, zorder=z + 2)[0] for _ in _AXLES]
        # Position marker: a triangle on the ground under the pivot.
        dynamic.append(ax.add_patch(Polygon([(0.0, 0.0), (-0.22, -0.38), (0.22, -0.38)], color=_OUTLINE, zorder=z,
                                            transform=body_tf)))

        # Boom, lift cylinder and bucket: recomputed from H each frame (world coordinates).
        self.cylinder, = ax.plot([], [], color="#7a7a7a", lw=3.0, solid_capstyle="round", zorder=z + 3)
        self.boom, = ax.plot([], [], color=_BODY_DARK, lw=6.5, solid_capstyle="round", zorder=z + 4)
        self.boom_edge, = ax.plot([], [], color=_OUTLINE, lw=8.5, solid_capstyle="round", zorder=z + 3.5)
        self.pivot, = ax.plot([], [], "o", color=_OUTLINE, ms=3.5, zorder=z + 5)
        self.bucket = Polygon(_BUCKET, closed=True, facecolor="#7d7d7d", edgecolor=_OUTLINE, lw=1.0, zorder=z + 6)
        self.load = Polygon(_BUCKET_LOAD, closed=True, facecolor=_LOAD, edgecolor="#5c452d", lw=0.8, zorder=z + 5.5)
        ax.add_patch(self.load)
        ax.add_patch(self.bucket)
        self._bucket_xy = np.array(_BUCKET, dtype=float)
        self._load_xy = np.array(_BUCKET_LOAD, dtype=float)
        ax.text(x_min + 0.25, y_max - 0.2, f"WheelLoader-v1  short loading cycle  ({_BRAKING_TEXT[env.braking]})",
                ha="left", va="top", fontsize=8, color="#333333", zorder=20)
        dynamic += self.spokes + [self.cylinder, self.boom_edge, self.boom, self.pivot, self.load, self.bucket]

        # Text panel: labels and units are static, the numbers are drawn per frame; what changes only with
        # the phase (phase text, phase bar, gear, highlighted target) is redrawn into the background.
        panel = fig.add_axes((0.0, 0.0, 1.0, panel_h))
        panel.set_axis_off()
        panel.add_patch(Rectangle((0, 0), 1, 1, transform=panel.transAxes, facecolor="#1f2a36", zorder=0))
        kw = {"fontsize": 9.5, "family": "monospace", "color": "white", "va": "center", "transform": panel.transAxes}
        self.txt_phase = panel.text(0.02, 0.82, "", fontweight="bold", **kw)
        self.phase_bar = [Rectangle((0.805 + 0.045 * i, 0.74), 0.038, 0.16, transform=panel.transAxes,
                                    facecolor="#44515e", edgecolor="none") for i in range(4)]
        for i, rect in enumerate(self.phase_bar):
            panel.add_patch(rect)
            panel.text(0.824 + 0.045 * i, 0.82, str(i + 1), ha="center", va="center", fontsize=7, color="white",
                       transform=panel.transAxes, zorder=3)
        # (label, unit) per cell; columns at x, values right-aligned at x + 0.215.
        layout = {
            "t": (0.02, 0.56, "time", "s"), "V": (0.02, 0.34, "speed V", "m/s"), "H": (0.02, 0.12, "bucket H", "m"),
            "gear": (0.36, 0.56, "gear", ""), "rpm": (0.36, 0.34, "engine", "rpm"),
            "braking": (0.36, 0.12, "braking", ""),
            "fuel": (0.69, 0.56, "fuel", "g"), "s": (0.69, 0.34, "position", "m"), "to_go": (0.69, 0.12, "to go", "m"),
        }
        dim = dict(kw, color="#aab7c4")
        self.values: dict[str, Any] = {}
        for key, (x, y, label, unit) in layout.items():
            panel.text(x, y, label, **dim)
            panel.text(x + 0.225, y, unit, **dim)
            self.values[key] = panel.text(x + 0.215, y, "", ha="right", **kw)
        self.values["braking"].set_text(env.braking)
        for key in ("t", "V", "H", "rpm", "fuel", "s", "to_go"):
            dynamic.append(self.values[key])
        # Draw order: the scene's artists before the panel's, each by z-order.
        order = {id(ax): 0, id(panel): 1}
        self.dynamic = sorted(dynamic, key=lambda a: (order[id(a.axes)], a.get_zorder()))
        for a in self.dynamic:
            a.set_animated(True)
        self._background = None
        self._phase: int | None = None

    # ------------------------------------------------------------------ per frame
    def _set_phase(self, phase: int, gear: float, braking: str) -> None:
        """Update what changes only with the phase; the cached background is redrawn."""
        self._phase = phase
        self._background = None
        to_truck = phase >= 3
        for a in self.truck:
            a.set_alpha(1.0 if to_truck else 0.18)
            a.set_zorder(6 if to_truck else 3)
        for a in self.pile:
            a.set_alpha(0.35 if to_truck else 1.0)
            a.set_zorder(4 if to_truck else 5)
        for i, rect in enumerate(self.phase_bar):
            rect.set_facecolor("#f2b705" if i + 1 == phase else ("#6d8196" if i + 1 < phase else "#44515e"))
        text = _PHASE_TEXT[phase]
        if isinstance(text, dict):
            text = text[braking]
        self.txt_phase.set_text(f"phase {phase}: {text}")
        self.values["gear"].set_text("N (0)" if gear == 0 else f"{gear:+.0f}")

    def update(self, snap: dict[str, Any]) -> np.ndarray:
        p = self.params
        s, H = snap["s"], snap["H"]
        self.shift.clear().translate(s, 0.0)
        ang = -s / p.r_w  # the wheels roll (clockwise when moving forward)
        r = 0.85 * p.r_w
        for line, xa in zip(self.spokes, _AXLES, strict=True):
            cx = s + xa
            dx, dy = r * math.cos(ang), r * math.sin(ang)
            line.set_data([cx - dx, cx + dx], [p.r_w - dy, p.r_w + dy])
        # Boom geometry (wl_env.physics.lift): sin(theta2) = (H - G)/r, end stops at |sin| = 0.98.
        sin_t = min(max((H - p.G) / p.r, -0.98), 0.98)
        cos_t = math.sqrt(1.0 - sin_t * sin_t)
        tip = (s + p.r * cos_t, p.G + p.r * sin_t)
        mid = (s + p.r1 * cos_t, p.G + p.r1 * sin_t)
        self.boom.set_data([s, tip[0]], [p.G, tip[1]])
        self.boom_edge.set_data([s, tip[0]], [p.G, tip[1]])
        self.pivot.set_data([s], [p.G])
        self.cylinder.set_data([s + p.x_c, mid[0]], [p.G + p.y_c, mid[1]])
        self.bucket.set_xy(self._bucket_xy + tip)
        self.load.set_xy(self._load_xy + tip)
        phase = snap["phase"]
        if phase != self._phase:
            self._set_phase(phase, snap["gear"], snap["braking"])
        v = self.values
        v["t"].set_text(f"{snap['t']:.1f}")
        v["V"].set_text(f"{_clean(snap['V']):+.2f}")
        v["H"].set_text(f"{H:.2f}")
        v["rpm"].set_text(f"{snap['rpm']:.0f}")
        v["fuel"].set_text(f"{snap['fuel_g']:.1f}")
        v["s"].set_text(f"{_clean(s):+.2f}")
        v["to_go"].set_text(f"{_clean(s + p.reverse_distance if phase <= 2 else p.final_position - s):.2f}")

        canvas = self.canvas
        if self._background is None:
            canvas.draw()  # the static scene only: the animated artists are skipped
            self._background = canvas.copy_from_bbox(self.fig.bbox)
        else:
            canvas.restore_region(self._background)
        renderer = canvas.get_renderer()
        for a in self.dynamic:
            a.draw(renderer)
        buf = np.asarray(canvas.buffer_rgba())
        return np.ascontiguousarray(buf[:, :, :3])


def _clean(x: float) -> float:
    """x, with values that print as -0.00 shown as 0.00."""
    return 0.0 if abs(x) < 0.005 else x


# --------------------------------------------------------------------------- public API
def render_frame(env: Any, *, size: tuple[int, int] = (WIDTH, HEIGHT)) -> np.ndarray:
    """An RGB frame (``size[1] x size[0] x 3``, uint8) of the environment's current state.

    Works on any ``WheelLoaderEnv`` (or a wrapper of one), with or without a display, before and after
    ``reset``. The figure is built once per environment and reused.
    """
    env = getattr(env, "unwrapped", env)
    size = check_size(size)
    scene = _cache.get(env)
    if scene is None or scene.params is not env.params or scene.braking != env.braking or scene.size != size:
        scene = _Scene(env, size)
        _cache[env] = scene
    return scene.update(_snapshot(env))


MAX_SIDE = 8192  # pixels a frame's side has at most (65000 x 65000, under matplotlib's own limit, asked for 17 GB)


def check_size(size: Any) -> tuple[int, int]:
    """A frame size (width, height) in pixels: two integers (numpy's too), at least (200, 150), at most MAX_SIDE each;
    ValueError naming ``size`` otherwise (a NaN or a 1-tuple was int()'s or an index error, a string or 250.9 was
    taken as a number, 10**400 an OverflowError)."""
    values = tuple(map(plain, size)) if isinstance(size, (tuple, list)) else ()
    if not (len(values) == 2 and all(is_integer(v) for v in values)
            and 200 <= values[0] <= MAX_SIDE and 150 <= values[1] <= MAX_SIDE):
        raise ValueError(f"size must be (width, height) in pixels, integers in [200, {MAX_SIDE}] and [150, {MAX_SIDE}], "
                         f"got {shown(size)}")
    return int(values[0]), int(values[1])


def release(env: Any) -> None:
    """Drop the environment's cached figure (it is also dropped when the environment is collected)."""
    _cache.pop(getattr(env, "unwrapped", env), None)


def _display_available() -> bool:
    import sys

    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


_NON_INTERACTIVE = {"agg", "cairo", "pdf", "pgf", "ps", "svg", "template"}


def _offscreen_handle(frame: np.ndarray) -> tuple[Any, Any]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    h, w = frame.shape[:2]
    fig = Figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    return fig, ax.imshow(frame, interpolation="nearest")


def _headless(reason: str) -> None:
    global _warned_headless
    if not _warned_headless:
        _warned_headless = True
        warnings.warn(f"render_mode='human': {reason}; drawing off-screen instead (use render_mode='rgb_array' "
                      "to get the frames)", RuntimeWarning, stacklevel=3)


def show(frame: np.ndarray, handle: tuple[Any, Any] | None = None, *, fps: float | None = None) -> tuple[Any, Any]:
    """Show ``frame`` in a matplotlib window and return ``(figure, image artist)`` for the next call.

    Pass ``None`` on the first call; a closed window is reopened. Without a display (or with a
    non-interactive backend) it warns once and updates an off-screen figure, so it never fails for lack
    of a screen. ``fps`` (optional) paces the calls to at most that many frames per second.
    """
    if handle is not None:
        fig, image = handle
        if getattr(fig, "_wl_offscreen", False):
            image.set_data(frame)
            return handle
        import matplotlib.pyplot as plt

        if plt.fignum_exists(fig.number):
            image.set_data(frame)
            fig.canvas.draw_idle()
            wait = 1e-3
            last = getattr(fig, "_wl_last_show", None)
            if fps and last is not None:
                wait = max(wait, 1.0 / fps - (time.monotonic() - last))
            fig.canvas.start_event_loop(wait)  # process GUI events (and pace)
            fig._wl_last_show = time.monotonic()
            return handle
    if not _display_available():
        _headless("no display available")
        fig, image = _offscreen_handle(frame)
        fig._wl_offscreen = True
        return fig, image
    try:
        import matplotlib
        import matplotlib.pyplot as plt

        backend = str(matplotlib.get_backend()).lower()
        if backend in _NON_INTERACTIVE or backend.startswith("module://matplotlib_inline"):
            raise RuntimeError(f"matplotlib backend {backend!r} is non-interactive")
        h, w = frame.shape[:2]
        fig = plt.figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI)
        plt.ion()
        if fig.canvas.manager is not None:
            fig.canvas.manager.set_window_title("WheelLoader-v1")
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        image = ax.imshow(frame, interpolation="nearest")
        plt.show(block=False)
        fig.canvas.draw_idle()
        fig.canvas.start_event_loop(1e-3)
        return fig, image
    except Exception as exc:  # no usable GUI backend (e.g. Tk without a display)
        _headless(f"cannot open a window ({exc})")
        fig, image = _offscreen_handle(frame)
        fig._wl_offscreen = True
        return fig, image


# --------------------------------------------------------------------------- animations
MIN_FPS, MAX_FPS = 0.01, 100.0  # a GIF's frame delay is a whole number of 1/100 s, at most 655 s


def check_fps(fps: Any, name: str = "fps") -> float:
    """A frame rate in [MIN_FPS, MAX_FPS] as a float; ValueError naming ``name`` otherwise (inf made a GIF of
    delay 0, 1e-300 an OverflowError after the whole rendering)."""
    fps = plain(fps)  # (a numpy scalar)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (is_finite(fps) and MIN_FPS <= fps <= MAX_FPS):
        raise ValueError(f"{name} must be a finite number of frames per second in [{MIN_FPS:g}, {MAX_FPS:g}], got "
                         f"{shown(fps)}")
    return float(fps)


def check_frames(frames: Iterable[Any]) -> list[np.ndarray]:
    """``frames`` as a list of RGB images of one size, (height, width, 3) arrays of uint8 (as :func:`render_frame`
    gives), or of integers in [0, 255]; ValueError naming the first frame that is none, or no frames. (A float frame
    of values in [0, 1] was cast to a black one, 300 to 44, NaN to 0, and frames of other sizes went into one GIF.)"""
    out: list[np.ndarray] = []
    for i, frame in enumerate(frames):
        try:
            a = np.asarray(frame)
        except (ValueError, TypeError):  # ragged nesting
            a = None
        if a is None or a.ndim != 3 or a.shape[2] != 3 or 0 in a.shape or a.dtype.kind not in "ui" or (
                a.dtype != np.uint8 and (a.min() < 0 or a.max() > 255)):
            what = f"an array of shape {a.shape} and dtype {a.dtype}" if a is not None else shown(frame)
            raise ValueError(f"frames[{i}] must be an RGB image, (height, width, 3) uint8 as render_frame gives, "
                             f"got {what}")
        if out and a.shape != out[0].shape:
            raise ValueError(f"frames must all have one size: frames[0] is {out[0].shape}, frames[{i}] {a.shape}")
        out.append(a.astype(np.uint8, copy=False))
    if not out:
        raise ValueError("no frames to write")
    return out


def save_gif(frames: Sequence[np.ndarray] | Iterable[np.ndarray], path: str, fps: float = 10.0) -> int:
    """Write frames as an animated GIF (Pillow), atomically; returns the number of frames written."""
    from PIL import Image

    fps = check_fps(fps)
    images = [Image.fromarray(f) for f in check_frames(frames)]
    # One palette for all frames, from a few frames spread over the run (the scene's colours change with
    # the phase), so colours do not flicker between frames.
    picks = sorted({round(i * (len(images) - 1) / 4) for i in range(5)})
    w, h = images[0].size
    montage = Image.new("RGB", (w, h * len(picks)))
    for k, i in enumerate(picks):
        montage.paste(images[i].convert("RGB"), (0, k * h))
    palette = montage.quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    indexed = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    with atomic_path(path, ".gif") as tmp:
        indexed[0].save(tmp, format="GIF", save_all=True, append_images=indexed[1:], duration=round(1000.0 / fps),
                        loop=0, optimize=False, disposal=1)
    return len(indexed)


def mp4_available() -> bool:
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def save_mp4(frames: Sequence[np.ndarray] | Iterable[np.ndarray], path: str, fps: float = 10.0) -> int:
    """Write frames as an H.264 MP4 with imageio-ffmpeg (``pip install imageio-ffmpeg``), atomically."""
    fps = check_fps(fps)
    frames = [np.ascontiguousarray(f) for f in check_frames(frames)]
    try:
        import imageio_ffmpeg
    except ImportError:
        raise RuntimeError("writing .mp4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                           "write a .gif instead") from None
    h, w = frames[0].shape[:2]
    with atomic_path(path, ".mp4") as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (w, h), fps=fps, codec="libx264", pix_fmt_out="yuv420p",
                                             macro_block_size=2)
        writer.send(None)
        for f in frames:
            writer.send(f)
        writer.close()
    return len(frames)


def save_animation(frames: Sequence[np.ndarray], path: str, fps: float = 10.0) -> int:
    """``.gif`` (Pillow) or ``.mp4`` (imageio-ffmpeg) by the file's extension."""
    ext = os.path.splitext(path)[1].lower()
    if ext == ".gif":
        return save_gif(frames, path, fps)
    if ext == ".mp4":
        return save_mp4(frames, path, fps)
    raise ValueError(f"unsupported animation format {ext!r}; use .gif or .mp4")
