"""What a flight log says: the numbers behind `cfrace log info` and the PNGs of `cfrace log plot`.

Readers are lenient about message fields (the log may come from an older or newer cfrace, or a
truncated flight): a missing field leaves that part of the report empty rather than failing.
Field names looked for (docs/flight-log.md): /timing t (the tick's start), compute_s, late_s, ...
(loop figures: cfrace.flight.log.timing, the one definition the live result uses too);
/estimate per body pos, vel, valid (fallback: /mocap/pose poses); /safety kind|check, body|drone,
action, detail (or a list under "violations"); race result from the summary ("race", or end,
winner, laps, lap_times) or the last /race message.
matplotlib is imported lazily with the Agg backend.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cfrace.flight.log.writer import FlightLogData
from cfrace.flight.log.timing import log_loop_figures, periods


@dataclass
class SafetyEvent:
    t: float
    who: str        #: body name, drone index or "all"
    kind: str
    action: str
    detail: str


@dataclass
class LogStats:
    duration_s: float
    counts: dict[str, int]
    closed_cleanly: bool
    truncated: bool
    stop_reason: str
    bodies: list[str]
    safety: list[SafetyEvent] = field(default_factory=list)
    race: dict | None = None
    loop: dict | None = None     #: the loop figures (cfrace.flight.log.timing.loop_figures) + skipped


def _first(msg: dict, keys: tuple[str, ...]):
    for k in keys:
        v = msg.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return float(v)
    return None


def timing_series(data: FlightLogData) -> dict[str, np.ndarray]:
    """{"t", "period_s", "compute_s", "late_s"} arrays (N,) from /timing; NaN where missing. t is
    each tick's start on the loop clock, the period the spacing of the starts (timing.periods)."""
    msgs = data.messages("/timing")
    t = np.array([m[0] for m in msgs], dtype=float)

    def column(key):
        return np.array([np.nan if (v := _first(m[1], (key,))) is None else v for m in msgs])

    return {"t": t, "period_s": periods(t), "compute_s": column("compute_s"), "late_s": column("late_s")}


def trajectories(data: FlightLogData) -> dict[str, dict[str, np.ndarray]]:
    """Per body {"t" (N,), "pos" (N, 3), "vel" (N, 3)} from /estimate (valid entries only), or
    from /mocap/pose with finite-difference velocities if the log has no estimates."""
    out: dict[str, dict[str, list]] = {}
    for t, msg in data.messages("/estimate"):
        for body, e in msg.items():
            if not isinstance(e, dict) or e.get("valid") is False:
                continue
            pos, vel = e.get("pos"), e.get("vel")
            if not _vec_ok(pos):
                continue
            d = out.setdefault(body, {"t": [], "pos": [], "vel": []})
            d["t"].append(t)
            d["pos"].append(pos)
            d["vel"].append(vel if _vec_ok(vel) else [np.nan] * 3)
    if not out:
        for t, msg in data.messages("/mocap/pose"):
            poses = msg.get("poses")
            for body, p in (poses.items() if isinstance(poses, dict) else ()):
                if isinstance(p, dict) and _vec_ok(p.get("pos")):
                    d = out.setdefault(body, {"t": [], "pos": [], "vel": []})
                    d["t"].append(float(msg.get("t_src", t)))
                    d["pos"].append(p["pos"])
        for d in out.values():
            pos, tt = np.array(d["pos"], float), np.array(d["t"], float)
            vel = np.full_like(pos, np.nan)
            if len(tt) > 1:
                vel[1:] = np.diff(pos, axis=0) / np.maximum(np.diff(tt), 1e-6)[:, None]
            d["vel"] = vel
    return {b: {k: np.asarray(v, dtype=float) for k, v in d.items()} for b, d in out.items()}


def _vec_ok(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v)


