"""A 2-D indoor world as a list of wall segments, and the ground truth it implies.

Orientation convention: a segment ``(x0, y0) -> (x1, y1)`` has free space on its
**left** (counter-clockwise normal). Closed rooms are therefore counter-clockwise and
solid blocks inside them clockwise, as for polygon boundaries; :func:`closed_polygon`
orients a vertex list for you. The ray caster treats walls as two-sided; only the
corner classification (convex or concave) relies on the convention.

Each segment has a material (:data:`MATERIALS`): ``"wall"`` reflects and makes the
map; ``"glass"`` is transparent to the scanner (the beam goes on to whatever is
behind it, or reports no return); ``"clutter"`` (boxes, pillars, bins) reflects but
is not part of the map, so its vertices are never ground-truth corners.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from lrfslam.errors import ConfigError

#: Endpoints closer than this are the same map vertex (hand-made maps).
SNAP_TOLERANCE_M = 0.01
#: A vertex is a corner when its two walls meet at 90° ± this.
CORNER_ANGLE_TOL_DEG = 20.0
#: Segment materials: map walls, transparent glass, and reflecting non-map clutter.
MATERIALS = ("wall", "glass", "clutter")


@dataclass(frozen=True, eq=False)
class MapCorners:
    """Ground-truth corners of a segment map.

    Attributes
    ----------
    xy_m : ndarray, shape (K, 2)
        Corner positions in the world frame, metres.
    kind : ndarray of str, shape (K,)
        ``"concave"`` (inside corner, free space within the wedge) or ``"convex"``
        (outside corner, e.g. the corner of a pillar or of a door jamb).
    angle_deg : ndarray, shape (K,)
        Angle between the two walls, degrees in [70, 110].
    wall_dirs : ndarray, shape (K, 2, 2)
        Unit vectors from the corner along each of its two walls.
    wall_lengths_m : ndarray, shape (K, 2)
        Length of each of the two walls, metres.
    """

    xy_m: np.ndarray
    kind: np.ndarray
    angle_deg: np.ndarray
    wall_dirs: np.ndarray
    wall_lengths_m: np.ndarray

    def __len__(self) -> int:
        return len(self.xy_m)


@dataclass(frozen=True, eq=False)
class World:
    """A named map of wall segments.

    Attributes
    ----------
    segments_m : ndarray, shape (M, 4)
        Rows ``(x0, y0, x1, y1)`` in metres, free space on the left of each row.
    name : str
        Registry name of the world.
    material : ndarray of str, shape (M,), optional
        One of :data:`MATERIALS` per segment; all ``"wall"`` when omitted.
    """

    segments_m: np.ndarray
    name: str
    material: np.ndarray | None = None

    def __post_init__(self) -> None:
        seg = np.asarray(self.segments_m, dtype=float)
        if seg.ndim != 2 or seg.shape[1] != 4 or len(seg) == 0:
            raise ConfigError(f"world {self.name!r}: segments must have shape (M, 4), got {seg.shape}")
        if not np.all(np.isfinite(seg)):
            raise ConfigError(f"world {self.name!r}: segments contain non-finite coordinates")
        if np.any(np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) < SNAP_TOLERANCE_M):
            raise ConfigError(f"world {self.name!r}: a segment is shorter than {SNAP_TOLERANCE_M} m")
        material = np.full(len(seg), "wall", dtype="<U7") if self.material is None else np.asarray(self.material)
        if material.shape != (len(seg),) or not np.all(np.isin(material, MATERIALS)):
            raise ConfigError(f"world {self.name!r}: material must be one of {MATERIALS} per segment")
        seg.setflags(write=False)
        material = material.astype("<U7")
        material.setflags(write=False)
        object.__setattr__(self, "segments_m", seg)
        object.__setattr__(self, "material", material)

    @cached_property
    def opaque_segments_m(self) -> np.ndarray:
        """Segments that return the beam (walls and clutter); shape (M', 4), metres."""
        return self.segments_m[self.material != "glass"]

    def corners(self) -> MapCorners:
        """Vertices shared by exactly two wall segments meeting at 90° ± 20° (glass and clutter ignored)."""
        return self._topology[0]

    def free_endpoints(self) -> np.ndarray:
        """Wall endpoints shared by no other wall (wall ends, door jambs, the edge of a glass pane); shape (F, 2), m."""
        return self._topology[1]

    @cached_property
    def _topology(self) -> tuple[MapCorners, np.ndarray]:
        # cached_property writes the instance __dict__ directly, which a frozen dataclass allows.
        # Only walls make the map: a wall ending at a glass pane is a jump edge to the scanner.
        return _analyse_vertices(self.segments_m[self.material == "wall"], self.name)


def distance_to_segments(points_xy_m, segments_m) -> np.ndarray:
    """Distance (m) from each point to the nearest segment.

    Parameters
    ----------
    points_xy_m : array_like, shape (P, 2)
    segments_m : array_like, shape (M, 4)
        ``(x0, y0, x1, y1)`` rows, metres, none of zero length.

    Returns
    -------
    ndarray, shape (P,)
    """
    points = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    segments = np.asarray(segments_m, dtype=float).reshape(-1, 4)
    a, d = segments[:, :2], segments[:, 2:] - segments[:, :2]
    s = np.clip(np.einsum("pmi,mi->pm", points[:, None] - a, d) / np.einsum("mi,mi->m", d, d), 0.0, 1.0)
    return np.min(np.linalg.norm(points[:, None] - (a + s[..., None] * d), axis=2), axis=1)


def inside_polygons(points_xy_m, segments_m) -> np.ndarray:
    """Whether each point is enclosed by an odd number of closed polygons (even-odd rule), (P,) bool.

    With a world's rooms and the solid blocks inside them as ``segments_m`` (M, 4):
    True in free space.
    """
    points = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    segments = np.asarray(segments_m, dtype=float).reshape(-1, 4)
    x, y = points[:, 0:1], points[:, 1:2]
    x0, y0, x1, y1 = (segments[:, k] for k in range(4))
    straddles = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(straddles & (x_cross > x), axis=1) % 2 == 1


def closed_polygon(vertices_m, free_inside: bool) -> np.ndarray:
    """Segments of a closed polygon, oriented so free space is on their left.

    Parameters
    ----------
    vertices_m : array_like, shape (P, 2)
        Polygon vertices in metres, either winding, without repeating the first.
    free_inside : bool
        True for a room or corridor boundary (free space enclosed), False for a
        solid block standing in free space.

    Returns
    -------
    ndarray, shape (P, 4)
    """
    v = np.asarray(vertices_m, dtype=float)
    nxt = np.roll(v, -1, axis=0)
    signed_area = 0.5 * np.sum(v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1])
    if (signed_area > 0) != free_inside:
        v = v[::-1]
        nxt = np.roll(v, -1, axis=0)
    return np.hstack((v, nxt))


