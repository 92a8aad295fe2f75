"""Evaluation plots (matplotlib Agg, PNG): trajectories over the track coloured by speed, the
ego's speed against a live vs a crashed opponent (paper Fig. 8 a-b) and the tournament heatmap."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cfrace.evaluate.entrants import Entrant
from cfrace.evaluate.metrics import RunSummary, speed_stats
from cfrace.evaluate.rollout import Recording
from cfrace.sim.simulator import REASONS
from cfrace.track import Track
from cfrace.trackplot import draw_track

CMAP = "turbo"


def _race_name(w: int, races: int) -> str:
    """Which race world w is: the first `races` worlds race a live opponent, the next ones a
    crashed one; numbered from 1 within each set."""
    return f"race {w + 1} of {races} (live opponent)" if w < races else \
        f"race {w - races + 1} of {races} (crashed opponent)"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def _trace(rec: Recording, world: int, drone: int):
    """(xyz (N, 3), speed (N,), t (N,)) of a recorded world's drone while it was racing (the speed
    of a crash step reads 0, the crashed drone is stopped: it is left out)."""
    k = rec.recorded.index(world)
    act = rec.active[:, world, drone]
    n = int(np.flatnonzero(act)[-1]) + 1 if act.any() else 0
    if n and rec.crashed_now[n - 1, world, drone]:
        n -= 1
    return rec.pos[:n, k, drone], rec.speed[:n, world, drone], rec.t[:n]


def _speed_path(ax, xyz: np.ndarray, speed: np.ndarray, norm, lw: float = 2.0):
    from matplotlib.collections import LineCollection

    if len(xyz) < 2:
        return None
    seg = np.stack([xyz[:-1, :2], xyz[1:, :2]], axis=1)
    lc = LineCollection(seg, cmap=CMAP, norm=norm, linewidths=lw, zorder=5)
    lc.set_array(0.5 * (speed[:-1] + speed[1:]))
    ax.add_collection(lc)
    ax.plot(*xyz[0, :2], "o", color="black", ms=5, zorder=6)
    return lc


def _mark_end(ax, xyz: np.ndarray, crashed: bool, color: str = "black") -> None:
    if len(xyz) and crashed:
        ax.plot(*xyz[-1, :2], "x", color=color, ms=10, mew=2.5, zorder=7)


def _pick(worlds, s: RunSummary, drone: int = 0) -> int:
    """The first world where the drone finished, else the one it raced longest in."""
    worlds = list(worlds)
    done = [w for w in worlds if s.finished[w, drone]]
    return done[0] if done else max(worlds, key=lambda w: s.flight_time[w, drone])


def _lap_text(s: RunSummary, w: int, d: int) -> str:
    laps = s.lap_times[w, d]
    laps = laps[~np.isnan(laps)]
    txt = "laps " + ", ".join(f"{x:.2f}" for x in laps) + " s" if laps.size else "no lap"
    if s.crashed[w, d]:
        txt += f"; crash ({REASONS[int(s.crash_reason[w, d])]}) at {s.crash_time[w, d]:.2f} s"
    return txt


def solo_trajectory_plots(plot_dir: Path, track: Track, obstacles: bool, entrants: list[Entrant], rec: Recording,
                          s: RunSummary, runs: int) -> list[Path]:
    """One top-view PNG per policy: a recorded run (several laps), coloured by speed."""
    from matplotlib.colors import Normalize

    plt = _plt()
    plot_dir = Path(plot_dir)
    plot_dir.mkdir(parents=True, exist_ok=True)
    out = []
    for k, e in enumerate(entrants):
        w = _pick([x for x in rec.recorded if k * runs <= x < (k + 1) * runs], s)
        xyz, v, _ = _trace(rec, w, 0)
        fig, ax = plt.subplots(figsize=(6.5, 7.0), layout="constrained")
        draw_track(ax, track, obstacles, "top")
        norm = Normalize(0.0, max(float(v.max()) if v.size else 1.0, 1.0))
        lc = _speed_path(ax, xyz, v, norm)
        _mark_end(ax, xyz, bool(s.crashed[w, 0]))
        if lc is not None:
            fig.colorbar(lc, ax=ax, label="speed [m/s]", shrink=0.8)
        st = speed_stats(v, np.ones_like(v, bool))
        ax.set_title(f"{e.name} on {track.name}{' with obstacles' if obstacles else ''}, run {w - k * runs}\n"
                     f"{_lap_text(s, w, 0)}\nmean {st['mean_mps'] or 0:.2f} m/s, max {st['max_mps'] or 0:.2f} m/s",
                     fontsize=9)
        path = plot_dir / f"trajectory_{_safe(e.name)}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        out.append(path)
    return out


def race_plots(plot_dir: Path, track: Track, obstacles: bool, entrants: list[Entrant], rec: Recording,
               s: RunSummary, races: int, profile: dict) -> list[Path]:
    """race_trajectories.png (a: ego vs a live opponent, b: vs a crashed one, coloured by speed) and
    speed.png (the ego's speed over time in both, with max and mean)."""
    plot_dir = Path(plot_dir)
    plot_dir.mkdir(parents=True, exist_ok=True)
    recorded = [w for w in rec.recorded if w < races]
    live_w = _pick([w for w in recorded if not s.crashed[w, 1]] or recorded, s)
    extra = [w for w in rec.recorded if w >= races]
    crash_w = (races + live_w if races + live_w in extra else _pick(extra, s)) if extra else None
    cases = [("a", "live opponent", live_w)] + ([("b", "crashed opponent", crash_w)] if crash_w is not None else [])
    traces = {c: _trace(rec, w, 0) for c, _, w in cases}
    vmax = max([float(tr[1].max()) for tr in traces.values() if tr[1].size] + [1.0])
    names = (entrants[0].name, entrants[1].name)
    traj = _race_trajectories(plot_dir / "race_trajectories.png", track, obstacles, names, rec, s, races, cases,
                              traces, vmax)
    speed = _race_speeds(plot_dir / "speed.png", names[0], rec, s, races, profile, cases, traces, vmax)
    return [traj, speed]


def _race_trajectories(path: Path, track: Track, obstacles: bool, names: tuple[str, str], rec: Recording,
                       s: RunSummary, races: int, cases: list, traces: dict, vmax: float) -> Path:
    """One top view per case (tag, label, world): the ego's path coloured by speed (0..vmax m/s), the
    opponent's dashed."""
    from matplotlib.colors import Normalize

    plt = _plt()
    norm = Normalize(0.0, vmax)
    ego, opp = names
    fig, axes = plt.subplots(1, len(cases), figsize=(6.0 * len(cases), 6.8), squeeze=False, layout="constrained")
    lc = None
    for ax, (tag, label, w) in zip(axes[0], cases):
        draw_track(ax, track, obstacles, "top")
        xyz, v, _ = traces[tag]
        lc = _speed_path(ax, xyz, v, norm) or lc
        _mark_end(ax, xyz, bool(s.crashed[w, 0]))
        oxyz, _, _ = _trace(rec, w, 1) if rec.active[:, w, 1].any() else (rec.pos[:1, rec.recorded.index(w), 1], 0, 0)
        ax.plot(oxyz[:, 0], oxyz[:, 1], "--", color="grey", lw=1.0, zorder=4, label=f"opponent ({opp})")
        _mark_end(ax, oxyz, bool(rec.crashed[-1, w, 1]), "dimgrey")
        ax.legend(loc="lower right", fontsize=7)
        ax.set_title(f"({tag}) {ego} vs {label}, {_race_name(w, races)}\n{_lap_text(s, w, 0)}", fontsize=9)
    if lc is not None:
        fig.colorbar(lc, ax=list(axes[0]), label=f"{ego} speed [m/s]", shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _race_speeds(path: Path, ego: str, rec: Recording, s: RunSummary, races: int, profile: dict, cases: list,
                 traces: dict, vmax: float) -> Path:
    """The ego's speed over time, one panel per case, with this race's and all such races' max / mean
    (``profile``: the speed profile's aggregates by case), laps and the opponent's crash marked."""
    plt = _plt()
    fig, axes = plt.subplots(len(cases), 1, figsize=(9.0, 3.2 * len(cases)), squeeze=False, sharex=True)
    keys = {"a": "vs_live_opponent", "b": "vs_crashed_opponent"}
    fmt = lambda x: "–" if x is None else f"{x:.2f}"
    for ax, (tag, label, w) in zip(axes[:, 0], cases):
        _, v, t = traces[tag]
        st = speed_stats(v, np.ones_like(v, bool))
        agg = profile[keys[tag]]
        ax.plot(t, v, color="tab:blue" if tag == "a" else "tab:orange", lw=1.3)
        if st["max_mps"] is not None:
            ax.axhline(st["mean_mps"], color="black", ls=":", lw=1.0)
        stamps = rec.lap_stamp[:, w, 0][rec.active[:, w, 0]]
        for x in stamps[~np.isnan(stamps)]:
            ax.axvline(x, color="green", lw=0.8, alpha=0.6)
        down = np.flatnonzero(rec.crashed[:, w, 1])
        if down.size and t.size and rec.t[down[0]] <= t[-1]:
            ax.axvline(rec.t[down[0]], color="red", lw=1.0, ls="--", label="opponent crashed")
            ax.legend(loc="lower right", fontsize=7)
        ax.set_title(f"({tag}) {ego} vs {label}, {_race_name(w, races)}: this race max "
                     f"{fmt(st['max_mps'])} / mean {fmt(st['mean_mps'])} m/s; all {agg['races']} such races max "
                     f"{fmt(agg['max_mps'])} / mean {fmt(agg['mean_mps'])} m/s", fontsize=8)
        ax.set_ylabel("speed [m/s]")
        ax.set_ylim(0.0, vmax * 1.08)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time [s] (green: lap completed)")
    axes[-1, 0].set_xlim(0.0, max([float(tr[2][-1]) for tr in traces.values() if tr[2].size] + [0.1]))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_heatmap(path: Path, names: list[str], win: list[list[float | None]], draw: list[list[float | None]],
                 title: str = "") -> Path:
    """Win rate of the row policy against the column policy (draws in small print), diagonal blank."""
    plt = _plt()
    n = len(names)
    m = np.array([[np.nan if x is None else 100.0 * x for x in row] for row in win])
    fig, ax = plt.subplots(figsize=(1.3 * n + 2.4, 1.1 * n + 1.6))
    im = ax.imshow(np.ma.masked_invalid(m), cmap="RdYlGn", vmin=0, vmax=100)
    for i in range(n):
        for j in range(n):
            if i == j:
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, color="lightgrey"))
                continue
            color = "white" if m[i, j] < 20 or m[i, j] > 85 else "black"   # readable on the dark ends
            ax.text(j, i - 0.08, f"{m[i, j]:.0f}%", ha="center", va="center", fontsize=11, weight="bold", color=color)
            ax.text(j, i + 0.25, f"draw {100 * draw[i][j]:.0f}%", ha="center", va="center", fontsize=7, color=color)
    ax.set_xticks(range(n), names)
    ax.set_yticks(range(n), names)
    ax.set_xlabel("opponent (column)")
    ax.set_ylabel("policy (row)")
    fig.colorbar(im, ax=ax, label="win rate [%]", shrink=0.8)
    return _finish(fig, ax, path, title)



