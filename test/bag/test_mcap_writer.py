"""MCAP recordings that mcap_ros2 and the independent ``rosbags`` reader both accept.

Messages are real ROS 2 messages serialised by rclpy; every sequence is filled because
``serialize_message`` may append junk bytes for empty sequences (DESIGN.md section 4).
"""

import errno
import json
import os
import signal
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as Rosbag2Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from dea_array_twin.bag import msg_definitions, writer
from dea_array_twin.bag.recover import RecoveryError, recover
from dea_array_twin.bag.writer import RecordingError, Ros2McapWriter, default_qos_yaml

REPO = Path(__file__).resolve().parents[2]
MAGIC = b"\x89MCAP0\r\n"
CONFIG = {"dea_array_twin_config": {"prestretch": "1.2", "units": "3", "membrane": "VHB4905"}}
FORCE, STATES = "std_msgs/msg/Float64MultiArray", "sensor_msgs/msg/JointState"
DIAG = "diagnostic_msgs/msg/DiagnosticArray"


# ---------------------------------------------------------------- message factories

def force_msg(i: int) -> Float64MultiArray:
    msg = Float64MultiArray(data=[0.1 * i, 0.2 * i, 0.3 * i])
    msg.layout.dim = [MultiArrayDimension(label="unit", size=3, stride=3)]
    return msg


def states_msg(i: int) -> JointState:
    msg = JointState(name=["unit_1", "unit_2", "unit_3"], position=[1e-3 * i, 2e-3 * i, 3e-3 * i],
                     velocity=[0.0, 1.0, 2.0], effort=[0.05 * i, 0.06 * i, 0.07 * i])
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + i, 250_000_000
    msg.header.frame_id = "array"
    return msg


def diag_msg(i: int) -> DiagnosticArray:
    status = DiagnosticStatus(level=DiagnosticStatus.WARN, name="dea_array_twin", message=f"step {i}",
                              hardware_id="sim", values=[KeyValue(key="newton_iterations", value=str(3 + i))])
    msg = DiagnosticArray(status=[status])
    msg.header.stamp.sec = 1000 + i
    msg.header.frame_id = "twin"
    return msg


TOPICS = [("/array/force", FORCE, force_msg), ("/array/unit_states", STATES, states_msg),
          ("/diagnostics", DIAG, diag_msg)]


def expected_values(topic: str, i: int) -> dict:
    """The field values both readers must decode for message ``i`` of ``topic``."""
    if topic == "/array/force":
        return {"data": [0.1 * i, 0.2 * i, 0.3 * i], "dim": ("unit", 3, 3)}
    if topic == "/array/unit_states":
        return {"name": ["unit_1", "unit_2", "unit_3"], "position": [1e-3 * i, 2e-3 * i, 3e-3 * i],
                "effort": [0.05 * i, 0.06 * i, 0.07 * i], "stamp": (1000 + i, 250_000_000), "frame_id": "array"}
    return {"level": 1, "message": f"step {i}", "kv": ("newton_iterations", str(3 + i)), "stamp": 1000 + i}


def decoded_values(topic: str, msg) -> dict:
    """Same shape as :func:`expected_values`, from an rclpy-like (mcap_ros2) or rosbags message."""
    if topic == "/array/force":
        d = msg.layout.dim[0]
        return {"data": list(msg.data), "dim": (d.label, d.size, d.stride)}
    if topic == "/array/unit_states":
        return {"name": list(msg.name), "position": list(msg.position), "effort": list(msg.effort),
                "stamp": (msg.header.stamp.sec, msg.header.stamp.nanosec), "frame_id": msg.header.frame_id}
    s = msg.status[0]
    level = s.level if isinstance(s.level, int) else s.level[0]  # byte: int or bytes depending on reader
    return {"level": level, "message": s.message, "kv": (s.values[0].key, s.values[0].value),
            "stamp": msg.header.stamp.sec}


def assert_values(topic, msg, i):
    got, want = decoded_values(topic, msg), expected_values(topic, i)
    for key, value in want.items():
        if isinstance(value, list) and value and isinstance(value[0], float):
            assert got[key] == pytest.approx(value, abs=0), (topic, i, key)
        else:
            assert got[key] == value, (topic, i, key)


