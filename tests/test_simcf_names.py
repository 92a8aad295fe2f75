"""Names and defaults a user's code reads, through the REAL cflib client: the Brushless's ESC
telemetry motor.m1_rpm..m4_rpm (bidirectional DShot; rpm.m* is the RPM deck's), pm.lowVoltage
3.35 V on the Brushless, pm.criticalLowVoltage, the supervisor's and power distribution's params."""

import time

import pytest

cflib = pytest.importorskip("cflib")
import cflib.crtp  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.syncLogger import SyncLogger  # noqa: E402
from cflib.crtp.crtpstack import CRTPPacket, CRTPPort  # noqa: E402

from cfrace.calibrate.stand_link import RPM_SOURCES  # noqa: E402
from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.params import FIRMWARE_RELEASE, FIRMWARE_REVISION  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402
from cflibtools import connect, served, wait_for  # noqa: E402

cflib.crtp.init_drivers()


@pytest.mark.parametrize("profile,arming,low", [("cf21bl", True, 3.35), ("cf2x_paper", False, 3.2)])
def test_battery_thresholds_and_params_as_the_platform_has_them(profile, arming, low):
    fleet = SimFleet("lemniscate", profile, 1, arming_required=arming)
    with served(fleet) as cf:
        assert float(cf.param.get_value("pm.lowVoltage")) == pytest.approx(low, abs=1e-6)
        assert float(cf.param.get_value("pm.criticalLowVoltage")) < low
        for name in ("powerDist.idleThrust", "supervisor.tmblChckEn", "supervisor.prefltTimeout",
                     "supervisor.landedTimeout"):
            assert cf.param.toc.get_element_by_complete_name(name) is not None, name


def test_esc_telemetry_is_logged_as_motor_m_rpm_and_calibrate_prefers_it():
    assert RPM_SOURCES[0] == tuple(f"motor.m{k}_rpm" for k in range(1, 5))
    fleet = SimFleet("lemniscate", "cf21bl", 1, arming_required=True)
    with served(fleet) as cf:
        cf.param.set_value("powerDist.idleThrust", "7000")   # the Brushless firmware's idle (docs/simcf.md)
        assert wait_for(lambda: fleet.get_param(0, "powerDist.idleThrust") == 7000)
        cf.supervisor.send_arming_request(True)
        conf = LogConfig(name="esc", period_in_ms=20)
        for name in RPM_SOURCES[0]:
            conf.add_variable(name, "uint16_t")
        with SyncLogger(cf, conf) as logger:
            for k, (_, data, _) in enumerate(logger):
                if k == 25:
                    break
        # armed: the props idle, so the ESCs report a speed, the simulator's rotor speed in rpm
        assert min(data.values()) > 1000
        truth = fleet.log_values(0)
        assert data["motor.m1_rpm"] == pytest.approx(truth["rpm.m1"], rel=0.05)


def test_compressed_state_estimate_and_the_thrust_target_are_logged():
    fleet = SimFleet("lemniscate", "cf2x_paper", 1, arming_required=False)
    with served(fleet) as cf:
        conf = LogConfig(name="z", period_in_ms=20)
        for name in ("stateEstimateZ.x", "stateEstimateZ.y", "stateEstimateZ.z"):
            conf.add_variable(name, "int16_t")
        conf.add_variable("ctrltarget.thrust", "float")
        with SyncLogger(cf, conf) as logger:
            for k, (_, data, _) in enumerate(logger):
                if k == 25:
                    break
        est = fleet._fw[0].estimator.pos
        assert data["stateEstimateZ.x"] == pytest.approx(1000.0 * est[0], abs=20.0)     # mm
        assert data["stateEstimateZ.y"] == pytest.approx(1000.0 * est[1], abs=20.0)
        assert data["ctrltarget.thrust"] == 0.0


@pytest.mark.parametrize("profile,arming,device", [("cf21bl", True, "Crazyflie 2.1 Brushless"),
                                                   ("cf2x_paper", False, "Crazyflie 2.1")])
def test_platform_and_firmware_release_are_reported_as_the_drone_does(profile, arming, device):
    """platformservice.c versionCommandProcess: the firmware's tag (V_STAG) and the device type name
    (platform_cf2.c / platform_cf21bl.c) after the command byte, no terminator; version.vtpl: the
    read-only firmware.revision0/revision1/modified params of the release's commit. The simulator
    names itself once, on the console."""
    fleet = SimFleet("lemniscate", profile, 1, arming_required=arming)
    answers, text = [], []
    with SimCrazyflieServer(fleet, base_port=0) as server:
        scf = connect(server.uris[0])
        scf.cf.console.receivedChar.add_callback(text.append)
        with scf:
            cf = scf.cf
            scf.wait_for_params()
            cf.add_port_callback(CRTPPort.PLATFORM, lambda pk: answers.append((pk.channel, bytes(pk.data))))
            for cmd in (1, 2):
                pk = CRTPPacket()
                pk.set_header(CRTPPort.PLATFORM, 1)
                pk.data = bytes([cmd])
                cf.send_packet(pk)
            assert wait_for(lambda: len([a for a in answers if a[0] == 1]) >= 2)
            replies = {data[0]: data[1:] for ch, data in answers if ch == 1}
            assert replies[1] == FIRMWARE_RELEASE.encode() and FIRMWARE_RELEASE == "2026.08"
            assert replies[2] == device.encode()
            rev0, rev1 = (int(cf.param.get_value(f"firmware.revision{k}")) for k in (0, 1))
            assert f"{rev0:08x}{rev1:04x}" == FIRMWARE_REVISION[:12]
            assert cf.param.get_value("firmware.modified") == "0"
            assert cf.param.toc.get_element_by_complete_name("firmware.revision0").get_readable_access() == "RO"
            time.sleep(0.3)
    console = "".join(text)
    assert f"{device} is up and running" in console
    assert console.count("simulated") == 1, console
    assert ("powerDist.idleThrust boots at 0, not the Brushless firmware's 7000" in console) == arming, console
