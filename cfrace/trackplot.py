"""Track description and pictures: gate table rows and the paper-style track figure.

``draw_track(ax, track, obstacles, view)`` draws one view of a track on a matplotlib axes (the
evaluation plots draw trajectories on top of it); ``plot_track`` writes the two-view PNG
(top view and side view). Conventions (the authors' training code, Jirl-upenn/AgileFlight_MultiAgent
ma_quadcopter_env.py): gate normal n = (cos yaw, sin yaw, 0); a gate is
passed flying along -n (green arrows). Gate openings are red, frames grey, obstacles transparent blue.
matplotlib is imported lazily and always with the Agg backend (no display needed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfrace.track import Track

#: view name -> (horizontal world axis, vertical world axis); "top" looks down -z (x right, y up),
#: "side" looks along +y (x right, z up: shares x with the top view, like an engineering drawing),
#: "side_y" looks along -x (y right, z up).
VIEWS = {"top": (0, 1), "side": (0, 2), "side_y": (1, 2)}
_AXIS_NAMES = "xyz"
_SAME_POS = 0.05   #: m, gate centres closer than this are "the same place"
_SAME_YAW = 0.05   #: rad

OPENING_COLOR = "#d62728"
FRAME_COLOR = "#555555"
ARROW_COLOR = "#2ca02c"
OBSTACLE_COLOR = "#1f77b4"


@dataclass(frozen=True)
class GateRow:
    index: int                       #: race order
    x: float                         #: m
    y: float                         #: m
    z: float                         #: m
    yaw_deg: float                   #: deg
    direction: tuple[float, float]   #: unit pass direction -n in the xy plane
    notes: str                       #: e.g. "same physical gate as #1", "stacked with #3"

    @property
    def direction_text(self) -> str:
        return direction_text(self.direction)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def pass_direction(yaw: float) -> tuple[float, float]:
    """Unit vector -n = -(cos yaw, sin yaw): the direction a drone flies through the gate."""
    return (-math.cos(yaw) + 0.0, -math.sin(yaw) + 0.0)


def direction_text(d: tuple[float, float]) -> str:
    """'+y', '-x', or '-x+y' for diagonals, followed by the vector: '+y (0.00, 1.00)'."""
    parts = [f"{'+' if v > 0 else '-'}{name}" for v, name in zip(d, "xy") if abs(v) > 0.2]
    x, y = (round(v, 2) + 0.0 for v in d)  # no "-0.00"
    return f"{''.join(parts)} ({x:+.2f}, {y:+.2f})"


def gate_rows(track: Track) -> list[GateRow]:
    """One row per gate in race order with its pose, pass direction and relations to other gates.

    "same physical gate as #j": same position and yaw (a gate passed twice per lap).
    "stacked with #j": same x, y but a different height (e.g. a split-S); "frames overlap" when the
    outer frames intersect vertically."""
    g = track.gate_array()
    rows = []
    for i, (x, y, z, yaw) in enumerate(g):
        notes = []
        for j, (xj, yj, zj, yawj) in enumerate(g):
            if j == i or math.hypot(x - xj, y - yj) > _SAME_POS:
                continue
            if abs(z - zj) <= _SAME_POS and abs(_wrap(yaw - yawj)) <= _SAME_YAW:
                notes.append(f"same physical gate as #{j}")
            elif abs(z - zj) > _SAME_POS:
                overlap = " (frames overlap)" if abs(z - zj) < track.gate.outer else ""
                notes.append(f"stacked with #{j}{overlap}")
            else:
                notes.append(f"same place as #{j}, other yaw")
        rows.append(GateRow(i, float(x), float(y), float(z), math.degrees(yaw), pass_direction(yaw), "; ".join(notes)))
    return rows


def arena_text(track: Track) -> str:
    a = track.arena
    return (f"x [{a.x[0]:g}, {a.x[1]:g}] y [{a.y[0]:g}, {a.y[1]:g}] z [0, {a.z_max:g}] m "
            f"({a.x[1] - a.x[0]:g} x {a.y[1] - a.y[0]:g} x {a.z_max:g} m)")


# ----------------------------------------------------------------------------------------- drawing

def _box_outline(centre, half, yaw: float, view: str) -> np.ndarray:
    """(N, 2) polygon of a z-aligned box yawed about z, projected on ``view``."""
    h, v = VIEWS[view]
    c, s = math.cos(yaw), math.sin(yaw)
    ex, ey = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    if view == "top":
        corners = [np.asarray(centre) + sx * half[0] * ex + sy * half[1] * ey
                   for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1))]
        return np.array([[p[h], p[v]] for p in corners])
    # vertical view: the projection of a z-aligned box is an axis-aligned rectangle
    w = abs(ex[h]) * half[0] + abs(ey[h]) * half[1]
    ch, cv, hz = centre[h], centre[v], half[2]
    return np.array([[ch - w, cv - hz], [ch + w, cv - hz], [ch + w, cv + hz], [ch - w, cv + hz]])


def draw_track(ax, track: Track, obstacles: bool = True, view: str = "top", *,
               numbers: bool = True, arrows: bool = True, arena: bool = True, limits: bool = True) -> None:
    """Draw one view of ``track`` on ``ax``: arena bounds (and floor/ceiling in vertical views),
    obstacles if ``obstacles`` (transparent blue boxes), gate frames (grey), openings (red), green
    pass-direction arrows (-n) and race-order numbers. Sets equal aspect, limits and axis labels."""
    from matplotlib.patches import Polygon, Rectangle

    if view not in VIEWS:
        raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")
    h, v = VIEWS[view]
    a = track.arena
    ranges = (a.x, a.y, (0.0, a.z_max))
    if arena:
        (h0, h1), (v0, v1) = ranges[h], ranges[v]
        ax.add_patch(Rectangle((h0, v0), h1 - h0, v1 - v0, fill=False, ls="--", lw=1.0, ec="black", zorder=1))
        if view != "top":
            ax.axhline(0.0, color="saddlebrown", lw=2.0, zorder=1)
            ax.axhline(a.z_max, color="black", lw=1.2, ls=":", zorder=1)
            ax.text(h0, a.z_max, " ceiling", va="bottom", ha="left", fontsize=7)
    if obstacles and track.obstacles:
        for c, half, yaw in zip(*track.obstacle_boxes()):
            if view != "top":  # obstacles are tall walls: cut them at the drawing's top edge
                top = min(c[2] + half[2], a.z_max + 0.3)
                c, half = np.array([c[0], c[1], top / 2.0]), np.array([half[0], half[1], top / 2.0])
            ax.add_patch(Polygon(_box_outline(c, half, yaw, view), closed=True, fc=OBSTACLE_COLOR,
                                 ec=OBSTACLE_COLOR, alpha=0.3 if view == "top" else 0.15, lw=1.0, zorder=2))
    gates = track.gate_array()
    d_open, t = track.gate.opening / 2.0, track.gate.thickness / 2.0
    centres, halves, yaws = track.gate_bars()
    for c, half, yaw in zip(centres, halves, yaws):
        if view == "top":
            continue  # drawn as one segment per gate below
        ax.add_patch(Polygon(_box_outline(c, half, yaw, view), closed=True, fc=FRAME_COLOR, ec=FRAME_COLOR,
                             lw=0.8, zorder=3))
    for x, y, z, yaw in gates:
        centre = np.array([x, y, z])
        if view == "top":
            gy = np.array([-math.sin(yaw), math.cos(yaw)])
            outer = track.gate.outer / 2.0
            for half_len, color, lw in ((outer, FRAME_COLOR, 5.0), (d_open, OPENING_COLOR, 3.0)):
                p0, p1 = centre[:2] - half_len * gy, centre[:2] + half_len * gy
                ax.plot([p0[0], p1[0]], [p0[1], p1[1]], color=color, lw=lw, solid_capstyle="butt", zorder=4)
        else:
            ax.add_patch(Polygon(_box_outline(centre, (t, d_open, d_open), yaw, view), closed=True, fill=False,
                                 ec=OPENING_COLOR, lw=1.5, zorder=4))
    if arrows:
        _draw_arrows(ax, gates, view)
    if numbers:
        _draw_numbers(ax, track, view)
    if limits:
        pad = 0.4
        ax.set_xlim(ranges[h][0] - pad, ranges[h][1] + pad)
        ax.set_ylim(ranges[v][0] - (0.2 if view != "top" else pad), ranges[v][1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(f"{_AXIS_NAMES[h]} [m]")
    ax.set_ylabel(f"{_AXIS_NAMES[v]} [m]")


def _draw_arrows(ax, gates: np.ndarray, view: str) -> None:
    """Green arrows along -n through each gate; a pass direction along the line of sight is a
    circled dot (towards the viewer) or a cross (away); coinciding markers are spread apart."""
    h, v = VIEWS[view]
    length = 0.9
    markers: dict[tuple[float, float], list[bool]] = {}
    for x, y, z, yaw in gates:
        centre = np.array([x, y, z])
        d = np.array([*pass_direction(yaw), 0.0])
        dh, dv = d[h], d[v]
        if math.hypot(dh, dv) < 0.3:  # pass direction (nearly) along the line of sight
            towards_viewer = float(np.cross(np.eye(3)[h], np.eye(3)[v]) @ d) > 0
            key = (round(float(centre[h]), 2), round(float(centre[v]), 2))
            markers.setdefault(key, [])
            if towards_viewer not in markers[key]:
                markers[key].append(towards_viewer)
            continue
        start = (centre[h] - 0.5 * length * dh, centre[v] - 0.5 * length * dv)
        ax.annotate("", xy=(start[0] + length * dh, start[1] + length * dv), xytext=start,
                    arrowprops=dict(arrowstyle="-|>", color=ARROW_COLOR, lw=2.0, mutation_scale=14), zorder=6)
    for (ph, pv), kinds in markers.items():
        offsets = [0.0] if len(kinds) == 1 else [-0.2, 0.2]
        for dh, towards_viewer in zip(offsets, kinds):
            if towards_viewer:
                ax.plot(ph + dh, pv, marker="o", ms=10, mfc="white", mec=ARROW_COLOR, mew=2.0, zorder=6)
                ax.plot(ph + dh, pv, marker="o", ms=3, color=ARROW_COLOR, zorder=7)
            else:
                ax.plot(ph + dh, pv, marker="o", ms=10, mfc="white", mec=ARROW_COLOR, mew=2.0, zorder=6)
                ax.plot(ph + dh, pv, marker="x", ms=6, mec=ARROW_COLOR, mew=2.0, zorder=7)


def _draw_numbers(ax, track: Track, view: str) -> None:
    """Race-order numbers; gates whose labels would land on the same spot share one label '1,4'."""
    h, v = VIEWS[view]
    labels: dict[tuple[float, float], list[int]] = {}
    for i, (x, y, z, yaw) in enumerate(track.gate_array()):
        centre = np.array([x, y, z])
        if view == "top":  # on the approach (+n) side, a little off the arrow
            n = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            gy = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
            pos = centre + 0.45 * n + 0.35 * gy
        else:
            pos = centre + np.array([0.0, 0.0, track.gate.outer / 2.0 + 0.18])
        key = (round(float(pos[h]), 1), round(float(pos[v]), 1))
        labels.setdefault(key, []).append(i)
    for (ph, pv), idx in labels.items():
        ax.text(ph, pv, ",".join(map(str, idx)), ha="center", va="center", fontsize=8, fontweight="bold",
                zorder=7, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))


def plot_track(track: Track, path: str | Path, obstacles: bool = False, *, dpi: int = 150) -> Path:
    """Write the two-view PNG of ``track`` to ``path``: top view above, side view (x-z) below,
    both to the same scale and sharing the x axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    a = track.arena
    width_m = a.x[1] - a.x[0] + 0.8
    top_m, side_m = a.y[1] - a.y[0] + 0.8, a.z_max + 0.6
    fig_w = 7.0
    scale = fig_w / width_m  # inches per metre
    fig = plt.figure(figsize=(fig_w + 1.0, scale * (top_m + side_m) + 1.5))
    gap_in = 1.1  # inches between the two views
    grid = fig.add_gridspec(2, 1, height_ratios=[top_m, side_m], hspace=gap_in / (scale * (top_m + side_m) / 2.0))
    top = fig.add_subplot(grid[0])
    side = fig.add_subplot(grid[1], sharex=top)
    draw_track(top, track, obstacles, view="top")
    draw_track(side, track, obstacles, view="side")
    top.set_title("top view", fontsize=9)
    side.set_title("side view (looking along +y)", fontsize=9)
    handles = [Line2D([], [], color=OPENING_COLOR, lw=3, label=f"gate opening {track.gate.opening:g} m"),
               Line2D([], [], color=FRAME_COLOR, lw=5, label="gate frame"),
               Line2D([], [], color=ARROW_COLOR, lw=2, marker=">", label="pass direction"),
               Line2D([], [], color="black", lw=1, ls="--", label="arena")]
    if obstacles and track.obstacles:
        handles.append(Patch(fc=OBSTACLE_COLOR, alpha=0.3, ec=OBSTACLE_COLOR, label="obstacle"))
    top.legend(handles=handles, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=7, framealpha=0.9)
    suffix = " with obstacles" if obstacles and track.obstacles else ""
    top.set_title(f"track '{track.name}'{suffix}: {track.num_gates} gates, top view", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path
