"""MCAP recordings read back with the mcap library, with embedded schemas, even after a crash or a full disk."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lrfslam import cli
from lrfslam.errors import RecordingError
from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import (
    UNINDEXED,
    ReadReport,
    RecordingWriter,
    SegmentedWriter,
    read_metadata,
    read_recording,
    recover,
)
from lrfslam.tools import info


def _scan(i: int) -> t.LaserScan:
    return t.LaserScan.from_ranges(1_000 + i, i, np.full(181, 1.0 + i), -np.pi / 2, np.radians(1))


def test_round_trip_with_embedded_schema(tmp_path):
    path = tmp_path / "r.mcap"
    with RecordingWriter(path, metadata={"lrfslam": {"robot": "r1"}}) as w:
        for i in range(5):
            w.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(_scan(i)), 1_000 + i, sequence=i)
        w.write("odom", topics.ODOM.schema, codec.ODOMETRY.encode(t.Odometry(stamp_ns=999, seq=1, pose=(1, 2, 3))), 999)
    got = list(read_recording(path))
    assert [m.topic for m in got] == ["odom", "scan", "scan", "scan", "scan", "scan"]  # log-time order
    assert codec.LASER_SCAN.decode(got[-1].data).ranges_m[0] == 5.0
    assert read_metadata(path)["lrfslam"]["robot"] == "r1"
    # Any MCAP tool can decode it from the file alone: the protobuf descriptors are embedded.
    with open(path, "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert decoded[1][0].name == "lrfslam.msgs.v1.LaserScan"
    assert list(decoded[4][3].ranges_m)[:1] == [4.0]


def test_unknown_schema_is_kept_schemaless(tmp_path):
    path = tmp_path / "r.mcap"
    with RecordingWriter(path) as w:
        w.write("future", "lrfslam.msgs.v7.Thing", b"\x01\x02", 5)
    (m,) = read_recording(path)
    assert (m.topic, m.schema, m.data) == ("future", "lrfslam.msgs.v7.Thing", b"\x01\x02")


def test_killed_writer_loses_at_most_the_unflushed_tail(tmp_path):
    path = tmp_path / "r.mcap"
    w = RecordingWriter(path)
    for i in range(10):
        w.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(_scan(i)), 1_000 + i)
    w.flush()
    for i in range(10, 13):
        w.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(_scan(i)), 1_000 + i)
    crashed = tmp_path / "crashed.mcap"
    shutil.copy(path, crashed)  # the file as a SIGKILL would leave it: no footer, no summary
    w.close()
    report = ReadReport()
    got = list(read_recording(crashed, report=report))
    assert report.truncated
    assert [codec.LASER_SCAN.decode(m.data).seq for m in got] == list(range(10))


# ---- recording folders, recovery, write errors ------------------------------------------------


def _write_scans(writer, seqs, size: int = 181) -> None:
    for i in seqs:
        scan = t.LaserScan.from_ranges(1_000 + i, i, np.random.default_rng(i).uniform(0.5, 8.0, size),
                                       -np.pi / 2, np.radians(1))
        writer.write("scan", topics.SCAN.schema, codec.LASER_SCAN.encode(scan), 1_000 + i, sequence=i)


def _seqs(source, **kw) -> list[int]:
    return [m.sequence for m in read_recording(source, **kw)]


def test_a_second_writer_takes_the_next_segment_and_never_overwrites(tmp_path):
    folder = tmp_path / "run"
    first = SegmentedWriter(folder, "run")
    _write_scans(first, range(5))
    first.close()
    before = (folder / "run_0.mcap").read_bytes()
    (folder / "run_7.recovered.mcap").write_bytes(b"not a segment")   # ignored: not <name>_<n>.mcap
    (folder / "other_9.mcap").write_bytes(b"")                        # another stem: not counted either
    second = SegmentedWriter(folder, "run")
    _write_scans(second, range(5, 8))
    second.close()
    assert (folder / "run_0.mcap").read_bytes() == before
    assert second.segments == [folder / "run_1.mcap"]
    (folder / "other_9.mcap").unlink()
    assert _seqs(folder) == list(range(8))
    assert [s.path.name for s in _report(folder).segments] == ["run_0.mcap", "run_1.mcap"]


def _report(source) -> ReadReport:
    report = ReadReport()
    for _ in read_recording(source, report=report):
        pass
    return report


@settings(max_examples=12, deadline=None)
@given(n=st.integers(1, 120), max_kb=st.integers(1, 12), chunk_kb=st.integers(1, 8))
def test_a_split_folder_reads_as_the_single_file(tmp_path_factory, n, max_kb, chunk_kb):
    tmp = tmp_path_factory.mktemp("split")
    with RecordingWriter(tmp / "one.mcap", chunk_size_bytes=chunk_kb * 1024) as single:
        _write_scans(single, range(n))
    split = SegmentedWriter(tmp / "run", "run", chunk_size_bytes=chunk_kb * 1024, max_bytes=max_kb * 1024)
    _write_scans(split, range(n))
    split.close()
    assert list(read_recording(tmp / "run")) == list(read_recording(tmp / "one.mcap"))
    # Also given as several files, and each segment but the last reached the size limit.
    assert list(read_recording(split.segments)) == list(read_recording(tmp / "one.mcap"))
    assert all(p.stat().st_size >= max_kb * 1024 for p in split.segments[:-1])


def test_split_by_age_on_the_writers_clock(tmp_path):
    now = [0.0]
    w = SegmentedWriter(tmp_path / "run", "run", max_duration_s=10.0, clock=lambda: now[0])
    for i in range(30):
        now[0] = float(i)
        _write_scans(w, [i])
    w.close()
    assert [p.name for p in w.segments] == ["run_0.mcap", "run_1.mcap", "run_2.mcap"]
    assert [len(_seqs(p)) for p in w.segments] == [10, 10, 10]
    assert read_metadata(w.segments[2])["lrfslam"]["segment"] == "2"


def test_segments_are_merged_by_log_time(tmp_path):
    with RecordingWriter(tmp_path / "a_0.mcap") as a, RecordingWriter(tmp_path / "a_1.mcap") as b:
        _write_scans(a, [0, 2, 4])
        _write_scans(b, [1, 3])
    assert _seqs(tmp_path) == [0, 1, 2, 3, 4]


def test_bad_sources_are_one_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    for source, words in ((tmp_path / "missing.mcap", "does not exist"), (tmp_path / "empty", "no recording segments"),
                          ([], "no recording")):
        with pytest.raises(RecordingError, match=words):
            list(read_recording(source))


def _crashed_copy(tmp_path, flushed: int, after: int):
    """A file as SIGKILL leaves it: ``flushed`` scans in complete chunks, ``after`` more unflushed."""
    path = tmp_path / "w.mcap"
    w = RecordingWriter(path, metadata={"lrfslam": {"robot": "r1"}}, chunk_size_bytes=4096)
    _write_scans(w, range(flushed))
    w.flush()
    _write_scans(w, range(flushed, flushed + after))
    crashed = tmp_path / "crashed.mcap"
    shutil.copy(path, crashed)
    w.close()
    return crashed


@settings(max_examples=15, deadline=None)
@given(cut=st.floats(0.05, 1.0))
def test_recover_keeps_every_complete_chunk_and_writes_an_indexed_file(tmp_path_factory, cut):
    tmp = tmp_path_factory.mktemp("rec")
    crashed = _crashed_copy(tmp, 40, 3)
    # Cut anywhere too: a write the kill interrupted leaves part of a chunk.
    data = crashed.read_bytes()
    crashed.write_bytes(data[:max(60, int(len(data) * cut))])
    report = ReadReport()
    tolerant = list(read_recording(crashed, report=report))
    assert report.truncated
    out = tmp / "out.mcap"
    rec = recover(crashed, out)
    with open(out, "rb") as f:  # the plain mcap library, default reader, indexed
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == rec.messages
        seqs = [m.sequence for _, _, m in reader.iter_messages()]
    assert seqs == list(range(len(seqs))) and len(seqs) == rec.messages
    assert list(read_recording(out)) == tolerant        # the same stream, from the damaged and the recovered file
    assert read_metadata(out)["lrfslam"]["robot"] == "r1"
    if cut == 1.0:
        assert rec.messages == 40 and not rec.complete


def test_recover_of_a_finished_file_loses_nothing_and_never_overwrites(tmp_path):
    src = tmp_path / "a.mcap"
    with RecordingWriter(src) as w:
        _write_scans(w, range(10))
    rec = recover(src, tmp_path / "b.mcap")
    assert rec.complete and rec.messages == 10 and rec.read_bytes == rec.total_bytes
    before = (tmp_path / "b.mcap").read_bytes()
    with pytest.raises(RecordingError, match="exists"):
        recover(src, tmp_path / "b.mcap")
    assert (tmp_path / "b.mcap").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]   # no temporary left
    (tmp_path / "junk").write_bytes(b"hello")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        recover(tmp_path / "junk", tmp_path / "c.mcap")
    assert not (tmp_path / "c.mcap").exists()


FULL_DISK = """
import resource, signal, sys
sys.path[:0] = {paths!r}
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)          # a write past the limit fails (EFBIG) like a full disk
resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
from test_recording import _write_scans
from lrfslam import cli
from lrfslam.errors import RecordingError
from lrfslam.runtime.recording import RecordingWriter
w = RecordingWriter({path!r}, chunk_size_bytes=2048)
try:
    for i in range({n}):
        _write_scans(w, [i])
    w.close()
