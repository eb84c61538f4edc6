"""The slam checkpoint (algo.checkpoint) and its file (runtime.npz_file): round trip, migration, bad input."""

from __future__ import annotations

import io

import numpy as np
import pytest

from lrfslam.algo import checkpoint
from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.errors import InputError
from lrfslam.runtime import npz_file

PARAMS = EkfParams()
CORNERS = np.array([[2.0, 1.0], [3.0, -1.0], [1.5, 2.5]])


def busy_filter() -> EkfSlam:
    """A filter that has moved, seen corners twice (confirmed) and set its building orientation."""
    f = EkfSlam(PARAMS, pose0=[0.5, -0.2, 0.1])
    for _ in range(2):
        f.observe_wall_direction(0.05, 0.01)
        f.observe(CORNERS, np.tile(np.eye(2) * 1e-4, (3, 1, 1)))
        f.predict([0.1, 0.0, 0.01])
    return f


def through_a_file(arrays: dict) -> dict:
    """What np.savez / np.load make of the arrays (scalars come back as 0-d arrays)."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    buf.seek(0)
    with np.load(buf) as data:
        return {k: data[k] for k in data.files}


def assert_same_filter(a: EkfSlam, b: EkfSlam) -> None:
    np.testing.assert_array_equal(a.state_mean, b.state_mean)
    np.testing.assert_array_equal(a.state_cov, b.state_cov)
    la, lb = a.landmarks(), b.landmarks()
    np.testing.assert_array_equal(la.ids, lb.ids)
    np.testing.assert_array_equal(la.confirmed, lb.confirmed)
    assert a.building_orientation == b.building_orientation


def test_round_trip_through_a_file():
    f = busy_filter()
    pose = np.array([1.0, 2.0, 0.3])
    ck = checkpoint.decode(PARAMS, through_a_file(checkpoint.encode(f, 17, pose)))
    assert_same_filter(ck.ekf, f)
    assert ck.scans == 17 and ck.ekf.n_landmarks == f.n_landmarks >= 3
    np.testing.assert_array_equal(ck.last_odom_pose, pose)
    # The restored filter goes on exactly as the original would.
    for g in (f, ck.ekf):
        g.predict([0.2, 0.1, -0.02])
        g.observe(CORNERS - 0.1)
    assert_same_filter(ck.ekf, f)


def test_without_odometry_or_a_scan_count():
    ck = checkpoint.decode(PARAMS, through_a_file(checkpoint.encode(busy_filter(), 3, None)))
    assert ck.last_odom_pose is None and ck.scans == 3
    bare = checkpoint.decode(PARAMS, through_a_file(busy_filter().snapshot()))
    assert bare.scans == 0 and bare.last_odom_pose is None


def test_a_checkpoint_of_the_first_filter_format_is_migrated():
    """Format 1 had no building orientation: its state lacks psi, which comes back unset."""
    f = EkfSlam(PARAMS, pose0=[0.5, -0.2, 0.1])
    f.observe(CORNERS)
    arrays = checkpoint.encode(f, 5, np.zeros(3))
    arrays["format"] = 1
    arrays["state_mean"] = np.delete(arrays["state_mean"], 3)
    arrays["state_cov"] = np.delete(np.delete(arrays["state_cov"], 3, axis=0), 3, axis=1)
    del arrays["psi_set"]
    ck = checkpoint.decode(PARAMS, through_a_file(arrays))
    assert_same_filter(ck.ekf, f)
    assert ck.ekf.building_orientation is None and ck.scans == 5


@pytest.mark.parametrize("change", [
    {"format": 99},
    {"last_odom_pose": np.zeros(2)},
    {"last_odom_pose": np.array([0.0, np.inf, 0.0])},
    {"service_seq": "many"},
])
def test_what_is_no_checkpoint_is_bad_input(change):
    arrays = {**checkpoint.encode(busy_filter(), 3, np.zeros(3)), **change}
    with pytest.raises(InputError):
        checkpoint.decode(PARAMS, arrays)
    lacking = checkpoint.encode(busy_filter(), 3, None)
    del lacking["state_cov"]
    with pytest.raises(InputError):
        checkpoint.decode(PARAMS, lacking)


def test_the_file_is_replaced_whole(tmp_path):
    path = tmp_path / "sub" / "slam.npz"
    npz_file.write_atomic(path, checkpoint.encode(busy_filter(), 1, None))
    npz_file.write_atomic(path, checkpoint.encode(busy_filter(), 2, None))
    assert sorted(p.name for p in path.parent.iterdir()) == ["slam.npz"]   # no .tmp left behind
    assert checkpoint.decode(PARAMS, npz_file.read(path)).scans == 2


@pytest.mark.parametrize("content", [b"not a zip file", b"PK\x03\x04 cut short"])
def test_an_unreadable_file_raises_value_error(tmp_path, content):
    path = tmp_path / "slam.npz"
    path.write_bytes(content)
    with pytest.raises(ValueError):
        npz_file.read(path)
