"""`cfrace sweep SPEC.yaml` and `cfrace bench sweep`: thin wrappers over cfrace.sweep."""

from __future__ import annotations

import os
import shlex
import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.live import Live
from rich.markup import escape
from rich.table import Table

# tables are wide: piped output gets 160 columns unless COLUMNS says otherwise
# no emoji codes: paths, names and addresses print as given (nohost:abc: is no emoji); user text in markup is escaped
console = Console(width=None if sys.stdout.isatty() or os.environ.get("COLUMNS") else 160, emoji=False)


def _summary(report, out_root: Path) -> None:
    console.print()
    t = Table(title="sweep summary", title_justify="left")
    for col in ("run", "state", "what", "tries", "time"):
        t.add_column(col)
    for s in report.states:
        t.add_row(escape(s.run.name), s.state, s.action or "-", str(s.attempts), f"{s.wall_s:.0f} s",
                  style="red" if s.state in ("failed", "blocked") else None)
    console.print(t)
    for s in report.states:
        if s.error and s.state in ("failed", "blocked"):
            console.print(f"[red]{escape(s.run.name)}: {escape(s.error)}[/red] "
                          f"(log: {escape(str(s.run.out_dir(out_root) / 'train.log'))})")
    ran = [s for s in report.states if s.wall_s > 0]
    if ran:
        console.print(f"sweep wall time {report.wall_s:.0f} s (after Ray was up); the {len(ran)} run(s) took "
                      f"{report.run_wall_s:.0f} s added up, the time one after another would take at the same speed: "
                      f"{report.run_wall_s / max(report.wall_s, 1e-9):.2f}x", highlight=False)


def sweep_cmd(
    spec: Path = typer.Argument(..., help="sweep file (docs/sweep.md)"),
    out: Optional[Path] = typer.Option(None, "--out", help="output root instead of the file's `out` (which "
                                                           "the file may then leave out)"),
    address: Optional[str] = typer.Option(None, "--address", help="Ray cluster address (default: a local instance)"),
    cpus: Optional[int] = typer.Option(None, "--cpus", min=1, help="CPUs of the local instance (default: all cores)"),
    retries: int = typer.Option(1, "--retries", min=0, help="times a failed run is tried again (it resumes)"),
    sequential: bool = typer.Option(False, "--sequential", help="one run after another here, without Ray"),
    dry_run: bool = typer.Option(False, "--dry-run", help="print the runs' commands and state, run nothing"),
    plot: Optional[Path] = typer.Option(None, "--plot", help="combined curves PNG (default OUT/curves.png)"),
) -> None:
    """Run a grid or list of training runs (on Ray by default); resume a stopped sweep; plot curves."""
    from cfrace.sweep.parse import load_spec

    sweep = load_spec(spec, out=out)   # every check of the real run, --dry-run included
    out_root = Path(sweep.out)
    if dry_run:
        _dry_run(sweep, out_root)
        return
    if sequential:
        from cfrace.sweep.local import run_local

        run_local(sweep, out_root, echo=lambda s: console.print(s, highlight=False, markup=False))
    else:
        _on_ray(sweep, spec, out_root, address, cpus, retries, plot)
    _curves(sweep, out_root, plot)


def _dry_run(sweep, out_root: Path) -> None:
    """Each run's state and the commands a real run would start for it now (none when it is done)."""
    from cfrace.sweep.local import start_command

    for run in sweep.runs:
        export = [run.export_argv(out_root)] if run.export is not None else []
        if run.done(out_root):
            state, argvs = "done", []
        elif run.trained(out_root):
            state, argvs = "trained, not exported", export
        else:
            action, argv = start_command(run, out_root)
            state, argvs = "new" if action == "start" else "interrupted", [argv, *export]
        console.print(f"[bold]{escape(run.name)}[/bold] ({state}; after {escape(', '.join(run.deps)) or 'nothing'})",
                      highlight=False)
        for argv in argvs:
            console.print("  cfrace " + shlex.join(argv), highlight=False, soft_wrap=True, markup=False)


