"""`cfrace calibrate thrust` (identify a Crazyflie on a thrust stand) and `cfrace sim stand`."""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console

from cfrace.errors import ConfigError

calibrate_app = typer.Typer(help="Identify a drone's motors and propellers on a thrust stand.", no_args_is_help=True)
console = Console(stderr=True)
out = Console(soft_wrap=True)

DEFAULT_MULTICAST = "can://udp_multicast/239.74.163.2"
SIM_TIMEOUT_MS = 500.0   #: ms, the least CAN timeout with --simulate


def _say(text: str) -> None:
    out.print(text, highlight=False)


def parse_faults(text: str | None) -> dict:
    """``KIND@SECONDS,...`` -> {kind: seconds after the motors first spin}."""
    from cfrace.rehearsal.thrust_stand import FAULTS

    faults = {}
    for item in filter(None, (text or "").split(",")):
        kind, _, at = item.strip().partition("@")
        try:
            when = float(at)
        except ValueError:
            when = -1.0
        if kind not in FAULTS or when < 0:
            raise ConfigError(f"--fault {item!r}: expected KIND@SECONDS with KIND one of {', '.join(FAULTS)}")
        faults[kind] = when
    return faults


@calibrate_app.command("thrust")
def thrust_cmd(
    out_path: Path = typer.Option(..., "--out", help="The profile to write, e.g. calibration/cf21bl_stand.yaml."),
    sensor: str = typer.Option(..., "--sensor", help="Sensor description: a name in calibration/sensors/ or a path."),
    uri: Optional[str] = typer.Option(None, "--uri", help="The Crazyflie on the stand (radio://... or udp://...)."),
    bus: Optional[str] = typer.Option(None, "--bus", help="The sensor's CAN bus: can://INTERFACE/CHANNEL[?bitrate=N], "
                                                          "e.g. can://socketcan/can0."),
    confirm: bool = typer.Option(False, "--confirm-secured", help="I fixed the Crazyflie on the stand with its "
                                                                  "propellers on and stand clear: start the motors."),
    base: str = typer.Option("cf21bl", "--base", help="Profile whose unmeasured values (mass, inertia, PID, ...) "
                                                      "the new one keeps."),
    quick: bool = typer.Option(False, "--quick", help="A short plan (3 levels, 2 motors alone, 2 lag steps): "
                                                      "seconds instead of ~2 minutes, less accurate."),
    report: Optional[Path] = typer.Option(None, "--report", help="Folder for the plots and report.json "
                                                                 "(default runs/calibrate/NAME)."),
    simulate: Optional[str] = typer.Option(None, "--simulate", help="No hardware: measure a simulated Crazyflie "
                                                                    "whose true parameters are this profile, on a "
                                                                    "simulated stand in this process (bus "
                                                                    "can://virtual/stand unless --bus)."),
    truth: Optional[str] = typer.Option(None, "--truth", help="Compare the result with this profile (default: "
                                                              "the --simulate one)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated stand's noise and bias."),
    force: bool = typer.Option(False, "--force", help="Overwrite --out if it exists."),
    can_timeout_ms: Optional[float] = typer.Option(None, "--can-timeout-ms", min=1.0,
                                                   help="Override the sensor file's timeout_ms (default: the "
                                                        f"file's; with --simulate at least {SIM_TIMEOUT_MS:g})."),
):
    """Step the motors through cflib's motor test parameters, read force and torque from the CAN sensor
    and the battery / motor speed from the drone's log, fit, and write a complete drone profile."""
    from cfrace.calibrate.procedure import QUICK_PLAN, Plan
    from cfrace.calibrate.sensor import load_sensor
    from cfrace.cli.calibrate_run import calibrate_thrust
    from cfrace.drone import load_profile

    spec = load_sensor(sensor)            # bad input fails here, before anything starts
    if can_timeout_ms is None and simulate is not None and spec.timeout_s * 1e3 < SIM_TIMEOUT_MS:
        can_timeout_ms = SIM_TIMEOUT_MS
        _say(f"simulated stand in this process: CAN timeout {SIM_TIMEOUT_MS:g} ms (a shared machine stalls the "
             "simulated sensor's thread for up to a few hundred ms)")
    if can_timeout_ms is not None:
        spec = dataclasses.replace(spec, timeout_s=can_timeout_ms / 1e3)
    base_profile = load_profile(base)
    true_profile = load_profile(truth or simulate) if (truth or simulate) else None
    if out_path.suffix != ".yaml":
        raise ConfigError(f"--out {out_path}: a profile is a .yaml file")
    if out_path.exists() and not force:
        raise ConfigError(f"--out {out_path}: exists (pass --force to overwrite)")
    if simulate is None and (uri is None or bus is None):
        raise ConfigError("--uri and --bus are required (or --simulate PROFILE to try it on a simulated stand)")
    folder = report or Path("runs") / "calibrate" / out_path.stem
    result = calibrate_thrust(out_path, spec, QUICK_PLAN if quick else Plan(), base_profile, true_profile, folder,
                              uri=uri, bus=bus, simulate=simulate, seed=seed, confirmed=confirm, say=_say)
    _say(f"wrote {out_path} ({result['run_s']:.0f} s on the stand); plots and report.json in {folder}")
    _say(f"fly with it: cfrace fly ... --profile {out_path}; train on it: cfrace train ... --profile {out_path}")


