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
* Watchdog (simulated time, supervisor.c): no setpoint for 500 ms -> level out (x, y disabled,
  roll/pitch 0 in angle mode, yaw rate 0, z kept); 2 s -> motors off; in flight the supervisor
  locks (reboot required), on the ground the thrust stays locked until a zero-thrust setpoint.
* Arming (the 2.1 Brushless): motors only run when armed (option ``arming_required``).
* Emergency stop (supervisor command, legacy localization packet, ``stabilizer.stop``, or the
  emergency-stop watchdog): motors off, locked until ``reboot``.

Beyond the legacy setpoint: the generic commander's setpoint types (simcf/crtp.py decodes them
into controller.Setpoint), the cascaded PID controller (simcf/controller.py; the simulator's own
body-rate PID is the last stage), the high-level commander (simcf/planner.py) with the commander's
priorities (a low-level setpoint overrides and stops the high-level commander; notify-stop relaxes
the priority so that it takes over again), and the state estimator (simcf/estimator.py) fed by
external positions and the simulated decks. See docs/simcf.md for what is not emulated.
"""

from __future__ import annotations

import errno
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from cfrace.drone import GRAVITY, DroneProfile, load_profile
from cfrace.errors import ConfigError
from cfrace.loopmodel import IDLE_THRUST_COUNTS
from cfrace.rotations import quat_to_rot
from cfrace.sim.dynamics import PHYSICS_DT
from cfrace.simcf import planner as hl
from cfrace.simcf.controller import ABS, DISABLE, VELOCITY, PidController, Setpoint
from cfrace.simcf.mellinger import MellingerController
from cfrace.simcf.estimator import DECK_PARAMS, PositionEstimator, check_decks, yaw_quat
from cfrace.simcf.memory import memories_of
from cfrace.simcf.params import (ATTITUDE_I_LIMIT, FIRMWARE_RELEASE, PARAM_BY_NAME, PID_I_LIMIT, coerce_param,
                                 default_params, device_type_name)
from cfrace.simcf.physics import crash_reason, make_physics
from cfrace.simcf.supervisor import AccelerometerFilter, SupervisorClock, crash_g, supervisor_tick
from cfrace.track import Track, ground_start_positions, load_track

DT = PHYSICS_DT            #: s, physics step of the simulator (500 Hz)
MIN_THRUST = 1000          #: counts, below this the firmware commands zero thrust
MAX_THRUST = 60000         #: counts, the firmware caps the legacy setpoint thrust here
WDT_LEVEL = 0.5            #: s without setpoint -> level out
WDT_SHUTDOWN = 2.0         #: s without setpoint -> motors off, thrust locked
ESTOP_WATCHDOG = 1.0       #: s, emergency-stop watchdog timeout once it has been fed
CONTROL_SUBSTEPS = 5       #: physics steps per control update (10 ms, the controller's period)
PRIORITY_DISABLE, PRIORITY_HIGHLEVEL, PRIORITY_CRTP = 0, 1, 2   #: the commander's setpoint priorities
LOW_POWER_TIMEOUT = 5.0    #: s below pm.lowVoltage before pm.state is low power (pm_stm32f4.c, PM_BAT_LOW_TIMEOUT)
PID_CONTROLLERS = (0, 1)   #: stabilizer.controller values that select PID (auto, PID)
MELLINGER = 2              #: stabilizer.controller of the Mellinger controller (controller.c, ControllerTypeMellinger)


@dataclass(frozen=True)
class BatteryModel:
    """A 1-cell LiPo for pm.vbat: open-circuit voltage falls linearly with the charge drawn; the
    terminal voltage sags by the internal resistance times the current, which grows with thrust."""

    volts_full: float = 4.2          #: V, open circuit when full
    volts_per_charge: float = 1.0    #: V from full to empty (open circuit)
    charge0: float = 0.9             #: state of charge at boot, 0-1
    capacity_mah: float = 250.0
    resistance: float = 0.08         #: ohm, internal
    idle_amps: float = 0.1           #: A with motors off
    full_amps: float = 8.0           #: A at full collective thrust

    def volts(self, charge: float, amps: float) -> float:
        return self.volts_full - self.volts_per_charge * (1.0 - charge) - self.resistance * amps


@dataclass
class DroneFirmware:
    """Mutable firmware state of one drone."""

    params: dict
    auto_armed: bool
    estimator: PositionEstimator
    thrust_locked: bool = True
    armed: bool = False
    emergency: str = ""              #: reason; non-empty means motors off until reboot
    setpoint: Setpoint | None = None
    last_setpoint_time: float | None = None
    watchdog: str = "idle"           #: idle (no setpoint yet) | ok | level | shutdown
    flying_at_level: bool = False    #: motors were running when the level-out began (-> lock at 2 s)
    estop_watchdog_time: float | None = None
    setpoints_received: int = 0
    packets_received: int = 0
    events: list = field(default_factory=list)  #: console lines not yet sent
    warned: set = field(default_factory=set)    #: console warnings already given once since boot
    priority: int = PRIORITY_DISABLE             #: of the setpoint in force
    controller: PidController = field(default_factory=lambda: PidController(ATTITUDE_I_LIMIT, PID_I_LIMIT))
    mellinger: MellingerController = field(default_factory=MellingerController)
    controller_type: int = 1                     #: the controller that ran last (PID 1, Mellinger 2)
    planner: hl.Planner = field(default_factory=hl.Planner)
    control_thrust: float = 0.0                  #: N, what the controller commanded last
    control_rates: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: rad/s, idem
    charge: float = 0.9                          #: battery state of charge, 0-1
    amps: float = 0.0                            #: A, battery current
    vbat_ok_time: float = 0.0                    #: s, the last time pm.vbat was at or above pm.lowVoltage
    clock: SupervisorClock = field(default_factory=SupervisorClock)   #: is-flying, timeouts, tumble
    tumbled: bool = False                        #: the supervisor's tumble condition (tmblChckEn on)
    accel: AccelerometerFilter = field(default_factory=AccelerometerFilter)   #: the reading the firmware sees
    crashed: bool = False                        #: the supervisor's Crashed state: tumbled in flight, recovery required
    ext_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))    #: m, ext_pos.X/Y/Z: the last position
    ext_pose: np.ndarray = field(default_factory=lambda: np.zeros(7))   #: locSrv.x y z qx qy qz qw: the last pose
    banner_told: bool = False                    #: the boot lines went to a client since this boot
    loc_tick: int = 0                            #: ms (uint16), locSrvZ.tick: when the last of its own arrived

    def __post_init__(self):
        self.armed = self.auto_armed

    def halted(self) -> bool:
        """Motors not allowed whatever is asked: locked (emergency) or crashed (supervisor.c)."""
        return bool(self.emergency or self.crashed)


def quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """wxyz world-from-body -> (roll, pitch, yaw) rad, ZYX, right-handed (pitch + = nose down)."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


