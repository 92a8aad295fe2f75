"""Sweeps: many `cfrace train` runs from one file, run one after another or on Ray (docs/sweep.md)."""

from cfrace.sweep.parse import load_spec, parse_spec
from cfrace.sweep.spec import Run, Sweep

__all__ = ["Run", "Sweep", "load_spec", "parse_spec"]
