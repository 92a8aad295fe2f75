"""`cfrace sim dry-run`: the whole flight stack against simulated Crazyflies.

Real time (default): a SimCrazyflieServer (in-process threads) serves the drones on free UDP
ports, the real cflib client connects to them (udp:// URIs) and the `sim` mocap source reads the
simulated poses; everything else is `cfrace fly`'s code (runner.run_race). --lockstep: the same
loop with DirectSimLinks and the simulator advanced exactly one tick per loop iteration (no
wall clock, no cflib, no threads): fast and deterministic, for tests.
This module builds the race's I/O (cfrace.flight.setup.RaceIO) for simulated drones: the runner
knows nothing of the fleet, the lockstep clock or the fault injection.

After the race every drone has been told to stop; the dry-run then keeps the simulation running
until every simulated drone reports zero thrust (at most 3 s: a drone whose link was cut is
stopped by the firmware's own 2 s watchdog) and records each drone's firmware status.
"""

from __future__ import annotations

import time
from dataclasses import replace

from cfrace.errors import LinkError
from cfrace.flight.loop.clock import LockstepClock, RealClock
from cfrace.flight.config import FlightConfig
from cfrace.flight.mocap.consistency import STILL_S
from cfrace.rehearsal.faults import FaultInjector, UdpCutRelay, parse_faults
from cfrace.flight.link.protocol import DirectSimLink
from cfrace.flight.link.opener import link_factory, stop_log_path
from cfrace.flight.loop.state import RaceResult
from cfrace.flight.mocap.sources import open_mocap
from cfrace.flight.loop.race import run_race
from cfrace.flight.setup import RaceIO, RaceSetup, resolve_race
from cfrace.simcf.firmware import SimFleet
from cfrace.simcf.server import SimCrazyflieServer

SETTLE_MAX_S = 3.0


def _final_status(fleet) -> list[dict]:
    out = []
    for i, name in enumerate(fleet.body_names):
        s = fleet.status(i)
        out.append({"body": name, "motors_off": s["thrust"] == 0.0, "thrust_n": s["thrust"],
                    "thrust_counts": s["thrust_counts"], "armed": s["armed"], "locked": s["locked"],
                    "watchdog": s["watchdog"], "emergency_stopped": s["emergency_stopped"], "crashed": s["crashed"],
                    "crash_reason": s["crash_reason"],
                    "pos": [round(float(v), 4) for v in fleet.state(i)["pos"]]})
    return out


def _settle(fleet, lockstep: bool, dt: float):
    def settle() -> list[dict]:
        t_end = fleet.time + SETTLE_MAX_S
        wall_end = time.monotonic() + SETTLE_MAX_S + 1.0
        while fleet.time < t_end and time.monotonic() < wall_end:
            if lockstep:
                fleet.advance(dt)
            else:
                time.sleep(dt)
            if all(s["motors_off"] for s in _final_status(fleet)) and fleet.time > 0.05:
                break
        if lockstep:
            fleet.advance(5 * dt)   # let the state settle into the snapshot
        return _final_status(fleet)
    return settle


def sim_io(cfg: FlightConfig, fleet: SimFleet, *, lockstep: bool, uris, injector: FaultInjector | None = None,
           mocap_options: dict | None = None, lockstep_warm_calls: int = 0) -> RaceIO:
    """The I/O of a race on ``fleet``: the `sim` mocap source (wrapped by the injector's faults),
    sim://N links (lockstep: straight to the fleet, on the fleet's clock) or udp:// links through
    cflib (real time), each registered with the injector as a link it may cut. With
    lockstep_warm_calls > 0 the loop's warm-up runs that often before every lockstep tick, as it
    does in real time (tests show it changes nothing)."""
    clock = LockstepClock(cfg.dt, advance=fleet.advance, warm_calls=lockstep_warm_calls) if lockstep \
        else RealClock(cfg.dt)
    link_clock = clock.now if lockstep else time.monotonic

    def mocap():
        source = open_mocap("sim", bodies=list(cfg.bodies), sim=fleet, **(mocap_options or {}))
        return injector.wrap_mocap(source) if injector is not None else source

    keeper_links = link_factory(uris, heartbeat_s=cfg.safety.overrun_stop_s, stop_log=stop_log_path(cfg.log),
                                rt_priority=cfg.rt_priority, loop_cpu=cfg.loop_cpu, clock=link_clock,
                                estop_watchdog=cfg.estop_watchdog)

    def link(i: int, uri: str):
        if uri.startswith("sim://"):
            try:
                made = DirectSimLink(fleet, int(uri[len("sim://"):]), clock=link_clock)
            except ValueError:
                raise LinkError(f"{uri}: expected sim://INDEX") from None
        else:
            made = keeper_links(i, uri)
        if injector is not None:
            injector.cutters.setdefault(cfg.names[i], getattr(made, "cut_link", None))
        return made

    prewarm_s = 0.0 if lockstep and not lockstep_warm_calls else cfg.prewarm_s
    return RaceIO(open_mocap=mocap, open_link=link, clock=clock, link_clock=link_clock, prewarm_s=prewarm_s,
                  uris=tuple(uris), hooks=injector, still_s=0.0 if lockstep else STILL_S,
                  wait=fleet.advance if lockstep else time.sleep)