class SimFleet:
    """N simulated Crazyflies (one simulator world) with the firmware's setpoint handling.

    Thread-safe: every public method takes ``self.lock``. ``advance`` is the only thing that moves
    simulated time; setpoints are stamped with the simulated time at which they arrive."""

    def __init__(self, track: Track | str, profile: DroneProfile | str, drones: int, *,
                 body_names=None, start_positions=None, seed: int = 0, arming_required: bool = True,
                 obstacles: bool = True, crash_rules=None, backend: str = "auto", sim=None,
                 decks=("lighthouse",), battery: BatteryModel | None = None, params: dict | None = None):
        self.track = load_track(track) if isinstance(track, str) else track
        self.profile = load_profile(profile) if isinstance(profile, str) else profile
        if drones < 1:
            raise ConfigError(f"drones (--drones): need at least one simulated drone, got {drones}")
        self.n = int(drones)
        names = list(body_names) if body_names is not None else [f"cf{i + 1}" for i in range(self.n)]
        if len(names) != self.n or len(set(names)) != self.n:
            raise ConfigError(f"bodies (--bodies): need {self.n} distinct mocap body names, one per drone, got {','.join(map(str, names)) or 'none'}")
        self.body_names = names
        self.arming_required = bool(arming_required)
        try:
            self.decks = check_decks(decks)   #: the simulated positioning decks every drone carries
        except ValueError as e:
            raise ConfigError(f"decks (--decks): {e}") from None
        self.battery = battery or BatteryModel()
        self.seed = int(seed)
        unknown = [name for name in (params or {}) if name not in PARAM_BY_NAME or PARAM_BY_NAME[name].readonly]
        if unknown:
            raise ConfigError(f"simcf: {unknown[0]!r} is not a writable parameter of the simulated Crazyflie")
        self.boot_params = dict(params or {})   #: {name: value} this fleet's drones boot with (as a build's defaults)
        floor_z = self.profile.collision_box[2] / 2.0
        pos, self._start_yaw = ground_start_positions(self.track, self.n, floor_z)
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
        self._fw = [self._boot(i) for i in range(self.n)]
        self.log_hooks: list = []   #: callables drone index -> {log name: value} overriding log_values
        self._acc = np.zeros((self.n, 3))     # (N, 3) m/s^2, world acceleration over the last chunk
        self._reset_physics()

    # ---------------------------------------------------------------- time and state
    @property
    def time(self) -> float:
        """s, simulated time."""
        return self._steps * DT

    def _reset_physics(self) -> None:
        quat = np.tile(yaw_quat(self._start_yaw), (self.n, 1))
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

    def param_defaults(self, i: int) -> dict:
        """{name: value} of the parameters whose boot value depends on this fleet: the thrust at
        hover of the profile (posCtlPid.thrustBase), the simulator's rate PID (pid_rate.*, deg), decks, and
        the fleet's boot_params (e.g. powerDist.idleThrust 7000, the Brushless build's)."""
        prof = self.profile
        hover = float(prof.thrust_curve.to_counts(prof.weight))
        out = {"posCtlPid.thrustBase": round(hover), "ctrlMel.mass": prof.mass, "ctrlMel.massThrust": hover / prof.weight}
        for axis, pid in (("roll", prof.pid_roll_pitch), ("pitch", prof.pid_roll_pitch), ("yaw", prof.pid_yaw)):
            out.update({f"pid_rate.{axis}_kp": pid.kp, f"pid_rate.{axis}_ki": pid.ki, f"pid_rate.{axis}_kd": pid.kd})
        out.update({DECK_PARAMS[d]: 1 for d in self.decks})
        out.update(self.boot_params)
        return out

    def _boot(self, i: int) -> DroneFirmware:
        params = default_params(i, self.arming_required, self.param_defaults(i))
        fw = DroneFirmware(params, not self.arming_required, PositionEstimator(self.decks, seed=self.seed * 1009 + i))
        fw.charge = self.battery.charge0
        self._reset_estimator(i, fw)
        return fw

    def _reset_estimator(self, i: int, fw: DroneFirmware) -> None:
        """estimator_kalman.c (resetEstimation, kalmanCoreInit): position kalman.initialX/Y/Z, attitude
        level with yaw kalman.initialYaw (rad), whatever the drone's true attitude."""
        p = fw.params
        true = self._quat[i] if hasattr(self, "_quat") else yaw_quat(self._start_yaw)
        fw.estimator.reset((p["kalman.initialX"], p["kalman.initialY"], p["kalman.initialZ"]),
                           p["kalman.initialYaw"], true)

    def teleport(self, i: int, pos, vel=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0)) -> None:
        """Put drone i in flight at pos (3,) m with velocity vel (3,) m/s and attitude quat (wxyz), its
        estimator reset there (scenarios and tests: e.g. a drone finishing a race at 5 m/s)."""
        with self.lock:
            i = self._check(i)
            self.sim.set_drone(i, pos, vel, quat)
            self._snapshot()
            est = self._fw[i].estimator
            est.reset(self._pos[i], quat_to_euler(self._quat[i])[2], self._quat[i])
            est.q_err = np.array([1.0, 0.0, 0.0, 0.0])   # the attitude estimate is right too
            est.vel = self._vel[i].copy()

    def reboot(self, i: int) -> None:
        """Power-cycle drone i's firmware: parameters to defaults, thrust locked, disarmed, estimator reset."""
        with self.lock:
            old = self._fw[self._check(i)]
            fw = self._boot(i)
            fw.packets_received = old.packets_received
            fw.charge = old.charge
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
            p = fw.params
            modes = [VELOCITY if p[f"flightmode.stabMode{a}"] == 0 else ABS for a in ("Roll", "Pitch", "Yaw")]
            sp = Setpoint(mode_roll=modes[0], mode_pitch=modes[1], mode_yaw=modes[2], thrust=float(counts),
                          source="legacy")
            values = (math.radians(roll), -math.radians(pitch),
                      -math.radians(yawrate) if modes[2] == VELOCITY else math.radians(yawrate))
            for k, value in enumerate(values):
                (sp.rates if modes[k] == VELOCITY else sp.attitude)[k] = value
            self._low_level(fw, sp)

    def stop_setpoint(self, i: int) -> None:
        """The generic commander's STOP setpoint: motors off now; feeds the watchdog, keeps the lock."""
        with self.lock:
            self._low_level(self._fw[self._check(i)], Setpoint(source="stop"))

    def low_level_setpoint(self, i: int, sp: Setpoint) -> None:
        """A generic-commander setpoint (decoded by simcf/crtp.py): it overrides the high-level commander."""
        values = (sp.position, sp.velocity, sp.attitude, sp.rates, [sp.thrust])
        if not all(np.all(np.isfinite(np.asarray(v, np.float64))) for v in values):
            raise ValueError(f"simcf: non-finite setpoint for drone {i}")
        with self.lock:
            self._low_level(self._fw[self._check(i)], sp)

    def _low_level(self, fw: DroneFirmware, sp: Setpoint) -> None:
        fw.setpoint = sp
        fw.priority = PRIORITY_CRTP
        fw.planner.stop()            # the firmware stops its planner: it forgets its plan
        self._fresh(fw)

    def notify_setpoint_stop(self, i: int) -> None:
        """The generic commander's notify-setpoint-stop: the setpoint in force gets the lowest priority,
        so the high-level commander's next setpoint (its plan, or motors off if it has none) replaces it."""
        with self.lock:
            fw = self._fw[self._check(i)]
            if fw.priority > PRIORITY_HIGHLEVEL:
                fw.priority = PRIORITY_HIGHLEVEL

    def _fresh(self, fw: DroneFirmware, count: bool = True) -> None:
        fw.last_setpoint_time = self.time
        fw.setpoints_received += int(count)
        if fw.watchdog in ("level", "shutdown"):
            fw.events.append("CMD: setpoints resumed")
        fw.watchdog = "ok"

    # ---------------------------------------------------------------- high-level commander
    def high_level(self, i: int, command: str, group_mask: int = 0, **args) -> int:
        """A high-level commander command: takeoff (height m, yaw rad or None, duration s), land (same),
        go_to (x, y, z m, yaw rad, duration s, relative, linear), stop, set_group_mask (mask in
        group_mask), define_trajectory and start_trajectory, spiral (simcf/planner.py). Returns 0,
        1 (refused by the planner), errno EBUSY (the drone cannot fly) or ENOEXEC (see the planner)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            if command == "set_group_mask":
                fw.params["hlCommander.groupmask"] = int(group_mask) & 0xFF
                return 0
            if command == "define_trajectory":           # no group mask, allowed while the drone cannot fly
                return fw.planner.define_trajectory(**args)
            if not hl.in_group(group_mask, fw.params["hlCommander.groupmask"]):
                return 0
            if command == "stop":
                fw.planner.stop()
                return 0
            if fw.halted() or not fw.armed:
                fw.events.append(f"HL: {command} refused, the drone cannot fly (arm it first)")
                return errno.EBUSY
            t = self.time
            est = self._estimate_goal(i)
            if command in ("takeoff", "land"):
                yaw = est.yaw if args.get("yaw") is None else float(args["yaw"])
                fn = fw.planner.takeoff if command == "takeoff" else fw.planner.land
                return fn(est.pos, est.yaw, float(args["height"]), yaw, float(args["duration"]), t)
            if command == "go_to":
                goal = (float(args["x"]), float(args["y"]), float(args["z"]))
                return fw.planner.go_to(est, bool(args.get("relative")), bool(args.get("linear")), goal,
                                        float(args["yaw"]), float(args["duration"]), t)
            if command in ("start_trajectory", "spiral"):   # from the last setpoint (simcf/planner.py)
                fn = fw.planner.start_trajectory if command == "start_trajectory" else fw.planner.spiral
                return fn(fw.planner.current(t, est), t=t, **args)
            raise ValueError(f"simcf: unknown high-level command {command!r}")

    def _estimate_goal(self, i: int) -> hl.Goal:
        """The estimated state as the planner's start: position, velocity, yaw."""
        est = self._fw[i].estimator
        yaw = quat_to_euler(est.attitude(self._quat[i]))[2]
        return hl.Goal(est.pos.copy(), est.vel.copy(), np.zeros(3), yaw, 0.0)

    def _high_level_setpoint(self, i: int) -> None:
        """Each control tick while the drone can fly: the planner's setpoint, if its priority allows."""
        fw = self._fw[i]
        if fw.halted() or not fw.armed:
            return
        goal = fw.planner.evaluate(self.time)
        if fw.priority > PRIORITY_HIGHLEVEL:
            return
        if goal is not None:
            sp = Setpoint(mode_x=ABS, mode_y=ABS, mode_z=ABS, mode_yaw=ABS, source="high-level")
            sp.position, sp.velocity, sp.acceleration, sp.rates = goal.pos, goal.vel, goal.acc, goal.omega
            sp.attitude[2] = goal.yaw
        elif fw.planner.state == hl.IDLE and fw.watchdog != "idle":
            sp = Setpoint(source="high-level stop")
        else:
            return
        fw.setpoint, fw.priority = sp, PRIORITY_HIGHLEVEL
        self._fresh(fw, count=False)

    # ---------------------------------------------------------------- positioning
    def external_position(self, i: int, pos, quat=None) -> None:
        """An external position (CRTP localization: mocap via the ground station), m (3,) world, and
        with an external pose its attitude ``quat`` (wxyz world-from-body), fused with std dev
        locSrv.extQuatStdDev (crtp_localization_service.c, extPoseHandler; kalman_core.c,
        kalmanCoreUpdateWithPose). A quaternion that is not finite or has no length is dropped."""
        with self.lock:
            fw = self._fw[self._check(i)]
            # crtp_localization_service.c (extPositionHandler + updateLogFromExtPos, extPoseHandler): the
            # logs of the last measurement, as received (a position keeps the last pose's quaternion)
            fw.ext_pose[:3] = np.asarray(pos, np.float32)
            if quat is None:
                fw.ext_pos[:] = fw.ext_pose[:3]
            else:
                fw.ext_pose[3:] = np.asarray([quat[1], quat[2], quat[3], quat[0]], np.float32)
            fw.loc_tick = int(self.time * 1000.0) & 0xFFFF
            fw.estimator.external_position(pos, float(fw.params["locSrv.extPosStdDev"]), self.time)
            if quat is not None and not fw.estimator.fuse_attitude(quat, self._quat[i],
                                                                  float(fw.params["locSrv.extQuatStdDev"])):
                if "quat" not in fw.warned:
                    fw.warned.add("quat")
                    fw.events.append("LOC: external pose with an invalid quaternion, its attitude ignored")

    def peer_position(self, i: int, pos) -> None:
        """A packed item for another drone (crtp_localization_service.c, peerLocalizationTellPosition):
        only the ext_pos log takes it."""
        with self.lock:
            self._fw[self._check(i)].ext_pos[:] = np.asarray(pos, np.float32)

    def radio_id(self, i: int) -> int:
        """The id a packed external position addresses drone i by: the low byte of its radio address
        (0xE7E7E7E7xx, xx = i + 1, the number in its default body name cf<i+1>)."""
        return (self._check(i) + 1) & 0xFF

    def memories(self, i: int) -> list:
        """Drone i's memories (simcf/memory.py: list index = memory id), its RAM cleared by a reboot."""
        with self.lock:
            return memories_of(self._fw[self._check(i)].planner, self.decks)

    def set_battery(self, i: int, charge: float) -> None:
        """Set drone i's battery state of charge (0-1), e.g. to test a low-battery landing."""
        with self.lock:
            self._fw[self._check(i)].charge = min(1.0, max(0.0, float(charge)))

    def note_packet(self, i: int) -> None:
        """Count one CRTP packet received for drone i (called by the server). The first since a boot
        queues the boot's console lines, so the client that connects reads them: the firmware's, and
        one naming the simulator (the drone itself reports the platform and release)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            fw.packets_received += 1
            if not fw.banner_told:
                fw.banner_told = True
                fw.events[:0] = [f"SYS: {device_type_name(self.arming_required)} is up and running!",
                                 f"SYS: Build {FIRMWARE_RELEASE}",
                                 "SIMCF: a simulated Crazyflie (cfrace.simcf), not a drone; where it differs "
                                 "from the firmware: docs/simcf.md"]
                if self.arming_required and not fw.params["powerDist.idleThrust"]:   # the one default that differs
                    fw.events.insert(3, f"SIMCF: powerDist.idleThrust boots at 0, not the Brushless firmware's "
                                        f"{IDLE_THRUST_COUNTS['cf21bl']:.0f} (docs/simcf.md, Idle thrust)")

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
            if name == "stabilizer.controller" and fw.params[name] not in (*PID_CONTROLLERS, MELLINGER):
                fw.events.append(f"SIMCF: controller {fw.params[name]} is not emulated (PID 1 and Mellinger 2 are), "
                                 "PID runs")
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
            if armed and fw.halted():
                return False
            if armed and fw.tumbled:
                return False          # supervisor.c: tumbled, the pre-flight checks do not pass
            if fw.armed != bool(armed):
                fw.events.append("SUP: armed" if armed else "SUP: disarmed")
                if armed:
                    fw.clock.armed_at = self.time
            fw.armed = bool(armed)
            return True

    def recover(self, i: int) -> bool:
        """Supervisor CMD_RECOVER_SYSTEM (supervisor.c, supervisorRequestCrashRecovery): leaves the
        Crashed state unless still tumbled; False also for a drone the simulator froze in a crash."""
        with self.lock:
            fw = self._fw[self._check(i)]
            if fw.crashed and fw.tumbled:
                return False
            if fw.crashed:
                fw.crashed = False
                fw.events.append("SUP: crash recovery")
            return not self._crashed[i]

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
            # supervisor_state_machine.c (transitionsFlying, transitionsWarningLevelOut): the commander
            # watchdog's timeout in flight -> ExceptFreeFall -> Locked, reboot required. On the ground
            # (not flying) the motors stop and the legacy thrust lock holds until a zero-thrust setpoint.
            flying = fw.watchdog == "level" and fw.flying_at_level
            fw.watchdog = "shutdown"
            fw.thrust_locked = True
            if flying:
                self._emergency(fw, "commander watchdog timeout in flight")
            else:
                fw.events.append("CMD: no setpoint for 2 s, motors off, thrust locked")
        elif age > WDT_LEVEL + 1e-9 and fw.watchdog == "ok":
            fw.watchdog = "level"
            # supervisor.c isFlyingCheck: flying while a motor ran above idle within the last 2 s
            fw.flying_at_level = bool(fw.armed and not fw.halted() and fw.clock.is_flying(t))
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

    def _gated(self, fw: DroneFirmware) -> bool:
        """Motors off whatever the setpoint: emergency, disarmed, no setpoint yet, watchdog shutdown."""
        return bool(fw.halted() or not fw.armed or fw.setpoint is None or fw.watchdog in ("idle", "shutdown"))

    def _command(self, i: int) -> tuple[float, np.ndarray]:
        """(thrust N, body rates rad/s (3,)) drone i commands now (no controller update: for status)."""
        fw = self._fw[i]
        if self._gated(fw) or fw.setpoint.is_stop:
            return self._idle_newtons(fw), np.zeros(3)
        if fw.setpoint.mode_z == DISABLE:
            newtons = float(self.profile.thrust_curve.to_newtons(fw.setpoint.thrust)) if fw.setpoint.thrust > 0 else 0.0
            return max(newtons, self._idle_newtons(fw)), fw.control_rates.copy()
        return fw.control_thrust, fw.control_rates.copy()

    @staticmethod
    def _levelled(sp: Setpoint) -> Setpoint:
        """The supervisor's level-out after 500 ms without setpoints (crazyflie-firmware
        src/modules/src/supervisor.c, supervisorOverrideSetpoint, state WarningLevelOut): x and y
        disabled, roll and pitch absolute 0, yaw rate 0; z (position, velocity or thrust) kept."""
        out = Setpoint(**{**sp.__dict__, "attitude": sp.attitude.copy(), "rates": sp.rates.copy()})
        out.mode_x = out.mode_y = DISABLE
        out.mode_roll = out.mode_pitch = ABS
        out.attitude[:2] = 0.0
        out.mode_yaw, out.rates[2] = VELOCITY, 0.0
        return out

    def idle_thrust(self, i: int) -> float:
        """N, drone i's collective thrust when it commands none: its props idling (armed, on a platform
        with powerDist.idleThrust), else 0."""
        with self.lock:
            return self._idle_newtons(self._fw[self._check(i)])

    def _idle_newtons(self, fw: DroneFirmware) -> float:
        """N, the collective thrust of every motor at powerDist.idleThrust counts while the motors may
        run (armed, not stopped: supervisorAreMotorsAllowedToRun); 0 otherwise or with no idle thrust."""
        idle = float(fw.params["powerDist.idleThrust"])
        if idle <= 0.0 or fw.halted() or not fw.armed:
            return 0.0
        return float(self.profile.thrust_curve.to_newtons(idle))

    def _control(self, i: int, dt: float) -> tuple[float, np.ndarray]:
        """One controller update of drone i over the next dt s: estimator reset request, the
        high-level commander, then the PID cascade. -> (thrust N, body rates rad/s (3,))."""
        fw = self._fw[i]
        p = fw.params
        if p["kalman.resetEstimation"]:
            self._reset_estimator(i, fw)
            p["kalman.resetEstimation"] = 0          # the firmware clears the request once done
        self._high_level_setpoint(i)
        if self._gated(fw):
            fw.controller.reset()
            fw.mellinger.reset()
            idle = self._idle_newtons(fw)                # armed: the props spin at idle whatever the setpoint
            fw.control_thrust, fw.control_rates = idle, np.zeros(3)
            return idle, np.zeros(3)
        sp = self._levelled(fw.setpoint) if fw.watchdog == "level" else fw.setpoint
        q_est = fw.estimator.attitude(self._quat[i])                # the estimate, not the truth
        kind = MELLINGER if p["stabilizer.controller"] == MELLINGER else 1
        if kind != fw.controller_type:               # controller.c controllerInit: the new one starts afresh
            fw.controller.reset()
            fw.mellinger.reset()
            fw.controller_type = kind
        if kind == MELLINGER:
            counts, rates = fw.mellinger.update(sp, fw.estimator.pos, fw.estimator.vel, q_est, p, dt)
        else:
            counts, rates = fw.controller.update(sp, fw.estimator.pos, fw.estimator.vel, quat_to_euler(q_est), p, dt)
        idle = float(p["powerDist.idleThrust"])
        fw.clock.note_thrust(self.time, counts > idle and counts > 0.0 and not sp.is_stop)
        newtons = float(self.profile.thrust_curve.to_newtons(counts)) if counts > 0.0 else 0.0
        # power_distribution_quadrotor.c, powerDistributionCap: each motor at least powerDist.idleThrust
        newtons = max(newtons, self._idle_newtons(fw))
        fw.control_thrust, fw.control_rates = newtons, rates
        return newtons, rates

    def _after_step(self, dt: float, vel_before: np.ndarray) -> None:
        """Sensors after dt s of physics: the estimators' prediction and deck measurements, batteries."""
        t = self.time
        acc = (self._vel - vel_before) / dt
        self._acc = acc
        ms = round(dt * 1000.0)                  # stabilizer ticks of this chunk
        start_ms = round(t * 1000.0) - ms
        tap = supervisor_tick(start_ms, ms)
        for i, fw in enumerate(self._fw):
            p = fw.params
            fw.estimator.predict(acc[i], dt, (p["kalman.pNAcc_xy"], p["kalman.pNAcc_z"]), p["kalman.pNVel"],
                                 p["kalman.pNPos"])
            fw.estimator.decks_measure(t, self._pos[i], self._vel[i], self._quat[i])
            reading = fw.accel.run(self._body_acc_g(i), ms, tap)
            if tap is not None:
                self._supervise(i, fw, (start_ms + tap) / 1000.0, reading)
            b = self.battery
            load = self._cmd_thrust[i] / self.profile.max_collective_thrust
            fw.amps = b.idle_amps + b.full_amps * min(1.0, max(0.0, load)) ** 1.5
            fw.charge = max(0.0, fw.charge - fw.amps * dt / 3.6 / b.capacity_mah)
            if b.volts(fw.charge, fw.amps) >= p["pm.lowVoltage"]:
                fw.vbat_ok_time = t

    def _body_acc_g(self, i: int) -> np.ndarray:
        """The specific force in the body frame over the last chunk, g (what the accelerometer
        senses, before the firmware's low-pass: fw.accel)."""
        return quat_to_rot(self._quat[i]).T @ (self._acc[i] + np.array([0.0, 0.0, GRAVITY])) / GRAVITY

    def _supervise(self, i: int, fw: DroneFirmware, t: float, acc_g) -> None:
        """supervisor.c, supervisorUpdate at its 25 Hz tick t: tumble check on the accelerometer
        reading acc_g (body, g, low-passed), preflight and landing timeouts."""
        p = fw.params
        crash = crash_g(acc_g, float(p["supervisor.crashDetectGs"]))
        tumbled = bool((crash is not None or fw.clock.tumbled(t, acc_g)) and p["supervisor.tmblChckEn"])
        if crash is not None and tumbled and not fw.tumbled:
            fw.events.append(f"SUP: crash detected @ {crash:.2f} Gs (max {p['supervisor.crashDetectGs']:.2f})")
        fw.tumbled = tumbled
        if fw.halted():
            return
        if fw.tumbled and fw.clock.is_flying(t) and fw.armed:
            # supervisor_state_machine.c: Flying -> Crashed (motors off, disarmed), left only by a
            # crash recovery request while no longer tumbled (supervisorRequestCrashRecovery)
            fw.crashed = True
            fw.armed = fw.auto_armed
            fw.events.append("SUP: tumbled while flying: crashed, recovery required")
        elif fw.auto_armed:
            return
        elif fw.tumbled and fw.armed:
            fw.armed = False
            fw.events.append("SUP: tumbled, disarming")
        elif fw.clock.preflight_timeout(t, fw.armed, p["supervisor.prefltTimeout"]):
            fw.armed = False
            fw.events.append("SUP: preflight timeout, disarming")
        elif fw.clock.landing_timeout(t, fw.armed, p["supervisor.landedTimeout"]):
            fw.armed = False
            fw.events.append("SUP: landed timeout, disarming")

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
                cmds = [self._control(i, k * DT) for i in range(self.n)]
                self._cmd_thrust = np.array([c[0] for c in cmds])
                vel_before = self._vel
                self.sim.step(self._cmd_thrust, np.stack([c[1] for c in cmds]), substeps=k)
                self._steps += k
                done += k
                self._snapshot()
                self._after_step(k * DT, vel_before)
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
                    "supervisor_crashed": fw.crashed,
                    "crashed": bool(self._crashed[i]), "crash_reason": crash_reason(int(self._reason[i])),
                    "setpoint_age": age,
                    "setpoints_received": fw.setpoints_received, "packets_received": fw.packets_received,
                    "thrust_counts": self._thrust_counts(i),
                    "thrust": float(self._command(i)[0]),
                    "setpoint_source": fw.setpoint.source if fw.setpoint else "", "priority": fw.priority,
                    "high_level": fw.planner.state}

    def _thrust_counts(self, i: int) -> int:
        """Counts of the thrust in force (the setpoint's, or the velocity controller's), 0 when off."""
        fw = self._fw[i]
        thrust = self._command(i)[0]
        if thrust <= 0.0:
            return 0
        if self._gated(fw) or fw.setpoint.is_stop:
            return int(fw.params["powerDist.idleThrust"])
        if fw.setpoint.mode_z == DISABLE:
            return max(int(fw.setpoint.thrust), int(fw.params["powerDist.idleThrust"]))
        return int(round(float(self.profile.thrust_curve.to_counts(thrust))))

    def supervisor_bitfield(self, i: int) -> int:
        """The firmware's supervisor.info bits (see cflib Supervisor.STATES)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            # supervisor.c updateLogData: flying = state Flying or WarningLevelOut (the 2 s hysteresis)
            flying = bool(fw.armed and not fw.halted() and fw.clock.is_flying(self.time))
            bits = 0
            bits |= int(not fw.armed and not fw.halted() and not fw.tumbled) << 0   # can be armed
            bits |= int(fw.armed) << 1
            bits |= int(fw.auto_armed) << 2
            bits |= int(fw.armed and not fw.halted()) << 3           # can fly
            bits |= int(flying) << 4
            bits |= int(self._tumbled(i)) << 5
            bits |= int(bool(fw.emergency)) << 6                      # locked, reboot required
            bits |= int(bool(self._crashed[i]) or fw.crashed) << 7   # crashed: the supervisor's, or the simulator's
            state = fw.planner.state
            bits |= int(state in (hl.FLYING, hl.LANDING)) << 8        # high-level commander active
            bits |= int(state == hl.FLYING and fw.planner.finished(self.time)) << 9   # its move finished
            bits |= int(state == hl.DISABLED) << 10                   # it produces no setpoints
            return bits

    def _tumbled(self, i: int) -> bool:
        return self._fw[i].tumbled

    def log_values(self, i: int) -> dict:
        """Values of the emulated log variables for drone i (firmware names and units: m, m/s, deg,
        deg/s, g; pitch with the firmware's legacy sign, nose up positive)."""
        with self.lock:
            i = self._check(i)
            fw = self._fw[i]
            est, om = fw.estimator, np.degrees(self._omega[i])
            q_est = est.attitude(self._quat[i])
            roll, pitch, yaw = (math.degrees(a) for a in quat_to_euler(q_est))
            w, x, y, z = q_est
            var_p, var_v = est.variances()
            info = self.supervisor_bitfield(i)
            acc_g = self._acc[i] / GRAVITY
            body_acc = fw.accel.reading          # sensorData.acc, the low-passed reading the firmware logs
            vbat = self.battery.volts(fw.charge, fw.amps)
            counts = self._thrust_counts(i)
            sp = fw.setpoint or Setpoint()
            debug = (fw.mellinger if fw.controller_type == MELLINGER else fw.controller).debug
            values = {
                **{f"stateEstimate.{k}": v for k, v in zip(("x", "y", "z", "vx", "vy", "vz"), (*est.pos, *est.vel))},
                **{f"stateEstimate.{k}": v for k, v in zip(("ax", "ay", "az"), acc_g)},
                "stateEstimate.roll": roll, "stateEstimate.pitch": -pitch, "stateEstimate.yaw": yaw,
                "stateEstimate.qw": w, "stateEstimate.qx": x, "stateEstimate.qy": y, "stateEstimate.qz": z,
                "stabilizer.roll": roll, "stabilizer.pitch": -pitch, "stabilizer.yaw": yaw,
                "stabilizer.thrust": float(counts),
                **{f"kalman.state{k}": v for k, v in zip("XYZ", est.pos)},
                **{f"kalman.stateP{k}": v for k, v in zip("XYZ", est.vel)},
                **{f"kalman.var{k}": v for k, v in zip("XYZ", var_p)},
                **{f"kalman.varP{k}": v for k, v in zip("XYZ", var_v)},
                "kalman.q0": w, "kalman.q1": x, "kalman.q2": y, "kalman.q3": z,
                "gyro.x": om[0], "gyro.y": om[1], "gyro.z": om[2],
                "acc.x": body_acc[0], "acc.y": body_acc[1], "acc.z": body_acc[2],
                "ctrltarget.x": sp.position[0], "ctrltarget.y": sp.position[1], "ctrltarget.z": sp.position[2],
                "ctrltarget.vx": sp.velocity[0], "ctrltarget.vy": sp.velocity[1], "ctrltarget.vz": sp.velocity[2],
                "ctrltarget.roll": math.degrees(sp.attitude[0]), "ctrltarget.pitch": -math.degrees(sp.attitude[1]),
                "ctrltarget.yaw": math.degrees(sp.rates[2]), "ctrltarget.thrust": float(sp.thrust),
                **{f"stateEstimateZ.{k}": 1000.0 * v for k, v in zip(("x", "y", "z", "vx", "vy", "vz"),
                                                                      (*est.pos, *est.vel))},
                **{f"stateEstimateZ.{k}": 1000.0 * GRAVITY * v for k, v in zip(("ax", "ay", "az"), acc_g)},
                **{f"controller.{k}": float(debug.get(k, 0.0)) for k in ("cmd_thrust", "roll", "yaw", "rollRate", "yawRate")},
                "controller.pitch": -float(debug.get("pitch", 0.0)), "controller.pitchRate": float(debug.get("pitchRate", 0.0)),
                **{f"posCtl.{k}": float(debug.get(k, 0.0)) for k in ("targetVX", "targetVY", "targetVZ", "targetX",
                                                                     "targetY", "targetZ")},
                "pm.vbat": vbat, "pm.vbatMV": vbat * 1000.0,
                "pm.state": 3 if self.time - fw.vbat_ok_time > LOW_POWER_TIMEOUT else 0,
                "pm.batteryLevel": 100.0 * fw.charge,
                "range.zrange": 1000.0 * self._pos[i][2] if "flow" in self.decks else 0.0,
                **{f"ext_pos.{k}": float(v) for k, v in zip("XYZ", fw.ext_pos)},
                **{f"locSrv.{k}": float(v) for k, v in zip(("x", "y", "z", "qx", "qy", "qz", "qw"), fw.ext_pose)},
                "locSrvZ.tick": fw.loc_tick,
                "supervisor.info": info, "sys.canfly": (info >> 3) & 1, "sys.isFlying": (info >> 4) & 1,
                "sys.isTumbled": (info >> 5) & 1,
                **self._motor_logs(i),
            }
            for hook in self.log_hooks:   # e.g. the thrust stand (rehearsal/thrust_stand.py): pm.vbat, rpm.*, motor.*
                values.update(hook(i))
            return values

    def _motor_logs(self, i: int) -> dict:
        """rpm.m1-m4 (rotor speeds, rpm) and motor.m1-m4 (each rotor's thrust as counts of the collective
        curve), from the simulator's rotor speeds; zeros for a physics without rotor states."""
        speeds = getattr(self.sim, "motor", None)
        if speeds is None:
            return {**{f"{g}.m{k}": 0 for g in ("rpm", "motor") for k in range(1, 5)},
                    **{f"motor.m{k}_rpm": 0 for k in range(1, 5)}}
        w = np.asarray(speeds[i], np.float64)
        counts = self.profile.thrust_curve.to_counts(4.0 * self.profile.k_eta * w * w)
        rpm = w * 60.0 / (2.0 * math.pi)
        return {**{f"rpm.m{k + 1}": rpm[k] for k in range(4)}, **{f"motor.m{k + 1}_rpm": rpm[k] for k in range(4)},
                **{f"motor.m{k + 1}": float(counts[k]) if w[k] > 0 else 0.0 for k in range(4)}}

    def drain_events(self, i: int) -> list[str]:
        """Console lines produced by drone i since the last call (the server prints them)."""
        with self.lock:
            fw = self._fw[self._check(i)]
            out, fw.events = fw.events + fw.planner.drain(), []
            return out
