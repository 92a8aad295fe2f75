"""A simulated thrust stand: one simulated Crazyflie bolted to a 6-axis force/torque sensor that
sends its readings on a python-can bus (``cfrace sim stand``; ``cfrace calibrate`` measures it).

The drone is the CRTP simulator (SimFleet + SimCrazyflieServer, driven through the real cflib
client over UDP). What the stand adds, with the true parameters from a drone profile:

* motors: the firmware's motor test override (parameters motorPowerSet.enable, m1..m4; enable 1 =
  each motor its own command, 2 = m1 to all, 3 = m1 to all with battery compensation), only while
  the drone is armed and not emergency-stopped. Without the override the motors follow the legacy
  setpoint's thrust. Command c (counts) at battery voltage V sets the rotor speed target
  ``w_des = min(sqrt(curve(c) / 4 / k_eta), w_max) * (V / V_ref)^(volts_exponent / 2)`` (the profile's
  collective thrust curve holds at V_ref = REFERENCE_VOLTS); rotor speed follows with the
  simulator's first-order lag tau_m (exact discretisation, as cfrace/sim/dynamics.py); thrust
  k_eta w^2 per rotor, wrench through the profile's allocation (yaw torque k_m / k_eta per N).
* battery: open-circuit voltage falling with the charge drawn, minus internal resistance x current;
  current ~ idle + full-load current x mean over rotors of (thrust / max thrust)^1.5. Logged as
  pm.vbat (V); rotor speeds as rpm.m1..m4 (rpm), commands as motor.m1..m4 (counts).
* sensor: at its own rate (SENSOR.yaml rate_hz), the wrench in the sensor's axes plus a constant
  bias, white noise and thrust-proportional vibration noise, encoded as the description says
  (integer fields saturate at their type's limits) and sent on the bus.

Faults for the safety tests (seconds after the motors first spin): ``silence`` (the sensor stops
sending), ``overload`` (someone leans on the stand: +20 N on body z), ``link_loss`` (the radio
link drops both ways: a UDP relay between cflib and the simulated drone stops forwarding).
"""

from __future__ import annotations

import math
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from cfrace.calibrate.bus import open_bus
from cfrace.calibrate.fit import REFERENCE_VOLTS
from cfrace.calibrate.sensor import QUANTITIES, SensorSpec, load_sensor
from cfrace.drone import DroneProfile, load_profile
from cfrace.errors import ConfigError

FAULTS = ("silence", "overload", "link_loss")
OVERLOAD_N = 20.0   #: N added on body z by the overload fault


@dataclass(frozen=True)
class StandTruth:
    """The stand's physical imperfections (what a calibration must see through)."""

    noise_force: float = 0.002        #: N, white noise per axis, 1 sigma
    noise_torque: float = 2.0e-5      #: N m
    vibration: float = 0.004          #: extra force noise per N of thrust (torque: x 0.01 m)
    bias_force: float = 0.05          #: N, 1 sigma of each axis's constant bias
    bias_torque: float = 5.0e-4       #: N m
    volts_full: float = 4.2           #: V, open-circuit voltage when full
    volts_per_charge: float = 0.6     #: V drop of the open-circuit voltage from full to empty
    charge0: float = 0.9              #: state of charge at start, 0-1
    capacity_mah: float = 250.0
    r_internal: float = 0.02          #: ohm (cell and wiring)
    idle_current: float = 0.25        #: A
    full_current: float = 7.0         #: A, all four rotors at full thrust
    volts_exponent: float = 2.0       #: thrust ~ V^volts_exponent at a fixed command
    vbat_noise: float = 0.003         #: V, 1 sigma of the pm.vbat log


