"""The mapper's checkpoint: every array needed to continue exactly where it stood.

:func:`snapshot` and :func:`restore` are :meth:`LoopClosingMapper.snapshot` and
:meth:`LoopClosingMapper.restore`; snapshots written before a key existed still restore
(each such key says what it means when absent).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lrfslam.algo.loop_closure.keyframes import Keyframe, Retired
from lrfslam.algo.loop_closure.params import LoopClosureParams
from lrfslam.algo.loop_closure.search import ClosureStats
from lrfslam.algo.pose_graph import PoseGraph
from lrfslam.errors import InputError

if TYPE_CHECKING:
    from lrfslam.algo.loop_closure.mapper import LoopClosingMapper

#: Version of :func:`snapshot`'s arrays.
SNAPSHOT_FORMAT = 1


def snapshot(mapper: LoopClosingMapper) -> dict[str, np.ndarray]:
    """Everything needed to continue exactly where ``mapper`` stands, as named arrays (copies).

    The graph's arrays (:meth:`PoseGraph.snapshot`); the keyframes' (``keyframe_*``, their
    points concatenated with ``keyframe_point_counts``); the per-scan history if kept; the
    closure search's state. Feeding the restored mapper the same scans gives the same results.
    """
    kfs = mapper._keyframes
    tentative = mapper._search.tentative
    return {
        "mapper_format": np.int64(SNAPSHOT_FORMAT),
        **mapper.graph.snapshot(),
        "keyframe_local_pose": mapper.keyframe_local_poses(),
        "keyframe_points": np.vstack([k.points_xy_m for k in kfs]) if kfs else np.zeros((0, 2)),
        "keyframe_point_counts": np.array([k.points_xy_m.shape[0] for k in kfs], dtype=np.int64),
        "keyframe_travel_m": np.array([k.travel_m for k in kfs], dtype=float),
        "keyframe_local_edge": mapper.keyframe_local_edges(),
        "keyframe_scan_index": mapper.keyframe_scans(),
        "keyframe_stamp_ns": np.array([k.stamp_ns for k in kfs], dtype=np.int64),
        "keyframe_revisit": np.array([k.revisit for k in kfs], dtype=bool),
        "keyframe_ordinal": np.array([k.ordinal for k in kfs], dtype=np.int64),
        # NaN rows: keyframes made without an online pose.
        "keyframe_online_pose": np.array([np.full(3, np.nan) if k.online_pose is None else k.online_pose
                                          for k in kfs], dtype=float).reshape(-1, 3),
        "keyframes_made": np.int64(mapper._made),
        **_retired_arrays("retired", mapper._retired),
        **_retired_arrays("retired_kept", mapper._retired_kept),
        "fold_queue": np.array(mapper._fold_queue, dtype=np.int64),
        "scans_fed": np.int64(mapper._scans_fed),
        "keep_scans": np.bool_(mapper._keep_scans),
        "scan_keyframe": np.array(mapper._scan_kf, dtype=np.int64),
        "scan_relative_pose": np.array(mapper._scan_rel, dtype=float).reshape(-1, 3),
        "scan_stamp_ns": np.array(mapper._stamps, dtype=np.int64),
        "loop_edges": np.array(mapper._loop_edges, dtype=np.int64),
        "closure_nis_total": np.array([float(mapper._search.closure_nis[0]), mapper._search.closure_nis[1]]),
        "stats": np.array([mapper._counts[name] for name in ClosureStats.__dataclass_fields__], dtype=np.int64),
        "last_local_pose": mapper._last_local_pose.copy(),
        "reference_step": np.full(3, np.nan) if mapper._reference is None else mapper._reference.copy(),
        "pending_closures": np.int64(mapper._pending),
        "pending_strong": np.bool_(mapper._pending_strong),
        "last_wide_search_m": np.float64(mapper._search.last_wide_search_m),
        "run_start": np.int64(mapper._search.run_start),
        # keyframe pairs (2,), measurement (3,), covariance (9,), innovation (3,); empty if none
        "tentative_closure": np.zeros(0) if tentative is None else np.concatenate(
            (np.array(tentative[:2], dtype=float), tentative[2], np.ravel(tentative[3]), tentative[4])),
        "cached_submaps": np.array([(k, entry[0]) for k, entry in mapper._search.submaps.items()],
                                   dtype=np.int64).reshape(-1, 2),
    }


def restore(cls: type[LoopClosingMapper], params: LoopClosureParams | None, arrays) -> LoopClosingMapper:
    """The mapper (of class ``cls``) :func:`snapshot` gave ``arrays`` of (e.g. loaded from an ``.npz``).

    Raises
    ------
    InputError
        If the arrays are not a snapshot of this format or disagree with each other.
    """
    try:
        fmt = int(arrays["mapper_format"])
        if fmt != SNAPSHOT_FORMAT:
            raise InputError(f"mapper snapshot format {fmt} is not {SNAPSHOT_FORMAT}")
        mapper = cls(params, keep_scans=bool(arrays["keep_scans"]))
        mapper.graph = PoseGraph.restore(arrays)
        counts = np.array(arrays["keyframe_point_counts"], dtype=np.int64)
        points = np.array(arrays["keyframe_points"], dtype=float).reshape(-1, 2)
        local = np.array(arrays["keyframe_local_pose"], dtype=float).reshape(-1, 3)
        travel = np.array(arrays["keyframe_travel_m"], dtype=float)
        edge = np.array(arrays["keyframe_local_edge"], dtype=bool)
        scan_index = np.array(arrays["keyframe_scan_index"], dtype=np.int64)
        stamps = np.array(arrays["keyframe_stamp_ns"], dtype=np.int64)
        revisit = np.array(arrays["keyframe_revisit"], dtype=bool)
        k = len(mapper.graph)
        # A snapshot from before keyframes were retired has every keyframe made in its graph.
        ordinal = np.array(arrays["keyframe_ordinal"], dtype=np.int64) if "keyframe_ordinal" in arrays \
            else np.arange(k, dtype=np.int64)
        mapper._made = int(arrays["keyframes_made"]) if "keyframes_made" in arrays else k
        # A snapshot from before the online poses has none.
        online = np.array(arrays["keyframe_online_pose"], dtype=float).reshape(-1, 3) \
            if "keyframe_online_pose" in arrays else np.full((k, 3), np.nan)
        mapper._retired = _retired_from("retired", arrays)
        mapper._retired_kept = _retired_from("retired_kept", arrays)
        # A snapshot from before revisits were folded has none queued.
        queue = np.array(arrays["fold_queue"], dtype=np.int64) if "fold_queue" in arrays \
            else np.zeros(0, dtype=np.int64)
        if not (counts.shape == travel.shape == edge.shape == scan_index.shape == stamps.shape == revisit.shape
                == ordinal.shape == (k,) and np.all((queue >= 0) & (queue < k))
                and np.all(np.diff(ordinal) > 0) and (k == 0 or 0 <= ordinal[0] and ordinal[-1] < mapper._made)
                and local.shape == online.shape == (k, 3) and np.all(counts >= 0)
                and counts.sum() == points.shape[0]):
            raise InputError("mapper snapshot: keyframe arrays disagree with the graph")
        for i, pts in enumerate(np.split(points, np.cumsum(counts)[:-1]) if k else []):
            mapper._keyframes.append(Keyframe(local[i], pts, float(travel[i]), bool(edge[i]),
                                               int(scan_index[i]), int(stamps[i]), int(ordinal[i]),
                                               bool(revisit[i]),
                                               None if np.isnan(online[i]).any() else online[i]))
        mapper._fold_queue = queue.tolist()
        mapper._scans_fed = int(arrays["scans_fed"])
        if mapper._keep_scans:
            mapper._scan_kf = np.array(arrays["scan_keyframe"], dtype=np.int64).tolist()
            mapper._scan_rel = list(np.array(arrays["scan_relative_pose"], dtype=float).reshape(-1, 3))
            mapper._stamps = np.array(arrays["scan_stamp_ns"], dtype=np.int64).tolist()
        mapper._loop_edges = np.array(arrays["loop_edges"], dtype=np.int64).tolist()
        if "closure_nis_total" in arrays:
            count, total = np.array(arrays["closure_nis_total"], dtype=float).reshape(2)
            mapper._search.closure_nis = (int(count), float(total))
        else:   # a snapshot from before the running total holds every closure's
            nis = np.array(arrays["closure_nis"], dtype=float)
            mapper._search.closure_nis = (nis.size, float(nis.sum()))
        stats = np.array(arrays["stats"], dtype=np.int64)
        if stats.shape != (len(ClosureStats.__dataclass_fields__),):
            raise InputError("mapper snapshot: wrong number of statistics")
        mapper._counts.update(zip(ClosureStats.__dataclass_fields__, stats.tolist(), strict=True))
        mapper._last_local_pose = np.array(arrays["last_local_pose"], dtype=float).reshape(3)
        reference = np.array(arrays["reference_step"], dtype=float).reshape(3)
        mapper._reference = None if np.any(np.isnan(reference)) else reference
        mapper._pending = int(arrays["pending_closures"])
        mapper._pending_strong = bool(arrays["pending_strong"])
        mapper._search.last_wide_search_m = float(arrays["last_wide_search_m"])
        # A snapshot from before saved maps were mapped on from has every keyframe its run's.
        mapper._search.run_start = int(arrays["run_start"]) if "run_start" in arrays else 0
        tentative = np.array(arrays["tentative_closure"], dtype=float)
        if tentative.size:
            mapper._search.tentative = (int(tentative[0]), int(tentative[1]), tentative[2:5],
                                 tentative[5:14].reshape(3, 3), tentative[14:17])
        for kf, last in np.array(arrays["cached_submaps"], dtype=np.int64).reshape(-1, 2).tolist():
            mapper._search.cache_submap(mapper._keyframes, mapper.graph, kf, last)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputError(f"mapper snapshot: {exc!r}") from None
    edges, keyframes = len(arrays["graph_edge_alive"]), len(mapper._keyframes)
    if any(not 0 <= e < edges for e in mapper._loop_edges) or (
            mapper._search.tentative is not None and not all(0 <= n < keyframes for n in mapper._search.tentative[:2])):
        raise InputError("mapper snapshot: a closure names an edge or a keyframe that is not there")
    return mapper


def _retired_arrays(prefix: str, retired: list[Retired]) -> dict[str, np.ndarray]:
    """Retired keyframes as a snapshot's named arrays (``<prefix>_*``, R rows each)."""
    return {
        f"{prefix}_ordinal": np.array([r.ordinal for r in retired], dtype=np.int64),
        f"{prefix}_stamp_ns": np.array([r.stamp_ns for r in retired], dtype=np.int64),
        f"{prefix}_local_pose": np.array([r.local_pose for r in retired], dtype=float).reshape(-1, 3),
        f"{prefix}_local_edge": np.array([r.local_edge for r in retired], dtype=bool),
        f"{prefix}_scan_index": np.array([r.scan_index for r in retired], dtype=np.int64),
        f"{prefix}_anchor_ordinal": np.array([r.anchor_ordinal for r in retired], dtype=np.int64),
        f"{prefix}_anchor_stamp_ns": np.array([r.anchor_stamp_ns for r in retired], dtype=np.int64),
        f"{prefix}_offset": np.array([r.offset for r in retired], dtype=float).reshape(-1, 3),
    }


def _retired_from(prefix: str, arrays) -> list[Retired]:
    """The retired keyframes :func:`_retired_arrays` wrote (none in a snapshot from before them)."""
    if f"{prefix}_ordinal" not in arrays:
        return []
    cols = [np.array(arrays[f"{prefix}_{name}"]) for name in
            ("ordinal", "stamp_ns", "local_pose", "local_edge", "scan_index", "anchor_ordinal", "anchor_stamp_ns",
             "offset")]
    r = cols[0].shape[0]
    if any(c.shape[0] != r for c in cols) or cols[2].shape != (r, 3) or cols[7].shape != (r, 3) \
            or not (np.all(np.isfinite(cols[2])) and np.all(np.isfinite(cols[7]))):
        raise InputError(f"mapper snapshot: {prefix} arrays of inconsistent shapes or not finite")
    return [Retired(int(o), int(st), lp.astype(float), bool(le), int(si), int(ao), int(ast), off.astype(float))
            for o, st, lp, le, si, ao, ast, off in zip(*cols, strict=True)]