def record(path, n_per_topic=4, t0=1_700_000_000_000_000_000, **kwargs) -> list[tuple[str, int, int]]:
    """Write ``n_per_topic`` messages on each of the 3 topics; returns (topic, index, log_time) written."""
    written = []
    with Ros2McapWriter(path, metadata=CONFIG, **kwargs) as rec:
        ids = {topic: rec.add_topic(topic, type_name, default_qos_yaml(reliable=topic != "/diagnostics"))
               for topic, type_name, _ in TOPICS}
        for i in range(n_per_topic):
            for k, (topic, _, make) in enumerate(TOPICS):
                log_time = t0 + i * 100_000_000 + k
                rec.write(ids[topic], serialize_message(make(i)), log_time, publish_time_ns=log_time - 1000)
                written.append((topic, i, log_time))
    return written


def read_with_mcap_ros2(path) -> list[tuple[str, int, object]]:
    return [(m.channel.topic, m.log_time_ns, m.ros_msg) for m in read_ros2_messages(str(path))]


def read_with_rosbags(path) -> list[tuple[str, int, object]]:
    """Decode with rosbags' Jazzy typestore (the reader an independent user would use)."""
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


def index_of(topic, msg) -> int:
    """Recover the message index ``i`` from a decoded message (each factory encodes it)."""
    if topic == "/array/force":
        return round(msg.data[0] / 0.1)
    return int(msg.header.stamp.sec) - 1000


def installed_hash(type_name: str) -> str:
    """The RIHS01 hash the message wheel installs in share/<pkg>/msg/<Type>.json."""
    pkg, _, name = type_name.split("/")
    data = json.loads((Path(sys.prefix) / "share" / pkg / "msg" / f"{name}.json").read_text())
    return next(h["hash_string"] for h in data["type_hashes"] if h["type_name"] == type_name)


# ------------------------------------------------------------------------- tests

def test_three_topics_read_back_identically_by_mcap_ros2_and_rosbags(tmp_path):
    path = tmp_path / "run.mcap"
    written = record(path)

    for reader in (read_with_mcap_ros2, read_with_rosbags):
        got = reader(path)
        assert [(topic, t) for topic, t, _ in got] == [(topic, t) for topic, _, t in written], reader.__name__
        for (topic, i, _), (_, _, msg) in zip(written, got):
            assert_values(topic, msg, i)

    with open(path, "rb") as f:
        mcap = make_reader(f)
        header, summary = mcap.get_header(), mcap.get_summary()
        assert header.profile == "ros2" and header.library.startswith("dea_array_twin/")
        metadata = {m.name: m.metadata for m in mcap.iter_metadata()}
    assert metadata == CONFIG
    assert summary.statistics.message_count == len(written)
    schemas = {s.name: s for s in summary.schemas.values()}
    assert sorted(schemas) == sorted(type_name for _, type_name, _ in TOPICS)  # one schema per type
    for channel in summary.channels.values():
        assert channel.message_encoding == "cdr"
        assert schemas[summary.schemas[channel.schema_id].name].encoding == "ros2msg"
        assert channel.metadata["offered_qos_profiles"] == default_qos_yaml(reliable=channel.topic != "/diagnostics")
        assert channel.metadata["topic_type_hash"] == installed_hash(summary.schemas[channel.schema_id].name)
    # JointState's schema carries its nested types, each once, after 80 '=' and a MSG: line
    js_schema = schemas[STATES].data.decode()
    assert js_schema.startswith((Path(sys.prefix) / "share/sensor_msgs/msg/JointState.msg").read_text())
    for nested in ("std_msgs/Header", "builtin_interfaces/Time"):
        assert js_schema.count(f"\n{'=' * 80}\nMSG: {nested}\n") == 1
    # the schemas alone (no built-in type store) are enough for rosbags to build every type
    store = get_typestore(Stores.EMPTY)
    for name, schema in schemas.items():
        store.register(get_types_from_msg(schema.data.decode(), name))
    assert store.deserialize_cdr(serialize_message(states_msg(7)), STATES).header.frame_id == "array"

    # rosbags' rosbag2 reader takes the single .mcap as a bag: QoS parsed, hash and count seen
    with Rosbag2Reader(path) as bag:
        assert bag.message_count == len(written)
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in bag.connections}
    assert qos["/array/force"].reliability.name == "RELIABLE" and qos["/diagnostics"].reliability.name == "BEST_EFFORT"
    assert qos["/array/force"].history.name == "KEEP_LAST" and qos["/array/force"].depth == 10
    assert qos["/array/force"].durability.name == "VOLATILE"


