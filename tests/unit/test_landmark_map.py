"""The landmark map sent as changes: what a subscriber rebuilds is the filter's map within the
tolerance after every state, exactly the filter's at every whole map, and it knows when it is not."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import (
    LandmarkMapReplica,
    apply,
    axis_sigmas,
    by_id,
    changes,
)

TOL = 0.005


def random_map(rng: np.random.Generator, ids) -> t.Landmarks:
    n = len(ids)
    a = rng.normal(size=(n, 2, 2)) * 0.05
    return t.Landmarks(ids=ids, xy_m=rng.uniform(-20, 20, (n, 2)), cov_m2=a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(2),
                       kind=rng.choice([1, 2], n), sightings=rng.integers(1, 5, n), confirmed=rng.random(n) < 0.5)


def evolve(rng: np.random.Generator, m: t.Landmarks, next_id: int) -> tuple[t.Landmarks, int]:
    """One filter update's worth of change: most landmarks drift by less than the tolerance, some
    jump, some spread changes, a few are seen again, born or removed; the filter's order is shuffled."""
    n = len(m)
    scale = np.where(rng.random(n) < 0.2, 0.05, 0.001)
    xy = m.xy_m + rng.normal(size=(n, 2)) * scale[:, None]
    cov = m.cov_m2 * np.where(rng.random(n) < 0.1, 0.7, 1.0)[:, None, None]
    sightings = m.sightings + (rng.random(n) < 0.1)
    confirmed = m.confirmed | (sightings > 3)
    moved = t.Landmarks(ids=m.ids, xy_m=xy, cov_m2=cov, kind=m.kind, sightings=sightings, confirmed=confirmed)
    kept = moved.take(rng.random(n) > 0.05)
    born = rng.integers(0, 3)
    new = random_map(rng, np.arange(next_id, next_id + born))
    both = t.Landmarks(**{f: np.concatenate((getattr(kept, f), getattr(new, f)))
                          for f in ("ids", "xy_m", "cov_m2", "kind", "sightings", "confirmed")})
    return both.take(rng.permutation(len(both))), next_id + born


def assert_within(held: t.Landmarks, exact: t.Landmarks, tol: float) -> None:
    exact = by_id(exact)
    np.testing.assert_array_equal(held.ids, exact.ids)
    for name in ("kind", "sightings", "confirmed"):
        np.testing.assert_array_equal(getattr(held, name), getattr(exact, name))
    assert np.all(np.hypot(*(held.xy_m - exact.xy_m).T) <= tol)
    assert np.all(np.abs(axis_sigmas(held.cov_m2) - axis_sigmas(exact.cov_m2)) <= tol)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), steps=st.integers(1, 60), every=st.integers(1, 25),
       tol=st.sampled_from([0.0, TOL, 0.05]))
def test_the_rebuilt_map_follows_the_filter_within_the_tolerance(seed, steps, every, tol):
    rng = np.random.default_rng(seed)
    exact, next_id = random_map(rng, np.arange(rng.integers(0, 8))), 100
    sent, replica = t.Landmarks(), LandmarkMapReplica()
    carried = travelled = 0   # landmarks present before an update, and those of them sent with it
    for seq in range(1, steps + 1):
        if seq > 1:
            before = set(sent.ids.tolist())
            exact, next_id = evolve(rng, exact, next_id)
        changed, removed = changes(sent, exact, tol)
        if seq > 1:
            carried += int(np.isin(exact.ids, list(before)).sum())
            travelled += int(np.isin(changed.ids, list(before)).sum())
        sent = apply(sent, changed, removed)
        replica.apply_state(t.SlamState(stamp_ns=seq, seq=seq, scan_seq=seq, pose=np.zeros(3), pose_cov=np.eye(3),
                                        landmarks=changed, removed_landmark_ids=removed))
        assert replica.complete and replica.state_seq == seq
        assert_within(replica.landmarks, exact, tol)
        if seq % every == 0:   # a whole map: exact again, and the sender holds it too
            sent = by_id(exact)
            replica.apply_map(t.LandmarkMap(stamp_ns=seq, seq=seq // every, state_seq=seq, landmarks=exact,
                                            tolerance_m=tol))
            assert_within(replica.landmarks, exact, 0.0)
    if tol == 0.0:
        return
    # Only what changed travels: untouched landmarks stay home. A new landmark always travels, so
    # only those already sent count; about a third of them change beyond the tolerance per update
    # (evolve), so over 20 or more all of them travelling would mean the tolerance is ignored.
    assert travelled < carried or carried < 20


