"""`cfrace fly`: race two Crazyflies from motion capture with two ONNX policies (docs/flight.md)."""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from cfrace.cli.common import (DEFAULT_PROFILE, check_port, check_writable, choose_profile, human_console, race_exit_code,
                               write_json)
from cfrace.errors import ConfigError

console = Console(stderr=True)
out = Console()

#: the forms of --mocap (cfrace.flight.mocap.sources)
MOCAP_FORMS = ("vicon://HOST, optitrack://HOST, qualisys://HOST, vrpn://HOST, replay://LOG.mcap, "
               "or sim://HOST:PORT for `cfrace sim serve`'s drones (its pose port: first drone's port - 1)")
FOXGLOVE_HELP = ("Serve the flight live to Foxglove (3D scene, commands) on ws://127.0.0.1:PORT; "
                 "`--foxglove` alone: port 8765.")


def _ms(stats: dict | None) -> str:
    if not stats or stats.get("p50") is None:
        return "-"
    return f"{stats['p50']:.3f} / {stats['p99']:.3f} / {stats['max']:.3f}"


def print_result(result: dict, con: Console = out) -> None:
    """The race result, loop timing figures and safety events as rich tables."""
    end, winner = result.get("end"), result.get("winner")
    con.print(f"[bold]race end:[/bold] {end}   [bold]winner:[/bold] {winner}   "
              f"duration {result.get('duration_s', 0):.2f} s   (track {result.get('track')}, "
              f"drone profile {result.get('profile')})")
    drones = result.get("drones") or []
    if drones:
        t = Table(title="drones")
        for col in ("drone", "policy", "laps (gates)", "lap times s", "speed max / mean m/s", "result"):
            t.add_column(col, overflow="fold")
        for d in drones:
            mean = "-" if d["speed_mean"] is None else f"{d['speed_mean']:.1f}"
            res = drone_outcome(d, result)
            t.add_row(f"{d['name']} ({d['body']})", str(d.get("method")), f"{d['laps']} ({d['gates_passed']})",
                      ", ".join(f"{x:.2f}" for x in d["lap_times"]) or "-", f"{d['speed_max']:.1f} / {mean}", res)
        con.print(t)
    loop = result.get("loop")
    if loop:
        con.print(loop_table(loop))
    events = result.get("safety_events") or []
    if events:
        t = Table(title="safety events")
        for col in ("t s", "kind", "drone", "action", "detail"):
            t.add_column(col)
        for e in events:
            t.add_row(f"{e['t']:.2f}", e["kind"], e["drone"] or "all", e["action"], e["detail"])
        con.print(t)
    else:
        con.print("safety events: none")
    if result.get("hover_start"):
        con.print(f"hover start: held within {result['hover_start']['hold_error_m']} m of the start positions")
    for name, land in (result.get("landings") or {}).items():
        if land is None:
            continue
        how = (f"down {land['t']:.2f} s after it began, {abs(land['vz_mps']):.2f} m/s at "
               f"({land['place'][0]:.2f}, {land['place'][1]:.2f})"
               + (f", after holding {land['held_s']:.2f} s for another drone" if land.get("held_s") else "")
               if land.get("down") and land.get("t") is not None
               else f"not down ({land.get('cut') or 'landing timeout'})")
        spot = f"spot ({land['spot'][0]:.2f}, {land['spot'][1]:.2f})" if land.get("spot") else "no spot chosen yet"
        con.print(f"landing {name} ({land['reason']}): {spot}, {how}")
    for d in result.get("drones_final") or []:
        con.print(f"  {final_state(d)}", highlight=False)
    if result.get("profile_rule"):
        con.print(f"drone profile {result.get('profile')}: {result['profile_rule']}", highlight=False)
    if result.get("log_error"):
        console.print(f"error: flight log incomplete: {result['log_error']}", highlight=False)
    elif result.get("log"):
        con.print(f"flight log: {result['log']}")