def test_topic_type_hash_is_the_installed_rihs01_hash():
    own = installed_hash(STATES)
    assert own.startswith("RIHS01_") and len(own) == 7 + 64
    assert msg_definitions.type_hash(STATES) == own == msg_definitions.type_hash("sensor_msgs/JointState")
    assert msg_definitions.type_hash("std_msgs/msg/Header") == installed_hash("std_msgs/msg/Header")


CHILD = r"""
import sys, time
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from sensor_msgs.msg import JointState
from dea_array_twin.bag.writer import Ros2McapWriter

rec = Ros2McapWriter(sys.argv[1], metadata={"dea_array_twin_config": {"units": "3"}}, flush_period=0.5)
force = rec.add_topic("/array/force", "std_msgs/msg/Float64MultiArray")
states = rec.add_topic("/array/unit_states", "sensor_msgs/msg/JointState")
print("ready", flush=True)
n = 0
while True:
    msg = Float64MultiArray(data=[float(n)] * 3)
    msg.layout.dim = [MultiArrayDimension(label="unit", size=3, stride=3)]
    now = time.time_ns()
    rec.write(force, serialize_message(msg), now)
    js = JointState(name=["unit_1"], position=[float(n)], velocity=[0.0], effort=[1.0])
    js.header.frame_id = "array"
    rec.write(states, serialize_message(js), now + 1)
    n += 1
    print(n, now, flush=True)
    time.sleep(0.005)
"""


def test_killed_recorder_loses_at_most_the_last_flush_period(tmp_path):
    path, fixed = tmp_path / "killed.mcap", tmp_path / "recovered.mcap"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert child.stdout.readline().strip() == "ready"
        lines = [child.stdout.readline()]
        while int(lines[-1].split()[0]) < 300:  # about 2 s of writing, however slowly the machine runs it
            lines.append(child.stdout.readline())
        child.send_signal(signal.SIGKILL)
        lines += child.communicate(timeout=10)[0].splitlines()
    finally:
        if child.poll() is None:
            child.kill()
    # the last round the child completed (a round may be half written at the kill), its log time
    written, last_written_ns = (int(v) for v in lines[-1].split())
    assert written >= 300

    assert path.stat().st_size > 0 and not path.read_bytes().endswith(MAGIC)  # no footer: killed
    count = recover(path, fixed)

    for reader in (read_with_mcap_ros2, read_with_rosbags):
        got = reader(fixed)
        assert len(got) == count, reader.__name__
        rounds = [int(msg.data[0]) for topic, _, msg in got if topic == "/array/force"]
        assert rounds == list(range(len(rounds))), "recovered rounds are a gap-free prefix"
        last_log_time = max(t for _, t, _ in got)
        # Everything written up to the last periodic flush survived: at most the last
        # flush period (0.5 s) is lost, plus 0.3 s for the flush itself to run late.
        # Measured on the child's own clock, so a pause of the child before the kill
        # (a loaded machine) loses nothing and costs nothing here.
        assert last_written_ns - last_log_time < 0.5e9 + 0.3e9, reader.__name__
        assert 0.5 * written < len(rounds) <= written + 1
    with open(fixed, "rb") as f:
        assert {m.name for m in make_reader(f).iter_metadata()} == {"dea_array_twin_config"}


def test_size_split_files_are_each_complete_bags(tmp_path):
    path = tmp_path / "split.mcap"
    written = record(path, n_per_topic=40, flush_period=0.0, split_size=20_000)
    files = sorted(tmp_path.glob("split*.mcap"), key=lambda p: (len(p.name), p.name))
    assert files[0] == path and files[1].name == "split_1.mcap" and len(files) >= 3

    seen = []
    for file in files:
        for reader in (read_with_mcap_ros2, read_with_rosbags):  # each file on its own
            got = reader(file)
            assert got, file.name
            for topic, _, msg in got:
                assert_values(topic, msg, index_of(topic, msg))
        seen += [(topic, t) for topic, t, _ in read_with_rosbags(file)]
        with open(file, "rb") as f:
            mcap = make_reader(f)
            assert {m.name: m.metadata for m in mcap.iter_metadata()} == CONFIG
            assert len(mcap.get_summary().channels) == 3
        assert 0.8 * 20_000 < file.stat().st_size < 1.1 * 20_000 or file == files[-1]
    assert seen == [(topic, t) for topic, _, t in written]  # nothing lost or repeated across files


