"""The training pipeline that makes every shipped policy: policies/pipeline.yaml, a sweep file
(docs/sweep.md) whose runs are the stages, with warm starts as dependencies.

`cfrace reproduce --train` prints the stages and their exact commands; `--run` runs them one after
another (cfrace.sweep.local.run_local: finished stages are skipped, interrupted ones resumed), and
`cfrace sweep policies/pipeline.yaml` runs the same file on Ray.

A stage with a ``select`` block chooses its shipped checkpoint on validation races instead of taking
the last one (cfrace.reproduction.select):

    select:
      against: ds        # race this shipped policy (short name, resolved for the stage's setting);
                         # omit to score alone (single-agent benchmark)
      runs: 50           # runs or races per checkpoint
      laps: 3
      seed: 0            # the validation seed; report on other seeds
      agent: ego         # which actor of a multi-agent checkpoint (ego | adversary | best)
      alone_min: 0.9     # with against: fly each checkpoint alone too, choose among those that
                         # finish at least this share of the runs (optional)
      export: policies/ours_complex.onnx

The chosen checkpoint is linked as OUT/NAME/selected.pt: later stages that name this one
(init_from, fixed_opponent) start from it, not from its last checkpoint (a sweep on Ray, which
does not select, uses the last one). After a stage is done, its training curve is kept as policies/curves/{method}_{setting}_s{seed}.csv
(a reduced metrics.csv, so that `cfrace reproduce` draws the curves on a fresh clone).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import os
import shutil
from pathlib import Path

from cfrace.errors import ConfigError
from cfrace.paths import POLICIES_DIR, ROOT
from cfrace.sweep.spec import SELECTED

PIPELINE = POLICIES_DIR / "pipeline.yaml"
SELECT_KEYS = {"against", "runs", "laps", "seed", "agent", "export", "alone_min"}


def load_pipeline(path: Path = PIPELINE, only: str | None = None):
    """The pipeline's Sweep; with ``only`` (comma-separated globs of stage names) just those stages
    and everything they depend on."""
    from cfrace.sweep.parse import load_spec

    sweep = load_spec(path, check_paths=False)
    for run in sweep.runs:
        if run.select is not None:
            bad = set(run.select) - SELECT_KEYS if isinstance(run.select, dict) else {"(not a mapping)"}
            if bad or "export" not in run.select:
                raise ConfigError(f"{path}: {run.name}.select: unknown key(s) {sorted(bad)} or no export "
                                  f"(keys: {', '.join(sorted(SELECT_KEYS))})")
    # the files it reads and writes are named relative to the repository (policies/...), wherever it
    # runs from (and wherever its printed commands are pasted)
    sweep = dataclasses.replace(sweep, runs=tuple(
        dataclasses.replace(r, options=_repo_paths(r.options),
                            export=None if r.export is None else {**r.export, "file": str(ROOT / r.export["file"])},
                            select=None if r.select is None
                            else {**r.select, "export": str(ROOT / r.select["export"])})
        for r in sweep.runs))
    if only:
        globs = [g.strip() for g in only.split(",") if g.strip()]
        keep = {r.name for r in sweep.runs if any(fnmatch.fnmatch(r.name, g) for g in globs)}
        if not keep:
            raise ConfigError(f"--only {only!r}: no stage matches (stages: {', '.join(r.name for r in sweep.runs)})")
        todo = list(keep)
        while todo:
            for dep in sweep.run(todo.pop()).deps:
                if dep not in keep:
                    keep.add(dep)
                    todo.append(dep)
        sweep = dataclasses.replace(sweep, runs=tuple(r for r in sweep.runs if r.name in keep))
    return sweep


def _repo_paths(options: dict) -> dict:
    """A stage's train options with every file they name inside the repository (--init-from,
    --fixed-opponent: A,B) made absolute; references to other stages are left as they are."""
    out = dict(options)
    for key in ("init_from", "fixed_opponent"):
        if isinstance(out.get(key), str):
            out[key] = ",".join(str(ROOT / x.strip()) if (ROOT / x.strip()).is_file() else x
                                for x in out[key].split(","))
    return out


def describe(sweep, out_root: Path) -> list[str]:
    """Each stage as lines: name, state, its `cfrace train` command and what follows it."""
    lines = []
    for i, run in enumerate(sweep.runs, 1):
        state = "done" if run.done(out_root) and _selected(run, out_root) else (
            "trained" if run.trained(out_root) else ("started" if run.started(out_root) else "to do"))
        after = f" (after {', '.join(run.deps)})" if run.deps else ""
        lines.append(f"# {i}. {run.name}{after}: {state}")
        lines.append("cfrace " + " ".join(run.train_argv(out_root)))
        if run.export is not None:
            lines.append("cfrace " + " ".join(run.export_argv(out_root)))
        if run.select is not None:
            s = run.select
            vs = f"races against {s['against']}" if s.get("against") else "runs alone"
            if s.get("against") and s.get("alone_min") is not None:
                vs += f" among those finishing >= {s['alone_min']:.0%} of the runs alone"
            lines.append(f"# choose among {run.out_dir(out_root)}/checkpoints/ by {s.get('runs', 50)} {vs} "
                         f"(seed {s.get('seed', 0)}), export the chosen {s.get('agent', 'best')} actor to "
                         f"{s['export']}")
    return lines


def _selected(run, out_root: Path) -> bool:
    if run.select is None:
        return True
    mark = run.out_dir(out_root) / "selected.json"
    return mark.exists() and mark.stat().st_mtime >= run.checkpoint(out_root).stat().st_mtime


def first_own_iteration(opts: dict) -> int:
    """The first checkpoint a stage may choose: after a warm start the actors stay frozen for the
    critic warm-up (cfrace.rl.train: iterations 0 .. critic_warmup - 1), so the checkpoints before
    iteration critic_warmup + 1 hold the warm start's actor, not this stage's (the SS stage on the
    complex track chose such a checkpoint: its DS warm start)."""
    if not opts.get("init_from"):
        return 0
    from cfrace.rl.train import TrainConfig

    warmup = opts.get("critic_warmup", TrainConfig.__dataclass_fields__["critic_warmup"].default)
    return int(warmup) + 1 if int(warmup) > 0 else 0


def post_stage(run, out_dir: Path, echo=print, curves_dir: Path = POLICIES_DIR / "curves") -> None:
    """After a stage is done: choose and export its checkpoint (select), keep its training curve."""
    from cfrace.reproduction.select import score_run
    from cfrace.rl.curves import reduce_metrics

    opts = run.options
    track, obstacles = opts["track"], bool(opts.get("obstacles", False))
    setting = f"{Path(track).stem}{'_obstacles' if obstacles else ''}"
    if run.select is not None and not _selected(run, out_dir.parent):
        s = run.select
        first = first_own_iteration(opts)
        echo(f"{run.name}: scoring its checkpoints from iteration {first} on seed {s.get('seed', 0)}")
        scored = score_run(out_dir, track, obstacles, s.get("against"), int(s.get("runs", 50)), int(s.get("laps", 3)),
                           int(s.get("seed", 0)), s.get("agent", "best"),
                           on_row=lambda r: echo(f"  it {r['iteration']}: " + ", ".join(
                               f"{k} {r[k]}" for k in ("success", "lap_time_s", "win_rate") if r.get(k) is not None)),
                           min_iteration=first, alone_min=s.get("alone_min"))
        dest = Path(s["export"])
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(scored.chosen["onnx"], dest)
        chosen = out_dir / SELECTED  # what later stages warm-start from (cfrace.sweep.spec.reference_checkpoint)
        chosen.unlink(missing_ok=True)
        os.link(scored.chosen["checkpoint"], chosen)
        (out_dir / "selected.json").write_text(json.dumps({"chosen": scored.chosen, "rows": scored.rows,
                                                           "select": s}, indent=2, default=str) + "\n")
        echo(f"{run.name}: chose iteration {scored.chosen['iteration']} -> {dest}")
    metrics = out_dir / "metrics.csv"
    if metrics.exists() and (run.export is not None or run.select is not None):
        reduce_metrics(metrics, Path(curves_dir) / f"{opts['method']}_{setting}_s{run.seed}.csv")


def run_pipeline(sweep, out_root: Path, echo=print) -> None:
    """Run the stages in order (resuming), each followed by post_stage."""
    from cfrace.sweep.local import run_local

    run_local(sweep, out_root, post_run=lambda run, out_dir: post_stage(run, out_dir, echo), echo=echo,
              log_dir=True)