def _on_ray(sweep, spec: Path, out_root: Path, address: Optional[str], cpus: Optional[int], retries: int,
            plot: Optional[Path]) -> None:
    """The sweep on Ray with a live table; Ctrl-C or SIGTERM stops it with one line (exit 130 / 143)."""
    from cfrace.sweep.progress import progress_table
    from cfrace.sweep.ray_exec import require_ray, run_ray

    require_ray()
    title = escape(f"sweep {spec} -> {out_root}" + (f" on {address}" if address else " on a local Ray instance"))
    console.print(f"{title}: {len(sweep.runs)} runs, starting Ray...")
    last = [0.0]
    try:
        with Live(console=console, refresh_per_second=2, transient=False) as live:
            def update(states) -> None:
                live.update(progress_table(states, out_root, title))
                if not console.is_terminal and time.perf_counter() - last[0] >= 30.0:  # logs: a table every 30 s
                    last[0] = time.perf_counter()
                    live.console.print(progress_table(states, out_root, title))

            report = run_ray(sweep, out_root, address, cpus, retries, on_update=update)
    except KeyboardInterrupt as exc:   # run_ray turns SIGTERM into KeyboardInterrupt("SIGTERM")
        how = "SIGTERM" if str(exc) == "SIGTERM" else "Ctrl-C"
        print(f"sweep stopped ({how}); run the same command again to resume", file=sys.stderr)
        raise typer.Exit(143 if how == "SIGTERM" else 130) from None
    _summary(report, out_root)
    if not report.ok:
        _curves(sweep, out_root, plot)
        console.print(f"[red]{len(report.failed)} run(s) failed, {len(report.blocked)} blocked[/red]; "
                      f"run the same command again to resume")
        sys.exit(1)


def _curves(sweep, out_root: Path, plot: Optional[Path]) -> None:
    from cfrace.sweep.curves import sweep_curves

    for path in sweep_curves(sweep, out_root, plot):
        console.print(f"combined training curves {path}", markup=False)


def bench_sweep_cmd(
    method: str = typer.Option("ds", "--method", help="reward scheme of the runs: ours | ds | ss | dm"),
    track: str = typer.Option("lemniscate", "--track", help="track name or YAML path"),
    envs: Optional[int] = typer.Option(None, "--envs", min=1, help="worlds per run (default: the cpu preset's)"),
    iterations: int = typer.Option(3, "--iterations", min=1, help="timed iterations per run (after one warm-up)"),
    address: Optional[str] = typer.Option(None, "--address", help="Ray cluster address (default: a local instance)"),
    spec: Optional[Path] = typer.Option(None, "--spec", help="also time this sweep file one run after another "
                                                             "and on Ray (fresh temporary folders)"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="write the figures to this JSON file"),
) -> None:
    """Env-steps/s of one single-thread training run alone vs two at once, as Ray tasks; with load."""
    from cfrace.cli.evaluate import _write_json
    from cfrace.sweep.ray_scaling import bench_parallel, bench_sweep_wall

    r = bench_parallel(method, track, envs, iterations, address)
    t = Table(title=f"training runs under Ray: {method} on {track}, {r['num_envs']} worlds, 1 thread each")
    t.add_column("figure")
    t.add_column("value", justify="right")
    t.add_row("one run alone, env steps/s", f"{r['alone_env_steps_per_s']:,.0f}")
    for i, v in enumerate(r["pair_env_steps_per_s"]):
        t.add_row(f"two at once, run {i + 1}, env steps/s", f"{v:,.0f}")
    t.add_row("two at once, total env steps/s", f"{r['pair_total_env_steps_per_s']:,.0f}")
    t.add_row("[bold]speed-up (two together / one alone)[/bold]", f"[bold]{r['speedup']:.2f}x[/bold]")
    if r["alone_cores"] is not None:
        t.add_row("env steps per CPU second: alone / two at once",
                  f"{r['alone_env_steps_per_cpu_s']:,.0f} / " + " + ".join(f"{v:,.0f}"
                                                                   for v in r["pair_env_steps_per_cpu_s"]))
        t.add_row("cores the runs got: alone / two at once",
                  f"{r['alone_cores']:.2f} / " + " + ".join(f"{v:.2f}" for v in r["pair_cores"]))
    console.print(t)
    console.print(f"load before: {r['load_before']}\nload after: {r['load_after']}", highlight=False)
    console.print("CPU use while the two ran (share of one core; ours are the ray:: workers):\n"
                  + "\n".join(r["busy_processes"]), highlight=False)
    if spec is not None:
        w = bench_sweep_wall(spec, address)
        r["sweep_wall"] = w
        console.print(f"sweep {spec} ({w['runs']} runs): one after another {w['sequential_wall_s']:.0f} s, on Ray "
                      f"{w['ray_wall_s']:.0f} s (+ {r['ray_start_s']:.0f} s to start Ray): "
                      f"[bold]{w['speedup']:.2f}x[/bold]; "
                      f"{w['load_before']} before, {w['load_after']} after", highlight=False)
    _write_json(json_out, r)


def register(app: typer.Typer) -> None:
    """Add `sweep` and `bench sweep`."""
    from cfrace.cli.measure import bench_app

    app.command("sweep")(sweep_cmd)
    bench_app.command("sweep")(bench_sweep_cmd)