def drone_outcome(d: dict, result: dict) -> str:
    """How one drone's race ended, in words."""
    end = result.get("end")
    if d["stopped"] and d["stop_t"] is not None and d["stop_kind"] != end:
        return f"stopped: {d['stop_kind']} at {d['stop_t']:.2f} s"
    if end == "operator_kill" or result.get("operator_kill"):
        return f"stopped by the operator ({result.get('operator_kill') or 'kill'}) at {result.get('duration_s') or 0:.2f} s"
    if end == "finished":
        return "finished the laps" if d["name"] == result.get("winner") or result.get("winner") == "draw" \
            else "flew until the winner finished"
    if end == "timeout":
        return "flew until the time-out"
    return f"stopped: the race ended ({end})"


def final_state(d: dict) -> str:
    """A simulated drone's firmware state after the race, in words."""
    if d["motors_off"]:
        motors = "motors off"
        if d.get("thrust_counts"):
            why = "by its watchdog" if d.get("watchdog") not in (None, "ok") else "by the firmware"
            motors += f" (stopped {why}; last setpoint {d['thrust_counts']} counts)"
    else:
        motors = f"motors ON at {d['thrust_counts']} counts"
    armed = "armed" if d["armed"] else "disarmed"
    return f"{d['body']}: {motors}, {armed}, watchdog {d['watchdog']}"


def loop_table(loop: dict, title: str | None = None) -> Table:
    """The loop figures (cfrace.flight.log.timing.loop_figures) as the table every command prints."""
    t = Table(title=title or f"loop timing, {loop['ticks']} ticks at {loop['rate_hz']:g} Hz (ms, p50 / p99 / max)")
    t.add_column("figure")
    t.add_column("ms")
    t.add_row("compute (tick start -> setpoints sent)", _ms(loop["compute_ms"]))
    t.add_row("period (tick start to tick start)", _ms(loop.get("period_ms")))
    t.add_row(f"period jitter |period - {1e3 / loop['rate_hz']:g} ms|", _ms(loop["period_jitter_ms"]))
    t.add_row("tick start late", _ms(loop["late_ms"]))
    for name, s in loop["observation_ms"].items():
        t.add_row(f"observation {name}", _ms(s))
    for name, s in loop["inference_ms"].items():
        t.add_row(f"inference {name} (ONNX)", _ms(s))
    t.add_row("skipped ticks", str(loop.get("skipped", 0)))
    return t


def race_policies(ego: str | None, opp: str | None, policies: str | None, drones: int | None) -> tuple[str, ...]:
    """The policy of every drone from --ego/--opp (two), or --policies P1,...,PN, or one policy and
    --drones N (every drone flies it). ConfigError (one line) on a mix that does not add up."""
    from cfrace.flight.config import MAX_DRONES, split_list

    if policies is not None:
        if ego is not None or opp is not None:
            raise ConfigError("give either --policies P1,...,PN or --ego and --opp, not both")
        specs = split_list(policies) or ()
        if len(specs) == 1 and drones:
            specs = specs * drones
    elif ego is not None and opp is not None:
        specs = (ego, opp)
        if drones not in (None, 2):
            raise ConfigError(f"--drones {drones} with --ego/--opp: give --policies P1,...,P{drones} instead")
    elif ego is not None and drones:
        specs = (ego,) * drones
    else:
        raise ConfigError("give --ego and --opp (two drones) or --policies P1,...,PN")
    if drones is not None and len(specs) != drones:
        raise ConfigError(f"--drones {drones} but {len(specs)} policies given ({','.join(specs)})")
    if not 2 <= len(specs) <= MAX_DRONES:
        raise ConfigError(f"a race needs 2 to {MAX_DRONES} drones, got {len(specs)}")
    return tuple(specs)


