"""`cfrace reproduce`: the paper's tables, matrices and figures measured on the shipped policies
(cfrace.reproduction.evidence), or with --train the training pipeline that makes those policies."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console

from cfrace.cli.common import check_folder

console = Console()


def reproduce_cmd(
    out: Optional[Path] = typer.Option(None, "--out", help="folder for report.md, report.json and the PNGs "
                                                          "(default: report)"),
    quick: bool = typer.Option(False, "--quick", help="a few runs per cell (under a minute; figures indicative)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="seed of Table I and the matrices (default 0)"),
    test_seeds: Optional[str] = typer.Option(None, "--test-seeds",
                                             help="fresh seeds of the ours-vs-DS races (default 1,2,3; --quick: 1)"),
    runs: Optional[int] = typer.Option(None, "--runs", min=1, help="Table I runs per policy (default 50)"),
    races: Optional[int] = typer.Option(None, "--races", min=1, help="races per pair (default 50)"),
    train: bool = typer.Option(False, "--train", help="print the training pipeline (policies/pipeline.yaml)"),
    run: bool = typer.Option(False, "--run", help="with --train: run its stages in order (resumes)"),
    only: Optional[str] = typer.Option(None, "--only", help="with --train: these stages (globs, comma-separated) "
                                                            "and what they depend on"),
    runs_dir: Optional[Path] = typer.Option(None, "--runs-dir", help="with --train: folder of the stages' runs "
                                                                     "(default: the file's out, runs/pipeline)"),
) -> None:
    """Write the reproduction report: Table I, the four head-to-head matrices, competition behaviour,
    training curves, each of the paper's claims beside the measured figure."""
    from cfrace.errors import ConfigError
    from cfrace.reproduction.evidence import ReproduceConfig, reproduce

    if not train:
        for given, option in ((run, "--run"), (only is not None, "--only"), (runs_dir is not None, "--runs-dir")):
            if given:
                raise ConfigError(f"{option} belongs to the training pipeline: give --train {option} ...")
    elif quick or any(x is not None for x in (test_seeds, runs, races, out, seed)):
        raise ConfigError("--out, --quick, --seed, --test-seeds, --runs and --races belong to the report, "
                          "not to --train")
    if train:
        _pipeline(run, only, runs_dir)
        return

    kw = {k: v for k, v in (("runs", runs), ("races", races)) if v is not None}
    if test_seeds is not None:
        try:
            kw["test_seeds"] = tuple(int(s) for s in test_seeds.split(",") if s.strip())
        except ValueError:
            raise ConfigError(f"--test-seeds {test_seeds!r}: expected comma-separated integers") from None
        if not kw["test_seeds"]:
            raise ConfigError(f"--test-seeds {test_seeds!r}: no seed given (the claims need fresh seeds)")
    check_folder(out or Path("report"), "--out")
    cfg = ReproduceConfig.make(out or Path("report"), quick, seed=0 if seed is None else seed, **kw)
    report = reproduce(cfg, on_progress=lambda text: console.print(f"[dim]{text}[/dim]"))
    for claim in report["claims"]:
        mark = {True: "[green]holds[/green]", False: "[red]does not hold[/red]", None: "–"}[claim["holds"]]
        console.print(f"{claim['claim']}: {claim['measured']} (paper {claim['paper']}): {mark}")
    console.print(f"report: {cfg.out / 'report.md'} ({report['wall_s']} s)")


def _pipeline(run: bool, only: str | None, runs_dir: Path | None) -> None:
    """`reproduce --train [--run]`: the stages of policies/pipeline.yaml, printed or run."""
    from cfrace.reproduction.pipeline import describe, load_pipeline, run_pipeline

    sweep = load_pipeline(only=only)
    out_root = runs_dir or Path(sweep.out)
    for line in describe(sweep, out_root):
        console.print(line, markup=False, highlight=False, soft_wrap=True)
    if run:
        run_pipeline(sweep, out_root, echo=lambda text: console.print(text, markup=False, highlight=False))


def register(app: typer.Typer) -> None:
    """Add `reproduce`."""
    app.command("reproduce")(reproduce_cmd)
