"""The simulated Crazyflie firmware: a per-drone state machine in front of the batched simulator.

What a real Crazyflie does with the legacy CRTP setpoint (port 3, ``<fffH`` roll, pitch, yaw,
thrust), read from crazyflie-firmware (crtp_commander_rpyt.c, controller_pid.c, supervisor.c)
and cflib 0.1.34 (commander.py):

* cflib sends ``-pitch``; the firmware's pitch axis is the legacy one (positive = nose up), so
  the pitch that the *cflib caller* passed is a right-handed rotation about body +y (nose down).
  In body-frame (x forward, y left, z up) terms, with the values as decoded from the packet:
  ``p = +roll``, ``q = -pitch``, ``r = -yaw`` (the firmware inverts the legacy yaw rate).
* Roll and pitch are body rates (deg/s) when ``flightmode.stabModeRoll`` / ``stabModePitch`` are
  0 (RATE) and angles (deg) when they are 1 (ANGLE, the firmware default). ``stabModeYaw`` 0 is
  a yaw rate (default), 1 an absolute yaw angle (deg, not inverted).
* Thrust: locked at boot and after the watchdog shut down; a packet with thrust == 0 unlocks it.
  Locked or below 1000 counts -> 0; above 60000 counts -> 60000. Counts -> newtons through the
  drone profile's thrust curve (collective).
* Watchdog (simulated time): no setpoint for 500 ms -> level attitude (angle mode 0/0, yaw rate
  0) with the last thrust; 2 s -> motors off and thrust locked until a zero-thrust setpoint.
* Arming (the 2.1 Brushless): motors only run when armed (option ``arming_required``).
* Emergency stop (supervisor command, legacy localization packet, ``stabilizer.stop``, or the
  emergency-stop watchdog): motors off, locked until ``reboot``.

Angle mode uses a proportional attitude loop, rates = 6/s x angle error (the firmware's default
attitude PID gain Kp = 6 for roll, pitch and yaw), clamped to 720 deg/s; the simulator's own
body-rate PID then tracks those rates. See docs/simcf.md for what is not emulated.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from cfrace.drone import DroneProfile, load_profile
from cfrace.errors import ConfigError
from cfrace.sim.dynamics import PHYSICS_DT
from cfrace.simcf.params import PARAM_BY_NAME, coerce_param, default_params
from cfrace.simcf.physics import crash_reason, make_physics
from cfrace.track import Track, load_track, start_grid

DT = PHYSICS_DT            #: s, physics step of the simulator (500 Hz)
MIN_THRUST = 1000          #: counts, below this the firmware commands zero thrust
MAX_THRUST = 60000         #: counts, the firmware caps the legacy setpoint thrust here
WDT_LEVEL = 0.5            #: s without setpoint -> level out
WDT_SHUTDOWN = 2.0         #: s without setpoint -> motors off, thrust locked
ESTOP_WATCHDOG = 1.0       #: s, emergency-stop watchdog timeout once it has been fed
ANGLE_KP = 6.0             #: 1/s, attitude P gain (firmware attitude PID Kp)
ANGLE_RATE_LIMIT = math.radians(720.0)  #: rad/s, clamp of the angle loop's rate output
CONTROL_SUBSTEPS = 5       #: physics steps per control update (10 ms, the angle loop's period)


@dataclass
class Setpoint:
    """The decoded legacy setpoint, already in body-frame SI terms."""

    roll_rate_mode: bool
    pitch_rate_mode: bool
    yaw_rate_mode: bool
    roll: float       #: rad/s (rate mode) or rad (angle mode), about body +x
    pitch: float      #: rad/s or rad about body +y (nose down positive)
    yaw: float        #: rad/s about body +z, or yaw angle rad (angle mode)
    thrust_counts: int  #: effective counts after lock / min / max
    thrust: float     #: N, collective


@dataclass
class DroneFirmware:
    """Mutable firmware state of one drone."""

    params: dict
    auto_armed: bool
    thrust_locked: bool = True
    armed: bool = False
    emergency: str = ""              #: reason; non-empty means motors off until reboot
    setpoint: Setpoint | None = None
    last_setpoint_time: float | None = None
    watchdog: str = "idle"           #: idle (no setpoint yet) | ok | level | shutdown
    estop_watchdog_time: float | None = None
    setpoints_received: int = 0
    packets_received: int = 0
    events: list = field(default_factory=list)  #: console lines not yet sent

    def __post_init__(self):
        self.armed = self.auto_armed


def quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """wxyz world-from-body -> (roll, pitch, yaw) rad, ZYX, right-handed (pitch + = nose down)."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def default_start_positions(track: Track, drones: int, floor_z: float) -> tuple[np.ndarray, float]:
    """(drones, 3) positions on the floor in the track's start grid (cfrace.track.start_grid: two
    side by side, spawn.opponent_offset apart; more in rows behind them), its front row
    track.spawn.ground_distance before gate 0 on its +n side; and the yaw (rad) facing gate 0."""
    gx, gy, _, gyaw = track.gates[0]
    n = np.array([math.cos(gyaw), math.sin(gyaw)])
    lateral = np.array([-n[1], n[0]])
    centre = np.array([gx, gy]) + track.spawn.ground_distance * n
    grid = start_grid(track.spawn, track.gate, drones)             # (N, 2) [sideways, back] m
    pos = np.zeros((drones, 3))
    pos[:, :2] = centre + grid[:, :1] * lateral + grid[:, 1:] * n
    pos[:, 2] = floor_z
    return pos, _wrap(gyaw + math.pi)