def test_an_unchanged_map_sends_nothing_and_a_removed_landmark_is_named():
    rng = np.random.default_rng(3)
    m = random_map(rng, [5, 2, 9])
    changed, removed = changes(by_id(m), m, TOL)
    assert len(changed) == 0 and removed.size == 0
    changed, removed = changes(by_id(m), m.take([0, 2]), TOL)
    assert len(changed) == 0 and removed.tolist() == [2]
    # A spread change along a diagonal alone (same x and y variances) is a change too.
    cov = m.cov_m2.copy()
    cov[0, 0, 1] = cov[0, 1, 0] = cov[0, 0, 1] + 0.5 * np.sqrt(cov[0, 0, 0] * cov[0, 1, 1])
    tilted = t.Landmarks(ids=m.ids, xy_m=m.xy_m, cov_m2=cov, kind=m.kind, sightings=m.sightings, confirmed=m.confirmed)
    changed, _ = changes(by_id(m), tilted, 1e-4)
    assert changed.ids.tolist() == [5]


def state(seq: int, changed: t.Landmarks | None = None, removed=()) -> t.SlamState:
    return t.SlamState(stamp_ns=seq, seq=seq, scan_seq=seq, pose=np.zeros(3), pose_cov=np.eye(3),
                       landmarks=changed or t.Landmarks(), removed_landmark_ids=removed)


def test_the_replica_knows_when_it_missed_a_state():
    rng = np.random.default_rng(4)
    m = random_map(rng, [1, 2, 3])
    joined = LandmarkMapReplica()
    joined.apply_state(state(7, m))
    assert not joined.complete             # joined mid-stream: the map before state 7 is unknown
    joined.apply_map(t.LandmarkMap(stamp_ns=7, seq=1, state_seq=7, landmarks=m, tolerance_m=TOL))
    assert joined.complete
    joined.apply_state(state(7, m))        # the map's own state, after it: already in it
    assert joined.complete and joined.missed == 0
    joined.apply_state(state(9))           # state 8 lost
    assert not joined.complete and joined.missed == 1
    joined.apply_map(t.LandmarkMap(stamp_ns=9, seq=2, state_seq=9, landmarks=m.take([0]), tolerance_m=TOL))
    assert joined.complete and joined.landmarks.ids.tolist() == [1]
    joined.apply_state(state(5))           # numbers going back: a restarted stage, until its map
    assert not joined.complete and joined.missed == 2
    joined.apply_map(t.LandmarkMap(stamp_ns=5, seq=1, state_seq=5, landmarks=m, tolerance_m=TOL))
    joined.apply_state(state(6, t.Landmarks(), [2]))
    assert joined.complete and joined.landmarks.ids.tolist() == [1, 3]


def test_a_first_state_and_a_v1_state_are_whole_maps():
    m = random_map(np.random.default_rng(5), [4, 8])
    first = LandmarkMapReplica()
    first.apply_state(state(1, m))
    assert first.complete and first.landmarks.ids.tolist() == [4, 8]
    old = LandmarkMapReplica()
    v1 = t.SlamState(stamp_ns=30, seq=30, scan_seq=30, pose=np.zeros(3), pose_cov=np.eye(3), landmarks=m.take([1]),
                     removed_landmark_ids=(), landmarks_complete=True, n_landmarks=1, n_confirmed=0)
    assert old.apply_state(v1).ids.tolist() == [8]
    assert old.complete and old.landmarks.ids.tolist() == [8]
