"""The runtime's checkpoints (runtime/checkpoints.py): cadence in data time, restore, damage, a full disk."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lrfslam.services import stage

from lrfslam.errors import ConfigError, InputError
from lrfslam.msgs import counters
from lrfslam.runtime import checkpoints
from lrfslam.runtime.checkpoints import Checkpointer, Resumable

SECOND = 1_000_000_000


class Counting:
    """A step whose state is the number of inputs it has seen."""

    def __init__(self) -> None:
        self.counts: Counter = Counter()
        self.seen = 0

    def on_input(self) -> None:
        self.seen += 1

    def snapshot(self):
        return {"seen": np.array(self.seen)} if self.seen else None

    def restore(self, arrays) -> str:
        if "seen" not in arrays:
            raise InputError("no count")
        self.seen = int(arrays["seen"])
        return f"{self.seen} inputs"


def test_a_step_with_snapshot_and_restore_is_resumable():
    assert isinstance(Counting(), Resumable) and not isinstance(object(), Resumable)


@settings(max_examples=50, deadline=None)
@given(gaps_s=st.lists(st.floats(0.0, 3.0), min_size=1, max_size=60), period_s=st.floats(0.5, 5.0))
def test_saves_come_once_a_period_of_data_time_has_passed(tmp_path_factory, gaps_s, period_s):
    step = Counting()
    ck = Checkpointer(step, tmp_path_factory.mktemp("ck") / "s.checkpoint.npz", period_s)
    stamps = np.cumsum([0, *(round(g * SECOND) for g in gaps_s)])
    period_ns = int(period_s * 1e9)
    last = stamps[0]
    for i, stamp in enumerate(stamps):
        step.on_input()
        before = step.counts[counters.CHECKPOINT_SAVED]
        ck.after(int(stamp))
        saved = step.counts[counters.CHECKPOINT_SAVED] > before
        # Saved exactly when a period has passed since the last save (or the first input).
        assert saved == (i > 0 and stamp - last >= period_ns)
        if saved:
            last = stamp


def test_data_time_going_back_starts_the_period_afresh(tmp_path):
    step = Counting()
    ck = Checkpointer(step, tmp_path / "s.checkpoint.npz", 5.0)
    for stamp_s in (100, 104, 50, 54, 55):   # a second run (or a replayed loop) from 50 s
        step.on_input()
        ck.after(stamp_s * SECOND)
    assert step.counts[counters.CHECKPOINT_SAVED] == 1   # at 55 s, five seconds into the second run


def test_a_restarted_step_resumes_from_the_file(tmp_path):
    path = checkpoints.path_for(tmp_path, "counting")
    first = Counting()
    for _ in range(7):
        first.on_input()
    assert Checkpointer(first, path, 5.0).save()
    second = Counting()
    Checkpointer(second, path, 5.0).restore()
    assert second.seen == 7 and second.counts == Counter({counters.CHECKPOINT_RESTORED: 1})


def test_nothing_to_save_leaves_the_file_as_it_was(tmp_path):
    path = tmp_path / "s.checkpoint.npz"
    path.write_bytes(b"not a checkpoint")
    step = Counting()
    ck = Checkpointer(step, path, 5.0)
    ck.restore()
    assert step.counts[counters.CHECKPOINT_UNREADABLE] == 1 and step.seen == 0
    assert not ck.save() and path.read_bytes() == b"not a checkpoint"


@pytest.mark.parametrize("content", [b"not a checkpoint", None])
def test_a_damaged_or_foreign_checkpoint_is_counted_and_the_step_starts_afresh(tmp_path, content):
    path = tmp_path / "s.checkpoint.npz"
    if content is None:
        np.savez(path, other=np.zeros(2))   # a readable file of something else
        path = tmp_path / "s.checkpoint.npz"
    else:
        path.write_bytes(content)
    step = Counting()
    Checkpointer(step, path, 5.0).restore()
    assert step.counts[counters.CHECKPOINT_UNREADABLE] == 1 and step.counts[counters.CHECKPOINT_RESTORED] == 0 and step.seen == 0


def test_a_write_that_fails_is_counted_and_the_stage_goes_on(tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the folder should be")
    step = Counting()
    ck = Checkpointer(step, blocker / "s.checkpoint.npz", 1.0)
    for stamp_s in range(5):
        step.on_input()
        ck.after(stamp_s * SECOND)   # raises nothing
    # Tried once a period (at 1, 2, 3, 4 s), not on every input after the first failure.
    assert step.counts[counters.CHECKPOINT_FAILED] == 4 and step.counts[counters.CHECKPOINT_SAVED] == 0


@pytest.mark.parametrize("service, old", [("slam", "checkpoint_path"), ("slam", "checkpoint_every_scans"),
                                          ("mapper", "checkpoint_path"), ("mapper", "checkpoint_every_keyframes")])
def test_the_stages_own_checkpoint_settings_name_their_replacement(service, old):
    with pytest.raises(ConfigError, match="bus.checkpoint_"):
        stage(service, sets=[f"{old}=1"])