except RecordingError as exc:
    print(exc)
    sys.exit(3)
"""


def write_on_a_small_disk(path: Path, limit: int, n: int) -> subprocess.CompletedProcess:
    script = FULL_DISK.format(paths=[str(Path(__file__).parent)], limit=limit, path=str(path), n=n)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})


@pytest.mark.parametrize("limit", [20_000, 20_000 + 7, 65_536])
def test_a_full_disk_leaves_a_valid_file_up_to_that_point(tmp_path, limit):
    path = tmp_path / "full.mcap"
    res = write_on_a_small_disk(path, limit, 1000)
    assert res.returncode == 3, res.stderr
    assert "cannot write" in res.stdout and "File too large" in res.stdout and "ended validly" in res.stdout
    assert path.stat().st_size <= limit
    with open(path, "rb") as f:   # valid for the default reader (footer, no index)
        seqs = [m.sequence for _, _, m in make_reader(f).iter_messages()]
    assert len(seqs) > 5 and seqs == list(range(len(seqs)))
    report = _report(path)
    assert not report.truncated and report.segments[0].state == UNINDEXED


def test_a_disk_full_while_writing_the_summary_keeps_every_message(tmp_path):
    with RecordingWriter(tmp_path / "probe.mcap", chunk_size_bytes=2048) as w:
        _write_scans(w, range(30))
        w.flush()
        data_end = w.bytes_written          # the same bytes again below: room for the data, not the index
    path = tmp_path / "full.mcap"
    res = write_on_a_small_disk(path, data_end + 100, 30)
    assert res.returncode == 3 and "cannot finish" in res.stdout, res.stdout + res.stderr
    with open(path, "rb") as f:
        assert [m.sequence for _, _, m in make_reader(f).iter_messages()] == list(range(30))
    assert _report(path).segments[0].state == UNINDEXED


def test_info_names_the_recover_command_and_it_works(tmp_path, capsys):
    folder = tmp_path / "run"
    folder.mkdir()
    shutil.move(_crashed_copy(tmp_path, 20, 3), folder / "run_0.mcap")
    with RecordingWriter(folder / "run_1.mcap") as w:
        _write_scans(w, range(100, 110))
    before = list(read_recording(folder))
    text = info.describe(folder)
    (line,) = [line for line in text.splitlines() if "NOT FINISHED" in line]
    assert "run_0.mcap" in line
    command = re.search(r"lrfslam (recover \S+ -o \S+)$", line)[1].split()
    assert cli.main(command) == 0
    assert "20 messages" in capsys.readouterr().out
    assert list(read_recording(folder)) == before          # the copy beside the segments is not one of them
    assert "WARNING" not in info.describe(Path(command[-1]))
    assert cli.main(command) == 2                          # never overwrites
    assert "exists" in capsys.readouterr().err
