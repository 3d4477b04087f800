"""The hand-written MCAP writer behind BagWriter: batches read back by three readers, CRCs, sync, metadata;
a full disk under it names the bag."""
import json
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import main_result, one_error_line

from has_control.wire import cdr
from has_control.bag import (CLOCK, FLOAT64_ARRAY, JOINT_STATE, BagError, BagWriter, QosSpec, read_bag,
                             typestore)
from has_control.bag.mcap_format import MAGIC

N = 4000                                    # samples: ~2.1 MiB of records, three chunks
STEP = 300_000                              # [ns]


def _matrix(msgs: list[bytes]) -> np.ndarray:
    return np.frombuffer(b"".join(msgs), np.uint8).reshape(len(msgs), -1)


def _clocks(stamps_ns: np.ndarray) -> np.ndarray:
    """rosgraph_msgs/Clock CDR messages as an (n, 12) matrix."""
    raw = np.zeros((len(stamps_ns), 12), np.uint8)
    raw[:, 1] = 1                                                   # little-endian CDR
    raw[:, 4:8] = (stamps_ns // 10**9).astype("<i4").view(np.uint8).reshape(-1, 4)
    raw[:, 8:12] = (stamps_ns % 10**9).astype("<u4").view(np.uint8).reshape(-1, 4)
    return raw


def _batches(n: int = N, start: int = 0) -> dict:
    """A run's five topics, one message each per sample (ties in log time across
    topics), and a String topic of varying sizes every 7th sample."""
    rng = np.random.default_rng(start)
    stamps = (start + np.arange(n, dtype=np.int64)) * STEP
    every7 = stamps[::7]
    return {
        "/state": (stamps, _matrix(cdr.encode_joint_states(stamps, ["actuator", "chamber_1", "chamber_2"],
                                                           *rng.normal(size=(3, n, 3))))),
        "/command": (stamps, _matrix(cdr.encode_joint_states(stamps, ["valve"], rng.normal(size=(n, 1))))),
        "/clock": (stamps, _clocks(stamps)),
        "/reference": (stamps, cdr.encode_float64_arrays(rng.normal(size=(n, 5)))),       # list of bytes
        "/controller_state": (stamps, _matrix(cdr.encode_float64_arrays(rng.normal(size=(n, 7))))),
        "/log": (every7, [_string("x" * int(k % 13)) for k in every7 // STEP]),
    }


TYPES = {"/state": JOINT_STATE, "/command": JOINT_STATE, "/clock": CLOCK, "/reference": FLOAT64_ARRAY,
         "/controller_state": FLOAT64_ARRAY, "/log": "std_msgs/msg/String"}


def _string(text: str) -> bytes:
    ts = typestore()
    return bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))


def _rows(batch) -> list[tuple[int, bytes]]:
    times, data = batch
    return [(int(t), bytes(d)) for t, d in zip(times, data)]


def _open(path, custom=None, compression="zstd") -> BagWriter:
    w = BagWriter(path, custom, compression=compression)
    for topic, ty in TYPES.items():
        w.add_topic(topic, ty, QosSpec(transient_local=topic == "/log"))
    return w


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A bag written with one write_batches call, and what went in."""
    path = tmp_path_factory.mktemp("mcap") / "batches"
    batches = _batches()
    with _open(path, {"has_control/parameters": json.dumps({"a": 1})}) as w:
        w.write_batches(batches)
    return path, batches


def test_write_batches_reads_back_identically_with_our_reader(written):
    path, batches = written
    bag = read_bag(path)
    assert bag.complete and bag.types == TYPES
    for topic, batch in batches.items():
        assert bag.messages[topic] == _rows(batch), topic
    assert bag.custom_data == {"has_control/parameters": '{"a": 1}'}
    bare = read_bag(path / "batches.mcap")                          # custom_data from the rosbag2 metadata record
    assert bare.custom_data == bag.custom_data and bare.messages == bag.messages


def test_rosbags_anyreader_deserialises_the_bag(written):
    from rosbags.highlevel import AnyReader
    path, batches = written
    counts, positions = {}, []
    with AnyReader([path], default_typestore=typestore()) as reader:
        for conn, t, raw in reader.messages():
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic == "/state":
                positions.append(reader.deserialize(raw, conn.msgtype).position)
    assert counts == {t: len(b[0]) for t, b in batches.items()}
    _, expected, _, _ = cdr.joint_states([bytes(r) for r in batches["/state"][1]])
    np.testing.assert_array_equal(positions, expected)


def test_mcap_reader_validates_crcs_and_decodes(written):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path, batches = written
    got = {}
    with open(path / "batches.mcap", "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        for _, channel, message, ros in reader.iter_decoded_messages(log_time_order=False):
            got.setdefault(channel.topic, []).append((message.log_time, message.data))
            if channel.topic == "/controller_state" and len(got[channel.topic]) == 5:
                assert list(ros.data) == cdr.float64_arrays([bytes(batches[channel.topic][1][4])])[0].tolist()
        summary = reader.get_summary()
    assert got == {t: _rows(b) for t, b in batches.items()}
    assert len(summary.chunk_indexes) > 1 and {c.compression for c in summary.chunk_indexes} == {"zstd"}
    assert summary.statistics.message_count == sum(len(b[0]) for b in batches.values())


def test_messages_are_merged_in_log_time_order_ties_in_topic_order(written):
    from mcap.stream_reader import StreamReader
    from mcap.records import Channel, Message
    path, _ = written
    order = {t: k for k, t in enumerate(TYPES)}
    topics, keys = {}, []
    with open(path / "batches.mcap", "rb") as f:
        for r in StreamReader(f, validate_crcs=True).records:                # file order; checks the data CRC
            if isinstance(r, Channel):
                topics[r.id] = r.topic
            elif isinstance(r, Message):
                keys.append((r.log_time, order[topics[r.channel_id]]))
    assert keys == sorted(keys)


def test_write_and_write_batches_mix(tmp_path):
    path = tmp_path / "mixed"
    first, second = _batches(50), _batches(3000, start=50)
    with _open(path) as w:
        for topic, (times, data) in first.items():
            for t, d in zip(times, data):
                w.write(topic, int(t), bytes(d))
        w.write_batches(second)
        w.write("/log", 10**12, _string("last"))
        assert w.counts["/log"] == len(first["/log"][0]) + len(second["/log"][0]) + 1
    bag = read_bag(path)
    for topic in TYPES:
        assert bag.messages[topic] == _rows(first[topic]) + _rows(second[topic]) + (
            [(10**12, _string("last"))] if topic == "/log" else []), topic


def test_sync_then_a_truncated_file_keeps_everything_synced(tmp_path):
    path = tmp_path / "synced"
    first, second = _batches(2000), _batches(2000, start=2000)
    w = _open(path)
    w.write_batches(first)
    w.sync()
    size = (path / "synced.mcap").stat().st_size
    w.write_batches(second)
    w.close()
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "cut.mcap").write_bytes((path / "synced.mcap").read_bytes()[:size])     # as after a SIGKILL
    warnings = []
    bag = read_bag(cut, on_warning=warnings.append)
    assert not bag.complete and bag.lost_bytes == 0
    for topic, batch in first.items():
        assert bag.messages[topic] == _rows(batch), topic


def _chunks(data: bytes):
    """(data offset, compression, compressed data, uncompressed size, crc) of each chunk, by the summary."""
    from io import BytesIO
    from mcap.reader import make_reader
    out = []
    for ci in make_reader(BytesIO(data)).get_summary().chunk_indexes:
        p = ci.chunk_start_offset + 9
        _, _, size, crc, n = struct.unpack_from("<QQQII", data, p)
        compression = data[p + 32:p + 32 + n].decode()
        length = struct.unpack_from("<Q", data, p + 32 + n)[0]
        out.append((p + 40 + n, compression, data[p + 40 + n:p + 40 + n + length], size, crc))
    return out


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_crcs_are_written_and_a_flipped_bit_is_caught(tmp_path, compression):
    import zstandard
    from mcap.reader import make_reader
    from mcap.stream_reader import CRCValidationError
    with _open(tmp_path / "bag", compression=compression) as w:
        w.write_batches(_batches())
    data = (tmp_path / "bag" / "bag.mcap").read_bytes()
    chunks = _chunks(data)
    assert len(chunks) > 1
    for _, kind, payload, size, crc in chunks:
        raw = zstandard.ZstdDecompressor().decompress(payload, max_output_size=size) if kind else payload
        assert kind == ("" if compression == "none" else "zstd") and len(raw) == size
        assert crc != 0 and crc == zlib.crc32(raw)
    footer = len(data) - len(MAGIC) - 29                  # opcode, length, summary start and offset, crc
    summary_start, offsets_start, summary_crc = struct.unpack_from("<QQI", data, footer + 9)
    assert summary_crc == zlib.crc32(data[footer:footer + 25], zlib.crc32(data[summary_start:footer]))
    assert summary_start < offsets_start < footer
    data_end = summary_start - 13                         # DataEnd: opcode, length, crc of all before it
    assert data[data_end] == 0x0F and struct.unpack_from("<I", data, data_end + 9)[0] == zlib.crc32(data[:data_end])

    start = chunks[1][0]
    bad = bytearray(data)
    bad[start + len(chunks[1][2]) // 2] ^= 0x10
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(bad))
    with open(path, "rb") as f, pytest.raises(CRCValidationError):    # zstd decompresses the flip to other bytes
        for _ in make_reader(f, validate_crcs=True).iter_messages():
            pass


# --- rosbag2 metadata ----------------------------------------------------------

def _shape(doc):
    """The structure of a YAML document: mappings by key, lists by their first item, scalars by type."""
    if isinstance(doc, dict):
        return {k: _shape(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_shape(doc[0])] if doc else []
    return type(doc).__name__


QOS = {"avoid_ros_namespace_conventions": "bool", "deadline": {"nsec": "int", "sec": "int"}, "depth": "int",
       "durability": "str", "history": "str", "lifespan": {"nsec": "int", "sec": "int"}, "liveliness": "str",
       "liveliness_lease_duration": {"nsec": "int", "sec": "int"}, "reliability": "str"}

#: The shape of the metadata.yaml the rosbags-based BagWriter wrote (rosbags 0.11.9, at 7e79e4b).
ROSBAGS_METADATA = {"rosbag2_bagfile_information": {
    "compression_format": "str", "compression_mode": "str", "custom_data": {"has_control/parameters": "str"},
    "duration": {"nanoseconds": "int"},
    "files": [{"duration": {"nanoseconds": "int"}, "message_count": "int", "path": "str",
               "starting_time": {"nanoseconds_since_epoch": "int"}}],
    "message_count": "int", "relative_file_paths": ["str"], "ros_distro": "str",
    "starting_time": {"nanoseconds_since_epoch": "int"}, "storage_identifier": "str",
    "topics_with_message_count": [{"message_count": "int", "topic_metadata": {
        "name": "str", "offered_qos_profiles": [QOS], "serialization_format": "str", "type": "str",
        "type_description_hash": "str"}}],
    "version": "int"}}

#: The offered_qos_profiles channel metadata rosbags wrote for QosSpec().
ROSBAGS_QOS = ("- avoid_ros_namespace_conventions: false\n  deadline:\n    nsec: 4294967295\n    sec: 2147483647\n"
               "  depth: 1\n  durability: volatile\n  history: keep_last\n  lifespan:\n    nsec: 4294967295\n"
               "    sec: 2147483647\n  liveliness: automatic\n  liveliness_lease_duration:\n    nsec: 4294967295\n"
               "    sec: 2147483647\n  reliability: reliable")


def test_metadata_yaml_has_the_shape_rosbags_wrote(written):
    from mcap.reader import make_reader
    path, batches = written
    doc = yaml.safe_load((path / "metadata.yaml").read_text())
    assert _shape(doc) == ROSBAGS_METADATA
    info = doc["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["batches.mcap"] and info["compression_format"] == ""
    assert info["starting_time"]["nanoseconds_since_epoch"] == 0
    assert info["duration"]["nanoseconds"] == (N - 1) * STEP
    assert {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]} == {
        t: len(b[0]) for t, b in batches.items()}
    assert info["message_count"] == info["files"][0]["message_count"] == sum(len(b[0]) for b in batches.values())
    with open(path / "batches.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert yaml.safe_load(meta["rosbag2"]["serialized_metadata"]) == info


def test_channels_carry_qos_and_type_hash_schemas_the_rosbags_definitions(written):
    from mcap.reader import make_reader
    path, _ = written
    with open(path / "batches.mcap", "rb") as f:
        reader = make_reader(f)
        summary, header = reader.get_summary(), reader.get_header()
    assert header.profile == "ros2"
    ts = typestore()
    channels = {c.topic: c for c in summary.channels.values()}
    assert channels["/state"].metadata["offered_qos_profiles"] == ROSBAGS_QOS
    for topic, ty in TYPES.items():
        schema = summary.schemas[channels[topic].schema_id]
        assert (schema.name, schema.encoding) == (ty, "ros2msg")
        assert schema.data.decode() == ts.generate_msgdef(ty, ros_version=2)[0]
        # the REP-2011 hash rosidl generated for the installed interface package
        pkg, _, name = ty.split("/")
        hashes = json.loads((Path(sys.prefix) / "share" / pkg / "msg" / f"{name}.json").read_text())["type_hashes"]
        assert channels[topic].metadata["topic_type_hash"] == hashes[0]["hash_string"]
        assert hashes[0]["type_name"] == ty


def test_misuse_is_one_line_naming_the_bag(tmp_path):
    with BagWriter(tmp_path / "b") as w:
        with pytest.raises(BagError, match=r"b: no topic /nope"):
            w.write_batches({"/nope": (np.zeros(1, np.int64), [b"\x00\x01\x00\x00"])})
        w.add_topic("/clock", CLOCK)
        with pytest.raises(ValueError, match="expected uint8 of shape"):
            w.write_batches({"/clock": (np.zeros(2, np.int64), np.zeros((2, 12)))})
        assert w.counts == {"/clock": 0}
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "b")
    with pytest.raises(BagError, match="not a string"):
        BagWriter(tmp_path / "c", {"k": 1})


def test_a_full_disk_under_the_bag_writer_names_the_bag(tmp_path, capsys, monkeypatch):
    import has_control.cli.bag_info as bag_info
    from has_control.bag import BagWriter, STRING

    def record_to_a_full_disk(args):
        w = BagWriter(tmp_path / "bag")
        w._mcap._file.close()
        w._mcap._file = open("/dev/full", "wb", buffering=0)
        w.add_topic("/x", STRING)
        w.write("/x", 1, b"\0" * 64)
        w.sync()
    monkeypatch.setattr(bag_info, "run", record_to_a_full_disk)
    rc, _, err = main_result(capsys, "bag-info", "x")
    one_error_line(rc, err, str(tmp_path / "bag" / "bag.mcap"), "No space left on device")
