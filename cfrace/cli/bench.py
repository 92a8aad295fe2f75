"""`cfrace bench ...`: benchmarks that print figures. Other CLI modules add commands to `bench_app`."""

from __future__ import annotations

import typer

bench_app = typer.Typer(help="Benchmarks that print figures (speed, latency).", no_args_is_help=True)


def register(app: typer.Typer) -> None:
    """Add the bench group to the top-level app."""
    app.add_typer(bench_app, name="bench")