class StandRig:
    """Motors, battery and the force/torque sensor of drone ``index`` of a SimFleet (a thread)."""

    def __init__(self, fleet, sensor: SensorSpec, bus, *, profile: DroneProfile | None = None, index: int = 0,
                 truth: StandTruth = StandTruth(), seed: int = 0, faults: dict | None = None):
        self.fleet, self.sensor, self.bus, self.index = fleet, sensor, bus, index
        self.profile = profile or fleet.profile
        self.truth = truth
        self.rng = np.random.default_rng(seed)
        self.faults = dict(faults or {})
        unknown = sorted(set(self.faults) - set(FAULTS))
        if unknown:
            raise ConfigError(f"sim stand: unknown fault {unknown[0]!r} ({', '.join(FAULTS)})")
        p = self.profile
        self._alloc = p.allocation()                        # (4, 4) rotor thrusts -> fz, tx, ty, tz
        self._w_max = p.motor_speed[1]
        self._t_max = p.thrust_curve.newtons[-1] / 4.0      # N per rotor at the curve's top
        self.bias = np.concatenate([self.rng.normal(0.0, truth.bias_force, 3),
                                    self.rng.normal(0.0, truth.bias_torque, 3)])
        self.omega = np.zeros(4)                            # rad/s
        self.commands = np.zeros(4)                         # counts, as applied now
        self.charge = truth.charge0
        self.volts = self._open_volts()
        self.motors_started: float | None = None            # monotonic time the motors first spun
        self.samples_sent = 0
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.on_fault = None      #: callable(name) run when a fault fires (the stand cuts the link)
        self._fired: set[str] = set()
        fleet.log_hooks.append(self._log_values)

    # ----------------------------------------------------------------- model
    def _open_volts(self) -> float:
        t = self.truth
        return t.volts_full - t.volts_per_charge * (1.0 - self.charge)

    def _command(self) -> tuple[np.ndarray, bool]:
        """(per-motor command counts (4,), battery compensated?) as the firmware would apply them."""
        f = self.fleet
        st = f.status(self.index)
        if not st["armed"] or st["emergency_stopped"]:
            return np.zeros(4), False
        enable = int(f.get_param(self.index, "motorPowerSet.enable"))
        m = np.array([f.get_param(self.index, f"motorPowerSet.m{k}") for k in range(1, 5)], dtype=np.float64)
        if enable == 1:
            return m, False
        if enable in (2, 3):
            return np.full(4, m[0]), enable == 3
        # no override: the legacy setpoint's thrust, battery compensated (the firmware's default build)
        return (np.full(4, float(st["thrust_counts"])) if st["thrust"] > 0 else np.zeros(4)), True

    def step(self, dt: float) -> np.ndarray:
        """Advance motors and battery by dt s; returns the true body wrench (6,) about the drone's centre."""
        p, t = self.profile, self.truth
        cmd, compensated = self._command()
        per_rotor = p.thrust_curve.to_newtons(cmd) / 4.0
        w_des = np.minimum(np.sqrt(np.maximum(per_rotor, 0.0) / p.k_eta), self._w_max)
        if not compensated:
            w_des = w_des * (self.volts / REFERENCE_VOLTS) ** (t.volts_exponent / 2.0)
        w_des[cmd <= 0] = 0.0
        omega = self.omega + (w_des - self.omega) * (1.0 - math.exp(-dt / p.tau_m))
        thrust = p.k_eta * omega ** 2
        current = t.idle_current + t.full_current * float(np.mean(np.clip(thrust / self._t_max, 0.0, None) ** 1.5))
        self.charge = max(0.0, self.charge - current * dt / (t.capacity_mah * 3.6))
        self.volts = self._open_volts() - t.r_internal * current
        with self.lock:
            self.omega, self.commands = omega, cmd
        if self.motors_started is None and cmd.max() > 0:
            self.motors_started = time.monotonic()
        fz, tx, ty, tz = self._alloc @ thrust
        return np.array([0.0, 0.0, fz, tx, ty, tz])

    def _log_values(self, i: int) -> dict:
        if i != self.index:
            return {}
        with self.lock:
            omega, cmd, volts = self.omega.copy(), self.commands.copy(), self.volts
        out = {"pm.vbat": volts + self.rng.normal(0.0, self.truth.vbat_noise)}
        for k in range(4):
            out[f"rpm.m{k + 1}"] = out[f"motor.m{k + 1}_rpm"] = omega[k] * 60.0 / (2.0 * math.pi)
            out[f"motor.m{k + 1}"] = cmd[k]
        return out

    def _fault_due(self, name: str, now: float) -> bool:
        at = self.faults.get(name)
        return at is not None and self.motors_started is not None and now >= self.motors_started + at

    # ----------------------------------------------------------------- the sensor thread
    def start(self) -> "StandRig":
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="simcf-stand", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def _run(self) -> None:
        import can

        period = 1.0 / self.sensor.rate_hz
        t = self.truth
        next_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                self._stop.wait(next_t - now)
                continue
            next_t += period
            if next_t < now - 0.5:          # fell far behind (machine stalled): no burst
                next_t = now + period
            body = self.step(period)
            for name in FAULTS:
                if name not in self._fired and self._fault_due(name, now):
                    self._fired.add(name)
                    if self.on_fault is not None:
                        self.on_fault(name)
            if "overload" in self._fired:
                body[2] += OVERLOAD_N
            if "silence" in self._fired:
                continue
            thrust = abs(body[2])
            noise = np.concatenate([self.rng.normal(0.0, t.noise_force + t.vibration * thrust, 3),
                                    self.rng.normal(0.0, t.noise_torque + 0.01 * t.vibration * thrust, 3)])
            reading = self.sensor.from_body(body + noise) + self.bias
            frames = self.sensor.encode(dict(zip(QUANTITIES, reading)), counter=self.samples_sent)
            try:
                for can_id, ext, data in frames:
                    self.bus.send(can.Message(arbitration_id=can_id, is_extended_id=ext, data=data))
            except can.CanError:
                pass            # a full queue / no listener: the reader sees a gap, as on a real bus
            self.samples_sent += 1