def stand_cmd(
    profile: str = typer.Option("cf21bl", "--profile", help="The simulated drone's true parameters."),
    sensor: str = typer.Option("ft6_int16_2frame", "--sensor", help="Sensor description (name or path)."),
    bus: str = typer.Option(DEFAULT_MULTICAST, "--bus", help="CAN bus for the sensor's frames; udp_multicast "
                                                             "reaches other processes on this machine."),
    port: int = typer.Option(19850, "--port", help="UDP port of the simulated Crazyflie."),
    seed: int = typer.Option(0, "--seed", help="Seed of the noise and the sensor's bias."),
    fault: Optional[str] = typer.Option(None, "--fault", help="KIND@S,...: silence (the sensor stops), overload "
                                                              "(+20 N on z), link_loss; S = seconds after the "
                                                              "motors first spin."),
    duration: Optional[float] = typer.Option(None, "--duration", help="Stop after this many seconds (default: "
                                                                      "Ctrl-C / SIGTERM)."),
):
    """A simulated Crazyflie on a simulated thrust stand: CRTP over UDP, a 6-axis sensor on a CAN bus."""
    from cfrace.calibrate.bus import parse_bus
    from cfrace.rehearsal.thrust_stand import SimStand

    if parse_bus(bus).interface == "virtual":
        raise ConfigError(f"--bus {bus}: the virtual interface only reaches this process; use "
                          f"{DEFAULT_MULTICAST} (or `cfrace calibrate thrust --simulate` for one process)")
    stop = threading.Event()
    restore = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        with SimStand(profile=profile, sensor=sensor, bus=bus, seed=seed, faults=parse_faults(fault),
                      port=port) as stand:
            _say(f"simulated stand: {stand.profile.name} on {stand.uri}, sensor {stand.sensor.name} on {bus}")
            _say(f"calibrate it: cfrace calibrate thrust --uri {stand.uri} --sensor {sensor} --bus {bus} "
                 "--out calibration/NAME.yaml --confirm-secured")
            _say("Ctrl-C to stop")
            t_end = None if duration is None else time.monotonic() + duration
            try:
                while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
                    stop.wait(0.2)
            except KeyboardInterrupt:
                pass
            _say(f"{stand.rig.samples_sent} sensor samples sent")
    finally:
        signal.signal(signal.SIGTERM, restore)


def register(app: typer.Typer) -> None:
    """Add `cfrace calibrate ...` and `cfrace sim stand`."""
    from cfrace.cli.sim import sim_app

    app.add_typer(calibrate_app, name="calibrate")
    sim_app.command("stand")(stand_cmd)