class SimFleet:
    """N simulated Crazyflies (one simulator world) with the firmware's setpoint handling.

    Thread-safe: every public method takes ``self.lock``. ``advance`` is the only thing that moves
    simulated time; setpoints are stamped with the simulated time at which they arrive."""

    def __init__(self, track: Track | str, profile: DroneProfile | str, drones: int, *,
                 body_names=None, start_positions=None, seed: int = 0, arming_required: bool = True,
                 obstacles: bool = True, crash_rules=None, backend: str = "auto", sim=None):
        self.track = load_track(track) if isinstance(track, str) else track
        self.profile = load_profile(profile) if isinstance(profile, str) else profile
        if drones < 1:
            raise ConfigError(f"simcf: need at least one drone, got {drones}")
        self.n = int(drones)
        names = list(body_names) if body_names is not None else [f"cf{i + 1}" for i in range(self.n)]
        if len(names) != self.n or len(set(names)) != self.n:
            raise ConfigError(f"simcf: body_names must be {self.n} distinct names, got {names}")
        self.body_names = names
        self.arming_required = bool(arming_required)
        floor_z = self.profile.collision_box[2] / 2.0
        pos, self._start_yaw = default_start_positions(self.track, self.n, floor_z)
        if start_positions is not None:
            pos = np.asarray(start_positions, dtype=np.float64)
            if pos.shape != (self.n, 3):
                raise ConfigError(f"simcf: start_positions must have shape ({self.n}, 3), got {pos.shape}")
        self._start_pos = pos
        self.lock = threading.RLock()
        if sim is None:
            sim, backend = make_physics(self.track, self.profile, self.n, backend=backend, obstacles=obstacles,
                                        crash_rules=crash_rules, seed=seed)
        else:
            backend = "custom"
        self.sim = sim
        self.backend = backend   #: which physics runs: c, torch, numpy or custom
        self._steps = 0          # physics steps done since construction
        self._pending = 0.0      # s of requested time not yet simulated (< DT)
        self._cmd_thrust = np.zeros(self.n)   # N, collective thrust commanded in the last chunk
        self._fw = [DroneFirmware(default_params(i, self.arming_required), not self.arming_required)
                    for i in range(self.n)]
        self.log_hooks: list = []   #: callables drone index -> {log name: value} overriding log_values
        self._reset_physics()

    # ---------------------------------------------------------------- time and state
    @property
    def time(self) -> float:
        """s, simulated time."""
        return self._steps * DT

    def _reset_physics(self) -> None:
        yaw = self._start_yaw
        quat = np.tile([math.cos(yaw / 2.0), 0.0, 0.0, math.sin(yaw / 2.0)], (self.n, 1))
        self.sim.reset(self._start_pos, np.zeros((self.n, 3)), quat, np.zeros(self.n, np.int64))
        self._snapshot()

    def _snapshot(self) -> None:
        s = self.sim
        self._pos = np.array(s.pos, np.float64)          # (N, 3) m
        self._vel = np.array(s.vel, np.float64)          # (N, 3) m/s
        self._quat = np.array(s.quat, np.float64)        # (N, 4) wxyz
        self._omega = np.array(s.omega, np.float64)      # (N, 3) rad/s body
        self._crashed = np.array(s.crashed, bool)        # (N,)
        self._reason = np.array(s.reason, np.int64)      # (N,) simulator crash reason code

    def reset(self) -> None:
        """Back to the start grid, every drone rebooted (simulated time keeps running)."""
        with self.lock:
            self._reset_physics()
            for i in range(self.n):
                self.reboot(i)

    def reboot(self, i: int) -> None:
        """Power-cycle drone i's firmware: parameters to defaults, thrust locked, disarmed."""
        with self.lock:
            old = self._fw[self._check(i)]
            fw = DroneFirmware(default_params(i, self.arming_required), not self.arming_required)
            fw.packets_received = old.packets_received
            fw.events.append("SYS: reboot")
            self._fw[i] = fw

    def _check(self, i: int) -> int:
        if not 0 <= int(i) < self.n:
            raise IndexError(f"simcf: drone index {i} out of range 0..{self.n - 1}")
        return int(i)

    # ---------------------------------------------------------------- inputs
    def handle_setpoint(self, i: int, roll: float, pitch: float, yawrate: float, thrust: int) -> None:
        """A legacy RPYT setpoint exactly as decoded from the CRTP packet (deg or deg/s, counts)."""
        if not all(math.isfinite(v) for v in (roll, pitch, yawrate)):
            raise ValueError(f"simcf: non-finite setpoint ({roll}, {pitch}, {yawrate}) for drone {i}")
        with self.lock:
            fw = self._fw[self._check(i)]
            thrust = int(thrust)
            if thrust == 0:
                fw.thrust_locked = False
            counts = 0 if (fw.thrust_locked or thrust < MIN_THRUST) else min(thrust, MAX_THRUST)
            newtons = float(self.profile.thrust_curve.to_newtons(counts)) if counts else 0.0
            p = fw.params
            rate_r, rate_p = p["flightmode.stabModeRoll"] == 0, p["flightmode.stabModePitch"] == 0
            rate_y = p["flightmode.stabModeYaw"] == 0
            fw.setpoint = Setpoint(rate_r, rate_p, rate_y, math.radians(roll), -math.radians(pitch),
                                   -math.radians(yawrate) if rate_y else math.radians(yawrate), counts, newtons)
            self._fresh(fw)

    def stop_setpoint(self, i: int) -> None:
        """The generic commander's STOP setpoint: motors off now; feeds the watchdog, keeps the lock."""
        with self.lock:
            fw = self._fw[self._check(i)]
            fw.setpoint = Setpoint(True, True, True, 0.0, 0.0, 0.0, 0, 0.0)
            self._fresh(fw)

    def _fresh(self, fw: DroneFirmware) -> None:
        fw.last_setpoint_time = self.time
        fw.setpoints_received += 1
        if fw.watchdog in ("level", "shutdown"):
            fw.events.append("CMD: setpoints resumed")
        fw.watchdog = "ok"

    def note_packet(self, i: int) -> None:
        """Count one CRTP packet received for drone i (called by the server)."""
        with self.lock:
            self._fw[self._check(i)].packets_received += 1

    def set_param(self, i: int, name: str, value) -> float | int:
        """Write a parameter; returns the value as stored. KeyError for unknown, PermissionError RO."""
        with self.lock:
            fw = self._fw[self._check(i)]
            spec = PARAM_BY_NAME.get(name)
            if spec is None:
                raise KeyError(f"simcf: no parameter {name!r}")
            if spec.readonly:
                raise PermissionError(f"simcf: parameter {name} is read-only")
            fw.params[name] = coerce_param(spec, value)
            if name == "stabilizer.stop" and fw.params[name]:
                self._emergency(fw, "stabilizer.stop")
            return fw.params[name]

    def get_param(self, i: int, name: str) -> float | int:
        with self.lock:
            fw = self._fw[self._check(i)]
            if name not in fw.params:
                raise KeyError(f"simcf: no parameter {name!r}")
            return fw.params[name]

    def arm(self, i: int, armed: bool) -> bool:
        """Supervisor arming request; returns success (refused while emergency-stopped)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            if fw.auto_armed:
                return True
            if armed and fw.emergency:
                return False
            if fw.armed != bool(armed):
                fw.events.append("SUP: armed" if armed else "SUP: disarmed")
            fw.armed = bool(armed)
            return True

    def emergency_stop(self, i: int, reason: str = "emergency stop request") -> None:
        with self.lock:
            self._emergency(self._fw[self._check(i)], reason)

    def feed_emergency_stop_watchdog(self, i: int) -> None:
        """Supervisor CMD_EMERGENCY_STOP_WATCHDOG: from now on, stop unless fed every second."""
        with self.lock:
            self._fw[self._check(i)].estop_watchdog_time = self.time

    def _emergency(self, fw: DroneFirmware, reason: str) -> None:
        if not fw.emergency:
            fw.emergency = reason
            fw.events.append(f"SUP: emergency stop ({reason}), motors off, reboot required")
        if not fw.auto_armed:
            fw.armed = False

    # ---------------------------------------------------------------- physics
    def _update_watchdog(self, fw: DroneFirmware, t: float) -> None:
        if fw.estop_watchdog_time is not None and t > fw.estop_watchdog_time + ESTOP_WATCHDOG:
            self._emergency(fw, "emergency-stop watchdog")
        if fw.last_setpoint_time is None or fw.watchdog == "shutdown":
            return
        age = t - fw.last_setpoint_time
        if age > WDT_SHUTDOWN + 1e-9:
            fw.watchdog = "shutdown"
            fw.thrust_locked = True
            fw.events.append("CMD: no setpoint for 2 s, motors off, thrust locked")
        elif age > WDT_LEVEL + 1e-9 and fw.watchdog == "ok":
            fw.watchdog = "level"
            fw.events.append("CMD: no setpoint for 500 ms, levelling out")

    def _next_deadline(self, t: float) -> float:
        """The earliest simulated time at which some drone's watchdog changes state."""
        best = math.inf
        for fw in self._fw:
            if fw.estop_watchdog_time is not None and not fw.emergency:
                best = min(best, fw.estop_watchdog_time + ESTOP_WATCHDOG)
            if fw.last_setpoint_time is not None:
                if fw.watchdog == "ok":
                    best = min(best, fw.last_setpoint_time + WDT_LEVEL)
                elif fw.watchdog == "level":
                    best = min(best, fw.last_setpoint_time + WDT_SHUTDOWN)
        return best

    def _command(self, i: int) -> tuple[float, np.ndarray]:
        """(thrust N, body rates rad/s (3,)) for drone i at the current state."""
        fw = self._fw[i]
        sp = fw.setpoint
        if fw.emergency or not fw.armed or sp is None or fw.watchdog in ("idle", "shutdown"):
            return 0.0, np.zeros(3)
        if sp.thrust <= 0.0:
            return 0.0, np.zeros(3)   # the firmware resets its controller and idles at zero thrust
        roll, pitch, yaw = quat_to_euler(self._quat[i])
        if fw.watchdog == "level":
            rates = np.array([ANGLE_KP * -roll, ANGLE_KP * -pitch, 0.0])
        else:
            rates = np.array([
                sp.roll if sp.roll_rate_mode else ANGLE_KP * (sp.roll - roll),
                sp.pitch if sp.pitch_rate_mode else ANGLE_KP * (sp.pitch - pitch),
                sp.yaw if sp.yaw_rate_mode else ANGLE_KP * _wrap(sp.yaw - yaw),
            ])
            for k, is_rate in enumerate((sp.roll_rate_mode, sp.pitch_rate_mode, sp.yaw_rate_mode)):
                if not is_rate:
                    rates[k] = max(-ANGLE_RATE_LIMIT, min(ANGLE_RATE_LIMIT, rates[k]))
        return sp.thrust, rates

    def advance(self, dt: float) -> int:
        """Advance simulated time by dt s (in whole 2 ms physics steps; the remainder carries over).
        Commands are re-evaluated every 10 ms and at every watchdog deadline. Returns steps done."""
        with self.lock:
            self._pending += max(0.0, float(dt))
            todo = int(self._pending / DT + 1e-6)
            self._pending = max(0.0, self._pending - todo * DT)
            done = 0
            while done < todo:
                t = self.time
                for fw in self._fw:
                    self._update_watchdog(fw, t)
                k = min(todo - done, CONTROL_SUBSTEPS)
                deadline = self._next_deadline(t)
                if deadline < math.inf:
                    k = max(1, min(k, math.ceil((deadline - t) / DT - 1e-6) + 1))
                cmds = [self._command(i) for i in range(self.n)]
                self._cmd_thrust = np.array([c[0] for c in cmds])
                self.sim.step(self._cmd_thrust, np.stack([c[1] for c in cmds]), substeps=k)
                self._steps += k
                done += k
                self._snapshot()
            for fw in self._fw:
                self._update_watchdog(fw, self.time)
            return done

    # ---------------------------------------------------------------- outputs
    def poses(self) -> tuple[float, dict]:
        """(t_sim s, {body_name: (pos (3,) float64 m, quat (4,) float64 wxyz)}) ground truth."""
        with self.lock:
            return self.time, {n: (self._pos[i].copy(), self._quat[i].copy()) for i, n in enumerate(self.body_names)}

    def state(self, i: int) -> dict:
        """Ground-truth state of drone i: pos, vel (world), quat (wxyz), omega (body rad/s)."""
        with self.lock:
            i = self._check(i)
            return {"pos": self._pos[i].copy(), "vel": self._vel[i].copy(), "quat": self._quat[i].copy(),
                    "omega": self._omega[i].copy()}

    def status(self, i: int) -> dict:
        with self.lock:
            fw = self._fw[self._check(i)]
            age = None if fw.last_setpoint_time is None else self.time - fw.last_setpoint_time
            return {"armed": fw.armed, "locked": fw.thrust_locked, "watchdog": fw.watchdog,
                    "emergency_stopped": bool(fw.emergency), "emergency_reason": fw.emergency,
                    "crashed": bool(self._crashed[i]), "crash_reason": crash_reason(int(self._reason[i])),
                    "setpoint_age": age,
                    "setpoints_received": fw.setpoints_received, "packets_received": fw.packets_received,
                    "thrust_counts": fw.setpoint.thrust_counts if fw.setpoint else 0,
                    "thrust": float(self._command(i)[0])}

    def supervisor_bitfield(self, i: int) -> int:
        """The firmware's supervisor.info bits (see cflib Supervisor.STATES)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            flying = bool(fw.armed and not fw.emergency and self._cmd_thrust[i] > 0.0)
            bits = 0
            bits |= int(not fw.armed and not fw.emergency) << 0       # can be armed
            bits |= int(fw.armed) << 1
            bits |= int(fw.auto_armed) << 2
            bits |= int(fw.armed and not fw.emergency) << 3           # can fly
            bits |= int(flying) << 4
            bits |= int(self._tumbled(i)) << 5
            bits |= int(bool(fw.emergency)) << 6                      # locked, reboot required
            bits |= int(bool(self._crashed[i])) << 7
            bits |= 1 << 10                                           # high-level commander idle
            return bits

    def _tumbled(self, i: int) -> bool:
        w, x, y, z = self._quat[i]
        return 1.0 - 2.0 * (x * x + y * y) < 0.0   # body z axis pointing down

    def log_values(self, i: int) -> dict:
        """Values of the emulated log variables for drone i (firmware names and units)."""
        with self.lock:
            i = self._check(i)
            roll, pitch, yaw = quat_to_euler(self._quat[i])
            w, x, y, z = self._quat[i]
            fw = self._fw[i]
            pos, vel, om = self._pos[i], self._vel[i], np.degrees(self._omega[i])
            info = self.supervisor_bitfield(i)
            values = {
                "stateEstimate.x": pos[0], "stateEstimate.y": pos[1], "stateEstimate.z": pos[2],
                "stateEstimate.vx": vel[0], "stateEstimate.vy": vel[1], "stateEstimate.vz": vel[2],
                "stateEstimate.roll": math.degrees(roll), "stateEstimate.pitch": -math.degrees(pitch),
                "stateEstimate.yaw": math.degrees(yaw),
                "stateEstimate.qw": w, "stateEstimate.qx": x, "stateEstimate.qy": y, "stateEstimate.qz": z,
                "gyro.x": om[0], "gyro.y": om[1], "gyro.z": om[2],
                "stabilizer.thrust": float(fw.setpoint.thrust_counts if fw.setpoint and self._cmd_thrust[i] > 0 else 0),
                "pm.vbat": 4.0, "pm.state": 0,
                "supervisor.info": info, "sys.canfly": (info >> 3) & 1, "sys.isFlying": (info >> 4) & 1,
                "sys.isTumbled": (info >> 5) & 1,
                **{f"{g}.m{k}": 0 for g in ("rpm", "motor") for k in range(1, 5)},
            }
            for hook in self.log_hooks:   # e.g. the thrust stand (simcf/stand.py): pm.vbat, rpm.*, motor.*
                values.update(hook(i))
            return values

    def drain_events(self, i: int) -> list[str]:
        """Console lines produced by drone i since the last call (the server prints them)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            out, fw.events = fw.events, []
            return out