class UdpRelay:
    """Forwards cflib's UDP datagrams to a simulated drone and back; ``cut()`` drops everything
    from then on (a radio link that died)."""

    def __init__(self, target_port: int, host: str = "127.0.0.1"):
        self.target = (host, target_port)
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind((host, 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.connect(self.target)
        self.port = self.front.getsockname()[1]
        self.client = None
        self.cut_at: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stand-relay", daemon=True)
        self._thread.start()

    def cut(self) -> None:
        if self.cut_at is None:
            self.cut_at = time.monotonic()

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self.front, selectors.EVENT_READ, "front")
        sel.register(self.back, selectors.EVENT_READ, "back")
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(timeout=0.1):
                    try:
                        if key.data == "front":
                            data, self.client = self.front.recvfrom(256)
                            if self.cut_at is None:
                                self.back.send(data)
                        else:
                            data = self.back.recv(256)
                            if self.cut_at is None and self.client is not None:
                                self.front.sendto(data, self.client)
                    except OSError:
                        pass
        finally:
            sel.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.front.close()
        self.back.close()


@dataclass
class SimStand:
    """A simulated Crazyflie on a simulated stand: ``with SimStand(...) as s:`` then calibrate
    ``s.uri`` with the sensor ``s.sensor`` on ``s.bus_spec``."""

    profile: str | DroneProfile = "cf21bl"
    sensor: str | SensorSpec = "ft6_int16_2frame"
    bus: str = "can://virtual/stand"
    truth: StandTruth = field(default_factory=StandTruth)
    seed: int = 0
    faults: dict = field(default_factory=dict)
    port: int = 0               #: UDP port of the drone (0: a free one)

    def __enter__(self) -> "SimStand":
        from cfrace.simcf.firmware import SimFleet
        from cfrace.simcf.server import SimCrazyflieServer

        self.profile = load_profile(self.profile) if isinstance(self.profile, str) else self.profile
        self.sensor = load_sensor(self.sensor) if isinstance(self.sensor, str) else self.sensor
        self.bus_spec = self.bus
        self.fleet = SimFleet("lemniscate", self.profile, 1, seed=self.seed, obstacles=False)
        self.server = SimCrazyflieServer(self.fleet, base_port=self.port).start()
        self.relay = UdpRelay(self.server.ports[0]) if "link_loss" in self.faults else None
        self.can_bus = open_bus(self.bus)
        self.rig = StandRig(self.fleet, self.sensor, self.can_bus, profile=self.profile, truth=self.truth,
                            seed=self.seed, faults=self.faults)
        self.rig.on_fault = self._on_fault
        self.rig.start()
        return self

    @property
    def uri(self) -> str:
        port = self.relay.port if self.relay is not None else self.server.ports[0]
        return f"udp://127.0.0.1:{port}"

    def _on_fault(self, name: str) -> None:
        if name == "link_loss" and self.relay is not None:
            self.relay.cut()

    def motors_running(self) -> bool:
        """True while any rotor turns faster than 1 rad/s or any command is non-zero."""
        with self.rig.lock:
            return bool(self.rig.omega.max() > 1.0 or self.rig.commands.max() > 0)

    def __exit__(self, *exc) -> None:
        self.rig.stop()
        self.server.stop()
        if self.relay is not None:
            self.relay.close()
        self.can_bus.shutdown()
