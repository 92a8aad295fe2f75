"""Flight configuration: frozen dataclasses, SI units, loadable from a strict YAML file.

A flight config file (``cfrace fly --config room.yaml``) names what belongs to a room and its
drones; command-line options override it. Example::

    uris: [radio://0/80/2M/E7E7E7E7E1, radio://1/90/2M/E7E7E7E7E2]   # ego, opp
    bodies: [cf1, cf2]                                               # mocap body of ego, opp
    mocap: vicon://192.168.1.10
    profile: cf21bl
    safety: {geofence_margin_m: 0.3, speed_max_mps: 6.0}
    velocity_alpha: 1.0      # optional: estimator velocity filter; prewarm_s, rt_priority, loop_cpu, ... likewise

Unknown keys are errors (cfrace.yamlcfg.Reader).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from cfrace.errors import ConfigError
from cfrace.flight.loop.realtime import parse_loop_cpu, parse_rt_priority
from cfrace.yamlcfg import Reader, load_yaml

DRONE_NAMES = ("ego", "opp")  #: drone 0 flies the ego policy, drone 1 the opponent policy
MAX_DRONES = 16               #: drones per race (the simulator's C kernel takes 16 per world)


def drone_names(n: int) -> tuple[str, ...]:
    """The drones' names in results, logs and fault specs: ego, opp for two; d1 .. dN for more."""
    return DRONE_NAMES if n == 2 else tuple(f"d{i + 1}" for i in range(n))


#: default mocap latency compensation (s) for real mocap systems and the sim:// pose stream: a 100-Hz
#: frame is 0-10 ms old when the tick reads it, plus the system's own latency (Vicon: a few ms). In
#: lockstep dry-runs the shipped policies flew with 10 ms too much compensation as well as with the
#: right amount, and compensation kept them flying at latencies where they fell without it
#: (docs/flight.md, "Mocap latency").
LATENCY_COMP_DEFAULT_S = 0.010


#: the largest value each safety limit may take (the one rule for the command line and the config
#: file): beyond these a limit no longer limits anything in a room
SAFETY_MAX = {"geofence_margin_m": 10.0, "floor_z_m": 2.0, "floor_grace_s": 3600.0, "tilt_max_deg": 180.0,
              "speed_max_mps": 50.0, "mocap_stale_s": 1.0, "link_timeout_s": 5.0, "overrun_stop_s": 1.0,
              "fence_soft_m": 10.0, "mocap_glitches": 1000.0, "opponent_clearance_m": 10.0, "low_battery_v": 5.0,
              "low_battery_s": 60.0, "min_separation_m": 5.0, "start_slot_m": 10.0}
#: limits that must be above 0: at 0 they would stop every drone at the start
SAFETY_ABOVE_ZERO = frozenset({"tilt_max_deg", "speed_max_mps", "mocap_stale_s", "link_timeout_s", "overrun_stop_s"})
TIMEOUT_MAX_S = 3600.0   #: s, the longest race and the longest connect / mocap wait


