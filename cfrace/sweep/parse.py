"""Reading a sweep file: strict validation with one-line ConfigErrors naming the file and key
(docs/sweep.md); the data model is cfrace.sweep.spec."""

from __future__ import annotations

import itertools
import string
from pathlib import Path
from typing import Any

from cfrace.rl.inputs import check_method
from cfrace.errors import ConfigError
from cfrace.sweep.spec import (EXPORT_AGENTS, EXPORT_KEYS, REFERENCES, RUN_KEYS, SWEEP_OWNED, TOP_KEYS, VERSION, Run,
                               Sweep, TrainOption, check_train, fmt_value, train_options)
from cfrace.track import load_track
from cfrace.yamlcfg import load_yaml


def _check_value(where: str, opt: TrainOption, value: Any) -> Any:
    if opt.kind == "set":   # --set (preset fields) or --reward (reward weights): KEY=VALUE items
        example = "{gate: 10}" if opt.key == "reward" else "{lr: 3.0e-4}"
        if not isinstance(value, dict) or not value:
            raise ConfigError(f"{where}: expected a mapping of {opt.flag} items, e.g. {example}")
        if opt.key == "reward":
            from cfrace.env.rewards import parse_reward_overrides as parse
        else:
            from cfrace.rl.config import parse_overrides as parse

        try:  # one definition of what is valid: the train command's own parser
            parse([f"{k}={fmt_value(v)}" for k, v in value.items()])
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


def parse_spec(data: dict, path: str = "<sweep>", check_paths: bool = True,
               out: str | Path | None = None) -> Sweep:
    """A Sweep from the parsed YAML mapping (see load_spec)."""
    data = _mapping(path, "top level", data)
    for k in data:
        if k not in TOP_KEYS:
            raise ConfigError(f"{path}: {k}: unknown key (top level: {', '.join(TOP_KEYS)})")
    if data.get("version") != VERSION:
        raise ConfigError(f"{path}: version: expected {VERSION}, got {data.get('version')!r}")
    file_out = data.get("out")   # --out stands in for a missing `out:`; a bad one is still an error
    if ("out" in data or out is None) and (not isinstance(file_out, str) or not file_out):
        raise ConfigError(f"{path}: out: expected the output folder (a string; or give --out), got {file_out!r}")
    out = str(out) if out is not None else file_out
    defaults = _check_options(path, "defaults", _mapping(path, "defaults", data.get("defaults") or {}))
    built = _named_runs(path, defaults, _raw_runs(path, data))
    names = {name: where for name, _, where, _ in built}
    runs = {name: _linked_run(path, names, name, opts, where, extra, check_paths)
            for name, opts, where, extra in built}
    order = _dependency_order(path, runs)
    for run in order:      # what `cfrace train` refuses before its banner, refused before any run starts
        check_train(run, out, path)
    return Sweep(path, out, tuple(order))


def _raw_runs(path: str, data: dict) -> list[tuple[Any, dict, str, dict]]:
    """(name template, options, where, run-only keys) of the grid's and the list's runs."""
    raw: list[tuple[Any, dict, str, dict]] = []
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
    return raw


def _named_runs(path: str, defaults: dict, raw: list) -> list[tuple[str, dict, str, dict]]:
    """Each run's options over the defaults, under its unique name."""
    built: list[tuple[str, dict, str, dict]] = []
    names: dict[str, str] = {}
    for template, opts, where, extra in raw:
        merged = {**defaults, **opts}
        name = _name(path, where, template, merged)
        if name in names:
            raise ConfigError(f"{path}: {where}: duplicate run name {name!r} (also {names[name]})")
        names[name] = where
        _check_task(f"{path}: {where} ({name})", merged)
        built.append((name, merged, where, extra))
    return built


def _check_task(where: str, opts: dict) -> None:
    """What `cfrace train` would refuse: a method it does not know, a track it cannot load."""
    for key in ("method", "track"):
        if key not in opts:
            raise ConfigError(f"{where}: {key} missing (give it in defaults, grid or the run)")
    check_method(opts["method"], f"{where}.method: ")   # the trainer's own rule (cfrace.rl.inputs)
    try:
        load_track(opts["track"])       # as the trainer loads it: a known name or a track file
    except ConfigError as exc:
        raise ConfigError(f"{where}.track: {exc}") from None


def _linked_run(path: str, names: dict, name: str, opts: dict, where: str, extra: dict, check_paths: bool) -> Run:
    """The Run with its references (to runs of this sweep or to files on disk) and `after` resolved."""
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
        elif check_paths:  # fixed_opponent may list several files: A,B
            for part in str(value).split(",") if key == "fixed_opponent" else [value]:
                if not Path(part).exists():
                    raise ConfigError(f"{path}: {where}.{key}: {part!r} is neither a run of this sweep nor an "
                                      f"existing checkpoint or run folder")
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
    return Run(name, opts, tuple(dict.fromkeys(deps)), refs, export, extra.get("select"), where)


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


def load_spec(path: str | Path, check_paths: bool = True, out: str | Path | None = None) -> Sweep:
    """Read and validate a sweep file. ``check_paths``: references that are not runs of the sweep
    must exist on disk (checkpoint or run folder). ``out`` (`cfrace sweep --out`): the output root
    instead of the file's `out`, which may then be left out."""
    return parse_spec(load_yaml(Path(path)), str(path), check_paths, out)
