"""`cfrace sim` commands: serve (simulated Crazyflies over CRTP/UDP) and dry-run."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add this module's commands to the top-level app."""
