"""Links to the drones: a small protocol with a real (cflib) and a direct simulated implementation.

Units at this boundary (design rule 10: conversions happen only here):
``send(roll_rate_dps, pitch_rate_dps, yaw_rate_dps, thrust_counts)`` takes the BODY rates the
drone must fly, right-handed, x forward, y left, z up (pitch + = nose down), in deg/s, and the
collective thrust in CRTP counts (cfrace.contract.actions.SetpointMap: the calibration curve).

The legacy CRTP setpoint (port 3, ``<fffH``) does not carry those values as they are:
cflib's ``send_setpoint`` negates pitch, and the firmware negates the yaw rate of this packet
(crtp_commander_rpyt.c), so with p, q, r the wanted body rates:

    cflib send_setpoint(roll=p, pitch=q, yawrate=-r, thrust)  ->  packet (p, -q, -r, thrust)

and the firmware (roll/pitch in rate mode: flightmode.stabModeRoll = stabModePitch = 0) tracks
gyro x = p, gyro y = q, gyro z = r. ``packet_values`` and ``cflib_setpoint_args`` hold this once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from cfrace.errors import LinkError

RATE_MODE_PARAMS = ("flightmode.stabModeRoll", "flightmode.stabModePitch")  #: set to 0 after EVERY connect


def packet_values(p_dps: float, q_dps: float, r_dps: float) -> tuple[float, float, float]:
    """Body rates (deg/s) -> (roll, pitch, yawrate) as they sit in the CRTP <fffH packet."""
    return p_dps, -q_dps, -r_dps


def cflib_setpoint_args(p_dps: float, q_dps: float, r_dps: float) -> tuple[float, float, float]:
    """Body rates (deg/s) -> the (roll, pitch, yawrate) arguments of cflib's send_setpoint."""
    return p_dps, q_dps, -r_dps


@dataclass
class LinkQuality:
    """Figures of one link, read by the loop every tick (cheap)."""

    connected: bool = False
    last_rx: float = float("nan")     #: time.monotonic() of the last packet from the drone
    latency_ms: float = float("nan")  #: round trip (cflib echo ping, p95), nan if unknown
    link_quality: float = float("nan")  #: % (Crazyradio ack rate), nan if unknown
    sent: int = 0                     #: setpoints sent
    errors: int = 0
    error: str = ""                   #: the last error message
    vbat: float = float("nan")        #: V, the drone's battery (pm.vbat), nan if unknown

    def rx_age(self, now: float) -> float:
        return now - self.last_rx if self.last_rx == self.last_rx else float("inf")

    def as_dict(self, now: float) -> dict:
        return {"connected": self.connected, "rx_age_s": self.rx_age(now), "latency_ms": self.latency_ms,
                "link_quality": self.link_quality, "sent": self.sent, "errors": self.errors, "error": self.error,
                "vbat": self.vbat}


@runtime_checkable
class Link(Protocol):
    uri: str
    quality: LinkQuality

    def connect(self, timeout_s: float) -> None:
        """Open the link; LinkError (one line naming the URI) when nothing answers in time."""

    def setup(self) -> None:
        """After every connect: rate mode params, arming, zero-thrust unlock."""

    def send(self, roll_rate_dps: float, pitch_rate_dps: float, yaw_rate_dps: float, thrust_counts: int) -> None:
        """Stream one setpoint (body rates deg/s, thrust counts)."""

    def stop(self) -> None:
        """Zero setpoint + stop: motors off. Safe to call many times and on a dead link."""

    def close(self) -> None:
        """Stop (if connected) and release the link."""

    # the firmware's own flight modes (take-off, landing, failsafes; docs/flight.md "Landing")
    def send_pose(self, pos, quat) -> None:
        """Stream the drone's mocap pose to its estimator: pos (3,) m world, quat (4,) wxyz. Never raises."""

    def high_level(self, command: str, **args) -> None:
        """A high-level commander command: takeoff / land (height m, yaw rad or None = current,
        duration s), go_to (x, y, z m, yaw rad, duration s), stop. Never raises."""

    def notify_stop(self) -> None:
        """Hand control from streamed setpoints to the high-level commander. Never raises."""

    def read_status(self, timeout_s: float = 2.0) -> dict:
        """For the pre-flight checks: {"protocol": CRTP protocol version, "vbat": V or nan}."""


def send_high_level(hlc, command: str, args: dict) -> None:
    """Call the high-level commander ``hlc`` (cflib's HighLevelCommander or anything with its methods)."""
    if command == "takeoff":
        hlc.takeoff(args["height"], args["duration"], yaw=args.get("yaw"))
    elif command == "land":
        hlc.land(args["height"], args["duration"], yaw=args.get("yaw"))
    elif command == "go_to":
        hlc.go_to(args["x"], args["y"], args["z"], args["yaw"], args["duration"])
    elif command == "stop":
        hlc.stop()
    else:
        raise ValueError(f"unknown high-level command {command!r}")


