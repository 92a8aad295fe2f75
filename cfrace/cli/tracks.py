"""`cfrace tracks list` and `cfrace tracks show NAME|PATH [--obstacles] [--png FILE]`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from cfrace.cli.common import check_writable, write_json
from cfrace.errors import ConfigError

tracks_app = typer.Typer(help="Race tracks: list them, show gates, obstacles and a picture.", no_args_is_help=True)
console = Console()


@tracks_app.command("list")
def list_cmd(json_out: Optional[Path] = typer.Option(None, "--json", help="Write the list as JSON (- : to stdout).")
             ) -> None:
    """List the tracks in tracks/: name, gates, obstacles and arena size."""
    from cfrace.track import list_tracks, load_track
    from cfrace.paths import TRACKS_DIR

    table = Table(title=f"tracks in {TRACKS_DIR}")
    for col in ("name", "gates", "obstacles", "arena x*y*z m", "file"):
        table.add_column(col)
    doc = []
    for path in list_tracks():
        try:
            t = load_track(path)
        except ConfigError as exc:  # one broken file must not hide the others
            table.add_row(path.stem, "-", "-", f"[red]invalid: {exc}[/red]", path.name)
            doc.append({"name": path.stem, "file": str(path), "error": str(exc)})
            continue
        a = t.arena
        size = f"{a.x[1] - a.x[0]:g} x {a.y[1] - a.y[0]:g} x {a.z_max:g}"
        table.add_row(t.name, str(t.num_gates), str(len(t.obstacles)), size, path.name)
        doc.append({"name": t.name, "file": str(path), "gates": t.num_gates, "obstacles": len(t.obstacles),
                    "arena": {"x": list(a.x), "y": list(a.y), "z_max": a.z_max}})
    console.print(table)
    write_json(doc, json_out)


@tracks_app.command("show")
def show_cmd(
    track: str = typer.Argument(..., help="track name (tracks/NAME.yaml) or path to a track YAML"),
    obstacles: bool = typer.Option(False, "--obstacles", help="draw the obstacles in the picture"),
    png: Optional[Path] = typer.Option(None, "--png", help="write a top + side view picture to this PNG file"),
) -> None:
    """Print the gates in race order, obstacles and arena; optionally write a picture."""
    from cfrace.track import load_track
    from cfrace.trackplot import arena_text, gate_rows, plot_track

    t = load_track(track)
    if png is not None:
        if png.suffix.lower() != ".png":
            raise ConfigError(f"--png {png}: the picture is a PNG file, give a name ending in .png")
        check_writable(png, "--png")
    gates = Table(title=f"track '{t.name}': gates in race order ({t.source})")
    for col in ("#", "x m", "y m", "z m", "yaw deg", "pass direction (-n)", "notes"):
        gates.add_column(col, justify="right" if col in ("#", "x m", "y m", "z m", "yaw deg") else "left")
    for r in gate_rows(t):
        gates.add_row(str(r.index), f"{r.x:.2f}", f"{r.y:.2f}", f"{r.z:.2f}", f"{r.yaw_deg:.1f}",
                      r.direction_text, r.notes)
    console.print(gates)
    console.print(f"gate: opening {t.gate.opening:g} m, frame border {t.gate.border:g} m "
                  f"(outer {t.gate.outer:g} m), thickness {t.gate.thickness:g} m")
    if t.obstacles:
        obs = Table(title="obstacles (boxes standing on the floor)")
        for col in ("#", "centre x m", "centre y m", "size x m", "size y m", "height m", "yaw deg"):
            obs.add_column(col, justify="right")
        for i, o in enumerate(t.obstacles):
            obs.add_row(str(i), f"{o.center[0]:.2f}", f"{o.center[1]:.2f}", f"{o.size[0]:.2f}",
                        f"{o.size[1]:.2f}", f"{o.size[2]:.2f}", f"{o.yaw * 57.29577951308232:.1f}")
        console.print(obs)
    else:
        console.print("obstacles: none")
    console.print(f"arena: {arena_text(t)}")
    if png is not None:
        out = plot_track(t, png, obstacles=obstacles)
        console.print(f"wrote {out} ({out.stat().st_size} bytes)")


def register(app: typer.Typer) -> None:
    """Add the tracks group to the top-level app."""
    app.add_typer(tracks_app, name="tracks")
