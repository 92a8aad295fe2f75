"""A rich live view of the race, one row per drone: target gate, lap, speed, safety state, link.

Rendered from the loop thread right after a tick's setpoints went out (every rate/view_hz ticks),
with rich's auto refresh off: no extra thread competes with the loop for the GIL, and a render
only uses the slack of that tick. Off in tests and with --quiet.
"""

from __future__ import annotations

import math

import numpy as np
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text


def _fmt(v: float, spec: str, unit: str = "") -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:{spec}}{unit}"


class LiveView:
    def __init__(self, *, title: str, laps: int, every_ticks: int, console: Console | None = None):
        self.title, self.laps, self.every = title, laps, max(1, int(every_ticks))
        self.console = console or Console(stderr=True)
        self._live: Live | None = None
        self._ticks = 0
        self._last_events = 0
        self._last: tuple | None = None   #: (loop, t, ests) of the newest tick: the final frame

    def __enter__(self) -> "LiveView":
        self._live = Live(Text("connecting..."), console=self.console, auto_refresh=False, transient=False)
        self._live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        """Show the race as it ended (not the last periodic frame), then end the view on a line
        of its own, also when the output is not a terminal."""
        if self._live is not None:
            if self._last is not None:
                loop, _, ests = self._last
                try:
                    self._live.update(self.render(loop, loop.t, ests), refresh=True)
                except Exception:  # noqa: BLE001 - a broken terminal must not hide the result
                    pass
            self._live.__exit__(*exc)
            self._live = None
            if not self.console.is_terminal:
                self.console.print()

    def maybe_update(self, loop, t: float, ests) -> None:
        self._ticks += 1
        self._last = (loop, t, ests)
        if self._live is None or self._ticks % self.every:
            return
        self._live.update(self.render(loop, t, ests), refresh=True)

    def render(self, loop, t: float, ests):
        table = Table(title=f"{self.title}   t = {t:5.1f} s", expand=False)
        for col in ("drone", "body", "gate", "lap", "speed", "max", "safety", "mocap age", "link", "latency"):
            table.add_column(col, justify="right" if col not in ("drone", "body", "safety") else "left")
        core = loop.core
        tally = core.tally()     # after the race's end: as it ended (nothing scores while drones land)
        now = loop.link_clock()
        for i, d in enumerate(loop.drones):
            e = ests[i]
            q = d.link.quality
            speed = float(np.linalg.norm(e.vel)) if e.valid else float("nan")
            state = (Text(f"STOPPED ({d.stop_kind})", style="bold red") if d.stopped else
                     Text("landing", style="yellow") if d.landing is not None else Text("flying", style="green"))
            link = "up" if q.connected and q.rx_age(now) < 0.5 else "LOST"
            if q.link_quality == q.link_quality:
                link += f" {q.link_quality:.0f}%"
            gate = "-" if core.race_over is not None or d.stopped else str(int(core.progress.target[i]))
            table.add_row(d.name, d.body, gate, f"{tally[i][1]}/{self.laps}",
                          _fmt(speed, ".1f", " m/s"), _fmt(d.speed_max, ".1f"), state,
                          _fmt(e.age_s * 1e3, ".0f", " ms"), link, _fmt(q.latency_ms, ".1f", " ms"))
        lines = [table]
        for ev in loop.events[-3:]:
            who = ev["drone"] or "all"
            lines.append(Text(f"  {ev['t']:6.2f} s  {ev['kind']:<13} {who:<4} -> {ev['action']}: {ev['detail']}",
                              style="yellow" if ev["action"] == "none" else "red"))
        return Group(*lines)