def _finish(fig, ax, path, title: str | None) -> Path:
    """The figure's optional title, layout and PNG at ``path`` (folders made); the figure closed."""
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    _plt().close(fig)
    return path

def _race_place(track_pos: np.ndarray, places_final: np.ndarray, stopped: np.ndarray) -> np.ndarray:
    """(T, D) place over time of one recorded race: by distance along the race line (1 = ahead);
    a drone that has finished or crashed keeps the place the race gave it (places_final)."""
    live_place = 1 + (track_pos[:, None, :] > track_pos[:, :, None]).sum(-1)
    return np.where(stopped, places_final[None, :], live_place)


def field_plots(plot_dir: Path, track: Track, obstacles: bool, names: list[str], rec: Recording,
                places: np.ndarray) -> list[Path]:
    """field_trajectories.png (every drone of each recorded race, top view, crashes marked x) and
    field_positions.png (each drone's place over time in those races)."""
    plt = _plt()
    plot_dir = Path(plot_dir)
    plot_dir.mkdir(parents=True, exist_ok=True)
    worlds = list(rec.recorded)
    d = len(names)
    colours = plt.get_cmap("tab10")
    fig, axes = plt.subplots(1, len(worlds), figsize=(5.0 * len(worlds), 6.0), squeeze=False, layout="constrained")
    for ax, w in zip(axes[0], worlds):
        draw_track(ax, track, obstacles, "top")
        for k in range(d):
            xyz, _, _ = _trace(rec, w, k)
            if not len(xyz):
                xyz = rec.pos[:1, rec.recorded.index(w), k]
            ax.plot(xyz[:, 0], xyz[:, 1], color=colours(k % 10), lw=1.4, zorder=5,
                    label=f"{names[k]} (P{places[w, k]})")
            ax.plot(*xyz[0, :2], "o", color=colours(k % 10), ms=4, zorder=6)
            _mark_end(ax, xyz, bool(rec.crashed[-1, w, k] and rec.crashed_now[:, w, k].any()), colours(k % 10))
        ax.legend(loc="lower right", fontsize=7)
        ax.set_title(f"race {w}: all {d} drones (x: crash; P: final place)", fontsize=9)
    traj = plot_dir / "field_trajectories.png"
    fig.savefig(traj, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(len(worlds), 1, figsize=(9.0, 2.6 * len(worlds)), squeeze=False, sharex=True)
    for ax, w in zip(axes[:, 0], worlds):
        k_rec = rec.recorded.index(w)
        act = rec.active[:, w, :]
        stopped = ~act & (np.cumsum(act, 0) > 0)
        place = _race_place(rec.track_pos[:, k_rec, :], places[w], stopped)
        for k in range(d):
            ax.step(rec.t, place[:, k] + 0.04 * (k - (d - 1) / 2), where="post", color=colours(k % 10), lw=1.5,
                    label=names[k])
            down = np.flatnonzero(rec.crashed_now[:, w, k] & act[:, k])
            if down.size:
                ax.plot(rec.t[down[0]], place[down[0], k], "x", color=colours(k % 10), ms=8, mew=2)
        ax.set_ylim(d + 0.5, 0.5)
        ax.set_yticks(range(1, d + 1))
        ax.set_ylabel(f"race {w}\nplace")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=7, ncol=min(d, 4))
    axes[-1, 0].set_xlabel("time [s] (place by distance along the race line; x: crash)")
    fig.tight_layout()
    pos = plot_dir / "field_positions.png"
    fig.savefig(pos, dpi=110)
    plt.close(fig)
    return [traj, pos]


def plot_ratings(path: Path, names: list[str], rating: list[float], mean_place: list[float], title: str = "") -> Path:
    """Bar chart of the free-for-all ratings (Elo scale), mean place written on each bar."""
    plt = _plt()
    order = np.argsort(rating)[::-1]
    fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2.5, 4.0))
    base = min(rating) - 50.0
    bars = ax.bar([names[i] for i in order], [rating[i] - base for i in order], bottom=base, color="tab:blue")
    for b, i in zip(bars, order):
        ax.text(b.get_x() + b.get_width() / 2, rating[i] + 5, f"{rating[i]:.0f}\nplace {mean_place[i]:.2f}",
                ha="center", va="bottom", fontsize=8)
    ax.set_ylabel("rating (Elo scale)")
    ax.grid(axis="y", alpha=0.3)
    return _finish(fig, ax, path, title)
