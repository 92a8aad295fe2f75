"""Run a cflib script unmodified against simulated Crazyflies (`cfrace sim script`): the radio URIs it
names (``radio://0/80/2M/E7E7E7E7E7``) reach the drones that `cfrace sim serve` serves over UDP.

The rule: a radio URI whose address is 0xE7E7E7E7xx reaches the served drone whose radio id is xx
(`SimFleet.radio_id`: drone i has id i + 1, so E7E7E7E701 is the first drone, E7E7E7E702 the
second); the default address E7E7E7E7E7 (cflib's and every example's default) reaches the first
drone. Channel and data rate are ignored (the simulated drones have no radio). Other URIs are left
to cflib's own drivers, so ``udp://`` URIs work as before and an address that no drone answers
fails as it would without a drone.

How: a link driver put first in cflib's driver list (``cflib.crtp.CLASSES``, filled by the script's
own ``cflib.crtp.init_drivers()``) that takes the radio URIs of the map and opens the UDP link of
their drone with cflib's own UDP driver.
"""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

from cfrace.errors import ConfigError

DEFAULT_ADDRESS = 0xE7E7E7E7E7   #: cflib's default radio address
_RADIO_URI = re.compile(r"^radio://[^/]+(?:/\d+(?:/[^/?]+(?:/([0-9A-Fa-f]{1,10}))?)?)?/?(?:\?.*)?$")


def radio_address(uri: str) -> int | None:
    """The radio address of a cflib radio URI (the default when it names none); None if not a radio URI."""
    m = _RADIO_URI.match(uri)
    if m is None:
        return None
    return int(m.group(1), 16) if m.group(1) else DEFAULT_ADDRESS


def served_links(base_port: int, drones: int, host: str = "127.0.0.1") -> dict[int, str]:
    """{radio address: UDP URI} of `cfrace sim serve --port base_port --drones drones`."""
    links = {(DEFAULT_ADDRESS & ~0xFF) | (i + 1): f"udp://{host}:{base_port + i}" for i in range(drones)}
    links[DEFAULT_ADDRESS] = f"udp://{host}:{base_port}"
    return links


def install(links: dict[int, str]) -> None:
    """Make cflib open the UDP link of ``links`` (radio address -> UDP URI) for those radio URIs."""
    import cflib.crtp
    from cflib.crtp.exceptions import WrongUriType
    from cflib.crtp.udpdriver import UdpDriver

    class SimRadioDriver(UdpDriver):
        """A radio URI of a served drone, over UDP."""

        def connect(self, uri, radio_link_statistics_callback, link_error_callback):
            udp = links.get(radio_address(uri))
            if udp is None:
                raise WrongUriType("not a radio URI of a simulated drone")
            super().connect(udp, radio_link_statistics_callback, link_error_callback)

    original = cflib.crtp.init_drivers

    def init_drivers(*args, **kwargs):
        original(*args, **kwargs)
        if SimRadioDriver not in cflib.crtp.CLASSES:
            cflib.crtp.CLASSES.insert(0, SimRadioDriver)

    cflib.crtp.init_drivers = init_drivers
    if cflib.crtp.CLASSES:
        cflib.crtp.CLASSES.insert(0, SimRadioDriver)


def run_script(script: str | Path, args: list[str], links: dict[int, str]) -> int:
    """Run a Python script as ``python script args...`` would, its radio URIs mapped by ``links``.
    Returns its exit code."""
    path = Path(script)
    if not path.is_file():
        raise ConfigError(f"script {script}: no such file")
    install(links)
    sys.argv = [str(path), *args]
    sys.path.insert(0, str(path.resolve().parent))
    try:
        runpy.run_path(str(path), run_name="__main__")
    except SystemExit as e:
        if e.code is None or isinstance(e.code, int):
            return int(e.code or 0)
        print(e.code, file=sys.stderr)
        return 1
    return 0