def _safety_events(data: FlightLogData) -> list[SafetyEvent]:
    events = []
    for t, msg in data.messages("/safety"):
        items = msg.get("violations") if isinstance(msg.get("violations"), list) else [msg]
        for v in items:
            if not isinstance(v, dict) or v.get("ok") is True:
                continue
            kind = v.get("kind") or v.get("check") or v.get("event")
            if not kind:
                continue
            who = v.get("body", v.get("drone"))
            detail = v.get("detail") or v.get("text") or ""
            events.append(SafetyEvent(t, "all" if who is None else str(who), str(kind),
                                      str(v.get("action", "")), str(detail)))
    return events


_RESULT_KEYS = ("end", "winner", "laps", "lap_times", "operator_kill", "error")


def _race_result(data: FlightLogData) -> dict | None:
    """The summary's race result (its "race" dict, or the result keys the flight runner writes),
    else the last /race message (a flight that did not close)."""
    if data.summary:
        for key in ("race", "race_result"):
            if isinstance(data.summary.get(key), dict):
                return data.summary[key]
        found = {k: data.summary[k] for k in _RESULT_KEYS if data.summary.get(k) is not None}
        if found:
            return found
    races = data.messages("/race")
    return races[-1][1] if races else None


def log_stats(data: FlightLogData) -> LogStats:
    """Everything `cfrace log info` prints."""
    bodies = data.meta.get("bodies")
    if not isinstance(bodies, list):
        bodies = sorted(trajectories(data))
    return LogStats(duration_s=data.duration_s,
                    counts={topic: data.count(topic) for topic in data.topics},
                    closed_cleanly=data.complete, truncated=data.truncated,
                    stop_reason=data.stop_reason, bodies=[str(b) for b in bodies],
                    safety=_safety_events(data), race=_race_result(data), loop=log_loop_figures(data))


# ----------------------------------------------------------------------------------------------
# plots

def _load_track(meta: dict):
    from cfrace.errors import CfraceError
    from cfrace.track import load_track
    name = meta.get("track")
    if not name:
        return None
    try:
        return load_track(str(name))
    except (CfraceError, OSError):
        return None


def _draw_gates_fallback(ax, track) -> None:
    """Gate openings as red segments (used if cfrace.trackplot is unavailable)."""
    for x, y, _, yaw in track.gate_array():
        d = 0.5 * track.gate.opening * np.array([-math.sin(yaw), math.cos(yaw)])
        ax.plot([x - d[0], x + d[0]], [y - d[1], y + d[1]], color="#d62728", lw=3)
    ax.set_aspect("equal")


def plot_log(data: FlightLogData, out_dir: str | Path, *, dpi: int = 120) -> list[Path]:
    """Write trajectory.png (top view over the track), speed.png and timing.png (those with
    data) into out_dir; returns the paths written."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = data.path.stem
    title = f"{data.path.name}" + ("" if data.complete else "  (truncated)" if data.truncated
                                   else "  (not closed)")
    written: list[Path] = []
    trajs = trajectories(data)
    colors = {b: f"C{i}" for i, b in enumerate(sorted(trajs))}
    track = _load_track(data.meta)
    if trajs or track is not None:
        written.append(_save(_trajectory_figure(plt, data, track, trajs, colors, title), out / f"{stem}_trajectory.png",
                             dpi))
    if trajs:
        written.append(_save(_speed_figure(plt, trajs, colors, title, racing_until(data)), out / f"{stem}_speed.png",
                             dpi))
    ts = timing_series(data)
    if len(ts["t"]):
        written.append(_save(_timing_figure(plt, data, ts, log_loop_figures(data), title), out / f"{stem}_timing.png",
                             dpi))
    return written


def _trajectory_figure(plt, data: FlightLogData, track, trajs: dict, colors: dict, title: str):
    """Top view: the track and each body's path (o start, square end)."""
    fig, ax = plt.subplots(figsize=(7, 7))
    if track is not None:
        obstacles = bool(data.meta.get("obstacles", True))
        try:
            from cfrace.trackplot import draw_track
            draw_track(ax, track, obstacles, view="top")
        except ImportError:
            _draw_gates_fallback(ax, track)
    for body, d in trajs.items():
        p = d["pos"]
        ax.plot(p[:, 0], p[:, 1], color=colors[body], lw=1.5, label=body, zorder=8)
        ax.plot(p[0, 0], p[0, 1], "o", color=colors[body], ms=6, zorder=9)
        ax.plot(p[-1, 0], p[-1, 1], "s", color=colors[body], mec="black", ms=6, zorder=9)
    if trajs:
        ax.legend(loc="upper right", title="o start, \u25a0 end")
    ax.set_title(f"{title}\ntrack {data.meta.get('track', '?')}, top view")
    return fig


