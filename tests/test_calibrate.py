"""cfrace calibrate: sensor descriptions, the CAN bus, the stand procedure's safety stops and the fits,
on the simulated stand through the real cflib client (UDP) and a real python-can bus."""

import _thread
import dataclasses
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("can", reason="the thrust stand needs the `stand` extra: pip install -e '.[stand]'")

from cfrace.calibrate.bus import SensorReader, StandError, open_bus, parse_bus
from cfrace.calibrate.fit import compare, fit_recording, profile_dict, write_profile
from cfrace.calibrate.procedure import QUICK_PLAN, Plan, run_stand
from cfrace.calibrate.sensor import QUANTITIES, SENSORS_DIR, load_sensor
from cfrace.drone import load_profile
from cfrace.errors import ConfigError, LinkError
from cfrace.rehearsal.thrust_stand import SimStand

SHIPPED = sorted(p.stem for p in SENSORS_DIR.glob("*.yaml"))
#: a short plan for the safety tests: they stop long before its end
SAFETY_PLAN = Plan(levels=(30000, 65535), motors=(0,), hold_s=0.6, settle_s=0.1, rest_s=0.2, slew=200000.0,
                   tau_repeats=1, tau_hold_s=0.2)
_bus_no = iter(range(1000))
CFRACE = str(Path(sys.executable).with_name("cfrace"))


def _bus() -> str:
    """A fresh in-process bus per test (python-can's virtual channels are shared by name)."""
    return f"can://virtual/test{next(_bus_no)}"


@pytest.fixture(scope="module")
def patient_sensor(tmp_path_factory) -> Path:
    """The shipped 2-frame sensor with a 500 ms CAN timeout: this shared machine may stall the process
    for a few hundred ms, which must not stop a test that is not about the timeout."""
    src = (SENSORS_DIR / "ft6_int16_2frame.yaml").read_text()
    p = tmp_path_factory.mktemp("sensor") / "ft6_patient.yaml"
    p.write_text(re.sub(r"(?m)^timeout_ms: \d+", "timeout_ms: 500", src))
    return p


# ------------------------------------------------------------------------------- sensor files
@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_sensors_round_trip(name):
    """Every shipped layout: body wrench -> sensor axes -> CAN frames -> decoded -> body wrench."""
    s = load_sensor(name)
    body = np.array([0.012, -0.034, 0.75, 0.0021, -0.0013, 0.0042])
    frames = s.encode(dict(zip(QUANTITIES, s.from_body(body))), counter=7)
    assert len(frames) == len(s.frames)
    got = {}
    for k, (can_id, ext, data) in enumerate(frames):
        assert (can_id, ext) == (s.frames[k].can_id, s.frames[k].extended)
        values, sat = s.decode(k, data)
        assert not sat
        got.update(values)
    back = s.to_body(np.array([got[q] for q in QUANTITIES]))
    tol = max(f.scale for fr in s.frames for f in fr.fields if f.quantity != "counter")
    assert np.allclose(back, body, atol=max(tol, 1e-6))
    if s.counter is not None:
        assert got["counter"] == 7


def test_integer_fields_saturate():
    s = load_sensor("ft6_int16_2frame")
    frames = s.encode({"fx": 0.0, "fy": 0.0, "fz": 50.0, "tx": 0.0, "ty": 0.0, "tz": 0.0})
    values, sat = s.decode(0, frames[0][2])
    assert sat and values["fz"] == pytest.approx(32767 * 5e-4)


def _sensor_yaml(**edit) -> dict:
    d = yaml.safe_load((SENSORS_DIR / "ft6_int16_2frame.yaml").read_text())
    for k, v in edit.items():
        d[k] = v
    return d


