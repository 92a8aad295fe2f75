"""The `cfrace` command. Thin: each command group lives in its own module with a register(app).

Every error a user can make ends the same way: one line ``error: ...`` on stderr (argument errors
add the command's `--help` hint), exit code 2, no traceback. Ctrl-C exits 130 from every command.
No command module imports torch, onnxruntime or matplotlib at import time: arguments are checked
(and `--help` printed) before any heavy import (tests/test_cli_habits.py).
"""

from __future__ import annotations

import sys
import warnings

import typer

try:
    from typer._click import exceptions as cx   # typer >= 0.2x carries its own click
except ImportError:                             # older typer: click itself
    from click import exceptions as cx

import cfrace
from cfrace.cli.common import json_to_stdout, restore_stdout
from cfrace.cli import calibrate, evaluate, flight, logs, measure, reproduce, sim, sweep, tracks, train
from cfrace.errors import CfraceError, CfraceWarning

app = typer.Typer(help="cfrace: multi-agent competitive drone racing for Crazyflies.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
                  rich_markup_mode=None)


def _version(value: bool) -> None:
    if value:
        print(f"cfrace {cfrace.__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """cfrace: multi-agent competitive drone racing for Crazyflies."""


for module in (tracks, measure, train, evaluate, reproduce, flight, sim, logs, calibrate, sweep):
    module.register(app)

#: options whose value may be left out (`fly --foxglove` = `fly --foxglove 8765`): option -> (default,
#: the commands that take it)
OPTIONAL_VALUES = {"--foxglove": ("8765", ("fly", "dry-run"))}


def fill_optional_values(argv: list[str]) -> list[str]:
    """argv with the default value inserted after an OPTIONAL_VALUES option given without one."""
    out = []
    for i, arg in enumerate(argv):
        out.append(arg)
        if arg in OPTIONAL_VALUES and any(c in argv[:i] for c in OPTIONAL_VALUES[arg][1]):
            nxt = argv[i + 1] if i + 1 < len(argv) else None
            if nxt is None or nxt.startswith("-"):
                out.append(OPTIONAL_VALUES[arg][0])
    return out


def _usage_error(exc: cx.UsageError, args: list[str]) -> int:
    """One line for an argument error, with the --help hint of the command it belongs to."""
    ctx = exc.ctx
    if ctx is not None:
        path = ctx.command_path
    else:   # the command words before the first option
        words = []
        for a in args:
            if a.startswith("-"):
                break
            words.append(a)
        path = " ".join(["cfrace", *words])
    print(f"error: {exc.format_message()} (see `{path} --help`)", file=sys.stderr)
    return 2


_python_format = warnings.formatwarning


def format_warning(message, category, filename, lineno, line=None) -> str:
    """cfrace's own warnings (CfraceWarning, e.g. the simulator's slower fallback) as one line
    ``warning: ...``; other packages' warnings keep Python's format (file, line, category)."""
    if issubclass(category, CfraceWarning):
        return f"warning: {message}\n"
    return _python_format(message, category, filename, lineno, line)


def main(argv: list[str] | None = None) -> None:
    """Entry point: user-facing errors as one line and exit code 2; Ctrl-C exits 130, SIGTERM 143."""
    warnings.formatwarning = format_warning
    args = fill_optional_values(list(sys.argv[1:] if argv is None else argv))
    json_to_stdout(args)
    try:
        code = _run(args)
    finally:
        restore_stdout()
    sys.exit(code)


def _run(args: list[str]) -> int:
    """The command's exit code; every way it can end as main() describes."""
    try:
        code = app(args=args, prog_name="cfrace", standalone_mode=False)
    except CfraceError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except cx.UsageError as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":    # `cfrace`, `cfrace sim`: the help, as asked
            print(exc.format_message())
            return 0
        return _usage_error(exc, args)
    except typer.Exit as exc:
        return exc.exit_code
    except (typer.Abort, KeyboardInterrupt) as exc:   # click turns Ctrl-C into Abort outside standalone mode
        print("interrupted", file=sys.stderr)
        return _interrupt_code(exc)
    except cx.ClickException as exc:
        print(f"error: {exc.format_message()}", file=sys.stderr)
        return exc.exit_code
    except MemoryError as exc:    # e.g. --runs 5000000: numpy cannot allocate the worlds (a flight has stopped its drones)
        print(f"error: not enough memory for this request ({str(exc).splitlines()[0] if str(exc) else 'MemoryError'}): "
              "ask for fewer runs, races or worlds", file=sys.stderr)
        return 2
    return code if isinstance(code, int) else 0


def _interrupt_code(exc: BaseException) -> int:
    """143 when the interrupt was a SIGTERM turned into KeyboardInterrupt("SIGTERM") (the flight
    stack's signal handlers), else 130 (Ctrl-C)."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return 143 if str(exc) == "SIGTERM" else 130
        exc = exc.__cause__ or exc.__context__
    return 130
