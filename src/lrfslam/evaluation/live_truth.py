"""A live run's SLAM estimate against its ground truth, as the messages come (``lrfslam up``).

``lrfslam up`` hears the simulator's ``truth`` and the slam's ``slam/state`` on the bus and hands
each to a :class:`LiveTruth`: it matches every state to the truth of its stamp at once with the one
error measure (:class:`~lrfslam.evaluation.truth.RunningTruthError`), so memory stays bounded
however long the run goes; it keeps which scans were published (:class:`SeqRanges`, to tell a
recording's losses) and where the simulated run began (a restarted sensor continues from there).
"""

from __future__ import annotations

import numpy as np

from lrfslam.evaluation.truth import RunningTruthError
from lrfslam.msgs import codec


class SeqRanges:
    """A set of sequence numbers as sorted, disjoint ``[first, last]`` ranges: memory grows with gaps, not length."""

    def __init__(self) -> None:
        self.ranges: list[list[int]] = []

    def add(self, seq: int) -> None:
        if self.ranges and self.ranges[-1][0] <= seq <= self.ranges[-1][1] + 1:
            self.ranges[-1][1] = max(self.ranges[-1][1], seq)
        elif not self.ranges or seq > self.ranges[-1][1]:
            self.ranges.append([seq, seq])
        else:   # out of order: rare, so a linear merge is fine
            for r in self.ranges:
                if r[0] - 1 <= seq <= r[1] + 1:
                    r[0], r[1] = min(r[0], seq), max(r[1], seq)
                    break
            else:
                self.ranges.append([seq, seq])
                self.ranges.sort()
            merged = [self.ranges[0]]
            for r in self.ranges[1:]:
                if r[0] <= merged[-1][1] + 1:
                    merged[-1][1] = max(merged[-1][1], r[1])
                else:
                    merged.append(r)
            self.ranges = merged

    def __len__(self) -> int:
        return sum(b - a + 1 for a, b in self.ranges)

    def missing_from(self, present: set[int]) -> int:
        """How many of these numbers are not in ``present``."""
        return sum(1 for a, b in self.ranges for q in range(a, b + 1) if q not in present)


class LiveTruth:
    """Truth and SLAM states of a live run, matched as they come.

    Attributes
    ----------
    errors : RunningTruthError
    published : SeqRanges
        Sequence numbers of the truth heard: one per scan the sensor published.
    first_truth : tuple of int, or None
        (seq, stamp ns) of the first truth heard.
    last_truth_stamp, last_state_stamp : int
        Stamps (ns) of the newest truth and state.
    last_state : bytes or None
        The newest state as it came (decoded again when shown: one kept, not every one).
    """

    def __init__(self) -> None:
        self.errors = RunningTruthError()
        self.published = SeqRanges()
        self.first_truth: tuple[int, int] | None = None
        self.last_truth_stamp = 0
        self.last_state: bytes | None = None
        self.last_state_stamp = 0

    def add_truth(self, seq: int, stamp_ns: int, pose: np.ndarray) -> None:
        """The simulator's true pose (3,) of scan ``seq``, stamped ``stamp_ns``."""
        if self.first_truth is None:
            self.first_truth = (seq, stamp_ns)
        self.published.add(seq)
        self.last_truth_stamp = max(self.last_truth_stamp, stamp_ns)
        self.errors.add_truth(stamp_ns, pose)

    def add_state(self, data: bytes) -> None:
        """An encoded ``slam/state``.

        Raises
        ------
        DecodeError
            If ``data`` is no slam state.
        """
        state = codec.SLAM_STATE.decode(data)
        self.last_state, self.last_state_stamp = data, state.stamp_ns
        self.errors.add_estimate(state.stamp_ns, state.pose)

    def caught_up(self) -> bool:
        """The slam has answered the newest truth heard."""
        return self.last_state_stamp >= self.last_truth_stamp

    def epoch_ns(self, rate_hz: float) -> int | None:
        """Wall-clock time of the simulated run's first frame (a restarted sensor continues from it), if known."""
        if self.first_truth is None:
            return None
        seq, stamp = self.first_truth
        return stamp - round((seq - 1) / rate_hz * 1e9)   # the sensor stamps frame i at t0 + i / rate

    def pose_errors(self) -> dict[str, float] | None:
        """Final-pose and trajectory errors of SLAM against truth, anchored at SLAM's first matched pose,
        with the last state's landmark counts; None before a state met its truth."""
        errors = self.errors
        if not errors.matched:
            return None
        last = codec.SLAM_STATE.decode(self.last_state)
        return {
            "scans": float(errors.matched),
            "final_xy_m": errors.final[0],
            "final_heading_deg": float(np.degrees(errors.final[1])),
            "ate_rmse_m": errors.ate_rmse_m,
            "landmarks": float(last.n_landmarks),
            "confirmed": float(last.n_confirmed),
        }
