"""`cfrace sim dry-run`: the whole flight stack against simulated Crazyflies.

Real time (default): a SimCrazyflieServer (in-process threads) serves the drones on free UDP
ports, the real cflib client connects to them (udp:// URIs) and the `sim` mocap source reads the
simulated poses; everything else is `cfrace fly`'s code (runner.run_race). --lockstep: the same
loop with DirectSimLinks and the simulator advanced exactly one tick per loop iteration (no
wall clock, no cflib, no threads): fast and deterministic, for tests.

After the race every drone has been told to stop; the dry-run then keeps the simulation running
until every simulated drone reports zero thrust (at most 3 s: a drone whose link was cut is
stopped by the firmware's own 2 s watchdog) and records each drone's firmware status.
"""

from __future__ import annotations

import time
from dataclasses import replace

from cfrace.flight.config import FlightConfig
from cfrace.flight.faults import FaultInjector, UdpCutRelay, parse_faults
from cfrace.flight.runner import run_race

SETTLE_MAX_S = 3.0


def _final_status(fleet) -> list[dict]:
    out = []
    for i, name in enumerate(fleet.body_names):
        s = fleet.status(i)
        out.append({"body": name, "motors_off": s["thrust"] == 0.0, "thrust_n": s["thrust"],
                    "thrust_counts": s["thrust_counts"], "armed": s["armed"], "locked": s["locked"],
                    "watchdog": s["watchdog"], "emergency_stopped": s["emergency_stopped"], "crashed": s["crashed"]})
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


def training_profile(track: str, ego: str, obstacles: bool, default: str = "cf21bl") -> str:
    """The drone profile the ego policy was trained for (metadata drone_profile), if it names a
    known profile; else ``default``. Policy errors surface later, in the checks before flight."""
    from cfrace.drone import load_profile
    from cfrace.errors import CfraceError
    from cfrace.policy import OnnxPolicy, resolve_policy
    from cfrace.track import load_track

    try:
        name = OnnxPolicy(resolve_policy(ego, load_track(track).name, obstacles)).meta["drone_profile"]
        load_profile(name)
        return name
    except (CfraceError, KeyError):
        return default


def dry_run(cfg: FlightConfig, *, lockstep: bool = False, faults: str | None = None, seed: int = 0,
            mocap_noise_m: float = 0.0, mocap_latency_s: float = 0.0, console=None,
            lockstep_warm_calls: int = 0) -> dict:
    """Race cfg.ego against cfg.opp on simulated drones; returns the run_race result plus sim info."""
    from cfrace.simcf.firmware import SimFleet
    from cfrace.simcf.server import SimCrazyflieServer

    fault_list = parse_faults(faults)
    cfg = replace(cfg, mocap="sim")
    if cfg.latency_comp_s is None:    # make up for the simulated latency (the `sim` default is none)
        cfg = replace(cfg, latency_comp_s=float(mocap_latency_s))
    fleet = SimFleet(cfg.track, cfg.profile, 2, body_names=list(cfg.bodies), seed=seed, obstacles=cfg.obstacles)
    injector = FaultInjector(fault_list, dict(zip(("ego", "opp"), cfg.bodies))) if fault_list else None
    server, relays = None, {}
    mocap_options = {"noise_m": mocap_noise_m, "latency_s": mocap_latency_s, "seed": seed}
    try:
        if lockstep:
            uris = ["sim://0", "sim://1"]
        else:
            server = SimCrazyflieServer(fleet, base_port=0).start()
            uris = list(server.uris)
            for f in fault_list:
                if f.kind == "link_loss":
                    i = 0 if f.drone == "ego" else 1
                    if f.drone not in relays:
                        relays[f.drone] = UdpCutRelay(server.ports[i])
                        uris[i] = relays[f.drone].uri
        if injector is not None:   # lockstep: run_race uses DirectSimLink.cut_link
            for name, relay in relays.items():
                injector.cutters[name] = relay.cut
        result = run_race(cfg, fleet=fleet, lockstep=lockstep, injector=injector,
                          mocap_options=mocap_options, uris=uris, settle=_settle(fleet, lockstep, cfg.dt),
                          extra_meta={"dry_run": True, "seed": seed, "faults": faults or "",
                                      "mocap_noise_m": mocap_noise_m, "mocap_latency_s": mocap_latency_s},
                          console=console, lockstep_warm_calls=lockstep_warm_calls)
        if server is not None:
            result["sim"] = {"overruns": server.overruns, "lag_s": round(server.sim_lag, 3), "errors": server.errors}
        return result
    finally:
        for relay in relays.values():
            relay.close()
        if server is not None:
            server.stop()