def announce(meta: dict, con: Console = console) -> None:
    """One line per drone and the limits, printed once everything answered, before arming."""
    if meta.get("profile"):
        con.print(f"drone profile {meta['profile']}: {meta.get('profile_rule') or '--profile'}", highlight=False)
    if meta.get("foxglove"):
        con.print(f"Foxglove: open connection {meta['foxglove']} (Foxglove WebSocket)", highlight=False)
    for (name, pol), uri, body in zip(meta["policies"].items(), meta["uris"], meta["bodies"]):
        con.print(f"{name}: {pol['method']} policy {pol['path']} ({pol['obs_layout']}) -> {uri}, mocap body {body}",
                  highlight=False)
    for note in meta.get("notes", ()):
        con.print(f"warning: {note}", highlight=False)
    f, s = meta["fence"], meta["safety"]
    con.print(f"fence x {f.lo[0]:.2f}..{f.hi[0]:.2f}, y {f.lo[1]:.2f}..{f.hi[1]:.2f}, z <= {f.hi[2]:.2f} m; "
              f"speed <= {s['speed_max_mps']:g} m/s, tilt <= {s['tilt_max_deg']:g} deg, "
              f"mocap stale {s['mocap_stale_s'] * 1e3:.0f} ms, link silent {s['link_timeout_s'] * 1e3:.0f} ms; "
              f"poses predicted {meta.get('latency_comp_s', 0.0) * 1e3:g} ms ahead for the mocap latency; "
              + (f"loop thread on CPU {meta['loop_cpu']}, the rest elsewhere" if meta.get("loop_cpu") is not None
                 else "loop thread not pinned")
              + (f", SCHED_FIFO {meta['rt_priority']} where permitted; " if meta.get("rt_priority") else "; ")
              + f"{meta['laps']} laps on {meta['track']}{' with obstacles' if meta.get('obstacles') else ''}. "
              f"Ctrl-C stops every drone.", highlight=False)


def first_flight_cmd(cfg, check: bool, hover_drones: list[int], json_out: Path | None) -> None:
    """`cfrace fly --check` / `--hover`: no race; one line per check, exit 2 on a failure."""
    from dataclasses import replace

    from cfrace.flight.landing.procedures import first_flight
    from cfrace.flight.setup import real_io, resolve_race
    cfg = replace(cfg, log=None)     # no race, no flight log (nor the link keeper's stop log)
    report = first_flight(resolve_race(cfg), real_io(cfg), check=check, hover_drones=hover_drones)
    for line in report["lines"]:
        out.print(line, highlight=False)
    write_json(report, json_out)
    if not report["ok"]:
        sys.exit(2)


