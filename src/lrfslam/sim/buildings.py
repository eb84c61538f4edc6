"""Large worlds that break a filter tuned on the hallway loop: a big building, twin corridors, a campus.

``large_building`` is what the ACES log is: long corridors round loops of tens of
metres, few corners, the same door-and-alcove pattern on every face, glass, clutter
and people. ``twin_corridors`` holds two identical corridors far apart, so a scan in
one is a perfect match for the same place in the other: a loop closure on looks
alone is wrong there. ``campus`` is what MIT Killian Court is: a ring of corridors round an open
courtyard and a long wing, every corridor lined with the same doors every 6 m, a crossing of the
courtyard where the scanner sees nothing but a few pillars, and a lap of 560 m whose first
revisit comes after 370 m.

Walls are Manhattan and corridors 2 m wide, as the paper assumes. Faces are written
as outlines with features cut into the solid side (:func:`outline`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.errors import ConfigError
from lrfslam.sim.people import body_segments
from lrfslam.sim.world import World


@dataclass(frozen=True)
class Feature:
    """A feature cut into one face of an outline.

    Attributes
    ----------
    kind : {"recess", "room", "window"}
        ``"recess"``: a door recess or alcove; ``"room"``: a recess whose mouth is a
        glass front, so the scanner sees into it; ``"window"``: a stretch of the face
        that is glass (an outside window: beams leave the building, no return).
    s_m : float
        Start of the feature along the face, metres from the face's first vertex.
    width_m : float
        Extent along the face, metres.
    depth_m : float
        How far the recess goes into the solid, metres (0 for a window).
    """

    kind: str
    s_m: float
    width_m: float
    depth_m: float = 0.0


def recess(s_m: float, width_m: float, depth_m: float) -> Feature:
    """A door recess (0.3-0.5 m deep) or an alcove (1.3 m deep or more)."""
    return Feature("recess", s_m, width_m, depth_m)


def outline(vertices_m, faces) -> tuple[np.ndarray, np.ndarray]:
    """Segments and materials of a closed Manhattan outline with features cut into its faces.

    Parameters
    ----------
    vertices_m : array_like, shape (P, 2)
        Outline corners in the order that puts free space on the left of each face:
        counter-clockwise for a room or corridor boundary, clockwise for a solid block.
        Features are cut into the right-hand (solid) side.
    faces : sequence of sequence of Feature, length P
        Features of face k (from vertex k to vertex k + 1), in increasing ``s_m``.

    Returns
    -------
    segments : ndarray, shape (M, 4)
        Metres, free space on the left.
    material : ndarray of str, shape (M,)
        ``"wall"`` or ``"glass"``; a room's glass front is an extra segment.
    """
    v = np.asarray(vertices_m, dtype=float)
    if len(faces) != len(v):
        raise ConfigError(f"outline: {len(v)} faces need {len(v)} feature lists, got {len(faces)}")
    points: list[np.ndarray] = []
    edge_material: list[str] = []
    fronts: list[np.ndarray] = []
    for k, features in enumerate(faces):
        p, q = v[k], v[(k + 1) % len(v)]
        length = float(np.hypot(*(q - p)))
        u = (q - p) / length
        into = np.array([u[1], -u[0]])  # right of travel: the solid side
        points.append(p)
        edge_material.append("wall")
        end_of_last = 0.0
        for f in features:
            if f.s_m <= end_of_last or f.s_m + f.width_m >= length:
                raise ConfigError(f"outline: feature {f} overlaps another or the end of a {length:g} m face")
            a, b = p + f.s_m * u, p + (f.s_m + f.width_m) * u
            if f.kind == "window":
                points += [a, b]
                edge_material += ["glass", "wall"]
            elif f.kind in ("recess", "room"):
                points += [a, a + f.depth_m * into, b + f.depth_m * into, b]
                edge_material += ["wall"] * 4
                if f.kind == "room":
                    fronts.append(np.concatenate((b, a)))
            else:
                raise ConfigError(f"outline: unknown feature kind {f.kind!r}")
            end_of_last = f.s_m + f.width_m
    pts = np.array(points)
    segments = np.hstack((pts, np.roll(pts, -1, axis=0)))
    material = np.array(edge_material, dtype="<U7")
    if fronts:
        segments = np.vstack((segments, fronts))
        material = np.concatenate((material, np.full(len(fronts), "glass")))
    return segments, material


def box(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """An axis-aligned solid box (a crate, a cabinet) as four segments, metres."""
    return np.array([[x0, y0, x0, y1], [x0, y1, x1, y1], [x1, y1, x1, y0], [x1, y0, x0, y0]], dtype=float)


def _assemble(name: str, parts, clutter) -> World:
    segments = np.vstack([s for s, _ in parts] + list(clutter))
    material = np.concatenate([m for _, m in parts] + [np.full(len(c), "clutter") for c in clutter])
    return World(segments_m=segments, name=name, material=material)


# --- large_building ------------------------------------------------------------------------
# Corridor centrelines form a 48 m x 30 m rectangle split by a middle corridor at x = 24,
# so the building has two loops. Corridors are 2 m wide; the two blocks are 22 m x 28 m.

# The same pattern on every block face, symmetric about the face's middle, so it reads
# the same from either direction: two door recesses each side of a 2 m x 1.4 m alcove.
_BLOCK_H = (recess(2.0, 0.9, 0.4), recess(6.0, 0.9, 0.4), recess(10.0, 2.0, 1.4),
            recess(15.1, 0.9, 0.4), recess(19.1, 0.9, 0.4))
_BLOCK_V = (recess(3.0, 0.9, 0.4), recess(9.0, 0.9, 0.4), recess(13.0, 2.0, 1.4),
            recess(18.1, 0.9, 0.4), recess(24.1, 0.9, 0.4))
# A meeting room 6 m x 4 m behind a glass front, on the right block's bottom face.
_BLOCK_H_GLASS_ROOM = (recess(2.0, 0.9, 0.4), Feature("room", 8.0, 6.0, 4.0), recess(19.1, 0.9, 0.4))

# Outer walls, counter-clockwise from the bottom-left corner: sparse stair landings and
# doors, and outside windows (glass, no return) along the top.
_OUTER_BOTTOM = (recess(6.0, 0.9, 0.4), recess(15.0, 2.0, 1.4), recess(30.0, 0.9, 0.4), recess(40.0, 2.0, 1.4))
_OUTER_RIGHT = (recess(7.0, 0.9, 0.4), recess(15.0, 2.0, 1.4), recess(25.0, 0.9, 0.4))
_OUTER_TOP = (Feature("window", 5.0, 6.0), Feature("window", 16.0, 6.0), recess(27.0, 0.9, 0.4),
              recess(35.0, 2.0, 1.4), recess(44.0, 0.9, 0.4))
_OUTER_LEFT = (recess(6.0, 0.9, 0.4), recess(16.0, 2.0, 1.4), recess(26.0, 0.9, 0.4))

# Outer loop (156 m) from mid-bottom, then the left loop through the middle corridor (106 m).
_LARGE_PATH = ((10.0, 0.0), (48.0, 0.0), (48.0, 30.0), (0.0, 30.0), (0.0, 0.0),
               (24.0, 0.0), (24.0, 30.0), (0.0, 30.0), (0.0, 0.0))

# People pace the block side of each corridor, 0.5 m off the robot's path, clear of the
# junctions; the clutter stands against the outer walls on the other side.
_LARGE_LANES = (
    (3.0, 0.5, 21.0, 0.5), (27.0, 0.5, 45.0, 0.5),
    (3.0, 29.5, 21.0, 29.5), (27.0, 29.5, 45.0, 29.5),
    (0.5, 3.0, 0.5, 27.0), (47.5, 3.0, 47.5, 27.0), (24.5, 3.0, 24.5, 27.0),
)


def large_building() -> World:
    """A 50 m x 32 m floor with two corridor loops, glass, and clutter along the outer walls.

    Returns
    -------
    World
        Walls, glass (two outside windows on the top wall, the front of a meeting
        room off the bottom corridor) and clutter (three boxes, a bin and a pillar).
    """
    outer = outline([(-1.0, -1.0), (49.0, -1.0), (49.0, 31.0), (-1.0, 31.0)],
                    [_OUTER_BOTTOM, _OUTER_RIGHT, _OUTER_TOP, _OUTER_LEFT])
    # Blocks clockwise (solid inside): left face up, top face east, right face down, bottom face west.
    left = outline([(1.0, 1.0), (1.0, 29.0), (23.0, 29.0), (23.0, 1.0)], [_BLOCK_V, _BLOCK_H, _BLOCK_V, _BLOCK_H])
    right = outline([(25.0, 1.0), (25.0, 29.0), (47.0, 29.0), (47.0, 1.0)],
                    [_BLOCK_V, _BLOCK_H, _BLOCK_V, _BLOCK_H_GLASS_ROOM])
    clutter = (
        box(20.0, -1.0, 20.6, -0.6),
        body_segments([(33.0, -0.75)], 0.2),
        box(48.6, 9.0, 49.0, 9.5),
        body_segments([(8.0, 30.7)], 0.25),
        box(-1.0, 8.0, -0.6, 8.8),
    )
    return _assemble("large_building", (outer, left, right), clutter)


def large_building_path() -> np.ndarray:
    """Waypoints of one lap of :func:`large_building`: the outer loop, then the left loop.

    Returns
    -------
    ndarray, shape (9, 2)
        Metres; the loop closes from the last back to the first. About 261 m with
        0.8 m corner arcs; the first revisit (of the start) comes after the 156 m outer loop.
    """
    return np.array(_LARGE_PATH, dtype=float)


def large_building_lanes() -> np.ndarray:
    """Lanes people pace in :func:`large_building`; shape (7, 4), metres."""
    return np.array(_LARGE_LANES, dtype=float)


# --- twin_corridors ------------------------------------------------------------------------
# A 60 m x 10 m corridor loop round one block. The bottom corridor holds two identical
# 18 m stretches, A at x in [6, 24] and B at x in [36, 54] (B = A moved 30 m east), joined by
# a 12 m link longer than the scanner's 8 m reach, so the scanner never sees both at once.
TWIN_A_X_M = (6.0, 24.0)
TWIN_SHIFT_M = 30.0


def _twin(x0: float) -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float]]]:
    """Outer-wall and block-face features (x_start, width, depth) of a twin stretch starting at x0."""
    outer = [(x0 + 2.0, 2.0, 1.4), (x0 + 8.0, 0.9, 0.4), (x0 + 13.0, 2.0, 1.4)]
    block = [(x0 + 4.5, 0.9, 0.4), (x0 + 9.0, 2.0, 1.4), (x0 + 15.0, 0.9, 0.4)]
    return outer, block


def twin_corridors() -> World:
    """Two identical corridor stretches 30 m apart on one loop, the rest of the loop unlike them.

    Returns
    -------
    World
        Walls only (no glass, clutter or people): the aliasing is the whole test.
    """
    (a_out, a_blk), (b_out, b_blk) = _twin(TWIN_A_X_M[0]), _twin(TWIN_A_X_M[0] + TWIN_SHIFT_M)
    link_out, link_blk = [(28.0, 3.0, 1.3)], [(31.0, 0.9, 0.4)]
    # Outer bottom wall runs east from x = -1; the block's bottom face runs west from x = 59.
    bottom = tuple(recess(x + 1.0, w, d) for x, w, d in sorted(a_out + link_out + b_out))
    block_bottom = tuple(recess(59.0 - (x + w), w, d) for x, w, d in sorted(a_blk + link_blk + b_blk, reverse=True))
    outer = outline(
        [(-1.0, -1.0), (61.0, -1.0), (61.0, 11.0), (-1.0, 11.0)],
        [bottom, (recess(4.0, 2.0, 1.4),),
         # top wall runs west from x = 61: landings and doors at irregular spacing
         (recess(8.0, 0.9, 0.4), recess(16.0, 3.0, 1.4), recess(34.0, 0.9, 0.4), recess(48.0, 2.0, 1.3)),
         (recess(5.0, 0.9, 0.4),)],
    )
    block = outline(
        [(1.0, 1.0), (1.0, 9.0), (59.0, 9.0), (59.0, 1.0)],
        [(), (recess(6.0, 2.5, 1.4), recess(19.0, 0.9, 0.4), recess(32.0, 2.0, 1.4), recess(46.0, 0.9, 0.4)),
         (), block_bottom],
    )
    return _assemble("twin_corridors", (outer, block), ())


def twin_corridors_path() -> np.ndarray:
    """Waypoints of one lap of :func:`twin_corridors` (about 140 m), driving east through A then B.

    Returns
    -------
    ndarray, shape (5, 2)
        Metres, counter-clockwise.
    """
    return np.array(((3.0, 0.0), (60.0, 0.0), (60.0, 10.0), (0.0, 10.0), (0.0, 0.0)), dtype=float)


# --- campus ---------------------------------------------------------------------------------
# Corridor centrelines: a ring round the courtyard, x in [0, 80], y in [0, 50], and a wing loop,
# x in [80, 140], y in [0, 12], off its east side. The courtyard (x in [1, 79], y in [1, 49]) is
# open ground behind glass, with doorways at x = 40 on its bottom and top sides.
CAMPUS_DOOR_PERIOD_M = 6.0


def alike(length_m: float, *odd: Feature, period_m: float = CAMPUS_DOOR_PERIOD_M) -> tuple[Feature, ...]:
    """A face lined with the same door recess (0.9 m x 0.4 m) every ``period_m`` (m), and the
    ``odd`` features (an alcove, a window) in place of the doors they would overlap.

    Parameters
    ----------
    length_m : float
        The face's length (m).
    odd : Feature
        Features that break the pattern; doors within 0.5 m of one are left out.
    """
    doors = []
    for s in np.arange(period_m / 2, length_m - 1.4, period_m):
        door = recess(float(s), 0.9, 0.4)
        if all(door.s_m + door.width_m + 0.5 <= f.s_m or f.s_m + f.width_m + 0.5 <= door.s_m for f in odd):
            doors.append(door)
    return tuple(sorted(doors + list(odd), key=lambda f: f.s_m))


def _glazed(length_m: float, doorway_s_m: float | None = None) -> tuple[Feature, ...]:
    """A courtyard face: 3 m windows every 6 m, and a 2 m doorway (glass to the scanner) at ``doorway_s_m``."""
    doorway = () if doorway_s_m is None else (Feature("window", doorway_s_m, 2.0),)
    windows = [Feature("window", float(s), 3.0) for s in np.arange(1.5, length_m - 3.5, CAMPUS_DOOR_PERIOD_M)]
    keep = [w for w in windows if all(w.s_m + w.width_m + 0.5 <= d.s_m or d.s_m + d.width_m + 0.5 <= w.s_m
                                      for d in doorway)]
    return tuple(sorted(keep + list(doorway), key=lambda f: f.s_m))


def campus() -> World:
    """A 142 m x 52 m campus: a corridor ring round an open courtyard, and a wing loop.

    Returns
    -------
    World
        Walls lined with the same doors every 6 m (a few alcoves break the pattern), the
        courtyard behind glass, and three pillars in the courtyard along its crossing.
    """
    alcove = (lambda s: recess(s, 2.0, 1.4))
    # Outer wall counter-clockwise from the bottom-left corner (free space on the left).
    outer = outline([(-1.0, -1.0), (141.0, -1.0), (141.0, 13.0), (81.0, 13.0), (81.0, 51.0), (-1.0, 51.0)],
                    [alike(142.0, alcove(23.0), alcove(97.0)), alike(14.0), alike(60.0, alcove(34.0)),
                     alike(38.0), alike(82.0, alcove(57.0)), alike(52.0)])
    # The courtyard's glass, clockwise (the courtyard is on the right of each face).
    courtyard = outline([(1.0, 1.0), (1.0, 49.0), (79.0, 49.0), (79.0, 1.0)],
                        [_glazed(48.0), _glazed(78.0, doorway_s_m=38.0), _glazed(48.0), _glazed(78.0, doorway_s_m=38.0)])
    wing = outline([(81.0, 1.0), (81.0, 11.0), (139.0, 11.0), (139.0, 1.0)],
                   [alike(10.0), alike(58.0), alike(10.0), alike(58.0)])
    pillars = (box(37.7, 12.0, 38.3, 12.6), box(41.7, 24.7, 42.3, 25.3), box(37.7, 37.4, 38.3, 38.0))
    return _assemble("campus", (outer, courtyard, wing), pillars)


def campus_path() -> np.ndarray:
    """Waypoints of one lap of :func:`campus` (560 m): east through the ring and round the wing,
    the ring's top and west corridors, across the courtyard, and round the ring's west half again.

    Returns
    -------
    ndarray, shape (11, 2)
        Metres; the loop closes from the last back to the first. The first revisit (of the
        start's corridor) comes after 370 m.
    """
    return np.array(((10.0, 0.0), (140.0, 0.0), (140.0, 12.0), (80.0, 12.0), (80.0, 50.0), (0.0, 50.0),
                     (0.0, 0.0), (40.0, 0.0), (40.0, 50.0), (0.0, 50.0), (0.0, 0.0)), dtype=float)
