"""Flights in Foxglove: the scene in the flight log (schemas Foxglove knows, messages that decode
against them), the live server (a real WebSocket client receives the scene), logs from before the
scene still read, and why the log file is still written by our writer (the SDK's loses a kill)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("foxglove")
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402

from cfrace.cli.main import main  # noqa: E402
from cfrace.flight.log.writer import read_log  # noqa: E402
from cfrace.track import load_track  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OLD_LOG = ROOT / "tests" / "data" / "flight_before_foxglove.mcap"   # written by cfrace before the scene existed


def _run(args: list[str]) -> int:
    argv, sys.argv = sys.argv, ["cfrace", *args]
    try:
        main()
    except SystemExit as exc:
        return int(exc.code or 0)
    finally:
        sys.argv = argv
    return 0


def _decoder(schema_name: str, schema_data: bytes):
    """A protobuf message class from a FileDescriptorSet schema, as Foxglove decodes it."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(schema_data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def _mcap_channels(path: Path):
    """{topic: (message_encoding, schema name, schema encoding, schema data, [payloads])}."""
    from mcap.reader import make_reader
    out = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            entry = out.setdefault(channel.topic, (channel.message_encoding, schema.name, schema.encoding,
                                                   schema.data, []))
            entry[4].append(message.data)
    return out


@pytest.fixture(scope="module")
def flight_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fg") / "race.mcap"
    code = _run(["sim", "dry-run", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--lockstep",
                 "--timeout-s", "1.5", "--log", str(path), "--quiet"])
    assert code == 0
    return path


def test_log_carries_foxglove_schemas_and_messages_decode(flight_log):
    import jsonschema

    ch = _mcap_channels(flight_log)
    expect = {"/foxglove/scene": ("protobuf", "foxglove.SceneUpdate", "protobuf"),
              "/foxglove/drones": ("protobuf", "foxglove.SceneUpdate", "protobuf"),
              "/foxglove/tf": ("protobuf", "foxglove.FrameTransforms", "protobuf"),
              "/foxglove/command/cf1": ("json", "cfrace.Command", "jsonschema"),
              "/foxglove/command/cf2": ("json", "cfrace.Command", "jsonschema")}
    for topic, (menc, name, senc) in expect.items():
        assert topic in ch, topic
        assert ch[topic][:3] == (menc, name, senc), topic
    track = load_track("lemniscate")
    # the track scene: 4 bars per gate, arena and geofence boxes (12 edges each), gate labels
    scene_cls = _decoder("foxglove.SceneUpdate", ch["/foxglove/scene"][3])
    scene = scene_cls.FromString(ch["/foxglove/scene"][4][0])
    ents = {e.id: e for e in scene.entities}
    assert set(ents) == {"gates", "arena", "geofence"}          # no obstacles in this race
    assert len(ents["gates"].cubes) == 4 * track.num_gates
    assert len(ents["gates"].texts) == track.num_gates
    assert len(ents["arena"].lines[0].points) == 24
    c0 = track.gate_bars()[0][0]
    assert ents["gates"].cubes[0].pose.position.x == pytest.approx(c0[0])
    assert ents["gates"].cubes[0].size.x == pytest.approx(track.gate.thickness)
    # drone poses: world -> cf1, cf2 at every tick, where the estimate says
    tf_cls = _decoder("foxglove.FrameTransforms", ch["/foxglove/tf"][3])
    tfs = [tf_cls.FromString(d) for d in ch["/foxglove/tf"][4]]
    assert {t.child_frame_id for t in tfs[-1].transforms} == {"cf1", "cf2"}
    assert all(t.parent_frame_id == "world" for t in tfs[-1].transforms)
    data = read_log(flight_log)
    t_last, est = data.messages("/estimate")[-1]
    x = next(t for t in tfs[-1].transforms if t.child_frame_id == "cf1").translation.x
    assert x == pytest.approx(est["cf1"]["pos"][0])
    # trails grow: the last drones update has a trail per drone with many points
    drones = scene_cls.FromString(ch["/foxglove/drones"][4][-1])
    trails = {e.id: e for e in drones.entities if e.id.startswith("trail/")}
    assert set(trails) == {"trail/cf1", "trail/cf2"} and len(trails["trail/cf1"].lines[0].points) >= 10
    # commands: valid against their JSON schema, equal to /setpoint
    schema = json.loads(ch["/foxglove/command/cf1"][3])
    cmds = [json.loads(d) for d in ch["/foxglove/command/cf1"][4]]
    for c in cmds:
        jsonschema.validate(c, schema)
    sp = data.messages("/setpoint")[-1][1]["cf1"]
    assert cmds[-1]["roll_rate_dps"] == pytest.approx(sp["rates_dps"][0])
    assert cmds[-1]["thrust_counts"] == sp["thrust_counts"]