def register(app: typer.Typer) -> None:
    """Add `cfrace fly` to the top-level app."""

    @app.command("fly")
    def fly_cmd(
        track: Optional[str] = typer.Option(None, help="Track name or YAML path."),
        ego: Optional[str] = typer.Option(None, help="Ego policy: ours/ds/ss/dm or an .onnx path (flies uris[0])."),
        opp: Optional[str] = typer.Option(None, help="Opponent policy (flies uris[1])."),
        uris: Optional[str] = typer.Option(None, help="Link URIs, one per drone: radio://0/80/2M/E7E7E7E7E1,... "
                                                      "(at most 4 per Crazyradio at 100 Hz), udp://127.0.0.1:19850,..."),
        policies: Optional[str] = typer.Option(None, help="N drones instead of --ego/--opp: P1,...,PN, one per URI."),
        mocap: Optional[str] = typer.Option(None, help="Required: vicon://HOST, optitrack://HOST, qualisys://HOST, "
                                                       "vrpn://HOST, replay://LOG.mcap, sim://HOST:PORT."),
        bodies: Optional[str] = typer.Option(None, help="Mocap body names, one per drone (default cf1,...,cfN)."),
        laps: Optional[int] = typer.Option(None, help="Laps to win (default 3)."),
        profile: Optional[str] = typer.Option(None, help=f"Drone profile of the flown drones (default {DEFAULT_PROFILE}, "
                                                          "as `sim serve` and `sim dry-run`; 'trained': the ego "
                                                          "policy's training profile)."),
        log: Optional[Path] = typer.Option(None, help="Flight log (.mcap); default flights/fly-DATE.mcap."),
        obstacles: Optional[bool] = typer.Option(None, "--obstacles/--no-obstacles", help="Race with the track's obstacles."),
        config: Optional[Path] = typer.Option(None, help="Flight config YAML (room, URIs, bodies, safety limits)."),
        timeout_s: Optional[float] = typer.Option(None, help="End the race (draw) after this many seconds."),
        geofence_margin_m: Optional[float] = typer.Option(None, help="Fence = track arena grown by this (m)."),
        speed_max_mps: Optional[float] = typer.Option(None, help="Stop a drone above this speed (m/s)."),
        tilt_max_deg: Optional[float] = typer.Option(None, help="Stop a drone tilted more than this (deg)."),
        json_out: Optional[Path] = typer.Option(None, "--json", help="Write the result as JSON (- : to stdout)."),
        foxglove: Optional[int] = typer.Option(None, "--foxglove", metavar="[PORT]", help=FOXGLOVE_HELP),
        rt_priority: Optional[str] = typer.Option(None, help="Run the loop thread SCHED_FIFO: auto (the default: "
                                                             "priority 50 where permitted, i.e. root or "
                                                             "CAP_SYS_NICE, else normal), 0 = off, or 1-99."),
        prewarm_ms: Optional[float] = typer.Option(None, help="Warm-up window: this many ms before each tick the "
                                                              "loop runs the tick's pure parts over and over and "
                                                              "does not sleep (default 3; 0 = off)."),
        velocity_alpha: Optional[float] = typer.Option(None, help="Velocity filter of the pose estimator: "
                                                                  "v += alpha (difference - v), (0, 1] (default 1: plain differences)."),
        latency_comp_ms: Optional[float] = typer.Option(None, help="Predict every mocap pose this many ms forward "
                                                                   "(position and attitude) to make up for the mocap "
                                                                   "latency (default 10; 0 = off; docs/flight.md, "
                                                                   "'Mocap latency')."),
        loop_cpu: Optional[str] = typer.Option(None, help="CPU of the loop thread: auto (the highest CPU, when "
                                                          "there are two or more), off, or a CPU number; the "
                                                          "process's other threads go to the other CPUs."),
        quiet: bool = typer.Option(False, "--quiet", help="No live view."),
        start: Optional[str] = typer.Option(None, help="ground (default): the policies take off; hover: take-off "
                                                       "to the start positions on the high-level commander first."),
        landing: Optional[bool] = typer.Option(None, "--landing/--no-landing",
                                               help="Land at the race's end and on soft failsafes (default on)."),
        pose_stream: Optional[bool] = typer.Option(None, "--pose-stream/--no-pose-stream",
                                                   help="Stream each drone's mocap pose to it (default on)."),
        estop_watchdog: Optional[bool] = typer.Option(
            None, "--estop-watchdog/--no-estop-watchdog",
            help="Feed each flying drone's emergency-stop watchdog: a drone whose link is lost cuts its motors "
                 "after 1 s (default off: the drones then stay locked until rebooted; docs/flight.md)."),
        check: bool = typer.Option(False, "--check", help="Pre-flight checks only (docs/first-flight.md): firmware, "
                                                          "battery, link, body and yaw of each drone; exit 2 on a failure."),
        hover: bool = typer.Option(False, "--hover", help="Hover test only: take off 0.5 m, hold 5 s, land "
                                                          "(the drones of --hover-drones, one after the other)."),
        hover_drones: Optional[str] = typer.Option(None, help="--hover: which drones, by index (0 ego, 1 opp; "
                                                               "default: all)."),
    ):
        """Race 2 (--ego/--opp) or N (--policies) Crazyflies from motion capture with ONNX policies at 100 Hz."""
        from cfrace.flight.config import split_list

        safety = {k: v for k, v in (("geofence_margin_m", geofence_margin_m), ("speed_max_mps", speed_max_mps),
                                    ("tilt_max_deg", tilt_max_deg)) if v is not None}
        if log is None:
            log = Path("flights") / f"fly-{time.strftime('%Y%m%d-%H%M%S')}.mcap"
        cfg, rule = fly_config(config, mocap, profile, track=track, ego=ego, opp=opp, policies=split_list(policies),
                               uris=split_list(uris), bodies=split_list(bodies), laps=laps, log=log,
                               obstacles=obstacles, foxglove_port=foxglove, timeout_s=timeout_s, quiet=quiet,
                               rt_priority=rt_priority, safety_overrides=safety, loop_cpu=loop_cpu,
                               prewarm_s=None if prewarm_ms is None else prewarm_ms / 1e3,
                               velocity_alpha=velocity_alpha,
                               latency_comp_s=None if latency_comp_ms is None else latency_comp_ms / 1e3,
                               start=start, landing=landing, pose_stream=pose_stream, estop_watchdog=estop_watchdog)
        if hover_drones is not None and not hover:
            raise ConfigError("--hover-drones chooses the drones of a hover test: give --hover too (without it "
                              "it would be ignored, or a race would fly)")
        if check or hover:
            return first_flight_cmd(cfg, check, hover_list(hover_drones, len(cfg.uris)) if hover else [], json_out)
        check_writable(cfg.log, "--log")
        check_port(cfg.foxglove_port, "--foxglove")
        from cfrace.flight.loop.race import fly
        from cfrace.flight.setup import resolve_race

        race_and_report(lambda say: fly(resolve_race(cfg), console=console, announce=say), rule, json_out)