BAD_SENSORS = [
    ({"rate_hz": 0}, "key 'rate_hz': must be > 0"),
    ({"byte_order": "middle"}, "key 'byte_order': expected little or big"),
    ({"axes": {"x": "+x", "y": "+x", "z": "+z"}}, "key 'axes': each sensor axis must be used once"),
    ({"axes": {"x": "+x", "y": "+y", "z": "-z"}}, "key 'axes': left-handed"),
    ({"axes": {"x": "+q", "y": "+y", "z": "+z"}}, "key 'axes.x': expected +x"),
    ({"range": {"force": [1, 1]}}, "key 'range.force': expected 3 numbers"),
    ({"colour": "red"}, "key 'colour': unknown key"),
    ({"frames": []}, "key 'frames': needs at least one frame"),
]


@pytest.mark.parametrize("edit,message", BAD_SENSORS)
def test_bad_sensor_files_one_line(tmp_path, edit, message):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(_sensor_yaml(**edit)))
    with pytest.raises(ConfigError) as e:
        load_sensor(p)
    assert message in str(e.value) and str(p) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("frame_edit,message", [
    ({"can_id": 0x800}, "frames[0].can_id': expected an 11-bit CAN id"),
    ({"fields": [{"quantity": "fx", "byte": 6, "type": "int32", "scale": 1.0}]}, "does not fit in 8 data bytes"),
    ({"fields": [{"quantity": "fw", "byte": 0, "type": "int16", "scale": 1.0}]}, "frames[0].fields[0].quantity'"),
    ({"fields": [{"quantity": "fx", "byte": 0, "type": "int16", "scale": 0.0}]}, "scale': must not be 0"),
])
def test_bad_frames_one_line(tmp_path, frame_edit, message):
    d = _sensor_yaml()
    d["frames"][0].update(frame_edit)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_sensor(p)


def test_every_quantity_once(tmp_path):
    d = _sensor_yaml()
    d["frames"][1]["fields"][2]["quantity"] = "tx"      # tz missing, tx twice
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(ConfigError, match="tx must appear in exactly one field, found 2"):
        load_sensor(p)


@pytest.mark.parametrize("text,message", [("socketcan/can0", "expected can://INTERFACE/CHANNEL"),
                                          ("can://virtual/x?speed=1", "unknown option 'speed'"),
                                          ("can://virtual/x?bitrate=fast", "bitrate must be an integer")])