def test_obstacles_in_the_scene_when_raced_with(tmp_path):
    from cfrace.flight.log.foxglove_scene import FoxgloveScene
    from cfrace.flight.safety.check import Fence

    track = load_track("lemniscate")
    scene = FoxgloveScene(track, Fence.from_track(track, 0.3), ["cf1", "cf2"], obstacles=True).static()
    cls = _decoder(scene.schema[0], scene.schema[2])
    ents = {e.id: e for e in cls.FromString(scene.data).entities}
    assert len(ents["obstacles"].cubes) == len(track.obstacles) > 0
    h = track.obstacle_boxes()[1][0]
    assert ents["obstacles"].cubes[0].size.z == pytest.approx(2 * h[2])


def test_logs_from_before_the_scene_still_read(tmp_path):
    """A log written by cfrace before the Foxglove scene: `log info`, `log plot` and `sim replay`."""
    assert "/foxglove/scene" not in read_log(OLD_LOG).topics
    assert _run(["log", "info", str(OLD_LOG)]) == 0
    assert _run(["log", "plot", str(OLD_LOG), "-o", str(tmp_path)]) == 0
    assert any(p.suffix == ".png" for p in tmp_path.iterdir())
    assert _run(["sim", "replay", str(OLD_LOG)]) == 0


def test_new_logs_read_by_info_plot_and_replay(flight_log, tmp_path, capsys):
    data = read_log(flight_log)
    assert data.bad_messages == 0 and data.channels["/foxglove/tf"][0] == "protobuf"
    assert _run(["log", "info", str(flight_log)]) == 0
    assert "/foxglove/tf" in capsys.readouterr().out
    assert _run(["log", "plot", str(flight_log), "-o", str(tmp_path)]) == 0
    assert _run(["sim", "replay", str(flight_log)]) == 0
    assert read_log(flight_log).bad_messages == 0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_live_client_receives_the_scene(tmp_path):
    """`cfrace sim dry-run --foxglove PORT` (real time, cflib over UDP): a WebSocket client speaking
    Foxglove's protocol subscribes and receives the track scene and the drones' poses."""
    import struct

    from websockets.sync.client import connect

    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "cfrace", "sim", "dry-run", "--track", "lemniscate", "--ego", "ours",
                             "--opp", "ds", "--timeout-s", "6", "--quiet", "--foxglove", str(port)],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        ws = None
        deadline = time.monotonic() + 60
        while ws is None and time.monotonic() < deadline:
            try:
                ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=2)
            except OSError:
                assert proc.poll() is None, proc.stdout.read()
                time.sleep(0.2)
        assert ws is not None, "the live server never answered"
        channels, got = {}, {}
        with ws:
            subscribed = set()
            end = time.monotonic() + 30
            while time.monotonic() < end and not {"/foxglove/scene", "/foxglove/tf"} <= set(got):
                frame = ws.recv(timeout=10)
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get("op") == "advertise":
                        for c in msg["channels"]:
                            channels[c["id"]] = c
                        want = [c for c in msg["channels"] if c["topic"] in ("/foxglove/scene", "/foxglove/tf")
                                and c["id"] not in subscribed]
                        if want:
                            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                                {"id": c["id"], "channelId": c["id"]} for c in want]}))
                            subscribed |= {c["id"] for c in want}
                    continue
                assert frame[0] == 0x01       # message data: opcode, subscription id, log time, payload
                sub, = struct.unpack_from("<I", frame, 1)
                got.setdefault(channels[sub]["topic"], frame[13:])
        scene_ch = next(c for c in channels.values() if c["topic"] == "/foxglove/scene")
        assert scene_ch["schemaName"] == "foxglove.SceneUpdate" and scene_ch["encoding"] == "protobuf"
        import base64
        cls = _decoder("foxglove.SceneUpdate", base64.b64decode(scene_ch["schema"]))
        ents = {e.id for e in cls.FromString(got["/foxglove/scene"]).entities}
        assert {"gates", "arena", "geofence"} <= ents
        tf_ch = next(c for c in channels.values() if c["topic"] == "/foxglove/tf")
        tfs = _decoder("foxglove.FrameTransforms", base64.b64decode(tf_ch["schema"])).FromString(got["/foxglove/tf"])
        assert {t.child_frame_id for t in tfs.transforms} <= {"cf1", "cf2"} and tfs.transforms
    finally:
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode in (0, 3), out       # 3: a loaded machine's race stopped both drones; served all the same
    assert f"ws://127.0.0.1:{port}" in out      # the banner says where to connect


