"""`cfrace bench ...`: benchmarks that print figures (the measuring: cfrace.sim.throughput and the modules
each command names). Other CLI modules add commands to `bench_app`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from cfrace.cli.common import write_json
from cfrace.errors import ConfigError
from cfrace.track import ground_start_positions, load_track

bench_app = typer.Typer(help="Benchmarks that print figures (speed, latency).", no_args_is_help=True)
console = Console()


def summary_table(rows: list[dict]) -> Table:
    from cfrace.sim.throughput import MODES, rate_text

    table = Table(title="simulator speed: drone-steps per second (one drone, one 2 ms step)")
    modes = [m for m in MODES if any(r[m] is not None for r in rows)]
    for col in ("worlds", "x drones", "= drones", *[f"cfrace {m}" for m in modes], "cfrace best",
                "crazyflow", "cfrace/crazyflow"):
        table.add_column(col, justify="right")
    for r in rows:
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}x"
        table.add_row(str(r["worlds"]), str(r["drones"]), str(r["total_drones"]), *[rate_text(r[m]) for m in modes],
                      rate_text(r["best"]), rate_text(r["crazyflow"]), ratio)
    return table


def _ints(text: str, what: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--{what}: expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 1 for v in values):
        raise ConfigError(f"--{what}: expected positive integers, got {text!r}")
    return values


def _measure(bench, sizes: list[int], drones: int, modes: list[str], **measure) -> tuple:
    """bench.measure_all under a progress bar (one step per size and mode)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("bench sim"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task("sim", total=len(sizes) * len(modes))

        def said(text: str) -> None:
            bar.console.print(text)
            bar.advance(task)

        return bench.measure_all(sizes, drones, modes, said, **measure)


@bench_app.command("sim")
def sim_cmd(
    worlds: str = typer.Option("1,64,1024,4096", help="comma-separated world counts"),
    drones: int = typer.Option(2, min=1, help="drones per world"),
    steps: int = typer.Option(30, min=1, help="timed policy steps (each `substeps` physics steps)"),
    warmup: int = typer.Option(3, min=1, help="untimed policy steps first (torch.compile compiles here)"),
    repeats: int = typer.Option(3, min=1, help="timed repeats per size and mode; the fastest counts"),
    substeps: int = typer.Option(10, min=1, help="physics steps of 2 ms per policy step"),
    compile: bool = typer.Option(False, "--compile/--no-compile", help="also measure torch.compile (minutes of "
                                                                       "compiling per size on a small machine)"),
    modes_opt: str = typer.Option("", "--modes", help="comma-separated subset of c,eager,compiled "
                                  "(default: c if built, else eager; compiled with --compile). eager at "
                                  "4096 worlds takes minutes on a small machine"),
    peer: Optional[bool] = typer.Option(None, "--peer/--no-peer",
                                        help="run the crazyflow peer (default: when a peer python is found)"),
    peer_python_path: Optional[Path] = typer.Option(None, "--peer-python", help="python of the crazyflow venv"),
    peer_calls: int = typer.Option(3, min=1, help="timed sim.step(1000) calls per size on the peer; the fastest counts"),
    threads: int = typer.Option(0, min=0, help="CPU threads for torch (and XLA); 0 keeps the defaults"),
    track: str = typer.Option("complex", help="track name or path"),
    profile: str = typer.Option("cf2x_paper", help="drone profile name or path"),
    scenario: str = typer.Option("hover", help="hover: drones 1.5 m before gate 0 | gates: every drone "
                                 "0.6 m before a gate, within reach of its frame bars"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="also write all numbers to this JSON file"),
) -> None:
    """Simulator drone-steps per second for each world count (C kernel, torch eager, torch.compile)
    against crazyflow."""
    from cfrace.sim import throughput as bench

    sizes = _ints(worlds, "worlds")
    modes = bench.checked_modes(compile, modes_opt, drones, scenario, track, profile)   # before any output
    if threads > 0:
        import torch

        torch.set_num_threads(threads)
    machine = bench.machine_info(threads)
    console.print(f"[bold]cfrace bench sim[/bold] on {machine['cpu']} ({machine['cores']} cores, torch "
                  f"{machine['torch']}, {machine['torch_threads']} threads), load average "
                  f"{machine['loadavg_start'][0]:.2f}")
    n = len(sizes) * len(modes)
    console.print(f"modes: {', '.join(modes)}; {n} measurements ({len(sizes)} sizes x {len(modes)} modes), "
                  f"{repeats} x {steps} timed steps each")
    results, errors = _measure(bench, sizes, drones, modes, steps=steps, warmup=warmup, substeps=substeps,
                               track=track, profile=profile, repeats=repeats, scenario=scenario)
    if not results:   # every mode asked for failed: nothing measured is no result
        raise ConfigError("no mode could run: " + "; ".join(f"{m}: {e}" for m, e in errors.items()))
    peer_doc = bench.measure_peer(peer, bench.peer_python(peer_python_path), sizes, drones, peer_calls, threads,
                                  console.print)
    machine["loadavg_end"] = list(os.getloadavg())
    rows = bench.summarize(results, (peer_doc or {}).get("results", []))
    console.print(summary_table(rows))
    if peer_doc:
        console.print(f"crazyflow {peer_doc['versions'].get('crazyflow')} (jax {peer_doc['versions'].get('jax')}): "
                      "first_principles + attitude control, 500 Hz, sim.step(1000) jitted; no collision checks")
    console.print(f"load average at start {machine['loadavg_start'][0]:.2f}, at end {machine['loadavg_end'][0]:.2f}")
    write_json(bench.bench_doc(results, peer_doc, rows, machine, errors), json_out, console, indent=2)


@bench_app.command("loop")
def bench_loop_cmd(
    duration_s: float = typer.Option(10.0, help="Seconds of real-time flight to measure."),
    track: str = typer.Option("lemniscate", help="Track name."),
    profile: Optional[str] = typer.Option(None, help="Drone profile (default: the shipped policies' training "
                                                     "profile with --policies shipped, else cf21bl)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the figures as JSON."),
    rt_priority: str = typer.Option("auto", help="SCHED_FIFO priority of the loop thread: auto (50 where permitted: "
                                              "root or CAP_SYS_NICE), 0 = off, or 1-99."),
    policies: str = typer.Option("paper", help="paper: a hold controller in the paper's actor size "
                                               "[512, 512, 256, 128]; shipped: policies/ours_TRACK vs ds_TRACK."),
    prewarm_ms: float = typer.Option(3.0, help="Warm-up window this many ms before each tick (as `cfrace fly`); "
                                               "0 = off."),
    latency_comp_ms: Optional[float] = typer.Option(None, help="Mocap latency compensation (as `cfrace fly`; "
                                                               "default 10: the pose stream is 0-10 ms old)."),
    loop_cpu: str = typer.Option("auto", help="CPU of the loop thread (as `cfrace fly`): auto, off or a CPU "
                                              "number; the simulated drones run on the other CPUs."),
    log: bool = typer.Option(True, "--log/--no-log", help="Write the flight log, as `cfrace fly` does."),
    floor_s: float = typer.Option(5.0, help="First measure the machine's floor this long: a loop with no work "
                                            "on the same CPU and priority (0 = skip)."),
    foxglove: bool = typer.Option(False, "--foxglove", help="Also fly with the live Foxglove server on (as `fly "
                                                             "--foxglove`, a free port): the loop without and with it, "
                                                             "alternating, and their ratios."),
    rounds: int = typer.Option(2, min=1, help="With --foxglove: runs of each, alternating."),
    pose_stream: bool = typer.Option(True, "--pose-stream/--no-pose-stream", help="Stream each drone's mocap pose "
                                                                                  "to it, as `cfrace fly` does."),
    compare_pose_stream: int = typer.Option(0, help="N > 0: the loop without and with the pose stream, "
                                                    "alternating, N runs each of --duration-s, in one run."),
    drones: str = typer.Option("2", help="Drones per run; a list (2,4,8) runs each in turn and prints the "
                                         "compute figures as ratios to the first."),
):
    """Flight-loop timing for N drones (2 by default) at 100 Hz, real time against the simulated Crazyflies."""
    if policies not in ("paper", "shipped"):
        raise ConfigError(f"--policies: paper or shipped, got {policies!r}")
    counts = drone_counts(drones)
    grid_track = load_track(track)
    for n in counts:                  # every count fits the track's start grid (one line if not) before any run
        ground_start_positions(grid_track, n)
    options = dict(track=track, profile=profile, rt_priority=rt_priority, policies=policies,
                   prewarm_s=prewarm_ms / 1e3, loop_cpu=loop_cpu, log=log,
                   latency_comp_s=None if latency_comp_ms is None else latency_comp_ms / 1e3)
    if foxglove or compare_pose_stream > 0:   # a comparison for each drone count
        docs = [_foxglove_compare(duration_s, rounds, options | {"pose_stream": pose_stream, "drones": n})
                if foxglove else _pose_stream_compare(duration_s, compare_pose_stream, options | {"drones": n})
                for n in counts]
        write_json(docs[0] if len(docs) == 1 else {"runs": docs}, json_out)
        return
    _loop_runs(counts, json_out, floor_s, duration_s, **options, pose_stream=pose_stream)


def _pose_stream_compare(duration_s: float, rounds: int, options: dict) -> dict:
    """The loop without and with the pose stream, alternating (cfrace.rehearsal.loop_timing): a table."""
    from cfrace.rehearsal.loop_timing import compare_pose_stream

    c = compare_pose_stream(duration_s, rounds, **options)
    t = Table(title=f"pose stream, {options.get('drones', 2)} drones: median of {rounds} run(s) each, "
                    f"{duration_s:g} s, alternating")
    for col in ("", "without", "with", "with / without"):
        t.add_column(col)
    for k in c["without"]:
        t.add_row(k, str(c["without"][k]), str(c["with"][k]), str(c["ratio_with_over_without"].get(k, "")))
    console.print(t)
    console.print(f"load average {c['load_avg']}")
    return c


def drone_counts(drones: str) -> list[int]:
    """The drone counts of ``--drones`` ("2,4,8"), 2 to 16 each."""
    try:
        counts = [int(x) for x in drones.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--drones: numbers like 2,4,8, got {drones!r}") from None
    if not counts or any(not 2 <= n <= 16 for n in counts):
        raise ConfigError(f"--drones: 2 to 16 drones per run, got {drones!r}")
    return counts


def _loop_runs(counts: list[int], json_out, floor_s: float, duration_s: float, **options) -> None:
    """bench_loop for each drone count: tables, ratios to the first, JSON."""
    from cfrace.rehearsal.loop_timing import bench_loop

    runs = []
    for n in counts:
        r = bench_loop(duration_s, floor_s=floor_s if not runs else 0.0, drones=n, **options)
        runs.append(r)
        console.print(loop_table(r))
        if r["floor"] is not None:
            console.print(floor_line(r, floor_s), highlight=False)
        console.print(goals_line(r))
    if len(runs) > 1:
        console.print(ratio_line(runs), highlight=False)
    write_json(runs[0] if len(runs) == 1 else {"runs": runs, "ratios": loop_ratios(runs)}, json_out)


def loop_ratios(runs: list[dict]) -> list[dict]:
    """Per run: drones and compute p50 / p99 and skipped ticks, with compute as a ratio to the first run."""
    base = runs[0]["loop"]["compute_ms"]
    out = []
    for r in runs:
        c = r["loop"]["compute_ms"]
        out.append({"drones": r["drones"], "compute_p50_ms": c["p50"], "compute_p99_ms": c["p99"],
                    "p50_ratio": round(c["p50"] / base["p50"], 2) if c["p50"] and base["p50"] else None,
                    "p99_ratio": round(c["p99"] / base["p99"], 2) if c["p99"] and base["p99"] else None,
                    "skipped": r["loop"].get("skipped"), "end": r["end"]})
    return out


def ratio_line(runs: list[dict]) -> str:
    parts = [f"{x['drones']} drones: compute p50 {x['compute_p50_ms']} ms (x{x['p50_ratio']}), p99 "
             f"{x['compute_p99_ms']} ms (x{x['p99_ratio']}), skipped {x['skipped']}" for x in loop_ratios(runs)]
    return "one run, ratios to the first: " + "; ".join(parts)


def _foxglove_compare(duration_s: float, rounds: int, options: dict) -> dict:
    """`bench loop --foxglove`: cfrace.rehearsal.loop_timing.compare_foxglove, printed as a table."""
    from cfrace.rehearsal.loop_timing import compare_foxglove

    def said(i: int, name: str, r: dict) -> None:
        console.print(f"round {i + 1}, {name}: compute p99 {r['loop']['compute_ms']['p99']:.3f} ms, "
                      f"jitter p99 {r['loop']['period_jitter_ms']['p99']:.3f} ms, end {r['end']}", highlight=False)

    doc = compare_foxglove(duration_s, rounds, on_run=said, **options)
    names = doc["configs"]
    t = Table(title=f"flight loop and Foxglove, {options.get('drones', 2)} drones: medians of {rounds} alternating "
                    f"runs of {duration_s:g} s each (ms)")
    for col in ("figure", *names, *[f"{n} / {names[0]}" for n in names[1:]]):
        t.add_column(col, justify="right" if col != "figure" else "left")
    for label, fig in doc["figures"].items():
        med = [fig["ms"][n] for n in names]
        t.add_row(label, *[f"{m:.3f}" for m in med], *[f"{m / med[0]:.2f}x" if med[0] else "-" for m in med[1:]])
    console.print(t)
    console.print(f"load average {os.getloadavg()[0]:.2f} (the machine is shared: ratios from one run, "
                  f"alternating, are what to compare)", highlight=False)
    return doc


def loop_table(r: dict) -> Table:
    """The figures of a bench_loop result as a table (ms)."""
    loop = r["loop"]
    t = Table(title=f"flight loop, {loop['ticks']} ticks at {loop['rate_hz']:g} Hz, {r.get('drones', 2)} drones "
                    f"({r['policies']}), ms")
    for col in ("figure", "p50", "p99", "max", "goal (p99)"):
        t.add_column(col)
    rows = [("compute latency", loop["compute_ms"], "1.0"), ("period jitter", loop["period_jitter_ms"], "0.5"),
            ("tick start late", loop["late_ms"], "")]
    rows += [(f"observation {n}", s, "") for n, s in loop["observation_ms"].items()]
    rows += [(f"inference {n} (ONNX)", s, "0.2") for n, s in loop["inference_ms"].items()]
    rows += [("compute, CPU time only", loop["compute_cpu_ms"], "")]
    if r["prewarm_s"] > 0:
        rows += [(f"warm-up in the {r['prewarm_s'] * 1e3:g} ms before each tick, CPU per tick "
                  f"({loop['prewarm_calls_mean']:.1f} passes; not in compute)", loop["prewarm_ms"], "")]
    for name, s, goal in rows:
        if s["p50"] is None:
            t.add_row(name, "-", "-", "-", goal)
            continue
        t.add_row(name, f"{s['p50']:.3f}", f"{s['p99']:.3f}", f"{s['max']:.3f}", goal)
    return t


def floor_line(r: dict, floor_s: float) -> str:
    """The machine's floor against the flight loop's late and jitter p99."""
    loop, fl = r["loop"], r["floor"]

    def ratio(ours, floor):
        return f" = {ours / floor:.1f} x the floor" if ours is not None and floor else ""
    ours_j, ours_l = loop["period_jitter_ms"]["p99"], loop["late_ms"]["p99"]
    return (f"machine floor, a loop with no work on the same CPU and priority for {floor_s:g} s: tick late "
            f"p99 {fl['late_ms']['p99']:.3f} (max {fl['late_ms']['max']:.3f}), period jitter p99 "
            f"{fl['period_jitter_ms']['p99']:.3f} ms; the flight loop: late p99 {ours_l:.3f}"
            f"{ratio(ours_l, fl['late_ms']['p99'])}, jitter p99 {ours_j:.3f}"
            f"{ratio(ours_j, fl['period_jitter_ms']['p99'])}")


def goals_line(r: dict) -> str:
    return ("goals met: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in r["goals_met"].items())
            + f"   (load average {r['load_avg'][0]:.2f} on {r['cpu_count']} CPUs"
            + (f", loop thread on CPU {r['loop_cpu']}" if r["loop_cpu"] is not None else ", loop not pinned")
            + (", loop thread SCHED_FIFO)" if r["rt_fifo"] else ")"))


def register(app: typer.Typer) -> None:
    """Add the bench group to the top-level app."""
    app.add_typer(bench_app, name="bench")