def sim_race(setup: RaceSetup, fleet: SimFleet, *, lockstep: bool = True, uris=("sim://0", "sim://1"),
             injector: FaultInjector | None = None, **run_options) -> RaceResult:
    """run_race on an in-process fleet (tests and the dry-run)."""
    return run_race(setup, sim_io(setup.cfg, fleet, lockstep=lockstep, uris=uris, injector=injector), **run_options)


def dry_run(cfg: FlightConfig, *, lockstep: bool = False, faults: str | None = None, seed: int = 0,
            mocap_noise_m: float = 0.0, mocap_latency_s: float = 0.0, console=None,
            lockstep_warm_calls: int = 0, setup: RaceSetup | None = None, announce=None,
            idle_thrust: int | None = None) -> RaceResult:
    """Race cfg's drones (cfg.ego against cfg.opp, or cfg.policies) on simulated drones, from the
    track's start grid; returns the run_race result plus sim info. ``setup``: the race resolved
    already (the CLI's), else resolved here from cfg; ``announce``: as `fly`'s (the banner);
    ``idle_thrust``: the powerDist.idleThrust the simulated drones boot with (None: the simulator's
    0; the Crazyflie 2.1 Brushless's firmware boots with 7000, docs/simcf.md)."""
    fault_list = parse_faults(faults, cfg.names)
    cfg = replace(cfg, mocap="sim")
    if cfg.latency_comp_s is None:    # make up for the simulated latency (the `sim` default is none)
        cfg = replace(cfg, latency_comp_s=float(mocap_latency_s))
    setup = replace(setup, cfg=cfg) if setup is not None else resolve_race(cfg)
    # no positioning deck: the drones know where they are from the mocap poses the flight stack streams
    n = len(cfg.specs)
    fleet = SimFleet(setup.track, setup.profile, n, body_names=list(cfg.bodies), seed=seed, obstacles=cfg.obstacles,
                     decks=(), params=None if idle_thrust is None else {"powerDist.idleThrust": int(idle_thrust)})
    injector = FaultInjector(fault_list, dict(zip(cfg.names, cfg.bodies))) if fault_list else None
    server, relays = None, {}
    mocap_options = {"noise_m": mocap_noise_m, "latency_s": mocap_latency_s, "seed": seed}
    try:
        if lockstep:
            uris = [f"sim://{i}" for i in range(n)]
        else:
            server = SimCrazyflieServer(fleet, base_port=0).start()
            uris = list(server.uris)
            for f in fault_list:
                if f.kind == "link_loss":
                    i = cfg.names.index(f.drone)
                    if f.drone not in relays:
                        relays[f.drone] = UdpCutRelay(server.ports[i])
                        uris[i] = relays[f.drone].uri
        if injector is not None:   # lockstep: the DirectSimLinks cut themselves (sim_io)
            for name, relay in relays.items():
                injector.cutters[name] = relay.cut
            for i, name in enumerate(cfg.names):
                injector.drainers[name] = lambda i=i: fleet.set_battery(i, 0.0)
        io = sim_io(cfg, fleet, lockstep=lockstep, uris=uris, injector=injector, mocap_options=mocap_options,
                    lockstep_warm_calls=lockstep_warm_calls)
        result = run_race(setup, io, settle=_settle(fleet, lockstep, cfg.dt), console=console, announce=announce,
                          extra_meta={"dry_run": True, "seed": seed, "faults": faults or "",
                                      "mocap_noise_m": mocap_noise_m, "mocap_latency_s": mocap_latency_s,
                                      **({} if idle_thrust is None else {"idle_thrust": int(idle_thrust)})})
        if server is not None:
            result.sim = {"overruns": server.overruns, "lag_s": round(server.sim_lag, 3), "errors": server.errors}
        return result
    finally:
        for relay in relays.values():
            relay.close()
        if server is not None:
            server.stop()
