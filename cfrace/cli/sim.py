"""`cfrace sim` commands: serve (simulated Crazyflies over CRTP/UDP), script (a cflib script against
them), dry-run, replay."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console

from cfrace.cli.common import DEFAULT_PROFILE, check_port, check_writable, choose_profile, human_console, write_json
from cfrace.cli.flight import FOXGLOVE_HELP
from cfrace.rehearsal.faults import KINDS as FAULT_KINDS

sim_app = typer.Typer(help="Simulated Crazyflies: serve them, race on them (dry-run), replay logs.",
                      no_args_is_help=True)
console = Console(stderr=True)
out = Console()


@sim_app.command("serve")
def serve_cmd(
    track: str = typer.Option(..., help="Track name or YAML path."),
    drones: int = typer.Option(2, min=1, help="Number of simulated Crazyflies."),
    port: int = typer.Option(19850, help="UDP port of the first drone (pose stream on port - 1)."),
    profile: Optional[str] = typer.Option(None, help=f"Drone profile (default {DEFAULT_PROFILE}, as `fly` and "
                                                      "`sim dry-run`)."),
    obstacles: bool = typer.Option(False, "--obstacles/--no-obstacles", help="Simulate the track's obstacles "
                                                                             "(off by default, as in `fly`)."),
    bodies: Optional[str] = typer.Option(None, help="Body names (default cf1,cf2,...)."),
    seed: int = typer.Option(0, help="Seed of the simulated drones' noise and start positions."),
    decks: str = typer.Option("lighthouse", help="Decks each drone carries: lighthouse, flow (positioning), "
                                                 "ledring (its memories), comma-separated, or none (external "
                                                 "position only)."),
    reset_after_flight: bool = typer.Option(False, "--reset-after-flight",
                                            help="Put every drone back on the start grid once a flight is over "
                                                 "(motors off, no packet for 1 s). Off: they stay where they "
                                                 "landed, as real drones do."),
):
    """Serve simulated Crazyflies on udp://127.0.0.1:PORT+i until Ctrl-C / SIGTERM."""
    from cfrace.flight.config import split_list
    from cfrace.simcf.server import serve

    if profile == "trained":
        from cfrace.errors import ConfigError
        raise ConfigError("--profile trained: `sim serve` flies no policy; name the profile (e.g. cf2x_paper)")
    profile, rule = choose_profile(profile)
    first = [f"drone profile {profile}: {rule}; obstacles {'on' if obstacles else 'off'} "
             f"(`cfrace fly` must be given the same: --profile, --obstacles)"]

    def say(text: str) -> None:     # the profile line with the banner, once the drones are served
        while first:
            out.print(first.pop(), highlight=False)
        out.print(text, highlight=False)

    serve(track, drones, port, profile, obstacles=obstacles, body_names=split_list(bodies), seed=seed,
          decks=() if decks.strip() == "none" else tuple(split_list(decks) or ()),
          reset_after_flight=reset_after_flight, out=say)


