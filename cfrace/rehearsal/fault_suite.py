"""`cfrace sim faults`: every fault and bad-input scenario through the real stack, one table.

Rows (scenario, detected at, all drones stopped at, distance flown after detection, log complete,
exit code, pass):
- each fault of cfrace.rehearsal.faults, injected at FAULT_T into a lockstep dry-run of the track's
  shipped policies (the whole flight stack, the simulated drones in-process);
- ``kill -9 of fly`` and ``link loss``: `cfrace sim serve` and `cfrace fly` as separate processes
  (cflib over UDP; the link keeper); the fly process is killed mid-race, or one drone's UDP link is
  cut by a relay; the drones' ground-truth poses come from the server's pose stream; times are
  where the link keeper sent the stops (its FLIGHT.stops.jsonl);
- bad inputs to `cfrace fly` (each must be refused with one line, exit code 2, before take-off).

Distance flown after detection: the path of the drone from the detection until it lies still (the
ground truth), with, for the two process scenarios, the bound of a drone whose motors went off at
that speed and height (a ballistic fall).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cfrace.contract import decode_meta, encode_meta
from cfrace.drone import GRAVITY
from cfrace.rehearsal.loop_timing import _free_base_port
from cfrace.flight.config import FlightConfig, SafetyConfig
from cfrace.rehearsal.dryrun import dry_run
from cfrace.rehearsal.faults import KINDS, UdpCutRelay
from cfrace.flight.log.writer import read_log
from cfrace.flight.mocap.sources import open_mocap
from cfrace.flight.loop.race import EXIT_CODES, result_exit_code
from cfrace.flight.setup import training_profile
from cfrace.paths import POLICIES_DIR
from cfrace.track import load_track

FAULT_T = 2.0            #: s of race time at which a dry-run fault is injected
RACE_S = 6.0             #: s, each dry-run race
CLI = [sys.executable, "-c", "from cfrace.cli.main import main; main()"]

#: fault -> the safety event that must show it (kind, action) and the exit code of the race
EXPECT = {"mocap_dropout_short": ("mocap_dropout", "none", 0), "mocap_dropout_long": ("mocap_stale", "stop_drone", 0),
          "pose_outlier": ("pose_outlier", "none", 0), "geofence": ("geofence", "stop_drone", 0),
          "nan_policy": ("non_finite", "stop_drone", 0), "link_loss": ("link_lost", "stop_drone", 0),
          "stall_50ms": ("tick_skipped", "none", 0), "stall_200ms": ("loop_overrun", "stop_all", 0),
          "sigterm": ("operator_kill", "stop_all", 143), "sigint": ("operator_kill", "stop_all", 130),
          "swap_bodies": ("pose_mismatch", "stop_all", 0), "replay_poses": ("pose_mismatch", "stop_all", 0),
          "mocap_glitchy": ("mocap_degraded", "land_drone", 0), "low_battery": ("low_battery", "land_drone", 0),
          "operator_land": ("operator_land", "land_all", 3)}   # every drone landed: the race's all-stopped code
#: faults injected at another time than FAULT_T: two mocap bodies swapped from the start (a labelling
#: mistake; swapped mid-race, the jump itself trips the speed rule first)
FAULT_AT = {"swap_bodies": 0.0}
#: detections that also count: a cut link stops the drone's response to its commands, which the
#: consistency check sees (0.2-0.3 s) before the link's silence does (0.5 s)
ALSO = {"link_loss": ("pose_mismatch", "stop_all")}


@dataclass
class Row:
    scenario: str
    detected_s: float | str | None = None      #: race time (s), "before take-off", or latency text
    stopped_s: float | str | None = None
    distance_m: float | str | None = None
    log_complete: bool | None = None
    exit_code: int | None = None
    passed: bool = False
    note: str = ""
    extra: dict = field(default_factory=dict)

    def cells(self) -> list[str]:
        def f(v, fmt):
            return "-" if v is None else (v if isinstance(v, str) else format(v, fmt))
        return [self.scenario, f(self.detected_s, ".2f"), f(self.stopped_s, ".2f"), f(self.distance_m, ".2f"),
                "-" if self.log_complete is None else ("yes" if self.log_complete else "NO"),
                "-" if self.exit_code is None else str(self.exit_code), "pass" if self.passed else "FAIL", self.note]


HEADER = ["scenario", "detected at (s)", "all drones stopped at (s)", "distance after detection (m)",
          "log complete", "exit code", "result", "note"]


def _path_length(points: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1))) if len(points) > 1 else 0.0


def ballistic_bound(pos, vel) -> float:
    """Straight-line distance a drone whose motors went off at pos with vel falls to the floor (m)."""
    h, vz = max(0.0, float(pos[2])), float(vel[2])
    t = (vz + math.sqrt(vz * vz + 2.0 * GRAVITY * h)) / GRAVITY
    return float(math.hypot(math.hypot(vel[0], vel[1]) * t, h))


# ----------------------------------------------------------------------------------- dry-run faults
def dry_run_row(kind: str, track: str, workdir: Path, drones: int = 2) -> Row:
    """One fault in a lockstep dry-run of ours vs ds (``drones`` > 2: ours, ds, ours, ds, ...; the
    fault hits d1, or d2 for nan_policy)."""
    names = ("ego", "opp") if drones == 2 else ("d1", "d2")
    drone = names[1] if kind == "nan_policy" else names[0]
    log = workdir / f"{kind}-{drones}.mcap"
    # bodies swapped from the start stand on each other's start slots, which the take-off check
    # refuses (safety.start_slot_m); this row shows what catches them once they fly, so it is off
    cfg = FlightConfig(track=track, ego="ours", opp="ds", profile=training_profile(load_track(track), "ours", False),
                       quiet=True, timeout_s=RACE_S, log=log,
                       policies=tuple("ours" if i % 2 == 0 else "ds" for i in range(drones)) if drones > 2 else (),
                       safety=SafetyConfig(start_slot_m=0.0) if kind == "swap_bodies" else SafetyConfig())
    at = FAULT_AT.get(kind, FAULT_T)
    res = dry_run(cfg, lockstep=True, faults=f"{kind}@{at}:{drone}").to_json()
    want_kind, want_action, want_code = EXPECT[kind]
    row = Row(f"fault {kind}@{at:g} ({drone}{'' if drones == 2 else f' of {drones}'})")
    ok = {(want_kind, want_action), ALSO.get(kind)}
    ev = next((e for e in res["safety_events"] if (e["kind"], e["action"]) in ok and e["t"] >= at - 1e-9), None)
    row.detected_s = None if ev is None else ev["t"]
    if want_action.startswith("land"):   # a soft failsafe: "stopped at" is when its landings touched down
        stopped_by_fault = [d for d in res["drones"] if (d.get("landing") or {}).get("reason") == want_kind
                            and d["landing"]["down"]]
    else:
        stopped_by_fault = [d for d in res["drones"] if d["stopped"] and d["stop_t"] is not None and d["stop_t"] < RACE_S]
    row.stopped_s = max(d["stop_t"] for d in stopped_by_fault) if want_action != "none" and stopped_by_fault else None
    data = read_log(log)
    row.log_complete = bool(data.complete)
    row.exit_code = result_exit_code(res)
    if ev is not None and ev["action"] == "stop_all" and want_code == 0:   # a safety check stopped every drone
        want_code = EXIT_CODES["all_stopped"]
    if ev is not None and want_action != "none":
        row.distance_m = _dry_run_distance(data, res, ev, {d["name"] for d in stopped_by_fault}
                                           if want_action.startswith("land") else None)
    motors_off = all(d["motors_off"] for d in res["drones_final"] or [])
    row.passed = (ev is not None and row.log_complete and motors_off
                  and row.exit_code == want_code and (want_action == "none" or row.stopped_s is not None))
    row.note = f"end {res['end']}" + ("" if ev is None else f", {ev['kind']}") + ("" if motors_off else ", MOTORS ON")
    return row


def _dry_run_distance(data, res: dict, ev: dict, names: set[str] | None = None) -> float:
    """Largest straight-line distance of a stopped drone (of ``names``, if given) from its
    ground-truth pose at the detection to where it came to rest (drones_final)."""
    frames = [(t, m) for t, m in data.messages("/mocap/pose")]
    t_ev = ev["t"]
    at = min(frames, key=lambda f: abs(f[0] - t_ev))[1]["poses"]
    out = 0.0
    for d, fin in zip(res["drones"], res["drones_final"]):
        if d["stopped"] and (names is None or d["name"] in names) and fin.get("pos") is not None and d["body"] in at:
            out = max(out, float(np.linalg.norm(np.asarray(fin["pos"]) - np.asarray(at[d["body"]]["pos"]))))
    return out


# ----------------------------------------------------------------------------------- separate processes
class _PoseRecorder:
    """Subscribes to a `cfrace sim serve` pose stream and keeps (time.monotonic, {body: pos})."""

    def __init__(self, port: int, bodies: list[str]):

        self.source = open_mocap(f"sim://127.0.0.1:{port}", bodies=bodies)
        self.samples: list[tuple[float, dict]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self, timeout_s: float = 15.0) -> "_PoseRecorder":
        self.source.open(timeout_s)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            frame = self.source.read(0.05)
            if frame is not None:
                self.samples.append((time.monotonic(), {b: p.pos.copy() for b, p in frame.poses.items()}))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.source.close()

    def track(self, body: str, t0: float, t1: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
        ts = [(t, s[body]) for t, s in self.samples if t0 <= t <= t1 and body in s]
        return np.array([t for t, _ in ts]), np.array([p for _, p in ts])


def _serve(track: str, profile: str, base: int) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["sim", "serve", "--track", track, "--drones", "2", "--port", str(base),
                                   "--profile", profile, "--no-obstacles"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _fly(track: str, profile: str, uris: list[str], pose_port: int, log: Path, timeout_s: float,
         extra: tuple[str, ...] = ()) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["fly", "--track", track, "--ego", "ours", "--opp", "ds", "--uris", ",".join(uris),
                                   "--mocap", f"sim://127.0.0.1:{pose_port}", "--profile", profile, "--quiet",
                                   "--log", str(log), "--timeout-s", str(timeout_s), "--json", str(log.with_suffix(".json")),
                                   *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_flying(rec: _PoseRecorder, bodies, seconds: float, timeout_s: float = 30.0) -> None:
    """Until every body has been above 0.5 m for ``seconds``."""
    end = time.monotonic() + timeout_s
    since = None
    while time.monotonic() < end:
        time.sleep(0.05)
        if rec.samples and all(rec.samples[-1][1].get(b, np.zeros(3))[2] > 0.5 for b in bodies):
            since = since or time.monotonic()
            if time.monotonic() - since >= seconds:
                return
        else:
            since = None
    raise RuntimeError("the drones did not take off")


def _after(rec: _PoseRecorder, body: str, t_from: float) -> tuple[float, float, float]:
    """(path length after t_from until still, speed at t_from, ballistic bound at t_from) of a body."""
    t, p = rec.track(body, t_from - 0.1)
    if len(p) < 3:
        return math.nan, math.nan, math.nan
    k = int(np.searchsorted(t, t_from))
    k = min(max(k, 1), len(p) - 1)
    vel = (p[k] - p[k - 1]) / max(t[k] - t[k - 1], 1e-3)
    return _path_length(p[k:]), float(np.linalg.norm(vel)), ballistic_bound(p[k], vel)


def process_rows(track: str, workdir: Path) -> list[Row]:
    """kill -9 of `cfrace fly` mid-race, and a link loss (without and with the emergency-stop
    watchdog fed), with `cfrace sim serve` in its own process."""
    profile = training_profile(load_track(track), "ours", False)
    rows = []
    for scenario, extra in (("kill -9 of fly", ()), ("link loss", ()), ("link loss", ("--estop-watchdog",))):
        base = _free_base_port()
        server = _serve(track, profile, base)
        relay = rec = fly = None
        log = workdir / f"{scenario.split()[0]}{len(extra)}.mcap"
        try:
            time.sleep(2.0)
            rec = _PoseRecorder(base - 1, ["cf1", "cf2"]).start(30.0)
            uris = [f"udp://127.0.0.1:{base}", f"udp://127.0.0.1:{base + 1}"]
            if scenario.startswith("link"):
                relay = UdpCutRelay(base)
                uris[0] = relay.uri
            fly = _fly(track, profile, uris, base - 1, log, 8.0 if scenario.startswith("link") else 30.0, extra)
            _wait_flying(rec, ["cf1", "cf2"], 1.5)
            rows.append(_kill9(fly, rec, log) if scenario.startswith("kill") else
                        _link_loss(fly, rec, relay, log, watchdog=bool(extra)))
        except Exception as exc:  # noqa: BLE001 - a failed scenario is a failed row, not the end of the suite
            why = server.stderr.read()[-200:] if server.poll() is not None else ""
            rows.append(Row(scenario, note=f"{type(exc).__name__}: {exc} {why}"[:300]))
        finally:
            if fly is not None and fly.poll() is None:
                fly.send_signal(signal.SIGTERM)
                try:
                    fly.wait(10)
                except subprocess.TimeoutExpired:
                    fly.kill()
            for thing in (rec, relay):
                if thing is not None:
                    thing.close()
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(5)
            except subprocess.TimeoutExpired:
                server.kill()
    return rows


def _stops(log: Path, timeout_s: float = 5.0) -> list[dict]:
    path = log.with_suffix(".stops.jsonl")
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not path.exists():
        time.sleep(0.05)
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def _kill9(fly: subprocess.Popen, rec: _PoseRecorder, log: Path) -> Row:
    t_kill = time.monotonic()
    os.kill(fly.pid, signal.SIGKILL)
    fly.wait()
    time.sleep(3.0)
    stops = [s for s in _stops(log) if s["why"] == "loop_gone"]
    row = Row("kill -9 of fly (sim serve, fly: processes)", exit_code=-9, log_complete=None)
    if len(stops) < 2:
        row.note = f"stops recorded: {stops}"
        return row
    lat = [s["t_mono"] - t_kill for s in stops]
    quiet = [s["since_loop_s"] for s in stops]
    figs = [_after(rec, body, s["t_mono"]) for body, s in zip(("cf1", "cf2"), sorted(stops, key=lambda s: s["drone"]))]
    row.detected_s = f"+{min(lat) * 1e3:.0f} ms after kill()"
    row.stopped_s = f"+{max(lat) * 1e3:.0f} ms ({max(quiet) * 1e3:.0f} ms after the last setpoint)"
    row.distance_m = max(f[0] for f in figs)
    row.passed = max(quiet) < 0.05 and all(s["was_flying"] for s in stops)
    row.note = "; ".join(f"{b}: {v:.1f} m/s at the stop, path {d:.2f} m to rest (ballistic fall {bd:.2f} m)"
                         for b, (d, v, bd) in zip(("cf1", "cf2"), figs))
    row.extra = {"stop_latency_ms": [round(x * 1e3, 1) for x in lat],
                 "since_last_setpoint_ms": [round(x * 1e3, 1) for x in quiet], "after_stop": figs}
    return row


def _link_loss(fly: subprocess.Popen, rec: _PoseRecorder, relay, log: Path, watchdog: bool = False) -> Row:

    t_cut = time.monotonic()
    relay.cut()
    fly.wait(30)
    time.sleep(0.5)
    which = "emergency-stop watchdog" if watchdog else "setpoint watchdog"
    row = Row("link loss of ego (sim serve, fly: processes" + (", --estop-watchdog)" if watchdog else ")"),
              exit_code=fly.returncode)
    lost = [s for s in _stops(log) if s["drone"] == 0]
    result = json.loads(log.with_suffix(".json").read_text()) if log.with_suffix(".json").exists() else {}
    ev = next((e for e in result.get("safety_events", []) if e["kind"] in ("link_lost", "pose_mismatch")
               and e["drone"] in ("ego", None)), None)
    if not lost or ev is None:
        row.note = f"no link_lost / pose_mismatch stop (end {result.get('end')})"
        return row
    t_det = lost[0]["t_mono"]
    row.detected_s = f"+{(t_det - t_cut) * 1e3:.0f} ms after the cut"
    row.stopped_s = f"firmware {which}"
    dist, v, bound = _after(rec, "cf1", t_det)
    whole, _, _ = _after(rec, "cf1", t_cut)
    row.distance_m = dist
    row.log_complete = bool(read_log(log).complete)
    want_code = EXIT_CODES["all_stopped"] if ev["action"] == "stop_all" else 0   # the pose check stops all
    row.passed = row.log_complete and row.exit_code == want_code and math.isfinite(dist)
    row.note = (f"{ev['kind']}; the stop cannot reach it: {whole:.2f} m from the cut, {dist:.2f} m after the "
                f"detection ({v:.1f} m/s then), until the firmware's {which}")
    return row


# ----------------------------------------------------------------------------------- bad inputs
def bad_input_rows(workdir: Path) -> list[Row]:
    """Each refused with one line and exit code 2 before anything flies (no drone needed: links to
    nowhere would only be opened after these checks)."""
    import onnx


    src = POLICIES_DIR / "ours_lemniscate.onnx"
    model = onnx.load(str(src))
    meta = decode_meta({p.key: p.value for p in model.metadata_props}) | {"max_rates_deg": [math.inf, 100, 200]}
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, encode_meta(meta))
    bad_pol = workdir / "inf_rates.onnx"
    onnx.save_model(model, str(bad_pol))
    room = workdir / "room.yaml"
    room.write_text("laps: 2.5\n")
    blocker = workdir / "a_file"
    blocker.write_text("")
    base = ["fly", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--uris",
            "udp://127.0.0.1:9,udp://127.0.0.1:10", "--mocap", "sim://127.0.0.1:8", "--quiet",
            "--log", str(workdir / "bad.mcap")]
    cases = {"policy max_rates_deg: [Infinity, ...]": ["--ego", str(bad_pol)],
             "--speed-max-mps inf": ["--speed-max-mps", "inf"], "--timeout-s nan": ["--timeout-s", "nan"],
             "laps: 2.5 in the config file": ["--config", str(room)],
             "--json to an unwritable path": ["--json", str(blocker / "r.json")],
             "--mocap replay:// with live links": ["--mocap", f"replay://{workdir / 'kill.mcap'}"]}
    rows = []
    for name, extra in cases.items():
        args = list(base)
        for k in range(0, len(extra), 2):   # options given twice: the later one wins in typer; replace instead
            if extra[k] in args:
                args[args.index(extra[k]) + 1] = extra[k + 1]
            else:
                args += extra[k:k + 2]
        p = subprocess.run(CLI + args, capture_output=True, text=True, timeout=120)
        err = p.stderr.strip().replace(f"{workdir}/", "")
        one = len(err.splitlines()) == 1 and err.startswith("error: ") and "Traceback" not in err
        rows.append(Row(f"bad input: {name}", detected_s="before take-off", exit_code=p.returncode,
                        passed=one and p.returncode == 2, note=err[:100]))
    return rows


def run_suite(track: str = "lemniscate", processes: bool = True, workdir: Path | None = None,
              drones: tuple[int, ...] = (2,)) -> list[Row]:
    """Every row of the table (module doc); the dry-run faults once per drone count."""
    with tempfile.TemporaryDirectory(prefix="cfrace-faults-") as tmp:
        work = Path(workdir or tmp)
        rows = [dry_run_row(kind, track, work, n) for n in drones for kind in KINDS]
        if processes:
            rows += process_rows(track, work)
        rows += bad_input_rows(work)
    return rows


def markdown(rows: list[Row]) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    lines += ["| " + " | ".join(r.cells()) + " |" for r in rows]
    return "\n".join(lines)
