"""`cfrace sim` commands: serve (simulated Crazyflies over CRTP/UDP), dry-run, replay; `cfrace bench loop`."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console

sim_app = typer.Typer(help="Simulated Crazyflies: serve them, race on them (dry-run), replay logs.",
                      no_args_is_help=True)
console = Console(stderr=True)
out = Console()


@sim_app.command("serve")
def serve_cmd(
    track: str = typer.Option(..., help="Track name or YAML path."),
    drones: int = typer.Option(2, help="Number of simulated Crazyflies."),
    port: int = typer.Option(19850, help="UDP port of the first drone (pose stream on port - 1)."),
    profile: str = typer.Option("cf21bl", help="Drone profile."),
    obstacles: bool = typer.Option(True, "--obstacles/--no-obstacles", help="Simulate the track's obstacles."),
    bodies: Optional[str] = typer.Option(None, help="Body names (default cf1,cf2,...)."),
    seed: int = typer.Option(0),
):
    """Serve simulated Crazyflies on udp://127.0.0.1:PORT+i until Ctrl-C / SIGTERM."""
    from cfrace.flight.config import split_list
    from cfrace.simcf.server import serve

    serve(track, drones, port, profile, obstacles=obstacles, body_names=split_list(bodies), seed=seed,
          out=lambda text: out.print(text, highlight=False))


