"""Sweep files: a grid and/or a list of `cfrace train` runs with dependencies (docs/sweep.md).

    load_spec(path) -> Sweep          strict validation, one-line ConfigErrors naming file and key
    Sweep.runs                        the runs in dependency order (a run after everything it needs)
    Run.train_argv(out_root)          the exact `cfrace train ...` argument list of a fresh start
    Run.resume_argv(out_root)         `cfrace train --resume ...` for the rest of the budget
    Run.export_argv(out_root)         `cfrace export ...` (None without `export:`)
    Run.done(out_root)                trained to its budget (and exported, if it exports)

The keys a run accepts are the options of `cfrace train` itself (read from its signature, '-' ->
'_'), so the sweep format and the command cannot drift apart; `out` and `resume` belong to the sweep.
"""

from __future__ import annotations

import functools
import inspect
import itertools
import json
import string
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cfrace.errors import ConfigError
from cfrace.rl.checkpoint import CHECKPOINT
from cfrace.yamlcfg import load_yaml

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
    kind: str     #: value | flag (--x when true) | toggle (--x / --no-x) | set (--set K=V ...)
    type: type    #: int | float | str (paths are str)


@functools.lru_cache(maxsize=1)
def train_options() -> dict[str, TrainOption]:
    """The options of `cfrace train`, read from the command's own signature (do not modify)."""
    from cfrace.cli.train import train_cmd

    hints = typing.get_type_hints(train_cmd)
    out: dict[str, TrainOption] = {}
    for name, param in inspect.signature(train_cmd).parameters.items():
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


def _fmt_value(value: Any) -> str:
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
                    argv += ["--set", f"{k}={_fmt_value(v)}"]
            elif opt.kind == "flag":
                if value:
                    argv.append(opt.flag)
            elif opt.kind == "toggle":
                argv.append(opt.flag if value else "--no-" + opt.flag[2:])
            else:
                argv += [opt.flag, _fmt_value(value)]
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
    out: str                 #: the output root of the file (`cfrace sweep --out` overrides it)
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
            label = ", ".join(f"{k}={_fmt_value(r.options.get(k))}" if k != "method" else str(r.options.get(k))
                              for k in varying if k != "seed") or "all runs"
            keyed.setdefault(label, []).append(r)
        return keyed


def _varying_keys(runs) -> list[str]:
    keys: list[str] = []
    for r in runs:
        keys += [k for k in r.options if k not in keys]
    return [k for k in keys if len({json.dumps(r.options.get(k), sort_keys=True) for r in runs}) > 1]


# ---------------------------------------------------------------------------------------- loading
def _check_value(where: str, opt: TrainOption, value: Any) -> Any:
    if opt.kind == "set":
        if not isinstance(value, dict) or not value:
            raise ConfigError(f"{where}: expected a mapping of preset fields, e.g. {{lr: 3.0e-4}}")
        from cfrace.rl.config import parse_overrides

        try:  # one definition of what is valid: the train command's own parser
            parse_overrides([f"{k}={_fmt_value(v)}" for k, v in value.items()])
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        return dict(value)
    if opt.type is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if opt.type is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if opt.type is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return value
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    return value


def _check_options(path: str, where: str, data: dict, allowed: tuple[str, ...] = ()) -> dict:
    opts = train_options()
    out = {}
    for key, value in data.items():
        if key in allowed:
            continue
        if key in SWEEP_OWNED:
            raise ConfigError(f"{path}: {where}.{key}: set by the sweep (OUT/NAME), not in the file")
        if key not in opts:
            raise ConfigError(f"{path}: {where}.{key}: unknown key (train options: {', '.join(sorted(opts))}; "
                              f"run keys: {', '.join(RUN_KEYS)})")
        out[key] = _check_value(f"{path}: {where}.{key}", opts[key], value)
    return out


def _mapping(path: str, where: str, value: Any) -> dict:
    if not isinstance(value, dict):
        raise ConfigError(f"{path}: {where}: expected a mapping, got {type(value).__name__}")
    for k in value:
        if not isinstance(k, str):
            raise ConfigError(f"{path}: {where}: keys must be strings, got {k!r}")
    return value


def _grid_runs(path: str, grid: dict) -> list[tuple[str, dict, str]]:
    grid = dict(_mapping(path, "grid", grid))
    template = grid.pop("name", None)
    opts = train_options()
    axes = {k: v for k, v in grid.items() if isinstance(v, list) and k in opts and opts[k].kind != "set"}
    for k, v in axes.items():
        if not v:
            raise ConfigError(f"{path}: grid.{k}: empty list")
    scalars = _check_options(path, "grid", {k: v for k, v in grid.items() if k not in axes})
    out = []
    for combo in itertools.product(*axes.values()):
        opts = {**scalars, **_check_options(path, "grid", dict(zip(axes, combo)))}
        out.append((template, opts, "grid"))
    return out


def _default_name(opts: dict) -> str:
    """`cfrace train`'s default folder name: METHOD_TRACK[_obstacles]_sSEED."""
    return (f"{opts.get('method')}_{Path(str(opts.get('track'))).stem}{'_obstacles' if opts.get('obstacles') else ''}"
            f"_s{opts.get('seed', 0)}")


def _name(path: str, where: str, template: Any, opts: dict) -> str:
    if template is None:
        return _default_name(opts)
    if not isinstance(template, str) or not template:
        raise ConfigError(f"{path}: {where}.name: expected a string, got {template!r}")
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(template) if f]
        for f in fields:
            if f not in opts:
                raise ConfigError(f"{path}: {where}.name: '{{{f}}}' is not an option of this run "
                                  f"({', '.join(sorted(opts))})")
        name = template.format(**opts)
    except (ValueError, IndexError) as exc:
        raise ConfigError(f"{path}: {where}.name: bad template {template!r} ({exc})") from None
    if not name or "/" in name or name in (".", "..") or name.startswith("."):
        raise ConfigError(f"{path}: {where}.name: {name!r} is not a folder name")
    return name


