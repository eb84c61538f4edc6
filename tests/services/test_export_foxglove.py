"""``lrfslam export RECORDING --foxglove OUT.mcap``: a recording made without views copied with Foxglove's views added.

An older layout of the times is exported in tests/unit/test_time_layouts.py.
"""

from __future__ import annotations

from collections import Counter

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from test_steps import sim_outputs

from lrfslam import cli
from lrfslam.msgs import topics
from lrfslam.runtime.recording import RecordingWriter, read_metadata, read_recording
from lrfslam.viz import foxglove as fx


def recording_without_views(path, n=30):
    with RecordingWriter(path, {"lrfslam": {"robot": "r1"}}, receive_times=True) as w:
        for o in sim_outputs(n):
            w.write(o.topic.name, o.topic.schema, o.topic.codec.encode(o.value), o.value.stamp_ns,
                    o.value.stamp_ns + 5, o.value.seq)
        w.write("scan", topics.SCAN.schema, b"\xff\xfe garbage", 1)


def test_the_copy_holds_every_message_and_the_views(tmp_path, capsys):
    src, out = tmp_path / "old.mcap", tmp_path / "fox.mcap"
    recording_without_views(src)
    assert cli.main(["export", str(src), "--foxglove", str(out)]) == 0
    text = capsys.readouterr()
    assert "91 messages copied" in text.out and "1 undecodable" in text.err

    before = [(m.topic, m.schema, m.data, m.log_time_ns, m.publish_time_ns, m.sequence) for m in read_recording(src)]
    after = list(read_recording(out))
    assert [(m.topic, m.schema, m.data, m.log_time_ns, m.publish_time_ns, m.sequence) for m in after
            if not topics.is_foxglove(m.topic)] == before
    assert read_metadata(out)["lrfslam"] == {"robot": "r1"}
    views = Counter(m.topic for m in after if topics.is_foxglove(m.topic))
    # scan, odom, truth of 30 steps (3 s): a scan view and a transform each, paths at 0, 1 and 2 s
    assert (views[fx.SCAN], views[fx.TF], views[fx.TRAJECTORY_TRUTH], views[fx.TRAJECTORY_ODOM]) == (30, 30, 3, 3)
    # each view at its source's log time (its receive time), the schema embedded and decodable by the mcap library
    scan_times = [m.log_time_ns for m in after if m.topic == "scan" and m.data != b"\xff\xfe garbage"]
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [(c.topic, s.name, s.encoding, c.message_encoding, m.log_time, d)
                   for s, c, m, d in reader.iter_decoded_messages(topics=[fx.SCAN])]
    assert [d[4] for d in decoded] == scan_times
    assert {d[1:4] for d in decoded} == {("foxglove.LaserScan", "protobuf", "protobuf")}


def test_views_in_the_input_are_made_anew_and_the_input_is_never_the_output(tmp_path, capsys):
    src, once, twice = tmp_path / "old.mcap", tmp_path / "a.mcap", tmp_path / "b.mcap"
    recording_without_views(src, 10)
    assert cli.main(["export", str(src), "--foxglove", str(once)]) == 0
    assert cli.main(["export", str(once), "--foxglove", str(twice)]) == 0
    assert "views of the input made anew" in capsys.readouterr().err
    a, b = list(read_recording(once)), list(read_recording(twice))
    assert [(m.topic, m.data, m.log_time_ns) for m in a] == [(m.topic, m.data, m.log_time_ns) for m in b]

    size = once.stat().st_size
    assert cli.main(["export", str(once), "--foxglove", str(once)]) == 2
    assert "is the input" in capsys.readouterr().err and once.stat().st_size == size
    assert cli.main(["export", str(tmp_path / "missing.mcap"), "--foxglove", str(tmp_path / "c.mcap")]) == 2
    assert not (tmp_path / "c.mcap").exists()


def test_a_replay_drops_the_views_of_its_input(tmp_path):
    src, fox, replayed = tmp_path / "old.mcap", tmp_path / "fox.mcap", tmp_path / "p.mcap"
    recording_without_views(src, 20)
    assert cli.main(["export", str(src), "--foxglove", str(fox)]) == 0
    assert cli.main(["pipeline", "--replay", str(fox), "--out", str(replayed), "--stages", "denoise", "-q"]) == 0
    got = Counter(m.topic for m in read_recording(replayed))
    assert not any(topics.is_foxglove(tp) for tp in got) and got["scan/filtered"] == 20
