"""`python -m cfrace ...` runs the `cfrace` command (used by sweeps to start runs)."""

from cfrace.cli.main import main

main()
