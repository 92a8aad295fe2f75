"""What every command shares: `--json FILE|-`, the drone-profile rule, exit codes of a race.

Light on purpose (no torch, onnxruntime or matplotlib): every command module imports it before
its arguments are checked.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from rich.console import Console

from cfrace.errors import ConfigError

#: `--json -`: the JSON document goes to stdout, so everything a command prints for people goes to stderr
STDOUT = "-"

#: the drone profile of `sim serve`, `fly` and `sim dry-run` unless --profile names another:
#: a Crazyflie 2.1 Brushless, the drone the flight stack is tuned for (docs/drones.md)
DEFAULT_PROFILE = "cf21bl"
#: `--profile trained`: the profile the ego policy was trained for (its metadata drone_profile)
TRAINED = "trained"

_json_stream = None   #: the real stdout once human output went to stderr (json_to_stdout)


def json_to_stdout(args: list[str]) -> bool:
    """If the command line says `--json -`, send everything printed for people (rich tables,
    progress, plain prints) to stderr from now on, keeping stdout for the JSON document alone."""
    global _json_stream
    wanted = any(a == "--json=-" or (a == "--json" and i + 1 < len(args) and args[i + 1] == STDOUT)
                 for i, a in enumerate(args))
    if wanted and _json_stream is None:
        _json_stream = sys.stdout
        sys.stdout = sys.stderr
    return wanted


def restore_stdout() -> None:
    """Undo json_to_stdout (the end of a command run in-process, e.g. by tests)."""
    global _json_stream
    if _json_stream is not None:
        sys.stdout, _json_stream = _json_stream, None


def to_stdout(path: Path | str | None) -> bool:
    """True when `--json` asks for stdout."""
    return path is not None and str(path) == STDOUT


def human_console(json_path: Path | str | None) -> Console:
    """Where a command prints its tables: stdout, or stderr when its JSON goes to stdout."""
    return Console(stderr=to_stdout(json_path))


def clean(obj):
    """JSON-safe copy: NaN/inf -> None, tuples -> lists, numpy scalars -> numbers."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item):
        return clean(obj.item())
    return obj


def write_json(doc, path: Path | str | None, said: Console | None = None, *, indent: int = 1) -> None:
    """Every `--json`: write doc to the file (parents made), or to stdout for "-". ``said``: a
    console to print "wrote FILE" on."""
    if path is None:
        return
    text = json.dumps(clean(doc), indent=indent, default=str, allow_nan=False) + "\n"
    if to_stdout(path):
        stream = _json_stream or sys.stdout
        stream.write(text)
        stream.flush()
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    if said is not None:
        said.print(f"wrote {path}", highlight=False)


def choose_profile(profile: str | None, track=None, ego: str | None = None, obstacles: bool = False,
                   room: dict | None = None, config=None, what: str = "--profile") -> tuple[str, str]:
    """The one rule for the drone profile of `sim serve`, `fly` and `sim dry-run`: --profile NAME
    if given, else ``profile:`` of the flight config file ``config`` (its keys: ``room``);
    ``trained``: the ego policy's training profile; else DEFAULT_PROFILE. Returns (profile name,
    why: the words the banner and the result show)."""
    if profile is None and room and "profile" in room:
        name, rule = choose_profile(room["profile"], track, ego, obstacles, what=f"{config}: profile:")
        return name, (rule if room["profile"] == TRAINED else f"profile: in {config}")
    if profile is None:
        return DEFAULT_PROFILE, "the default (--profile to change)"
    if profile == TRAINED:
        if track is None or ego is None:
            from cfrace.errors import ConfigError
            raise ConfigError("--profile trained needs a policy (the ego's training profile)")
        from cfrace.flight.setup import training_profile
        return training_profile(track, ego, obstacles, default=DEFAULT_PROFILE), "the ego policy's training profile"
    from cfrace.paths import CALIBRATION_DIR, resolve_named
    if not resolve_named(profile, CALIBRATION_DIR, ".yaml").exists():
        from cfrace.errors import ConfigError
        known = ", ".join(sorted(p.stem for p in CALIBRATION_DIR.glob("*.yaml")))
        raise ConfigError(f"{what} {profile}: no such drone profile (known: {known}; or '{TRAINED}': the ego "
                          "policy's training profile)")
    return profile, "--profile"


def race_exit_code(result: dict, late_signal: str | None = None) -> int:
    """The exit code of `fly` / `sim dry-run` after a race (cfrace.flight.loop.race.result_exit_code:
    0, 3 when the safety checks stopped every drone, 74, 130 / 143, 1)."""
    from cfrace.flight.loop.race import result_exit_code

    return result_exit_code(result, late_signal)


def check_writable(path: Path | None, what: str) -> None:
    """ConfigError (one line) unless ``path`` can be written (`-`: stdout, always); checked before
    anything flies."""
    if path is None or to_stdout(path):
        return
    existed = path.exists()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab"):
            pass
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot write there ({exc.strerror or exc})") from None
    if not existed:
        path.unlink()


def check_port(port: int | None, what: str, host: str = "127.0.0.1") -> None:
    """ConfigError (one line) if nothing could serve on host:port now (in use, not permitted): checked
    before any link opens, so that a flight is not refused after its drones were connected."""
    if not port:       # None: no server; 0: a free port is taken
        return
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)     # as servers bind (TIME_WAIT is no use)
        try:
            s.bind((host, int(port)))
        except (OSError, OverflowError) as exc:
            raise ConfigError(f"{what} {port}: cannot serve on {host}:{port} "
                              f"({getattr(exc, 'strerror', None) or exc})") from None


def check_folder(path: Path | None, what: str) -> None:
    """ConfigError (one line) unless ``path`` is a folder or can be made one (made here)."""
    if path is None:
        return
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{what} {path}: not a folder (a file of that name exists)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot make that folder ({exc.strerror or exc})") from None
