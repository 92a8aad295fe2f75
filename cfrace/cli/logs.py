"""`cfrace log info FILE` and `cfrace log plot FILE [-o DIR]`: read a flight log (MCAP)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from cfrace.cli.common import check_folder, check_writable, human_console, write_json

log_app = typer.Typer(help="Flight logs (MCAP): summary and plots. A truncated log (a killed flight) is "
                           "read up to the cut and says so; exit code 0.", no_args_is_help=True)
console = Console()

_META_SHOWN = ("track", "obstacles", "policies", "uris", "bodies", "mocap", "profile",
               "cfrace_version", "start_time", "command")
_MAX_EVENTS = 30


def _short(value, width: int = 100) -> str:
    text = value if isinstance(value, str) else json.dumps(value, default=str)
    return text if len(text) <= width else text[:width - 3] + "..."


@log_app.command("info")
def info_cmd(file: Path = typer.Argument(..., help="flight log (.mcap) written by `cfrace fly`"),
             json_out: Optional[Path] = typer.Option(None, "--json", help="Write the summary as JSON (- : to stdout).")
             ) -> None:
    """Meta, duration, messages per topic, safety events, race result, loop timing (the figures the
    flight printed, computed by the same function), and whether the log was closed cleanly or cut
    off (a killed flight: read up to the cut, exit code 0)."""
    from cfrace.cli.flight import loop_table
    from cfrace.flight.log.writer import read_log
    from cfrace.flight.log.plots import log_stats

    check_writable(json_out, "--json")
    data = read_log(file)
    s = log_stats(data)
    console = human_console(json_out)
    if s.closed_cleanly:
        state = "[green]closed cleanly[/green]"
    elif s.truncated:
        state = f"[yellow]truncated[/yellow] ({s.stop_reason}; everything before it was read)"
    else:
        state = "[yellow]not closed (no /summary)[/yellow]"
    console.print(f"[bold]{file}[/bold]: {state}, duration {s.duration_s:.2f} s")
    console.print(_key_value_table("meta", {k: data.meta[k] for k in _META_SHOWN if k in data.meta}))
    console.print(_topics_table(data, s.counts))
    if s.loop:
        console.print(loop_table(s.loop))
    _print_safety(console, s.safety)
    if s.race:
        console.print(_key_value_table("race result", s.race))
    else:
        console.print("race result: none recorded")
    if data.bad_messages:
        console.print(f"[yellow]{data.bad_messages} messages could not be decoded[/yellow]")
    write_json({"file": str(file), "closed_cleanly": s.closed_cleanly, "truncated": s.truncated,
                "stop_reason": s.stop_reason, "duration_s": s.duration_s, "meta": data.meta,
                "topics": {t: {"count": n, "encoding": data.channels.get(t, ("",))[0],
                               "schema": data.channels.get(t, ("", ""))[1]} for t, n in s.counts.items()},
                "loop": s.loop, "safety_events": [asdict(e) for e in s.safety], "race": s.race,
                "bad_messages": data.bad_messages}, json_out)


def _key_value_table(title: str, values: dict) -> Table:
    """Two columns, no header: each key and its value shortened to one line."""
    table = Table(title=title, show_header=False)
    table.add_column("key")
    table.add_column("value", overflow="fold")
    for key, value in values.items():
        table.add_row(str(key), _short(value))
    return table


def _topics_table(data, counts: dict[str, int]) -> Table:
    """Messages per topic with the channel's encoding and schema (``data``: a read flight log)."""
    topics = Table(title="messages per topic")
    topics.add_column("topic")
    topics.add_column("count", justify="right")
    topics.add_column("encoding (schema)")
    for topic, n in counts.items():
        enc, schema, _ = data.channels.get(topic, ("", "", ""))
        topics.add_row(topic, str(n), f"{enc} ({schema})" if schema else enc)
    return topics


def _print_safety(console: Console, safety: list) -> None:
    """The first _MAX_EVENTS safety events as a table, and how many more there were."""
    if not safety:
        console.print("safety events: none")
        return
    events = Table(title=f"safety events ({len(safety)})")
    for col in ("t s", "who", "kind", "action", "detail"):
        events.add_column(col)
    for e in safety[:_MAX_EVENTS]:
        events.add_row(f"{e.t:.2f}", e.who, e.kind, e.action, _short(e.detail, 80))
    console.print(events)
    if len(safety) > _MAX_EVENTS:
        console.print(f"... and {len(safety) - _MAX_EVENTS} more safety events")


@log_app.command("plot")
def plot_cmd(
    file: Path = typer.Argument(..., help="flight log (.mcap)"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="output directory (default: next to the log)"),
) -> None:
    """Write PNGs: trajectories over the track (top view), speed per drone, loop timing."""
    from cfrace.flight.log.writer import read_log
    from cfrace.flight.log.plots import plot_log

    data = read_log(file)
    check_folder(out, "-o")
    paths = plot_log(data, out if out is not None else file.parent)
    if not paths:
        console.print("nothing to plot (no trajectories, timing or known track in this log)")
    for p in paths:
        console.print(f"wrote {p}")


def register(app: typer.Typer) -> None:
    """Add this module's commands to the top-level app."""
    app.add_typer(log_app, name="log")