def polyline(vertices_m) -> np.ndarray:
    """Segments of an open chain, in the given order (free space on the left of travel).

    Parameters
    ----------
    vertices_m : array_like, shape (P, 2)

    Returns
    -------
    ndarray, shape (P - 1, 4)
    """
    v = np.asarray(vertices_m, dtype=float)
    return np.hstack((v[:-1], v[1:]))


def _analyse_vertices(seg: np.ndarray, name: str) -> tuple[MapCorners, np.ndarray]:
    if len(seg) == 0:
        return MapCorners(np.zeros((0, 2)), np.zeros(0, dtype="<U7"), np.zeros(0), np.zeros((0, 2, 2)),
                          np.zeros((0, 2))), np.zeros((0, 2))
    endpoints = seg.reshape(-1, 2)  # row 2j = start of segment j, row 2j+1 = its end
    labels = _snap(endpoints, SNAP_TOLERANCE_M)
    n_vertices = labels.max() + 1
    counts = np.bincount(labels, minlength=n_vertices)

    free = [endpoints[labels == v].mean(axis=0) for v in range(n_vertices) if counts[v] == 1]
    xy, kind, angle, dirs, lengths = [], [], [], [], []
    for v in np.flatnonzero(counts == 2):
        rows = np.flatnonzero(labels == v)
        seg_ids = rows // 2
        if seg_ids[0] == seg_ids[1]:
            continue
        vertex = endpoints[rows].mean(axis=0)
        # The far endpoint of each segment is the other row of the same segment.
        far = endpoints[rows ^ 1]
        u = far - vertex
        wall_len = np.hypot(u[:, 0], u[:, 1])
        u = u / wall_len[:, None]
        a = np.degrees(np.arccos(np.clip(u[0] @ u[1], -1.0, 1.0)))
        if abs(a - 90.0) > CORNER_ANGLE_TOL_DEG:
            continue
        xy.append(vertex)
        angle.append(a)
        dirs.append(u)
        lengths.append(wall_len)
        kind.append(_corner_kind(seg[seg_ids], u[0] + u[1], vertex, name))

    corners = MapCorners(
        xy_m=np.array(xy, dtype=float).reshape(-1, 2),
        kind=np.array(kind, dtype="<U7"),
        angle_deg=np.array(angle, dtype=float),
        wall_dirs=np.array(dirs, dtype=float).reshape(-1, 2, 2),
        wall_lengths_m=np.array(lengths, dtype=float).reshape(-1, 2),
    )
    return corners, np.array(free, dtype=float).reshape(-1, 2)


def _snap(points: np.ndarray, tol_m: float) -> np.ndarray:
    """Cluster label per point; points within ``tol_m`` of a cluster's first point join it."""
    labels = np.full(len(points), -1)
    n = 0
    for i in range(len(points)):
        if labels[i] >= 0:
            continue
        near = (np.hypot(*(points - points[i]).T) <= tol_m) & (labels < 0)
        labels[near] = n
        n += 1
    return labels


def _corner_kind(two_segments: np.ndarray, bisector: np.ndarray, vertex: np.ndarray, name: str) -> str:
    d = two_segments[:, 2:] - two_segments[:, :2]
    free_normals = np.column_stack((-d[:, 1], d[:, 0]))
    side = free_normals @ bisector
    if np.all(side > 0):
        return "concave"
    if np.all(side < 0):
        return "convex"
    raise ConfigError(
        f"world {name!r}: the walls meeting at ({vertex[0]:.3f}, {vertex[1]:.3f}) disagree on which "
        "side is free space; orient segments with free space on their left"
    )
