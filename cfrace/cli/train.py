"""`cfrace train`, `cfrace export`, `cfrace bench train`: thin wrappers over cfrace.rl.train and
cfrace.export (parse, call one library function, print with rich)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.live import Live
from rich.markup import escape
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from cfrace.cli.common import write_json
from cfrace.rl.train_options import COMPILE, UPDATE_WORKERS, checked_config, takes_train_options

console = Console(emoji=False)   # paths and names print as given (a:abc:b is no emoji)

_STATS = (("gates_per_s", "gates/s", "{:.2f}"), ("success", "lap done", "{:.0%}"), ("crash_rate", "crashed", "{:.0%}"),
          ("lap_time_s", "lap s", "{:.2f}"), ("lead_share_agent0", "ego leads", "{:.0%}"),
          ("win_share_agent0", "ego wins", "{:.0%}"), ("lead_share", "lead", "{:.0%}"),
          ("win_share_agent1", "adv wins", "{:.0%}"))



def _fmt(value, spec="{:.3g}") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return spec.format(value)


def _figures(metrics: dict, info: dict) -> Table:
    """The live table under the progress bar: per-agent rewards and terms, race stats, speed."""
    n = info["meta"].get("num_agents", 1)
    names = ["ego", "adversary"][:n] if n > 1 else ["agent"]
    table = Table(show_header=True, header_style="bold", box=None, pad_edge=False)
    table.add_column("")
    for name in names:
        table.add_column(name, justify="right")
    rows = [("return (episode)", "return_agent{}"), ("reward / step", "reward_agent{}"),
            ("total reward", "total_reward_agent{}")]
    rows += [(k[5:-7], k[:-1] + "{}") for k in metrics if k.startswith("term_") and k.endswith("_agent0")]
    rows += [("value loss", "value_loss_agent{}"), ("action std", "std_agent{}"), ("alive", "alive_agent{}")]
    for label, key in rows:
        table.add_row(label, *(_fmt(metrics.get(key.format(a))) for a in range(n)))
    stats = "  ".join(f"{label} {_fmt(metrics.get('stat_' + key), spec)}" for key, label, spec in _STATS
                      if ("stat_" + key) in metrics)
    speed = (f"{metrics['fps']:,.0f} env-steps/s  (sim {metrics['sim_s']:.1f} s, policy {metrics['infer_s']:.1f} s, "
             f"update {metrics['update_s']:.1f} s per iteration)")
    outer = Table.grid()
    outer.add_row(table)
    if stats:
        outer.add_row(stats)
    outer.add_row(f"[dim]{speed}[/dim]")
    return outer


def _line(metrics: dict, info: dict) -> str:
    """One plain line for non-terminal output (logs)."""
    n = info["meta"].get("num_agents", 1)
    parts = [f"it {metrics['iteration']}", f"steps {metrics['env_steps']:,}", f"{info['progress']:.0%}",
             f"{metrics['fps']:,.0f} steps/s"]
    parts += [f"reward{a} {_fmt(metrics.get(f'reward_agent{a}'))}" for a in range(n)]
    parts += [f"return{a} {_fmt(metrics.get(f'return_agent{a}'))}" for a in range(n)]
    parts += [f"{label} {_fmt(metrics.get('stat_' + key), spec)}" for key, label, spec in _STATS
              if ("stat_" + key) in metrics]
    return "  ".join(parts)


@takes_train_options
def train_cmd(**options) -> None:
    """Train policies with IPPO; checkpoint, CSV + TensorBoard logs, training-curve PNG. Ctrl-C
    (or SIGTERM) finishes the iteration, checkpoints and exits 130."""
    cfg = checked_config(**options)   # one line, before the banner and the run folder
    resume = options["resume"]
    from cfrace.rl.train import train

    budget = " and ".join(x for x in (f"{cfg.minutes:g} min" if cfg.minutes is not None else "",
                                       f"{cfg.steps:,} env steps" if cfg.steps is not None else "") if x)
    ippo = cfg.ippo()
    per_it = ippo.num_envs * ippo.rollout
    if cfg.steps is not None and cfg.steps % per_it:
        budget += (f" (an iteration is {ippo.num_envs} worlds x {ippo.rollout} steps = {per_it:,} env steps, so it "
                   f"stops after {-(-cfg.steps // per_it) * per_it:,})")
    console.print(f"training [bold]{escape(cfg.method)}[/bold] on [bold]{escape(cfg.track)}[/bold]"   # user text
                  f"{' with obstacles' if cfg.obstacles else ''}, preset {escape(cfg.preset)}, budget {budget}, "
                  f"out {escape(cfg.out)}{' (resumed)' if resume else ''}")
    progress = Progress(TextColumn("[bold]it {task.fields[it]}"), BarColumn(), TaskProgressColumn(),
                        TextColumn("{task.fields[steps]} steps"), TimeElapsedColumn(), console=console)
    task = progress.add_task("train", total=1.0, it=0, steps=0)
    grid = Table.grid()
    grid.add_row(progress)
    last_line = [0.0]
    said_precision: list[bool] = []
    with Live(grid, console=console, refresh_per_second=4, transient=False) as live:
        def update(metrics: dict, info: dict) -> None:
            if metrics["iteration"] == 1 or not said_precision:
                said_precision.append(True)
                live.console.print(f"update precision: {info['precision'].dtype} ({info['precision'].reason})")
            progress.update(task, completed=info["progress"], it=metrics["iteration"], steps=f"{metrics['env_steps']:,}")
            view = Table.grid()
            view.add_row(progress)
            view.add_row(_figures(metrics, info))
            live.update(view)
            if not console.is_terminal and info["elapsed_s"] - last_line[0] >= 30.0:  # logs to a file: a line
                last_line[0] = info["elapsed_s"]
                live.console.print(_line(metrics, info))

        result = train(cfg, resume=resume, on_iteration=update)
    if not console.is_terminal:
        console.print()
    how = "stopped by signal, checkpointed" if result.interrupted else "done"
    console.print(f"{how}: {result.iterations} iterations, {result.env_steps:,} env steps, "
                  f"{result.wall_s / 60:.1f} min total")
    if result.exact_resume is False:
        console.print("[yellow]note: the environment has no saved state; its races restarted on resume[/yellow]")
    console.print(f"checkpoint {result.checkpoint}\nmetrics {result.out / 'metrics.csv'}  tensorboard {result.out / 'tb'}",
                  markup=False)
    if result.curve:
        console.print(f"training curve {result.curve}", markup=False)
    if result.interrupted:
        raise typer.Exit(130)      # as every command after Ctrl-C (the checkpoint is written)


def export_cmd(
    checkpoint: Path = typer.Argument(..., help="checkpoint.pt or the run folder holding it"),
    output: Path = typer.Option(..., "-o", "--output", help="ONNX file to write"),
    agent: str = typer.Option("best", "--agent", help="ego | adversary | best (greater total training reward)"),
) -> None:
    """Export a trained actor (with its observation normaliser and metadata) to ONNX; parity-checked."""
    from cfrace.export import export_checkpoint

    path, meta, err = export_checkpoint(checkpoint, output, agent)
    table = Table(title=f"exported {path}")
    table.add_column("key")
    table.add_column("value")
    for k, v in meta.items():
        table.add_row(k, json.dumps(v) if not isinstance(v, str) else v)
    table.add_row("parity (max |onnx - torch|, 1000 obs)", f"{err:.2e}")
    console.print(table)


def bench_train_cmd(
    preset: str = typer.Option("cpu", "--preset", help="cpu | paper"),
    method: str = typer.Option("ours", "--method", help="reward scheme: ours | ds | ss | dm"),
    track: str = typer.Option("complex", "--track", help="track name or YAML path"),
    obstacles: bool = typer.Option(False, "--obstacles", help="with the track's obstacles"),
    envs: Optional[int] = typer.Option(None, "--envs", min=1, help="parallel worlds (default: the preset's)"),
    iterations: int = typer.Option(3, "--iterations", min=1, help="timed iterations (after one warm-up)"),
    device: Optional[str] = typer.Option(None, "--device", help="cpu | cuda (default: cuda when available)"),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="torch threads (default 1 on CPU)"),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="override a preset field, e.g. --set epochs=3"),
    precision: str = typer.Option("auto", "--precision", help="PPO update in auto | fp32 | bf16"),
    update_workers: int = UPDATE_WORKERS,
    compile_: bool = COMPILE,
    compare: Optional[str] = typer.Option(None, "--compare",
                                          help="time a second configuration side by side: KEY=VALUE[,...] "
                                               "(e.g. precision=fp32) or a git revision (e.g. main)"),
    rounds: int = typer.Option(2, "--rounds", min=1, help="with --compare: alternating runs of each"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="write the figures to this JSON file"),
) -> None:
    """Env-steps/s of whole training iterations, split into simulation, policy inference and update."""
    from cfrace.rl.config import parse_overrides

    overrides = parse_overrides(set_ or [])
    if compare is not None:
        _bench_compare(compare, rounds, json_out, set_ or [], method=method, track=track, preset=preset,
                       envs=envs, iterations=iterations, device=device, threads=threads, precision=precision,
                       update_workers=update_workers if update_workers != 1 else None,
                       compile=True if compile_ else None)
        return
    from cfrace.rl.train import bench_train

    r = bench_train(method, track, obstacles, preset, envs, iterations, device, threads,
                    overrides=overrides, precision=precision, update_workers=update_workers,
                    compile=compile_)
    table = Table(title=f"training speed: {method} on {r['track']}, preset {r['preset']}, {r['device']}, "
                        f"{r['threads']} thread(s)")
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_row("worlds x drones", f"{r['num_envs']} x {r['num_agents']}")
    table.add_row("env steps / s (whole iterations)", f"{r['env_steps_per_s']:,.0f}")
    table.add_row("env steps / CPU s of this process", f"{r['env_steps_per_cpu_s']:,.0f}")
    table.add_row("drone steps / s", f"{r['drone_steps_per_s']:,.0f}")
    table.add_row("simulation only, env steps / s", f"{r['sim_env_steps_per_s']:,.0f}")
    table.add_row("seconds per iteration", f"{r['iteration_s']:.2f}")
    for k in ("sim", "inference", "update", "other"):
        table.add_row(f"share {k}", f"{r['share_' + k]:.0%}")
    table.add_row("update precision", f"{r['precision']['dtype']} ({r['precision']['reason']})")
    console.print(table)
    write_json(r, json_out, console, indent=2)


def _bench_compare(text: str, rounds: int, json_out: Path | None, set_: list[str], **options) -> None:
    """`bench train --compare`: this configuration (A) against the other (B), alternating; ratios A / B."""
    from cfrace.rl.speed_compare import Config, compare, parse_compare, rev_knows

    base = {k: v for k, v in options.items() if v is not None}
    a, b = Config("this tree", base), parse_compare(text, base)
    if b.rev is not None:  # an older revision may not know some options: time it with its defaults for those
        b = Config(b.label, {k: v for k, v in base.items() if rev_knows(b.rev, k)}, b.rev)

    def said(r: int, cfg: Config, res: dict) -> None:
        console.print(f"round {r + 1}: {cfg.label}: {res['env_steps_per_s']:,.0f} env steps/s")

    res = compare(a, b, set_, rounds, on_result=said)
    table = Table(title=f"bench train, {options.get('method')} on {options.get('track')}, preset "
                        f"{options.get('preset')}: medians of {rounds} alternating runs each")
    table.add_column("figure")
    for key, cfg in (("a", a), ("b", b)):
        p = res[key]["precision"]
        table.add_column(f"{key.upper()}: {cfg.label}" + (f" ({p['dtype']})" if p else ""), justify="right")
    table.add_column("A / B", justify="right")
    fmt = lambda spec, v: "–" if v is None else spec.format(v)
    for f, label, spec in (("env_steps_per_s", "env steps / s (wall clock)", "{:,.0f}"),
                           ("env_steps_per_cpu_s", "env steps / CPU s", "{:,.0f}"),
                           ("iteration_s", "s per iteration", "{:.2f}"), ("share_update", "share update", "{:.0%}"),
                           ("share_sim", "share sim", "{:.0%}"), ("share_inference", "share inference", "{:.0%}")):
        table.add_row(label, fmt(spec, res["a"]["median"][f]), fmt(spec, res["b"]["median"][f]),
                      fmt("{:.2f}x", res["ratio_a_over_b"][f]))
    console.print(table)
    write_json(res, json_out, console, indent=2)


def register(app: typer.Typer) -> None:
    """Add `train`, `export` and `bench train`."""
    from cfrace.cli.measure import bench_app

    app.command("train")(train_cmd)
    app.command("export")(export_cmd)
    bench_app.command("train")(bench_train_cmd)