@sim_app.command("script", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def script_cmd(
    ctx: typer.Context,
    script: Path = typer.Argument(..., help="A Python script that flies Crazyflies with cflib, e.g. one of "
                                            "cflib's examples; its own arguments follow it."),
    port: int = typer.Option(19850, help="The --port of the `cfrace sim serve` to fly."),
    drones: int = typer.Option(2, min=1, help="The --drones of that `cfrace sim serve`."),
):
    """Run a cflib script unmodified against `cfrace sim serve`: its radio URIs reach the served drones
    (address E7E7E7E7E7 the first, E7E7E7E7xx the drone with radio id xx = 1, 2, ...). Exits with the
    script's exit code."""
    from cfrace.simcf.cflib_script import run_script, served_links

    sys.exit(run_script(script, list(ctx.args), served_links(port, drones)))


@sim_app.command("dry-run")
def dry_run_cmd(
    track: str = typer.Option(..., help="Track name or YAML path."),
    ego: Optional[str] = typer.Option(None, help="Ego policy: ours/ds/ss/dm or an .onnx path."),
    opp: Optional[str] = typer.Option(None, help="Opponent policy."),
    policies: Optional[str] = typer.Option(None, help="N drones instead of --ego/--opp: P1,...,PN (repeats allowed)."),
    drones: Optional[int] = typer.Option(None, min=2, help="N drones; one --policies entry (or --ego): all fly it."),
    laps: int = typer.Option(3, help="Laps to win."),
    profile: Optional[str] = typer.Option(None, help=f"Drone profile, simulated and flown (default {DEFAULT_PROFILE}, "
                                                      "as `fly` and `sim serve`; 'trained': the one the ego "
                                                      "policy was trained for, from its metadata)."),
    obstacles: Optional[bool] = typer.Option(None, "--obstacles/--no-obstacles",
                                             help="Race with the track's obstacles (default: off, as `fly`)."),
    config: Optional[Path] = typer.Option(None, help="The flight config YAML of `cfrace fly --config`: the dry-run "
                                                     "takes its profile, obstacles and safety limits (the room's "
                                                     "URIs and mocap are not used), so it flies what `fly` will."),
    bodies: Optional[str] = typer.Option(None, help="Mocap body names, one per drone (default cf1,...,cfN)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON (- : to stdout)."),
    log: Optional[Path] = typer.Option(None, help="Flight log (.mcap)."),
    foxglove: Optional[int] = typer.Option(None, "--foxglove", metavar="[PORT]", help=FOXGLOVE_HELP),
    faults: Optional[str] = typer.Option(None, help="KIND@T[:ego|opp|dK],...: " + ", ".join(FAULT_KINDS) + "."),
    lockstep: bool = typer.Option(False, "--lockstep", help="No wall clock, no cflib: the sim advances one tick "
                                                            "per loop iteration (fast, deterministic)."),
    timeout_s: float = typer.Option(60.0, help="End the race (draw) after this many seconds of race time."),
    mocap_noise_m: float = typer.Option(0.0, help="Gaussian mocap position noise (m)."),
    mocap_latency_ms: float = typer.Option(0.0, min=0.0, help="Simulated mocap latency (ms): a pose reaches the loop this "
                                                     "long after it was taken (interpolated between the "
                                                     "per-tick reads of the simulated drones)."),
    latency_comp_ms: Optional[float] = typer.Option(None, help="The estimator predicts poses this many ms forward "
                                                               "(as `cfrace fly`; default: the simulated latency)."),
    seed: int = typer.Option(0, help="Seed of the simulation (start positions, mocap noise, faults)."),
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
    start: str = typer.Option("ground", help="ground: the policies take off; hover: the drones take off to "
                                             "their start positions on the high-level commander first."),
    landing: bool = typer.Option(True, "--landing/--no-landing", help="Land at the race's end and on soft "
                                                                      "failsafes (off: motors off, they drop)."),
    pose_stream: bool = typer.Option(True, "--pose-stream/--no-pose-stream",
                                     help="Stream each drone's mocap pose to it (external position)."),
    idle_thrust: Optional[int] = typer.Option(None, min=0, max=65535, help="powerDist.idleThrust (counts per motor) "
                                              "the simulated drones boot with (default 0; a Crazyflie 2.1 Brushless "
                                              "boots with 7000: rehearse with that)."),
):
    """Race 2 (--ego/--opp) or N (--policies, --drones) simulated Crazyflies through the whole flight stack
    (real cflib over UDP)."""
    from cfrace.cli.flight import race_and_report, race_policies
    from cfrace.flight.config import FlightConfig, check_policy_sources, load_flight_file, split_list
    from cfrace.rehearsal.dryrun import dry_run
    from cfrace.flight.setup import resolve_race
    from cfrace.track import load_track

    room = load_flight_file(config) if config else {}
    check_policy_sources(room, config, ego, opp, split_list(policies))
    if policies is None:     # the file's drones where none are typed, as `fly` merges them
        if ego is None and opp is None and room.get("policies"):
            policies = ",".join(room["policies"])
        else:
            ego, opp = ego or room.get("ego"), opp or room.get("opp")
    specs, the_track = race_policies(ego, opp, policies, drones), load_track(track)
    obstacles, profile, rule = _room(room, config, profile, obstacles, the_track, specs[0])
    cfg = FlightConfig(track=track, ego=specs[0], opp=specs[1], policies=specs if len(specs) > 2 else (), laps=laps,
                       profile=profile, obstacles=obstacles, **({"safety": room["safety"]} if "safety" in room else {}),
                       bodies=split_list(bodies) or (), log=log, timeout_s=timeout_s,
                       quiet=quiet or lockstep, foxglove_port=foxglove,
                       rt_priority=rt_priority, prewarm_s=prewarm_ms / 1e3, velocity_alpha=velocity_alpha,
                       loop_cpu=loop_cpu, latency_comp_s=(mocap_latency_ms if latency_comp_ms is None else latency_comp_ms) / 1e3,
                       start=start, landing=landing, pose_stream=pose_stream)
    check_writable(log, "--log")
    check_port(foxglove, "--foxglove")
    race_and_report(lambda say: dry_run(cfg, lockstep=lockstep, faults=faults, seed=seed, mocap_noise_m=mocap_noise_m,
                                        mocap_latency_s=mocap_latency_ms / 1e3, console=console,
                                        setup=resolve_race(cfg, the_track), announce=say, idle_thrust=idle_thrust),
                    rule, json_out)


def _room(room: dict, config: Path | None, profile: str | None, obstacles: bool | None, track, ego: str):
    """What the dry-run takes from `fly`'s config file ``room`` (its keys) besides the policies:
    (obstacles, profile, the words of the profile rule); the options win over the file."""
    if obstacles is None:
        obstacles = bool(room.get("obstacles", False))
    name, rule = choose_profile(profile, track, ego, obstacles, room, config)
    return obstacles, name, rule


@sim_app.command("faults")
def faults_cmd(
    track: str = typer.Option("lemniscate", help="Track (its shipped ours / ds policies race)."),
    processes: bool = typer.Option(True, "--processes/--no-processes",
                                   help="Also kill -9 `cfrace fly` and cut a link, with `cfrace sim serve` "
                                        "and `cfrace fly` as separate processes (about 30 s more)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the rows as JSON (- : to stdout)."),
    drones: str = typer.Option("2", help="Drone counts of the dry-run faults, comma-separated (e.g. 2,4: every "
                                         "fault again with ours, ds, ours, ds; the fault hits d1)."),
):
    """Every fault and bad-input scenario through the real stack, as one table (docs/flight.md)."""
    from dataclasses import asdict

    from rich.table import Table

    from cfrace.rehearsal.fault_suite import HEADER, run_suite

    from cfrace.errors import ConfigError
    from cfrace.flight.config import split_list

    try:
        counts = [int(n) for n in split_list(drones)]
    except ValueError:
        counts = []
    if not counts or not all(2 <= n <= 8 for n in counts):
        raise ConfigError(f"--drones: expected drone counts from 2 to 8, comma-separated, got {drones!r}")
    rows = run_suite(track, processes, drones=tuple(counts))
    table = Table(title=f"faults and bad inputs, {track}")
    for col in HEADER:
        table.add_column(col, overflow="fold")
    for r in rows:
        table.add_row(*r.cells())
    out.print(table)
    write_json([asdict(r) for r in rows], json_out)
    failed = [r.scenario for r in rows if not r.passed]
    if failed:
        console.print(f"error: {len(failed)} scenario(s) failed: {', '.join(failed)}", highlight=False)
        sys.exit(1)


@sim_app.command("replay")
def replay_cmd(
    log: Path = typer.Argument(..., help="A flight log written by cfrace fly / cfrace sim dry-run."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON (- : to stdout)."),
    via_replay_source: bool = typer.Option(False, help="Read the frames through the mocap source "
                                                       "replay://LOG?speed=0 (one frame per tick logs)."),
):
    """Re-run a logged flight lockstep and check that every logged observation is reproduced exactly.
    Exit code 0: identical; 1: an observation differs, or the log holds none; 2: not a flight log."""
    from cfrace.rehearsal.replay import replay_log

    check_writable(json_out, "--json")
    r = replay_log(log, via_replay_source=via_replay_source)
    verdict = ("[green]identical[/green]" if r["identical"] else
               "[red]nothing to compare[/red] (the log ends before the first policy step)" if not r["observations"]
               else "[red]MISMATCH[/red]")
    detail = (f" ({r['mismatched']} differ: {r['not_replayed']} not replayed, the others by at most "
              f"{r['max_abs_diff']:.3g})" if r["mismatched"] else "")
    human_console(json_out).print(f"{r['observations']} observations over {r['ticks']} ticks replayed: {verdict}{detail}")
    write_json(r, json_out)
    if not r["identical"]:
        sys.exit(1)


def register(app: typer.Typer) -> None:
    """Add `cfrace sim ...` to the top-level app."""
    app.add_typer(sim_app, name="sim")


def _numbers(option: str, text: str, kind=float) -> tuple:
    from cfrace.errors import ConfigError
    try:
        values = tuple(kind(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"{option}: comma-separated numbers, got {text!r}") from None
    if not values:
        raise ConfigError(f"{option}: at least one value")
    return values


@sim_app.command("robustness")
def robustness_cmd(
    track: str = typer.Option("lemniscate", help="Track name or YAML path."),
    ego: str = typer.Option("ours", help="First policy: ours/ds/ss/dm or an .onnx path."),
    opp: str = typer.Option("ds", help="Second policy."),
    latencies_ms: str = typer.Option("0,10,20,30", "--latencies-ms", help="Mocap latencies (ms), comma-separated."),
    profiles: str = typer.Option("cf2x_paper,cf21bl", help="Drone profiles flown, comma-separated."),
    noise_mm: str = typer.Option("1,3", "--noise-mm", help="Mocap position noise std (mm), comma-separated."),
    seeds: str = typer.Option("1,2,3", help="Seeds per cell, comma-separated."),
    laps: int = typer.Option(2, help="Laps per run."),
    duels: int = typer.Option(2, help="Head-to-head races per seed and cell (slots swapped every other); 0: none."),
    alone: bool = typer.Option(True, "--alone/--no-alone", help="Also fly each policy alone (the other stopped)."),
    comp_ms: Optional[float] = typer.Option(None, "--comp-ms", help="Latency compensation of the estimator (ms); "
                                                                     "default: as much as the latency (the dry-run's)."),
    firmware_idle: bool = typer.Option(False, "--firmware-idle", help="Each profile at its firmware's idle thrust "
                                                                      "(the Brushless: 7000 counts; default: the simulator's 0)."),
    out_dir: Path = typer.Option(Path("robustness"), "--out", help="Folder of robustness.json / .md / .png."),
    quick: bool = typer.Option(False, "--quick", help="A small grid: latencies 0,20, noise 1 mm, seed 1, 1 lap, "
                                                      "1 race (CI size)."),
):
    """Fly two policies through the lockstep flight stack over a grid of latency x drone profile x mocap
    noise x seeds: alone (laps flown, failures by cause, lap time) and head to head; table and heat map."""
    from cfrace.evaluate.robustness import Grid, run_grid, write
    from cfrace.policy import resolve_policy

    from cfrace.errors import ConfigError, PolicyError
    from cfrace.track import load_track

    the_track = load_track(track)
    for option, p in (("--ego", ego), ("--opp", opp)):
        try:
            resolve_policy(p, the_track.name, False)
        except PolicyError as exc:
            raise ConfigError(f"{option}: {exc}") from None
    kw = dict(latencies_ms=_numbers("--latencies-ms", latencies_ms), profiles=tuple(x.strip() for x in profiles.split(",") if x.strip()),
              noise_mm=_numbers("--noise-mm", noise_mm), seeds=_numbers("--seeds", seeds, int), laps=laps, duels=duels)
    grid = Grid(track=track, ego=ego, opp=opp, alone=alone, comp_ms=comp_ms, firmware_idle=firmware_idle,
                **kw).check()   # what was typed
    if quick:
        grid = grid.quick().check()
    check_writable(out_dir / "robustness.json", "--out")
    result = run_grid(grid, on_progress=lambda t: console.print(t, highlight=False))
    files = write(result, out_dir)
    out.print(files["md"].read_text(), highlight=False, soft_wrap=True)
    out.print(f"wrote {files['json']}, {files['md']}, {files['png']} ({result['wall_s']:.0f} s)", highlight=False)
