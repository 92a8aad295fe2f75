"""The `cfrace` command. Thin: each command group lives in its own module with a register(app)."""

from __future__ import annotations

import sys

import typer

from cfrace.cli import bench, calibrate, evaluate, flight, logs, reproduce, sim, sweep, tracks, train
from cfrace.errors import CfraceError

app = typer.Typer(help="cfrace: multi-agent competitive drone racing for Crazyflies.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)

for module in (tracks, bench, train, evaluate, reproduce, flight, sim, logs, calibrate, sweep):
    module.register(app)


def main() -> None:
    """Entry point that turns user-facing errors into one line and exit code 2."""
    try:
        app()
    except CfraceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt as exc:
        print("interrupted", file=sys.stderr)
        sys.exit(143 if str(exc) == "SIGTERM" else 130)