def test_duration_split_starts_a_file_per_second_of_log_time(tmp_path):
    written = record(tmp_path / "timed.mcap", n_per_topic=25, split_duration=1.0)  # 10 rounds per second
    files = sorted(tmp_path.glob("timed*.mcap"), key=lambda p: (len(p.name), p.name))
    assert [len(read_with_mcap_ros2(f)) for f in files] == [30, 30, 15]
    assert sum(len(read_with_rosbags(f)) for f in files) == len(written)


def test_unwritable_directory_raises_recording_error_naming_the_path(tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("a file where the directory should be")
    target = blocker / "rec" / "run.mcap"
    with pytest.raises(RecordingError, match="not_a_dir") as info:
        Ros2McapWriter(target)
    assert isinstance(info.value, OSError) and str(target) in str(info.value)


def test_full_disk_at_start_raises_recording_error():
    with pytest.raises(RecordingError, match="No space left on device") as info:
        Ros2McapWriter("/dev/full", overwrite=True)
    assert info.value.filename == "/dev/full"


def test_an_existing_file_is_never_opened_for_writing(tmp_path):
    """Two recorders that pick the same name: the second is refused and the first file is intact."""
    path = tmp_path / "run.mcap"
    with Ros2McapWriter(path) as first:
        cid = first.add_topic("/force", "std_msgs/msg/Float64MultiArray")
        first.write(cid, serialize_message(Float64MultiArray(data=[1.0])), 1)
        with pytest.raises(RecordingError, match="exists") as info:
            Ros2McapWriter(path)
        assert info.value.errno == errno.EEXIST
    assert [list(m.ros_msg.data) for m in read_ros2_messages(str(path))] == [[1.0]]


class _FillingDisk:
    """A file that accepts ``capacity`` bytes, then fails like a full disk."""

    def __init__(self, path, mode="wb", capacity=4000):
        self._f, self.capacity = open(path, mode), capacity

    def write(self, data):
        if self._f.tell() + len(data) > self.capacity:
            raise OSError(28, "No space left on device")
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)


def test_disk_filling_up_mid_recording_stops_the_writer_cleanly(tmp_path, monkeypatch):
    monkeypatch.setattr(writer, "open", _FillingDisk, raising=False)
    path = tmp_path / "full.mcap"
    rec = Ros2McapWriter(path, flush_period=0.0)
    cid = rec.add_topic("/array/unit_states", STATES)
    with pytest.raises(RecordingError, match=f"{path}.*No space left on device"):
        for i in range(1000):
            rec.write(cid, serialize_message(states_msg(i)), 1_000 + i)
    with pytest.raises(RecordingError, match="earlier error"):
        rec.write(cid, serialize_message(states_msg(0)), 5_000)
    rec.close()  # only releases the file
    assert recover(path, tmp_path / "saved.mcap") > 0  # what reached the disk is still recoverable


@pytest.mark.parametrize("content, reason", [
    (b"", "ends before the first record"),
    (MAGIC[:5], "ends before the first record"),
    (b"rosbag2_bagfile_information:\n  version: 9\n", "does not start with the MCAP magic"),
    (MAGIC + bytes(range(256)) * 4, "not an MCAP file"),
])
def test_recover_rejects_input_that_is_not_mcap(tmp_path, content, reason):
    src = tmp_path / "bad.mcap"
    src.write_bytes(content)
    with pytest.raises(RecoveryError, match=reason) as info:
        recover(src, tmp_path / "out.mcap")
    assert str(src) in str(info.value)
    assert not (tmp_path / "out.mcap").exists()


def test_recover_of_a_truncated_file_keeps_the_complete_chunks(tmp_path):
    path = tmp_path / "full.mcap"
    written = record(path, n_per_topic=30, flush_period=0.0)  # one chunk per message
    data = path.read_bytes()
    summary_start = struct.unpack_from("<Q", data, len(data) - len(MAGIC) - 20)[0]  # from the Footer record
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: summary_start * 2 // 3 + 5])  # cut through the data section, mid-record
    count = recover(cut, tmp_path / "fixed.mcap")
    assert 0 < count < len(written)
    got = read_with_rosbags(tmp_path / "fixed.mcap")
    assert [(topic, t) for topic, t, _ in got] == [(topic, t) for topic, _, t in written[:count]]
    assert recover(path, tmp_path / "copy.mcap") == len(written)  # a complete file copies whole