_SDK_WRITER = """
import os, signal, sys, foxglove
w = foxglove.open_mcap(sys.argv[1], allow_overwrite=True)    # the SDK's file writer, its defaults
ch = foxglove.Channel("/estimate", schema={"type": "object"})
for k in range(int(sys.argv[2])):                            # 100 Hz ticks of about 1 kB, as a flight logs
    ch.log({"t": k / 100, "pad": "x" * 1000}, log_time=1_000_000_000 + k * 10_000_000)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_sdk_file_writer_loses_more_than_a_second_on_a_kill(tmp_path):
    """Why the flight log keeps our writer (which loses at most the tick being written:
    tests/test_flight_log.py::test_sigkill_mid_flight_leaves_a_readable_log): the SDK's MCAP
    writer keeps a whole chunk in memory, so a killed flight loses its last seconds. If this test
    fails, the SDK no longer loses them and may write the log (docs/flight-log.md, "Foxglove")."""
    path = tmp_path / "sdk.mcap"
    ticks = 300
    proc = subprocess.run([sys.executable, "-c", _SDK_WRITER, str(path), str(ticks)], capture_output=True)
    assert proc.returncode == -signal.SIGKILL
    kept = 0
    if path.exists() and path.stat().st_size > 8:
        from mcap.stream_reader import StreamReader
        from mcap.records import Message
        try:
            for r in StreamReader(open(path, "rb"), record_size_limit=None).records:
                kept += isinstance(r, Message)
        except Exception:  # noqa: BLE001 - cut off: count what came before
            pass
    lost_s = (ticks - kept) / 100
    assert lost_s > 1.0, f"the SDK's writer lost only {lost_s:.2f} s"


def test_bench_loop_foxglove_alternates_the_three_configurations(monkeypatch):
    """`cfrace bench loop --foxglove`: each round runs the plain log, the scene in the log and the
    scene served live, in that order, with the options given; medians and ratios to the plain log.
    (bench_loop itself runs for real in test_flight_faults.test_bench_loop_against_a_sim_serve_process.)"""
    import cfrace.rehearsal.loop_timing as benchloop
    from cfrace.cli.measure import _foxglove_compare

    calls = []

    def fake_bench_loop(duration_s, *, floor_s, foxglove, scene, **options):
        calls.append((foxglove, scene, options["drones"]))
        ms = 1.0 + foxglove + 0.5 * scene + len(calls) / 100      # differs by configuration and round
        stats = {"p50": ms, "p99": 2 * ms, "max": 3 * ms}
        return {"end": "timeout", "loop": {k: stats for k in ("compute_ms", "compute_cpu_ms", "period_jitter_ms",
                                                                  "late_ms")}}

    monkeypatch.setattr(benchloop, "bench_loop", fake_bench_loop)
    doc = _foxglove_compare(1.0, 2, {"drones": 4, "pose_stream": True})
    assert calls == [(False, False, 4), (False, True, 4), (True, True, 4)] * 2
    fig = doc["figures"]["compute p99"]
    assert fig["ms"] == pytest.approx({"plain log": 2 * 1.025, "scene in log": 2 * 1.535, "scene + live": 2 * 2.545})
    assert fig["ratio_to_plain"]["scene + live"] == pytest.approx(2.545 / 1.025)
    assert [len(v) for v in doc["runs"].values()] == [2, 2, 2]

