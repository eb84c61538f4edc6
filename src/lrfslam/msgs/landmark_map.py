"""The slam stage's landmark map as its subscribers hold it: the changes it sends, and the map rebuilt.

A slam state carries only the landmarks that changed since the previous state; ``slam/map``
carries the whole map at a low rate, at the first and the last state, and on request. The
stage decides what to send with :func:`changes` and keeps what it has sent with :func:`apply`,
the function every subscriber's :class:`LandmarkMapReplica` applies too, so the stage knows
exactly the map its subscribers rebuild: within the tolerance of the filter's, and exactly
the filter's at each whole map.

A landmark is sent again when it moved more than the tolerance, when its standard deviation
along x, y or either diagonal changed more than it (those four fix a 2x2 covariance), or when
its kind, sightings or confirmation changed.
"""

from __future__ import annotations

import numpy as np

from lrfslam.msgs import types as t


def axis_sigmas(cov_m2: np.ndarray) -> np.ndarray:
    """Standard deviations (L, 4) along x, y and the two diagonals of covariances (L, 2, 2), m."""
    xx, yy, xy = cov_m2[:, 0, 0], cov_m2[:, 1, 1], 0.5 * (cov_m2[:, 0, 1] + cov_m2[:, 1, 0])
    mid = 0.5 * (xx + yy)
    return np.sqrt(np.maximum(np.stack((xx, yy, mid + xy, mid - xy), axis=1), 0.0))


def _rows(held_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each of ``ids`` sits in the sorted ``held_ids`` (N,), and whether it is there (N,) bool."""
    if not held_ids.size:
        return np.zeros(ids.size, np.intp), np.zeros(ids.size, bool)
    pos = np.minimum(np.searchsorted(held_ids, ids), held_ids.size - 1)
    return pos, held_ids[pos] == ids


def by_id(landmarks: t.Landmarks) -> t.Landmarks:
    """``landmarks`` sorted by id."""
    if np.all(landmarks.ids[1:] > landmarks.ids[:-1]):
        return landmarks
    return landmarks.take(np.argsort(landmarks.ids, kind="stable"))


def changes(sent: t.Landmarks, current: t.Landmarks, tolerance_m: float) -> tuple[t.Landmarks, np.ndarray]:
    """What a state must carry so that a map equal to ``sent`` follows ``current``.

    Parameters
    ----------
    sent : the map the subscribers hold, sorted by id.
    current : the filter's map, any order.
    tolerance_m : how far a landmark may move, or a standard deviation change, unsent (m).

    Returns
    -------
    (the rows of ``current`` to send, sorted by id; the ids (R,) to remove)
    """
    current = by_id(current)
    pos, known = _rows(sent.ids, current.ids)
    send = ~known
    if known.any():
        # Rows not held are sent anyway; what they are compared with does not matter.
        step = current.xy_m - sent.xy_m[pos]
        send |= np.hypot(step[:, 0], step[:, 1]) > tolerance_m
        send |= (np.abs(axis_sigmas(current.cov_m2) - axis_sigmas(sent.cov_m2[pos])) > tolerance_m).any(axis=1)
        send |= (current.kind != sent.kind[pos]) | (current.sightings != sent.sightings[pos]) \
            | (current.confirmed != sent.confirmed[pos])
    _, kept = _rows(current.ids, sent.ids)
    return current.take(send), sent.ids[~kept]


_FIELDS = ("xy_m", "cov_m2", "kind", "sightings", "confirmed")


def apply(held: t.Landmarks, changed: t.Landmarks, removed_ids: np.ndarray) -> t.Landmarks:
    """The map ``held`` (sorted by id) after one state's ``changed`` rows and ``removed_ids``; sorted by id."""
    removed_ids = np.asarray(removed_ids, np.int64)
    if not len(changed) and not removed_ids.size:
        return held
    pos, known = _rows(held.ids, changed.ids)
    if known.all() and not removed_ids.size:
        # The usual state: landmarks seen again, none born or dropped; rows replaced in place.
        columns = {}
        for name in _FIELDS:
            column = getattr(held, name).copy()
            column[pos] = getattr(changed, name)
            columns[name] = column
        return t.Landmarks(ids=held.ids, **columns)
    drop = np.zeros(len(held), bool)
    drop[pos[known]] = True
    at, there = _rows(held.ids, removed_ids)
    drop[at[there]] = True
    kept = held.take(~drop)
    return by_id(t.Landmarks(ids=np.concatenate((kept.ids, changed.ids)),
                             **{name: np.concatenate((getattr(kept, name), getattr(changed, name))) for name in _FIELDS}))


class LandmarkMapReplica:
    """The landmark map rebuilt from ``slam/map`` and ``slam/state`` messages, fed in the order they came.

    ``complete`` says whether the map is the slam stage's (within its tolerance): it becomes
    true at a whole map (a ``slam/map``, or a v1 state, which held the whole map) or at the
    stage's first state (the map before it was empty), and false when a state is missing
    (its number skipped, or numbers going back: a restarted stage, until its whole map
    comes). ``missed`` counts the states found missing.
    """

    def __init__(self) -> None:
        self.landmarks = t.Landmarks()
        self.state_seq: int | None = None   # the state the map follows
        self.complete = False
        self.missed = 0
        self._map_seq: int | None = None    # the state of the last whole map

    def apply_map(self, m: t.LandmarkMap) -> None:
        """Take a whole map: it replaces what is held."""
        self.landmarks = by_id(m.landmarks)
        self.state_seq = self._map_seq = m.state_seq
        self.complete = True

    def apply_state(self, state: t.SlamState) -> t.Landmarks:
        """Apply one state's changes; the landmarks it changed (all of them for a v1 state; none if skipped)."""
        if state.landmarks_complete:
            self.landmarks = by_id(state.landmarks)
            self.state_seq, self.complete = state.seq, True
            return self.landmarks
        if self.state_seq is not None and state.seq <= self.state_seq:
            # The state of the whole map just taken is in it; any other was reordered or restarted.
            if state.seq != self._map_seq:
                self.complete = False
                self.missed += 1
            return t.Landmarks()
        if self.state_seq is None:
            self.complete = state.seq == 1
        elif state.seq != self.state_seq + 1:
            self.complete = False
            self.missed += state.seq - self.state_seq - 1
        self.landmarks = apply(self.landmarks, state.landmarks, state.removed_landmark_ids)
        self.state_seq = state.seq
        return by_id(state.landmarks)

    def apply_message(self, value: t.SlamState | t.LandmarkMap) -> None:
        """Apply a decoded ``slam/state`` or ``slam/map`` message."""
        if isinstance(value, t.LandmarkMap):
            self.apply_map(value)
        else:
            self.apply_state(value)