def hover_list(text: str | None, drones: int) -> list[int]:
    """--hover-drones: distinct drone indices 0..drones-1 (None: every drone); ConfigError (one
    line) otherwise, before anything connects."""
    from cfrace.flight.config import split_list

    if text is None:
        return list(range(drones))
    try:
        picked = [int(v) for v in split_list(text) or ()]
    except ValueError:
        raise ConfigError(f"--hover-drones {text!r}: expected drone indices such as 0,1") from None
    bad = [i for i in picked if not 0 <= i < drones]
    if not picked or bad or len(set(picked)) < len(picked):
        raise ConfigError(f"--hover-drones {text!r}: expected distinct indices from 0 to {drones - 1} "
                          f"({drones} drones)")
    return picked


def fly_config(config: Path | None, mocap: str | None, profile: str | None, **options):
    """`fly`'s FlightConfig (the config file, then the options) and the words of its profile rule.
    ConfigError for what real drones cannot fly without: --mocap, --uris."""
    from cfrace.flight.config import load_flight_file, make_config

    from_file = load_flight_file(config) if config else {}
    cfg = make_config(config, mocap=mocap, profile=profile, **options)
    if mocap is None and "mocap" not in from_file:
        raise ConfigError(f"missing --mocap: real drones fly from motion capture; give one of {MOCAP_FORMS}")
    name, rule = choose_profile(profile, _track_or_none(cfg.track), cfg.ego, cfg.obstacles, from_file, config)
    if not cfg.uris:
        raise ConfigError("missing --uris (one link URI per drone)")
    return replace(cfg, profile=name), rule


def race_and_report(race, rule: str, json_out: Path | None) -> None:
    """Fly ``race(announce)`` (`fly`, `sim dry-run`), print its result, write its JSON and exit with
    its code (cfrace.cli.common.race_exit_code); ``rule``: why this drone profile. The --json path
    is checked before anything flies; a signal after the race no longer interrupts the printing
    and the writing (it only sets the exit code)."""
    from cfrace.flight.loop.race import SignalGuard

    check_writable(json_out, "--json")
    with SignalGuard() as guard:
        result = race(lambda meta: announce(meta | {"profile_rule": rule})).to_json() | {"profile_rule": rule}
        guard.after = True
        print_result(result, human_console(json_out))
        write_json(result, json_out)
    code = race_exit_code(result, guard.late)
    if code:
        sys.exit(code)


def _track_or_none(name: str | None):
    """The track for the profile rule, or None (its error comes later, from resolve_race)."""
    if name is None:
        return None
    from cfrace.errors import CfraceError
    from cfrace.track import load_track
    try:
        return load_track(name)
    except CfraceError:
        return None