def _export(path: str, where: str, value: Any) -> dict:
    value = _mapping(path, f"{where}.export", value)
    for k in value:
        if k not in EXPORT_KEYS:
            raise ConfigError(f"{path}: {where}.export.{k}: unknown key ({', '.join(EXPORT_KEYS)})")
    if not isinstance(value.get("file"), str) or not value["file"].endswith(".onnx"):
        raise ConfigError(f"{path}: {where}.export.file: expected an .onnx path, got {value.get('file')!r}")
    agent = value.get("agent", "best")
    if agent not in EXPORT_AGENTS:
        raise ConfigError(f"{path}: {where}.export.agent: one of {', '.join(EXPORT_AGENTS)}, got {agent!r}")
    return {"file": value["file"], "agent": agent}


def parse_spec(data: dict, path: str = "<sweep>", check_paths: bool = True) -> Sweep:
    """A Sweep from the parsed YAML mapping (see load_spec)."""
    data = _mapping(path, "top level", data)
    for k in data:
        if k not in TOP_KEYS:
            raise ConfigError(f"{path}: {k}: unknown key (top level: {', '.join(TOP_KEYS)})")
    if data.get("version") != VERSION:
        raise ConfigError(f"{path}: version: expected {VERSION}, got {data.get('version')!r}")
    out = data.get("out")
    if not isinstance(out, str) or not out:
        raise ConfigError(f"{path}: out: expected the output folder (a string), got {out!r}")
    defaults = _check_options(path, "defaults", _mapping(path, "defaults", data.get("defaults") or {}))
    raw: list[tuple[Any, dict, str, dict]] = []   # (name template, options, where, run-only keys)
    if data.get("grid") is not None:
        raw += [(t, o, w, {}) for t, o, w in _grid_runs(path, data["grid"])]
    runs_list = data.get("runs")
    if runs_list is not None and not isinstance(runs_list, list):
        raise ConfigError(f"{path}: runs: expected a list of runs, got {type(runs_list).__name__}")
    for i, item in enumerate(runs_list or []):
        where = f"runs[{i}]"
        item = _mapping(path, where, item)
        opts = _check_options(path, where, item, allowed=RUN_KEYS)
        if "name" not in item:
            raise ConfigError(f"{path}: {where}.name: missing")
        raw.append((item["name"], opts, where, {k: item[k] for k in RUN_KEYS if k in item and k != "name"}))
    if not raw:
        raise ConfigError(f"{path}: no runs (give a grid and/or runs)")

    built: list[tuple[str, dict, str, dict]] = []
    names: dict[str, str] = {}
    for template, opts, where, extra in raw:
        merged = {**defaults, **opts}
        name = _name(path, where, template, merged)
        if name in names:
            raise ConfigError(f"{path}: {where}: duplicate run name {name!r} (also {names[name]})")
        names[name] = where
        for key in ("method", "track"):
            if key not in merged:
                raise ConfigError(f"{path}: {where} ({name}): {key} missing (give it in defaults, grid or the run)")
        built.append((name, merged, where, extra))

    runs: dict[str, Run] = {}
    for name, opts, where, extra in built:
        refs, deps = {}, []
        for key in REFERENCES:
            if key not in opts:
                continue
            value = opts[key]
            if value in names:
                if value == name:
                    raise ConfigError(f"{path}: {where}.{key}: run {name!r} refers to itself")
                refs[key] = value
                deps.append(value)
            elif check_paths and not Path(value).exists():
                raise ConfigError(f"{path}: {where}.{key}: {value!r} is neither a run of this sweep nor an existing "
                                  f"checkpoint or run folder")
        after = extra.get("after", [])
        if isinstance(after, str):
            after = [after]
        if not isinstance(after, list) or not all(isinstance(a, str) for a in after):
            raise ConfigError(f"{path}: {where}.after: expected a list of run names, got {after!r}")
        for a in after:
            if a not in names:
                raise ConfigError(f"{path}: {where}.after: unknown run {a!r}")
            if a == name:
                raise ConfigError(f"{path}: {where}.after: run {name!r} refers to itself")
            deps.append(a)
        export = _export(path, where, extra["export"]) if "export" in extra else None
        runs[name] = Run(name, opts, tuple(dict.fromkeys(deps)), refs, export, extra.get("select"), where)
    return Sweep(path, out, tuple(_dependency_order(path, runs)))


def _dependency_order(path: str, runs: dict[str, Run]) -> list[Run]:
    """Depth-first topological order that keeps the file's order where it can; cycles are errors."""
    order: list[Run] = []
    state: dict[str, int] = {}   # 1 visiting, 2 done
    stack: list[str] = []

    def visit(name: str) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            cycle = stack[stack.index(name):] + [name]
            raise ConfigError(f"{path}: dependency cycle: {' -> '.join(cycle)}")
        state[name] = 1
        stack.append(name)
        for d in runs[name].deps:
            visit(d)
        stack.pop()
        state[name] = 2
        order.append(runs[name])

    for name in runs:
        visit(name)
    return order


def load_spec(path: str | Path, check_paths: bool = True) -> Sweep:
    """Read and validate a sweep file. ``check_paths``: references that are not runs of the sweep
    must exist on disk (checkpoint or run folder)."""
    return parse_spec(load_yaml(Path(path)), str(path), check_paths)
