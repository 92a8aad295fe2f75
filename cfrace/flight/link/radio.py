"""How many Crazyflies one Crazyradio may carry at the loop's rate, from Bitcraze's figures.

Several Crazyflies share one Crazyradio the usual lab way: one channel and data rate, a
different radio address each (``radio://0/80/2M/E7E7E7E7E1``, ``radio://0/80/2M/E7E7E7E7E2``).
The radio talks to them one packet at a time: it sends a packet and waits for the acknowledgement
before the next one (Enhanced ShockBurst PTX mode, no buffering), and Bitcraze's Crazyradio
USB/radio protocol documentation gives this protocol "about 500 packets per second". The
flight loop sends every drone one setpoint per tick (100 Hz), and the link needs some packets of
its own (downlink polling, the occasional parameter or log packet, retries), kept here as a
RESERVE share of the budget. So one radio carries

    floor(RADIO_PACKETS_PER_S x (1 - RESERVE) / rate_hz) = floor(500 x 0.8 / 100) = 4 drones,

and `cfrace fly` refuses a fifth on the same radio (one line naming the radio and the URIs).
Drones on one radio must share its channel and data rate (switching them per packet costs a USB
setup transaction of about 1 ms each, Bitcraze's figure: more than a whole tick at 4 drones) and
need distinct addresses. Non-radio links (udp://, sim://, null://) are not counted.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from cfrace.errors import ConfigError

RADIO_PACKETS_PER_S = 500.0   #: packets/s of one Crazyradio (Bitcraze, Crazyradio USB/radio protocol doc)
RESERVE = 0.2                 #: share of that budget kept for the link's own packets (polling, retries)
DEFAULT_ADDRESS = "E7E7E7E7E7"

_RADIO = re.compile(r"^radio://(?P<dev>\d+)/(?P<ch>\d+)(?:/(?P<rate>250K|1M|2M))?(?:/(?P<addr>[0-9A-Fa-f]{10}))?"
                    r"(?:\?.*)?$")


@dataclass(frozen=True)
class RadioUri:
    uri: str
    device: int       #: the Crazyradio's index on this computer
    channel: int      #: 0..125
    datarate: str     #: 250K | 1M | 2M
    address: str      #: 10 hex digits, upper case


def parse_radio_uri(uri: str) -> RadioUri | None:
    """A radio:// URI's parts; None for other links. ConfigError for a malformed radio:// URI."""
    if not uri.startswith("radio://"):
        return None
    m = _RADIO.match(uri)
    if m is None or not 0 <= int(m["ch"]) <= 125:
        raise ConfigError(f"{uri}: not a Crazyradio URI (radio://DEVICE/CHANNEL 0-125[/250K|1M|2M][/ADDRESS 10 hex])")
    return RadioUri(uri, int(m["dev"]), int(m["ch"]), m["rate"] or "2M", (m["addr"] or DEFAULT_ADDRESS).upper())


def max_drones_per_radio(rate_hz: float = 100.0) -> int:
    """Drones one Crazyradio carries when each gets one packet per loop tick at ``rate_hz``."""
    return max(0, int(math.floor(RADIO_PACKETS_PER_S * (1.0 - RESERVE) / rate_hz + 1e-9)))


def check_radios(uris: list[str] | tuple[str, ...], rate_hz: float = 100.0) -> dict[int, list[RadioUri]]:
    """The radio:// URIs grouped by Crazyradio; ConfigError (one line) when a radio carries more
    drones than max_drones_per_radio, mixes channels or data rates, or two drones share an address."""
    radios: dict[int, list[RadioUri]] = {}
    for uri in uris:
        r = parse_radio_uri(uri)
        if r is not None:
            radios.setdefault(r.device, []).append(r)
    limit = max_drones_per_radio(rate_hz)
    for dev, group in radios.items():
        names = ", ".join(r.uri for r in group)
        if len(group) > limit:
            raise ConfigError(f"Crazyradio {dev} carries {len(group)} drones ({names}); at {rate_hz:g} Hz one radio "
                              f"carries at most {limit} (about {RADIO_PACKETS_PER_S:g} packets/s, "
                              f"{RESERVE:.0%} kept for the link): add a radio (radio://1/...)")
        if len({(r.channel, r.datarate) for r in group}) > 1:
            raise ConfigError(f"Crazyradio {dev}: its drones must share one channel and data rate ({names})")
        if len({r.address for r in group}) < len(group):
            raise ConfigError(f"Crazyradio {dev}: two drones on one address ({names}); give each its own")
    seen: dict[tuple, str] = {}
    for r in (r for group in radios.values() for r in group):    # one drone reached by two radios
        key = (r.channel, r.datarate, r.address)
        if key in seen:
            raise ConfigError(f"{seen[key]} and {r.uri}: the same drone (channel, data rate and address) on two "
                              "radios; give each drone its own address")
        seen[key] = r.uri
    return radios