def racing_until(data: FlightLogData) -> dict:
    """body -> flight time at which it stopped racing, as the race's result counts its speeds: the
    start of its landing (/landing t_start) or its stop (/event "stop"), the earlier; bodies that
    raced to the log's end are absent."""
    out: dict = {}
    ends = [(m.get("body"), m.get("t_start")) for _, m in data.messages("/landing")]
    ends += [(m.get("body"), t) for t, m in data.messages("/event") if m.get("kind") == "stop"]
    for body, t in ends:
        if body is not None and t is not None:
            out[body] = min(float(t), out.get(body, math.inf))
    return out


def _speed_figure(plt, trajs: dict, colors: dict, title: str, until: dict):
    """Each body's estimated speed over the flight; max and mean in the legend over its racing
    (until it began to land or was stopped: the result table's figures), marked by a dotted line."""
    fig, ax = plt.subplots(figsize=(9, 4))
    for body, d in trajs.items():
        speed = np.linalg.norm(d["vel"], axis=1)
        ok = np.isfinite(speed)
        racing = ok & (d["t"] < until.get(body, np.inf))
        if racing.any():
            ax.plot(d["t"][ok], speed[ok], color=colors[body], lw=1.2,
                    label=f"{body} racing: max {speed[racing].max():.2f}, mean {speed[racing].mean():.2f} m/s")
        if body in until:
            ax.axvline(until[body], color=colors[body], ls=":", lw=1)
    ax.set_xlabel("flight time t [s] (dotted: stops racing)")
    ax.set_ylabel("speed [m/s]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right")
    ax.set_title(f"{title}: speed")
    return fig


def _timing_figure(plt, data: FlightLogData, ts: dict, loop: dict, title: str):
    """The loop's period, compute and lateness per tick, and their histogram; the legend's
    figures are ``loop``'s (timing.loop_figures, as `log info` prints them)."""
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 4), gridspec_kw={"width_ratios": [2, 1]})
    both = np.concatenate([ts["period_s"], ts["compute_s"]]) * 1e3
    top = float(np.nanmax(both)) if np.isfinite(both).any() else 1.0
    bins = np.linspace(0.0, top * 1.02 + 1e-6, 120)
    for key, figure, color, label in (("period_s", "period_ms", "C0", "period"),
                                      ("compute_s", "compute_ms", "C3", "compute"), ("late_s", "late_ms", "C2", "start late")):
        ms = ts[key] * 1e3
        ok = np.isfinite(ms)
        if not ok.any():
            continue
        st = loop[figure]
        text = f"{label}: p50 {st['p50']:.2f}, p99 {st['p99']:.2f}, max {st['max']:.2f} ms"
        ax0.plot(ts["t"][ok], ms[ok], ".", ms=2, color=color, label=text)
        ax1.hist(ms[ok], bins=bins, color=color, alpha=0.6, label=label)
    period = 1.0 / loop["rate_hz"]
    if isinstance(period, (int, float)):
        for ax in (ax0, ax1):
            (ax.axhline if ax is ax0 else ax.axvline)(period * 1e3, color="black", ls="--", lw=0.8)
    ax0.set_xlabel("flight time t [s]")
    ax0.set_ylabel("ms")
    ax0.grid(alpha=0.3)
    ax0.legend(loc="best", fontsize=8, markerscale=4)
    ax0.set_title(f"{title}: loop timing")
    ax1.set_xlabel("ms")
    ax1.set_ylabel("ticks")
    ax1.set_yscale("log")
    ax1.legend(fontsize=8)
    ax1.set_title("histogram")
    return fig


def _save(fig, path: Path, dpi: int) -> Path:
    import matplotlib.pyplot as plt
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
