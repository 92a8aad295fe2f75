"""Sweep files: a grid and/or a list of `cfrace train` runs with dependencies (docs/sweep.md).

    cfrace.sweep.parse.load_spec(path) -> Sweep   strict validation, one-line ConfigErrors
    Sweep.runs                        the runs in dependency order (a run after everything it needs)
    Run.train_argv(out_root)          the exact `cfrace train ...` argument list of a fresh start
    Run.resume_argv(out_root)         `cfrace train --resume ...` for the rest of the budget
    Run.export_argv(out_root)         `cfrace export ...` (None without `export:`)
    Run.done(out_root)                trained to its budget (and exported, if it exports)

The keys a run accepts are the options of `cfrace train` itself (read from its signature,
cfrace.rl.train_options.train_parameters, '-' -> '_'), so the sweep format and the command cannot
drift apart; `out` and `resume` belong to the sweep.
"""

from __future__ import annotations

import functools
import inspect
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cfrace.errors import ConfigError
from cfrace.rl.checkpoint import CHECKPOINT

VERSION = 1
TOP_KEYS = ("version", "out", "defaults", "grid", "runs")
RUN_KEYS = ("name", "after", "export", "select")   #: keys of a run that are not train options
REFERENCES = ("init_from", "fixed_opponent")       #: a run NAME (=> dependency) or a checkpoint path
SWEEP_OWNED = ("out", "resume")                    #: set by the sweep, never by the file
#: flags passed through to `cfrace train` even before this checkout's train command has them
PASS_THROUGH_FLAGS = ("keep_checkpoints",)
EXPORT_KEYS = ("file", "agent")
EXPORT_AGENTS = ("ego", "adversary", "best")
MIN_REMAINING_MIN = 1e-3   #: a minutes budget with less than this left counts as spent


@dataclass(frozen=True)
class TrainOption:
    """One option of `cfrace train`: its spec key, flag and how a value is written."""

    key: str      #: spec key (the parameter name, e.g. init_from)
    flag: str     #: --init-from
    kind: str     #: value | flag (--x when true) | toggle (--x / --no-x) | set (--set or --reward K=V ...)
    type: type    #: int | float | str (paths are str)


@functools.lru_cache(maxsize=1)
def train_options() -> dict[str, TrainOption]:
    """The options of `cfrace train`, read from the command's own signature (do not modify)."""
    from cfrace.rl.train_options import train_parameters

    hints = typing.get_type_hints(train_parameters)
    out: dict[str, TrainOption] = {}
    for name, param in inspect.signature(train_parameters).parameters.items():
        key = name.rstrip("_")
        if key in SWEEP_OWNED:
            continue
        decl = param.default.param_decls[0]
        tp = hints[name]
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        base = args[0] if args else tp
        if typing.get_origin(base) is list:
            out[key] = TrainOption(key, decl, "set", str)
        elif base is bool:
            kind = "toggle" if "/" in decl else "flag"
            out[key] = TrainOption(key, decl.split("/")[0], kind, bool)
        else:
            out[key] = TrainOption(key, decl, "value", base if base in (int, float) else str)
    for key in PASS_THROUGH_FLAGS:
        out.setdefault(key, TrainOption(key, "--" + key.replace("_", "-"), "flag", bool))
    return out


def check_train(run: "Run", out_root: str | Path, path: str) -> None:
    """ConfigError (one line naming the file and the run) where `cfrace train` would refuse the run's
    options before its banner: the command's own parser and checks (cfrace.rl.train_options.check_train_argv)."""
    from cfrace.rl.train_options import check_train_argv

    try:
        check_train_argv(run.train_argv(out_root)[1:])
    except ConfigError as exc:
        raise ConfigError(f"{path}: {run.source} ({run.name}): {exc}") from None