def test_bad_bus_urls(text, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        parse_bus(text)
    assert parse_bus("can://pcan/PCAN_USBBUS1?bitrate=1000000").bitrate == 1000000


def test_unknown_interface_one_line():
    with pytest.raises(ConfigError, match="interface 'nosuchcan' not available"):
        open_bus("can://nosuchcan/0")


@pytest.mark.parametrize("plan,message", [(Plan(levels=(3000, 2000)), "levels must increase"),
                                          (Plan(tau_low=10000, tau_high=30000), "at most max_step"),
                                          (Plan(settle_s=1.0, hold_s=0.5), "settle_s")])
def test_bad_plans(plan, message):
    with pytest.raises(ConfigError, match=message):
        plan.check()


# ------------------------------------------------------------------------------- the full procedure
def _nonlinear_truth(tmp_path: Path) -> Path:
    """A true profile unlike the shipped ones: a quadratic thrust curve (the Crazyflie 2.0 shape),
    consistent with its motor speed range, tau_m 12 ms, k_m / k_eta 0.03 m."""
    d = yaml.safe_load(Path(load_profile("cf21bl").source).read_text())
    c = np.linspace(0, 65535, 14)
    per_motor = 2.130295e-11 * c ** 2 + 1.032633e-6 * c          # N (Foerster 2015 shape)
    newtons = 0.9 * per_motor / per_motor[-1]                    # collective, 0.9 N at full command
    d.update(name="truth_quadratic", k_eta=2.5e-8, k_m=7.5e-10, tau_m=0.012,
             motor_speed=[0.0, float(np.sqrt(newtons[-1] / 4 / 2.5e-8))],
             thrust_curve={"counts": [int(v) for v in c], "newtons": [float(v) for v in newtons]})
    p = tmp_path / "truth_quadratic.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def test_quick_calibration_recovers_a_nonlinear_truth(tmp_path, patient_sensor):
    """QUICK plan (seconds) against a quadratic thrust curve: the written profile loads, the simulator
    accepts it, and the goals hold (curve 2 % FS, k_m 5 %, tau_m 10 %) even on the short plan."""
    truth = load_profile(_nonlinear_truth(tmp_path))
    bus = _bus()
    plan = Plan(levels=(10000, 25000, 40000, 55000, 65535), motors=(1,), hold_s=0.3, settle_s=0.12,
                rest_s=0.2, slew=250000.0, tau_repeats=2, tau_hold_s=0.25)
    lines = []
    with SimStand(profile=truth, sensor=str(patient_sensor), bus=bus, seed=3) as stand:
        rec = run_stand(stand.uri, stand.sensor, bus, plan, confirmed=True, out=lines.append)
        time.sleep(0.1)
        assert not stand.motors_running()
    assert any("motor M2 alone" in ln for ln in lines) and not any("motor M1 alone" in ln for ln in lines)
    fit = fit_recording(rec)
    assert fit.spin_dirs == [0, -1, 0, 0] and fit.gamma_fitted
    out = tmp_path / "recovered.yaml"
    write_profile(out, profile_dict(fit, load_profile("cf21bl"), "recovered", rec.info))
    prof = load_profile(out)
    assert "measured on" not in prof.sources["mass"] and "measured with cfrace calibrate" in prof.sources["tau_m"]
    c = compare(prof, truth)
    assert c["curve_max_err_pct_fs"] < 2.0 and c["k_m_err_pct"] < 5.0 and c["tau_m_err_pct"] < 10.0, c
    from cfrace.sim.simulator import Simulator
    from cfrace.track import load_track

    sim = Simulator(load_track("lemniscate"), prof, worlds=1, drones=2, threads=1)
    assert sim is not None


# ------------------------------------------------------------------------------- every way out
def _stopped_within(stand: SimStand, seconds: float) -> bool:
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        if not stand.motors_running():
            return True
        time.sleep(0.01)
    return False


def test_refuses_without_confirmation(patient_sensor):
    bus = _bus()
    with SimStand(sensor=str(patient_sensor), bus=bus) as stand:
        with pytest.raises(StandError, match="refusing to start the motors.*--confirm-secured"):
            run_stand(stand.uri, stand.sensor, bus, SAFETY_PLAN, confirmed=False)
        assert stand.rig.motors_started is None and stand.fleet.status(0)["setpoints_received"] == 0


def test_ctrl_c_stops_the_motors(patient_sensor):
    bus = _bus()
    running = []
    with SimStand(sensor=str(patient_sensor), bus=bus) as stand:
        def interrupt():
            while stand.rig.motors_started is None or time.monotonic() < stand.rig.motors_started + 0.5:
                time.sleep(0.01)
            running.append(stand.motors_running())
            _thread.interrupt_main()
        threading.Thread(target=interrupt, daemon=True).start()
        long_plan = dataclasses.replace(SAFETY_PLAN, hold_s=3.0)  # the interrupt lands mid-plan on a busy machine too
        # interrupt_main() calls whatever SIGINT handler is installed: make it Python's own, as in a terminal
        old_handler = signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            with pytest.raises(KeyboardInterrupt):
                run_stand(stand.uri, stand.sensor, bus, long_plan, confirmed=True, out=lambda s: None)
        finally:
            signal.signal(signal.SIGINT, old_handler)
        assert running == [True] and _stopped_within(stand, 0.3)
        assert stand.fleet.status(0)["emergency_stopped"]


@pytest.mark.parametrize("fault,error,message", [
    ("silence", StandError, "CAN timeout, no sample from the sensor"),
    ("overload", StandError, "the sensor saturated"),
    ("link_loss", LinkError, "link lost"),
])
def test_faults_stop_the_motors(patient_sensor, fault, error, message):
    """CAN timeout, a reading beyond range, a dead link: one line, and the motors stop (for the dead
    link, by the drone's own emergency-stop watchdog within its 1 s)."""
    bus = _bus()
    with SimStand(sensor=str(patient_sensor), bus=bus, faults={fault: 0.4}) as stand:
        with pytest.raises(error, match=message) as e:
            run_stand(stand.uri, stand.sensor, bus, SAFETY_PLAN, confirmed=True, out=lambda s: None)
        assert "\n" not in str(e.value)
        assert stand.rig.motors_started is not None
        assert _stopped_within(stand, 1.6 if fault == "link_loss" else 0.3)
        assert stand.fleet.status(0)["emergency_stopped"]


def test_over_range_before_saturation(tmp_path):
    """A reading beyond the rated range (not the converter's limit) stops the run too."""
    src = (SENSORS_DIR / "ft6_int16_2frame.yaml").read_text()
    p = tmp_path / "small_range.yaml"
    p.write_text(re.sub(r"force: \[10.0, 10.0, 15.0\]", "force: [10.0, 10.0, 0.4]",
                        re.sub(r"(?m)^timeout_ms: \d+", "timeout_ms: 500", src)))
    bus = _bus()
    with SimStand(sensor=str(p), bus=bus) as stand:
        with pytest.raises(StandError, match=r"fz = 0\.4\d* N beyond the sensor's range 0.4 N"):
            run_stand(stand.uri, stand.sensor, bus, SAFETY_PLAN, confirmed=True, out=lambda s: None)
        assert _stopped_within(stand, 0.3)


def test_silent_bus_fails_before_the_drone_is_touched(patient_sensor):
    bus = _bus()
    sensor = load_sensor(patient_sensor)
    t0 = time.monotonic()
    with pytest.raises(StandError, match=r"no frame from the sensor \(ids 0x1A0, 0x1A1\) within 1 s"):
        run_stand("udp://127.0.0.1:9", sensor, bus, SAFETY_PLAN, confirmed=True)
    assert time.monotonic() - t0 < 10.0           # gave up at its 1 s time-out (a loose bound: a loaded VM)


def test_unplugged_crazyflie_one_line(patient_sensor):
    bus = _bus()
    with SimStand(sensor=str(patient_sensor), bus=bus) as stand:
        stand.server.stop()                     # the drone is gone; the sensor still sends
        with pytest.raises(LinkError) as e:
            run_stand(stand.server.uris[0], stand.sensor, bus, SAFETY_PLAN, confirmed=True, connect_timeout_s=1.5)
        assert "\n" not in str(e.value)
        assert stand.rig.motors_started is None


def test_sensor_reader_timestamps_from_counter(patient_sensor):
    """Sample times come from the sensor's counter (rate_hz apart), wrapping at 65535."""
    import can

    sensor = load_sensor(patient_sensor)
    spec = _bus()
    tx, rx = open_bus(spec), open_bus(spec)
    reader = SensorReader(rx, sensor).start()
    try:
        for n in (65534, 65535, 0, 1):
            for can_id, ext, data in sensor.encode(dict.fromkeys(QUANTITIES, 0.0), counter=n):
                tx.send(can.Message(arbitration_id=can_id, is_extended_id=ext, data=data))
        t_end = time.monotonic() + 2.0
        while reader.count() < 4 and time.monotonic() < t_end:
            time.sleep(0.01)
        _, st, _ = reader.samples()
    finally:
        reader.stop()
        tx.shutdown()
        rx.shutdown()
    assert np.allclose(np.diff(st), 1.0 / sensor.rate_hz)


# ------------------------------------------------------------------------------- the commands
def _cfrace(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([CFRACE, *args], capture_output=True, text=True,
                          timeout=kw.pop("timeout", 120), **kw)


def test_cli_bad_sensor_file_one_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: x\nrate_hz: -5\n")
    r = _cfrace("calibrate", "thrust", "--simulate", "cf21bl", "--sensor", str(p), "--out", str(tmp_path / "o.yaml"),
                "--confirm-secured")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == f"error: {p}: key 'rate_hz': must be > 0, got -5.0"


def test_cross_process_stand_over_udp_multicast(tmp_path):
    """`cfrace sim stand` in one process, `cfrace calibrate thrust --quick` in another: the sensor's
    frames cross between them on python-can's udp_multicast interface."""
    group = f"239.74.163.{100 + next(_bus_no) % 100}"
    bus = f"can://udp_multicast/{group}"
    stand = subprocess.Popen([CFRACE, "sim", "stand", "--bus", bus, "--port", "0",
                              "--duration", "90"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        uri = None
        t_end = time.monotonic() + 60
        while uri is None and time.monotonic() < t_end:
            line = stand.stdout.readline()
            m = re.search(r"on (udp://127\.0\.0\.1:\d+)", line)
            uri = m.group(1) if m else None
            assert line or stand.poll() is None, stand.stderr.read()
        assert uri, "sim stand printed no URI"
        out = tmp_path / "cf21bl_quick.yaml"
        r = _cfrace("calibrate", "thrust", "--uri", uri, "--sensor", "ft6_int16_2frame", "--bus", bus, "--out",
                    str(out), "--quick", "--confirm-secured", "--truth", "cf21bl", "--report", str(tmp_path / "rep"),
                    "--can-timeout-ms", "500")
        assert r.returncode == 0, r.stderr + r.stdout
        assert load_profile(out).name == "cf21bl_quick"
        for png in ("thrust_curve", "voltage", "k_eta", "k_m", "tau_m"):
            assert (tmp_path / "rep" / f"{png}.png").stat().st_size > 5000
        m = re.search(r"thrust curve within ([\d.]+) % of full scale .* k_m ([\d.]+) %, tau_m ([\d.]+) %", r.stdout)
        assert m and float(m.group(1)) < 2.0 and float(m.group(2)) < 5.0 and float(m.group(3)) < 10.0, r.stdout
    finally:
        stand.terminate()
        stand.wait(timeout=10)


def test_low_battery_stops_the_run(patient_sensor):
    bus = _bus()
    with SimStand(sensor=str(patient_sensor), bus=bus) as stand:
        with pytest.raises(StandError, match=r"battery at 4\.\d\d V, below 4.5 V: charge it"):
            run_stand(stand.uri, stand.sensor, bus, Plan(min_vbat=4.5), confirmed=True, out=lambda s: None)
        assert not stand.motors_running()


def test_sim_stand_refuses_the_in_process_bus():
    r = _cfrace("sim", "stand", "--bus", "can://virtual/x", "--duration", "1")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "the virtual interface only reaches this process" in r.stderr


def test_second_run_refuses_a_locked_drone(patient_sensor):
    """After a run the drone's emergency-stop watchdog locks it (reboot required): a second run on
    the same drone says so in one line before the plan runs, and sends it nothing more."""
    bus = _bus()
    tiny = Plan(levels=(30000,), motors=(0,), hold_s=0.2, settle_s=0.1, rest_s=0.1, slew=300000.0,
                tau_repeats=1, tau_hold_s=0.1)
    with SimStand(sensor=str(patient_sensor), bus=bus) as stand:
        run_stand(stand.uri, stand.sensor, bus, tiny, confirmed=True, out=lambda s: None)
        t_end = time.monotonic() + 3.0
        while not stand.fleet.status(0)["emergency_stopped"] and time.monotonic() < t_end:
            time.sleep(0.05)          # the watchdog fires 1 s after the last feed
        assert stand.fleet.supervisor_bitfield(0) >> 6 & 1                   # "is locked"
        sent, lines = stand.fleet.status(0)["setpoints_received"], []
        with pytest.raises(LinkError, match=r"locked .*power-cycle it") as e:
            run_stand(stand.uri, stand.sensor, bus, tiny, confirmed=True, out=lines.append)
        assert "\n" not in str(e.value) and lines == []
        # nothing sent after the check but the zero-thrust setpoint of cflib's own close_link (the run's
        # stop would add its STOP setpoints, the plan its override writes and lines)
        assert stand.fleet.status(0)["setpoints_received"] <= sent + 1
        assert int(stand.fleet.get_param(0, "motorPowerSet.enable")) == 0