@dataclass
class _DirectQuality(LinkQuality):
    """A direct link always answers at once, until it is cut."""

    cut_at: float = float("nan")

    def rx_age(self, now: float) -> float:
        return 0.0 if self.cut_at != self.cut_at else max(0.0, now - self.cut_at)


class DirectSimLink:
    """A link straight to one drone of a simcf SimFleet: no UDP, no cflib, no threads (--lockstep).

    It applies the same packet convention as the real link (packet_values), so the simulated
    firmware decodes exactly what it would decode from cflib's packet."""

    def __init__(self, fleet, index: int, clock=time.monotonic):
        self.fleet, self.index = fleet, int(index)
        self.uri = f"sim://{self.index}"
        self.quality = _DirectQuality()
        self._clock = clock
        self.cut = False   #: fault injection: a cut link delivers nothing and hears nothing

    def cut_link(self) -> None:
        """Fault injection: from now on nothing gets through either way."""
        self.cut = True
        self.quality.cut_at = self._clock()

    def connect(self, timeout_s: float = 5.0) -> None:
        if not 0 <= self.index < self.fleet.n:
            raise LinkError(f"{self.uri}: no such simulated drone (fleet has {self.fleet.n})")
        self.quality.connected = True
        self._heard()

    def _heard(self) -> None:
        if not self.cut:
            self.quality.last_rx = self._clock()

    def setup(self) -> None:
        self._need()
        for name in RATE_MODE_PARAMS:
            self.fleet.set_param(self.index, name, 0)
        self.fleet.arm(self.index, True)
        self.fleet.handle_setpoint(self.index, 0.0, 0.0, 0.0, 0)
        self._heard()

    def _need(self) -> None:
        if not self.quality.connected:
            raise LinkError(f"{self.uri}: not connected")

    def send(self, roll_rate_dps, pitch_rate_dps, yaw_rate_dps, thrust_counts) -> None:
        if self.cut or not self.quality.connected:
            return
        r, p, y = packet_values(float(roll_rate_dps), float(pitch_rate_dps), float(yaw_rate_dps))
        self.fleet.handle_setpoint(self.index, r, p, y, int(thrust_counts))
        self.quality.sent += 1
        if self.quality.sent % 10 == 1:      # the battery, as the real link logs it (10 Hz)
            self.quality.vbat = float(self.fleet.log_values(self.index)["pm.vbat"])
        self._heard()

    def stop(self) -> None:
        if self.cut or not self.quality.connected:
            return
        self.fleet.handle_setpoint(self.index, 0.0, 0.0, 0.0, 0)
        self.fleet.stop_setpoint(self.index)
        self.fleet.arm(self.index, False)

    def close(self) -> None:
        if self.quality.connected:
            self.stop()
        self.quality.connected = False

    def send_pose(self, pos, quat) -> None:
        if not self.cut and self.quality.connected:
            self.fleet.external_position(self.index, pos, quat)

    def high_level(self, command: str, **args) -> None:
        if not self.cut and self.quality.connected:
            self.fleet.high_level(self.index, command, **args)

    def notify_stop(self) -> None:
        if not self.cut and self.quality.connected:
            self.fleet.notify_setpoint_stop(self.index)

    def read_status(self, timeout_s: float = 2.0) -> dict:
        self._need()
        from cfrace.simcf.crtp import PROTOCOL_VERSION
        return {"protocol": PROTOCOL_VERSION, "vbat": float(self.fleet.log_values(self.index)["pm.vbat"])}


class RecordingLink:
    """A link to nothing that keeps what it was sent (replays and unit tests)."""

    def __init__(self, uri: str = "null://", clock=time.monotonic):
        self.uri = uri
        self.quality = LinkQuality()
        self._clock = clock
        self.sent: list[tuple[float, float, float, int]] = []
        self.stops = 0
        self.setups = 0
        self.poses: list = []      #: (pos, quat) sent with send_pose
        self.commands: list = []   #: (high-level command or "notify_stop", args)

    def connect(self, timeout_s: float = 5.0) -> None:
        self.quality.connected = True
        self.quality.last_rx = self._clock()

    def setup(self) -> None:
        self.setups += 1

    def send(self, roll_rate_dps, pitch_rate_dps, yaw_rate_dps, thrust_counts) -> None:
        self.sent.append((float(roll_rate_dps), float(pitch_rate_dps), float(yaw_rate_dps), int(thrust_counts)))
        self.quality.sent += 1
        self.quality.last_rx = self._clock()

    def stop(self) -> None:
        self.stops += 1

    def close(self) -> None:
        self.quality.connected = False

    def send_pose(self, pos, quat) -> None:
        self.poses.append((tuple(float(v) for v in pos), tuple(float(v) for v in quat)))

    def high_level(self, command: str, **args) -> None:
        self.commands.append((command, dict(args)))

    def notify_stop(self) -> None:
        self.commands.append(("notify_stop", {}))

    def read_status(self, timeout_s: float = 2.0) -> dict:
        return {"protocol": 12, "vbat": float("nan")}