@sim_app.command("dry-run")
def dry_run_cmd(
    track: str = typer.Option(..., help="Track name or YAML path."),
    ego: str = typer.Option(..., help="Ego policy: ours/ds/ss/dm or an .onnx path."),
    opp: str = typer.Option(..., help="Opponent policy."),
    laps: int = typer.Option(3, help="Laps to win."),
    profile: Optional[str] = typer.Option(None, help="Drone profile, simulated and flown (default: the one "
                                                      "the ego policy was trained for, from its metadata)."),
    obstacles: bool = typer.Option(False, "--obstacles/--no-obstacles", help="Race with the track's obstacles."),
    bodies: str = typer.Option("cf1,cf2", help="Mocap body names ego,opp."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON."),
    log: Optional[Path] = typer.Option(None, help="Flight log (.mcap)."),
    faults: Optional[str] = typer.Option(None, help="KIND@T[:ego|opp],...: mocap_dropout_short, mocap_dropout_long, "
                                                    "pose_outlier, geofence, nan_policy, link_loss, stall_50ms, "
                                                    "stall_200ms, sigterm, sigint."),
    lockstep: bool = typer.Option(False, "--lockstep", help="No wall clock, no cflib: the sim advances one tick "
                                                            "per loop iteration (fast, deterministic)."),
    timeout_s: float = typer.Option(60.0, help="End the race (draw) after this many seconds of race time."),
    mocap_noise_m: float = typer.Option(0.0, help="Gaussian mocap position noise (m)."),
    mocap_latency_ms: float = typer.Option(0.0, help="Simulated mocap latency (ms): a pose reaches the loop this "
                                                     "long after it was taken (interpolated between the "
                                                     "per-tick reads of the simulated drones)."),
    latency_comp_ms: Optional[float] = typer.Option(None, help="The estimator predicts poses this many ms forward "
                                                               "(as `cfrace fly`; default: the simulated latency)."),
    seed: int = typer.Option(0),
    rt_priority: str = typer.Option("auto", help="SCHED_FIFO priority of the loop thread: auto (50 where permitted: "
                                                  "root or CAP_SYS_NICE), 0 = off, or 1-99."),
    prewarm_ms: float = typer.Option(3.0, help="Warm-up window: this many ms before each tick the loop runs the "
                                               "tick's pure parts over and over on the newest data and does not "
                                               "sleep, so that the tick runs warm; 0 = off."),
    velocity_alpha: float = typer.Option(1.0, help="Velocity filter of the pose estimator: v += alpha (difference - v), "
                                                   "(0, 1]; 1 = plain differences."),
    loop_cpu: str = typer.Option("auto", help="CPU of the loop thread: auto (the highest CPU, when there are two "
                                              "or more), off, or a CPU number; the other threads (the simulated "
                                              "drones' too) go to the other CPUs."),
    quiet: bool = typer.Option(False, "--quiet", help="No live view."),
):
    """Race two policies on simulated Crazyflies through the whole flight stack (real cflib over UDP)."""
    from cfrace.cli.flight import exit_code, print_result, write_json
    from cfrace.flight.config import FlightConfig, split_list
    from cfrace.flight.dryrun import dry_run
    from cfrace.flight.setup import resolve_race, training_profile
    from cfrace.track import load_track

    the_track = load_track(track)
    if profile is None:
        profile = training_profile(the_track, ego, obstacles)
    cfg = FlightConfig(track=track, ego=ego, opp=opp, laps=laps, profile=profile, obstacles=obstacles,
                       bodies=split_list(bodies), log=log, timeout_s=timeout_s, quiet=quiet or lockstep,
                       rt_priority=rt_priority, prewarm_s=prewarm_ms / 1e3, velocity_alpha=velocity_alpha,
                       loop_cpu=loop_cpu, latency_comp_s=(mocap_latency_ms if latency_comp_ms is None else latency_comp_ms) / 1e3)
    result = dry_run(cfg, lockstep=lockstep, faults=faults, seed=seed, mocap_noise_m=mocap_noise_m,
                     mocap_latency_s=mocap_latency_ms / 1e3, console=console, setup=resolve_race(cfg, the_track))
    print_result(result)
    write_json(result, json_out)
    code = exit_code(result)
    if code:
        sys.exit(code)


@sim_app.command("replay")
def replay_cmd(
    log: Path = typer.Argument(..., help="A flight log written by cfrace fly / cfrace sim dry-run."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON."),
    via_replay_source: bool = typer.Option(False, help="Read the frames through the mocap source "
                                                       "replay://LOG?speed=0 (one frame per tick logs)."),
):
    """Re-run a logged flight lockstep and check that every logged observation is reproduced exactly."""
    from cfrace.flight.replay import replay_log

    r = replay_log(log, via_replay_source=via_replay_source)
    verdict = "[green]identical[/green]" if r["identical"] else "[red]MISMATCH[/red]"
    out.print(f"{r['observations']} observations over {r['ticks']} ticks replayed: {verdict} "
              f"({r['mismatched']} differ, max |diff| {r['max_abs_diff']:.3g})")
    if json_out is not None:
        json_out.write_text(json.dumps(r, indent=1) + "\n")
    if not r["identical"]:
        sys.exit(1)


def register(app: typer.Typer) -> None:
    """Add `cfrace sim ...` and `cfrace bench loop` to the top-level app."""
    from cfrace.cli.bench import bench_app

    app.add_typer(sim_app, name="sim")

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
    ):
        """Flight-loop timing for two drones at 100 Hz, real time against the simulated Crazyflies."""
        from rich.table import Table

        from cfrace.flight.benchloop import bench_loop

        if policies not in ("paper", "shipped"):
            from cfrace.errors import ConfigError
            raise ConfigError(f"--policies: paper or shipped, got {policies!r}")
        r = bench_loop(duration_s, track=track, profile=profile, rt_priority=rt_priority, policies=policies,
                        prewarm_s=prewarm_ms / 1e3, loop_cpu=loop_cpu, floor_s=floor_s, log=log,
                        latency_comp_s=None if latency_comp_ms is None else latency_comp_ms / 1e3)
        loop = r["loop"]
        t = Table(title=f"flight loop, {loop['ticks']} ticks at {loop['rate_hz']:g} Hz, two drones "
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
        out.print(t)
        fl = r["floor"]
        if fl is not None:
            def ratio(ours, floor):
                return f" = {ours / floor:.1f} x the floor" if ours is not None and floor else ""
            ours_j, ours_l = loop["period_jitter_ms"]["p99"], loop["late_ms"]["p99"]
            out.print(f"machine floor, a loop with no work on the same CPU and priority for {floor_s:g} s: tick late "
                      f"p99 {fl['late_ms']['p99']:.3f} (max {fl['late_ms']['max']:.3f}), period jitter p99 "
                      f"{fl['period_jitter_ms']['p99']:.3f} ms; the flight loop: late p99 {ours_l:.3f}"
                      f"{ratio(ours_l, fl['late_ms']['p99'])}, jitter p99 {ours_j:.3f}"
                      f"{ratio(ours_j, fl['period_jitter_ms']['p99'])}", highlight=False)
        out.print("goals met: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in r["goals_met"].items())
                  + f"   (load average {r['load_avg'][0]:.2f} on {r['cpu_count']} CPUs"
                  + (f", loop thread on CPU {r['loop_cpu']}" if r["loop_cpu"] is not None else ", loop not pinned")
                  + (", loop thread SCHED_FIFO)" if r["rt_fifo"] else ")"))
        if json_out is not None:
            json_out.write_text(json.dumps(r, indent=1, default=str) + "\n")
