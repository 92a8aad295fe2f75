"""Pre-flight checks against simulated drones: status checks, the hop signal, body matching, yaw."""

import math
import re

import numpy as np
import pytest

from cfrace.flight.link.protocol import DirectSimLink
from cfrace.flight.safety.preflight import PreflightConfig, run_checks, yaw_offset_deg
from cfrace.simcf.firmware import SimFleet


def quat_mul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def setup(profile="cf2x_paper", yaw_offset_deg_=0.0, swap=False):
    fleet = SimFleet("lemniscate", profile, 2, arming_required=True)
    links = [DirectSimLink(fleet, i, clock=lambda: fleet.time) for i in range(2)]
    for link in links:
        link.connect()
    d = math.radians(yaw_offset_deg_)
    q_off = (math.cos(d / 2), 0.0, 0.0, math.sin(d / 2))

    def poses():
        _, p = fleet.poses()
        names = {"cf1": "cf2", "cf2": "cf1"} if swap else {"cf1": "cf1", "cf2": "cf2"}
        return {names[b]: (pos, quat_mul(q, q_off)) for b, (pos, q) in p.items()}
    return fleet, links, poses


def test_yaw_offset_of_a_nose_down_rotation():
    q0 = np.array([1.0, 0, 0, 0])
    tilt = math.radians(10)
    down = np.array([math.cos(tilt / 2), 0, math.sin(tilt / 2), 0])        # about body +y
    assert yaw_offset_deg(q0, down) == pytest.approx(0.0, abs=1e-9)
    d = math.radians(25)
    off = np.array([math.cos(d / 2), 0, 0, math.sin(d / 2)])
    assert yaw_offset_deg(quat_mul(q0, off), quat_mul(down, off)) == pytest.approx(25.0, abs=1e-6)


@pytest.mark.parametrize("profile", ["cf2x_paper", "cf21bl"])
def test_all_checks_pass_on_a_good_setup(profile):
    fleet, links, poses = setup(profile)
    checks = run_checks(links, ["cf1", "cf2"], fleet.profile, poses, fleet.advance)
    assert all(c.ok for c in checks), [c.line() for c in checks]
    assert [c.name for c in checks] == ["firmware", "battery", "link"] * 2 + ["body", "yaw"] * 2
    for i in range(2):
        st = fleet.status(i)
        assert st["thrust"] == 0.0 and not st["armed"] and not st["crashed"]
        assert fleet.state(i)["pos"][2] < 0.02                      # back on the floor


def test_swapped_bodies_and_a_yawed_mocap_frame_fail():
    fleet, links, poses = setup(swap=True)
    checks = run_checks(links, ["cf1", "cf2"], fleet.profile, poses, fleet.advance)
    bad = [c for c in checks if not c.ok]
    assert [c.name for c in bad] == ["body", "body"] and "rose most" in bad[0].detail
    fleet, links, poses = setup(yaw_offset_deg_=40.0)
    checks = run_checks(links, ["cf1", "cf2"], fleet.profile, poses, fleet.advance)
    yaw = [c for c in checks if c.name == "yaw"]
    assert len(yaw) == 2 and not any(c.ok for c in yaw)
    for c in yaw:
        assert float(re.search(r"yawed ([-+0-9.]+) deg", c.detail).group(1)) == pytest.approx(40.0, abs=2.0)


def test_a_low_battery_arms_nothing():
    fleet, links, poses = setup()
    fleet.set_battery(1, 0.05)
    fleet.advance(0.05)
    checks = run_checks(links, ["cf1", "cf2"], fleet.profile, poses, fleet.advance, PreflightConfig())
    assert [c.name for c in checks if not c.ok] == ["battery"] and len(checks) == 6
    assert not fleet.status(0)["armed"] and not fleet.status(1)["armed"]


def test_a_radio_that_reports_no_link_quality_fails_the_link_check():
    """A UDP link to simulated drones measures no link quality (it passes, and says so); a Crazyradio
    link must report one: without it the check fails rather than passing on NaN."""
    from cfrace.flight.safety.preflight import check_status
    fleet, links, _ = setup()
    link = links[0]
    link.quality.link_quality = float("nan")
    (udp,) = [c for c in check_status(link, 0, PreflightConfig()) if c.name == "link"]
    assert udp.ok and "not measured on this link" in udp.detail
    link.uri = "radio://0/80/2M/E7E7E7E701"
    (radio,) = [c for c in check_status(link, 0, PreflightConfig()) if c.name == "link"]
    assert not radio.ok and "not reported" in radio.detail
    link.quality.link_quality = 95.0
    assert [c for c in check_status(link, 0, PreflightConfig()) if c.name == "link"][0].ok