def fmt_value(value: Any) -> str:
    """A YAML scalar or list as `cfrace train` reads it on the command line."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    return str(value)


@dataclass(frozen=True)
class Run:
    """One training run of a sweep: its train options, dependencies and follow-ups."""

    name: str
    options: dict                   #: train option key -> value (defaults, grid/run merged)
    deps: tuple[str, ...] = ()      #: runs that must finish first (references and `after`)
    refs: dict = field(default_factory=dict)  #: reference key -> run NAME (resolved under out_root)
    export: dict | None = None      #: {file, agent}
    select: Any = None              #: stored raw for the reproduction pipeline
    source: str = ""                #: where in the file the run was defined (for messages)

    # ------------------------------------------------------------------ paths and budget
    def out_dir(self, out_root: str | Path) -> Path:
        return Path(out_root) / self.name

    def checkpoint(self, out_root: str | Path) -> Path:
        return self.out_dir(out_root) / CHECKPOINT

    @property
    def minutes(self) -> float | None:
        return self.options.get("minutes")

    @property
    def steps(self) -> int | None:
        return self.options.get("steps")

    @property
    def seed(self) -> int:
        return int(self.options.get("seed", 0))

    # ------------------------------------------------------------------ commands
    def _option_args(self, out_root: str | Path, skip: tuple[str, ...] = ()) -> list[str]:
        opts = train_options()
        argv: list[str] = []
        for key, value in self.options.items():
            if key in skip:
                continue
            opt = opts[key]
            if key in self.refs:
                value = str(reference_checkpoint(Path(out_root) / self.refs[key]))
            if opt.kind == "set":
                for k, v in value.items():
                    argv += [opt.flag, f"{k}={fmt_value(v)}"]
            elif opt.kind == "flag":
                if value:
                    argv.append(opt.flag)
            elif opt.kind == "toggle":
                argv.append(opt.flag if value else "--no-" + opt.flag[2:])
            else:
                argv += [opt.flag, fmt_value(value)]
        return argv

    def train_argv(self, out_root: str | Path) -> list[str]:
        """`cfrace train ...` arguments (without the program name) of a fresh start."""
        return ["train", *self._option_args(out_root), "--out", str(self.out_dir(out_root))]

    def resume_argv(self, out_root: str | Path) -> list[str]:
        """`cfrace train --resume OUT/NAME ...` for what is left of the budget: the steps budget
        counts across resumes, the minutes budget is reduced by the checkpoint's wall time. Only
        options a resume accepts are passed (the task and hyperparameters come from the checkpoint)."""
        argv = ["train", "--resume", str(self.out_dir(out_root))]
        keep = {"device", "threads", "checkpoint_min", "precision", *PASS_THROUGH_FLAGS}
        opts = {k: v for k, v in self.options.items() if k in keep}
        argv += Run(self.name, opts)._option_args(out_root)
        if self.minutes is not None:
            wall_s = checkpoint_progress(self.checkpoint(out_root))[1]
            argv += ["--minutes", f"{max(self.minutes - wall_s / 60.0, MIN_REMAINING_MIN):.6g}"]
        if self.steps is not None:
            argv += ["--steps", str(self.steps)]
        return argv

    def export_argv(self, out_root: str | Path = ".") -> list[str] | None:
        """`cfrace export OUT/NAME/checkpoint.pt -o FILE --agent AGENT`, or None."""
        if self.export is None:
            return None
        return ["export", str(self.checkpoint(out_root)), "-o", str(self.export["file"]),
                "--agent", self.export.get("agent", "best")]

    # ------------------------------------------------------------------ state on disk
    def trained(self, out_root: str | Path) -> bool:
        """The run's checkpoint has spent its budget (steps reached or minutes used up)."""
        ckpt = self.checkpoint(out_root)
        if not ckpt.exists():
            return False
        env_steps, wall_s = checkpoint_progress(ckpt)
        if self.steps is not None and env_steps >= self.steps:
            return True
        minutes = 30.0 if self.minutes is None and self.steps is None else self.minutes  # train's default
        return minutes is not None and wall_s / 60.0 >= minutes - MIN_REMAINING_MIN

    def started(self, out_root: str | Path) -> bool:
        """A checkpoint exists (finished or interrupted)."""
        return self.checkpoint(out_root).exists()

    def done(self, out_root: str | Path) -> bool:
        """Trained to its budget, and exported (an ONNX file newer than the checkpoint) if it exports."""
        if not self.trained(out_root):
            return False
        if self.export is None:
            return True
        onnx = Path(self.export["file"])
        return onnx.exists() and onnx.stat().st_mtime >= self.checkpoint(out_root).stat().st_mtime


SELECTED = "selected.pt"  #: a run's chosen checkpoint, where the reproduction pipeline chose one


def reference_checkpoint(run_dir: Path) -> Path:
    """What a reference to a run means: its chosen checkpoint (RUN/selected.pt, written by the
    reproduction pipeline's `select`) where there is one, else its last (RUN/checkpoint.pt)."""
    chosen = Path(run_dir) / SELECTED
    return chosen if chosen.exists() else Path(run_dir) / CHECKPOINT


def checkpoint_progress(path: Path) -> tuple[int, float]:
    """(env steps, wall seconds over all sessions) saved in a training checkpoint."""
    from cfrace.rl.train import load_checkpoint

    ckpt = load_checkpoint(path)
    return int(ckpt["runner"].get("env_steps", 0)), float(ckpt.get("wall_s", 0.0))


@dataclass(frozen=True)
class Sweep:
    path: str
    out: str                 #: the output root: `cfrace sweep --out`, else the file's `out`
    runs: tuple[Run, ...]    #: dependency order

    def run(self, name: str) -> Run:
        for r in self.runs:
            if r.name == name:
                return r
        raise KeyError(name)

    def groups(self) -> dict[str, list[Run]]:
        """Runs that differ only in their seed, keyed by a label (the curves' mean and spread)."""
        keyed: dict[str, list[Run]] = {}
        varying = _varying_keys(self.runs)
        for r in self.runs:
            label = ", ".join(f"{k}={fmt_value(r.options.get(k))}" if k != "method" else str(r.options.get(k))
                              for k in varying if k != "seed") or "all runs"
            keyed.setdefault(label, []).append(r)
        return keyed


def _varying_keys(runs) -> list[str]:
    keys: list[str] = []
    for r in runs:
        keys += [k for k in r.options if k not in keys]
    return [k for k in keys if len({json.dumps(r.options.get(k), sort_keys=True) for r in runs}) > 1]