def _limit(name: str, value, hi: float, lo: float = 0.0, *, lo_open: bool = False) -> None:
    """ConfigError unless value is a finite number in [lo, hi] (or (lo, hi])."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) \
        and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        raise ConfigError(f"{name}: must be a finite number in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {value!r}")


@dataclass(frozen=True)
class SafetyConfig:
    """Limits of the per-tick safety check (cfrace.flight.safety.check). See docs/flight.md."""

    geofence_margin_m: float = 0.3   #: m, the fence is the track arena grown by this on every side
    floor_z_m: float = 0.1           #: m, below this after ``floor_grace_s`` = crashed (training rule)
    floor_grace_s: float = 1.0       #: s after the start during which the floor rule is off (take-off)
    tilt_max_deg: float = 80.0       #: deg, body z axis against world up
    speed_max_mps: float = 12.0      #: m/s, estimated speed
    mocap_stale_s: float = 0.15      #: s, a pose estimate older than this stops the drone
    link_timeout_s: float = 0.5      #: s without any packet from a drone = link lost
    overrun_stop_s: float = 0.1      #: s, a tick starting later than this past its deadline stops all
    #: m, least distance between two drones' centres before take-off (checked on the first mocap frame)
    #: and while the take-off grace lasts (floor_grace_s); closer stops both (cfrace.flight.safety.check)
    min_separation_m: float = 0.2
    #: m, a ground start (start: ground): on the first mocap frame every drone must stand within this
    #: of its start-grid slot and face gate 0 within the training's heading jitter, else nothing
    #: flies (the policies were trained from there, cfrace.flight.loop.swarm.check_take_off); 0 = off
    start_slot_m: float = 0.3
    # soft failsafes: these land the drone (docs/flight.md, "Safety")
    fence_soft_m: float = 0.3        #: m, inside the fence but closer than this to it: land
    mocap_glitches: float = 3        #: pose dropouts and outliers within 2 s that mean degraded mocap: land
    opponent_clearance_m: float = 0.7   #: m, a downed drone this close to the path to the next gate: land
    low_battery_v: float = 3.3       #: V (pm.vbat under load), below it ...
    low_battery_s: float = 1.0       #: ... for this long: land (sags at full thrust are shorter); 0 V = off

    def __post_init__(self):
        for f in fields(self):
            _limit(f"safety.{f.name}", getattr(self, f.name), SAFETY_MAX[f.name], lo_open=f.name in SAFETY_ABOVE_ZERO)


@dataclass(frozen=True)
class FlightConfig:
    """Everything `cfrace fly` needs. Lists hold one entry per drone, ego first."""

    track: str                                   #: track name or path
    ego: str                                     #: policy short name or .onnx path
    opp: str
    #: N > 2 drones: one policy per drone (ego and opp are then the first two); () = (ego, opp)
    policies: tuple[str, ...] = ()
    uris: tuple[str, ...] = ()                   #: link URI per drone (radio://, udp://, sim://N)
    mocap: str = "sim"                           #: mocap source spec (vicon://HOST, replay://F.mcap, sim)
    bodies: tuple[str, ...] = ()                 #: mocap body name per drone (() : cf1 .. cfN)
    laps: int = 3
    profile: str = "cf21bl"                      #: drone profile of the flown drones
    obstacles: bool = False
    log: Path | None = None                      #: flight log (.mcap); None = no log
    foxglove_port: int | None = None             #: serve the flight live to Foxglove on 127.0.0.1:PORT (0: any free port)
    foxglove_scene: bool = True                  #: the Foxglove scene in the log (when the SDK is installed); off: `bench loop`'s baseline
    timeout_s: float = 120.0                     #: s, the race ends (draw) after this
    connect_timeout_s: float = 5.0               #: s per link
    mocap_timeout_s: float = 3.0                 #: s to wait for the first frame with every body
    rate_hz: float = 100.0                       #: Hz, control loop (setpoints streamed every tick)
    quiet: bool = False                          #: no live view
    view_hz: float = 4.0                         #: Hz, live view refresh
    #: SCHED_FIFO priority of the loop thread: "auto" (50 where this process may, else normal), 0
    #: (normal) or 1-99 (flight/loop/realtime.py)
    rt_priority: int | str = "auto"
    #: CPU of the loop thread: "auto" (the highest CPU of this process when it has two or more),
    #: "off" or a CPU number; the process's other threads go to the other CPUs (flight/loop/realtime.py)
    loop_cpu: int | str = "auto"
    prewarm_s: float = 0.003                     #: s before each tick: the warm-up window (FlightLoop.prewarm; 0 = off)
    velocity_alpha: float = 1.0                  #: estimator low-pass on pose differences, (0, 1]; 1 = none (docs/flight.md)
    #: s the estimator predicts every pose forward (position with the velocity, attitude with the
    #: body rates) to make up for the mocap's latency; None: LATENCY_COMP_DEFAULT_S, 0 for `sim`
    latency_comp_s: float | None = None
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    start: str = "ground"                        #: ground (policies take off) or hover (high-level take-off first)
    landing: bool = True                         #: land at the race's end and on soft failsafes (else motors off)
    pose_stream: bool = True                     #: stream each drone's mocap pose to it (external position)
    #: feed each flying drone's emergency-stop watchdog (the link keeper, every ESTOP_FEED_S): a drone
    #: whose link is lost cuts its motors 1 s after the last feed instead of flying on its last
    #: setpoint for 2 s; the firmware then stays locked until the drone is rebooted (docs/flight.md)
    estop_watchdog: bool = False

    def __post_init__(self):
        if self.start not in ("ground", "hover"):
            raise ConfigError(f"start: must be ground or hover, got {self.start!r}")
        if self.start == "hover" and not self.landing:
            raise ConfigError("start: hover needs landing on (the firmware flies the take-off and the landing)")
        if self.landing and not self.pose_stream:
            raise ConfigError("landing needs pose_stream on: the firmware lands from the mocap poses it is sent "
                              "(use --no-landing with --no-pose-stream)")
        if not (isinstance(self.laps, int) and not isinstance(self.laps, bool) and 1 <= self.laps <= 1000):
            raise ConfigError(f"laps: must be a whole number in 1..1000, got {self.laps!r}")
        for key in ("timeout_s", "connect_timeout_s", "mocap_timeout_s"):
            _limit(key, getattr(self, key), TIMEOUT_MAX_S, lo_open=True)
        n = len(self.specs)
        if not 2 <= n <= MAX_DRONES:
            raise ConfigError(f"policies: a race needs 2 to {MAX_DRONES} drones, got {n}")
        if not self.bodies:
            object.__setattr__(self, "bodies", tuple(f"cf{i + 1}" for i in range(n)))
        if len(self.bodies) != n:
            raise ConfigError(f"bodies: need {n} mocap body names (one per drone), got {list(self.bodies)}")
        if len(set(self.bodies)) != len(self.bodies):
            raise ConfigError(f"bodies: names must differ, got {list(self.bodies)}")
        if self.uris and len(self.uris) != n:
            raise ConfigError(f"uris: need {n} URIs (one per drone), got {list(self.uris)}")
        if self.uris and len(set(self.uris)) != len(self.uris):
            raise ConfigError(f"uris: every drone needs its own URI, got {list(self.uris)}")
        if not (1.0 <= self.rate_hz <= 1000.0):
            raise ConfigError(f"rate_hz: must be in [1, 1000], got {self.rate_hz}")
        if not (0.0 < self.velocity_alpha <= 1.0):
            raise ConfigError(f"velocity_alpha: must be in (0, 1], got {self.velocity_alpha}")
        if not (0.0 <= self.prewarm_s < 1.0 / self.rate_hz):
            raise ConfigError(f"prewarm_s: must be in [0, one period = {1.0 / self.rate_hz} s), got {self.prewarm_s}")
        if self.latency_comp_s is not None and not (0.0 <= self.latency_comp_s < 0.1):
            raise ConfigError(f"latency_comp_s: must be in [0, 0.1) s, got {self.latency_comp_s}")
        object.__setattr__(self, "loop_cpu", parse_loop_cpu(self.loop_cpu))
        object.__setattr__(self, "rt_priority", parse_rt_priority(self.rt_priority))
        if self.foxglove_port is not None and not (0 <= self.foxglove_port < 65536):
            raise ConfigError(f"foxglove_port: must be a TCP port 0-65535, got {self.foxglove_port}")

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def specs(self) -> tuple[str, ...]:
        """The policy of every drone, in drone order."""
        return tuple(self.policies) if self.policies else (self.ego, self.opp)

    @property
    def names(self) -> tuple[str, ...]:
        return drone_names(len(self.specs))

    @property
    def latency_comp(self) -> float:
        """latency_comp_s, or its default: none for the in-process `sim` source (its poses are read
        at the tick, no latency), LATENCY_COMP_DEFAULT_S for every other source."""
        if self.latency_comp_s is not None:
            return self.latency_comp_s
        return 0.0 if self.mocap == "sim" else LATENCY_COMP_DEFAULT_S


def split_list(text: str | None) -> tuple[str, ...] | None:
    """'a,b' -> ('a', 'b'); None stays None (option not given)."""
    if text is None:
        return None
    return tuple(s.strip() for s in text.split(",") if s.strip())


def load_flight_file(path: str | Path) -> dict:
    """Read a flight config YAML into keyword arguments for FlightConfig (strict)."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such flight config file")
    r = Reader(path, load_yaml(path))
    out: dict = {}
    for key in ("uris", "bodies", "policies"):
        if r.has(key):
            seq = r.sequence(key)
            if not seq or not all(isinstance(s, str) and s for s in seq):
                raise r.fail(key, f"expected a list of strings, got {seq!r}")
            out[key] = tuple(seq)
    for key in ("mocap", "profile", "track", "ego", "opp", "start"):
        if r.has(key):
            out[key] = r.string(key)
    for key in ("timeout_s", "connect_timeout_s", "mocap_timeout_s", "rate_hz"):
        if r.has(key):
            out[key] = r.number(key, positive=True)
    if r.has("velocity_alpha"):
        out["velocity_alpha"] = r.number("velocity_alpha", positive=True, max=1.0)
    if r.has("latency_comp_s"):
        out["latency_comp_s"] = r.number("latency_comp_s", min=0.0, max=0.099)
    if r.has("prewarm_s"):
        out["prewarm_s"] = r.number("prewarm_s", min=0.0)
    for key, parse in (("rt_priority", parse_rt_priority), ("loop_cpu", parse_loop_cpu)):
        if r.has(key):
            try:
                out[key] = parse(r.raw(key))
            except ConfigError as exc:
                raise r.fail(key, str(exc).removeprefix(f"{key}: ")) from None
    if r.has("laps"):
        laps = r.number("laps", min=1)
        if laps != int(laps):
            raise r.fail("laps", f"must be a whole number, got {laps:g}")
        out["laps"] = int(laps)
    for key in ("obstacles", "landing", "pose_stream", "estop_watchdog"):
        if r.has(key):
            v = r.raw(key)
            if not isinstance(v, bool):
                raise r.fail(key, f"expected true or false, got {v!r}")
            out[key] = v
    if r.has("safety"):
        s = r.mapping("safety")
        kw = {f.name: s.number(f.name, min=0.0, max=SAFETY_MAX[f.name], positive=f.name in SAFETY_ABOVE_ZERO)
              for f in fields(SafetyConfig) if s.has(f.name)}
        s.done()
        out["safety"] = SafetyConfig(**kw)
    r.done()
    return out


