"""Offline outputs are complete or absent (lrfslam.runtime.outputs), and bad inputs are one line and exit 2."""

from __future__ import annotations

import signal

import pytest

from lrfslam import cli
from lrfslam.runtime.outputs import Interrupted, atomic_output


def test_a_finished_output_replaces_the_old_one(tmp_path):
    out = tmp_path / "sub" / "out.mcap"
    with atomic_output(out) as partial:
        assert partial.parent == out.parent and partial.suffix == ".mcap" and partial.name.startswith(".")
        partial.write_bytes(b"new")
        assert not out.exists()
    assert out.read_bytes() == b"new" and sorted(p.name for p in out.parent.iterdir()) == ["out.mcap"]


@pytest.mark.parametrize("exc", [RuntimeError("boom"), KeyboardInterrupt(), Interrupted(signal.SIGTERM)])
def test_an_unfinished_output_leaves_nothing_and_the_old_file_alone(tmp_path, exc):
    out = tmp_path / "out.json"
    out.write_text("old")
    with pytest.raises(type(exc)), atomic_output(out) as partial:
        partial.write_text("half")
        raise exc
    assert out.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


@pytest.fixture
def signals_restored():
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    yield
    for s, handler in saved.items():
        signal.signal(s, handler)


@pytest.fixture
def bad_inputs(tmp_path):
    (tmp_path / "junk.mcap").write_bytes(bytes(range(256)) * 20)
    (tmp_path / "empty.mcap").write_bytes(b"")
    (tmp_path / "folder.mcap").mkdir()
    return tmp_path


@pytest.mark.parametrize("name", ["missing.mcap", "junk.mcap", "empty.mcap", "folder.mcap"])
@pytest.mark.parametrize("command", [
    ["slam", "--log-level", "ERROR", "--replay", "{in}", "--out", "{out}/o.mcap"],
    ["pipeline", "-q", "--log-level", "ERROR", "--replay", "{in}", "--out", "{out}/o.mcap"],
    ["export", "{in}", "-o", "{out}"],
    ["info", "{in}"],
], ids=lambda c: c[0])
def test_a_missing_or_foreign_input_exits_2_and_writes_nothing(bad_inputs, signals_restored, capsys, name, command):
    out = bad_inputs / "out"
    argv = [a.format(**{"in": bad_inputs / name, "out": out}) for a in command]
    assert cli.main(argv) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert "Traceback" not in err


def test_an_import_of_junk_exits_2_writes_nothing_and_echoes_little(tmp_path, signals_restored, capsys):
    junk = tmp_path / "junk.clf"
    # A megabyte of binary on few lines: the first tokens are long and unprintable.
    junk.write_bytes(bytes(range(11, 256)) * 4000 + b"\n" + bytes(range(14, 256)) * 4000)
    assert cli.main(["import", "carmen", str(junk), "-o", str(tmp_path / "out.mcap"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("lrfslam import: error:") and len(err) < 400, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.clf"]