def check_policy_sources(from_file: dict, file, ego, opp, policies) -> None:
    """The file's ``policies:`` (N drones) and --ego/--opp (two), or its ``ego:``/``opp:`` and
    --policies, do not mix: one of them would be dropped without a word."""
    if (ego or opp) and from_file.get("policies"):
        raise ConfigError(f"{file}: its 'policies:' race {len(from_file['policies'])} drones and --ego/--opp "
                          "race two: give one of them")
    if policies and (from_file.get("ego") or from_file.get("opp")):
        raise ConfigError(f"{file}: its 'ego:'/'opp:' race two drones and --policies races "
                          f"{len(policies)}: give one of them")


def make_config(file: str | Path | None = None, **options) -> FlightConfig:
    """FlightConfig from an optional YAML file, overridden by the options that are not None."""
    kw = load_flight_file(file) if file else {}
    check_policy_sources(kw, file, options.get("ego"), options.get("opp"), options.get("policies"))
    safety_over = options.pop("safety_overrides", None) or {}
    kw.update({k: v for k, v in options.items() if v is not None})
    if safety_over:
        kw["safety"] = replace(kw.get("safety", SafetyConfig()), **safety_over)
    if options.get("policies") and (options.get("ego") or options.get("opp")):
        raise ConfigError("give either --policies P1,...,PN or --ego and --opp, not both")
    if kw.get("policies"):   # N drones: ego and opp are the first two
        pols = tuple(kw["policies"])
        if len(pols) < 2:
            raise ConfigError(f"--policies: at least 2, got {list(pols)}")
        kw.setdefault("ego", pols[0])
        kw.setdefault("opp", pols[1])
    for key in ("track", "ego", "opp"):
        if key not in kw:
            raise ConfigError(f"missing --{key} (or '{key}:' in the flight config file)")
    return FlightConfig(**kw)
