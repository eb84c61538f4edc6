"""The live occupancy grid rebuilt from ``map/grid`` messages, as a viewer or a recording's reader keeps it.

The mapper publishes the tiles that changed; a replica keeps the newest of each tile and starts
again from a whole message (a late joiner's reply, or the first after the resolution changed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.msgs import types as t

#: nav_msgs/OccupancyGrid's unknown.
UNKNOWN = -1


@dataclass(frozen=True, eq=False)
class GridImage:
    """The grid as one array.

    Attributes
    ----------
    cells : ndarray of int8, shape (H, W)
        100 occupied, 0 free, -1 unknown; row 0 is the lowest y (as nav_msgs/OccupancyGrid).
    resolution_m : float
        Side of a cell, metres.
    origin_xy_m : ndarray, shape (2,)
        Map position of the lower-left corner of cell [0, 0], metres.
    """

    cells: np.ndarray
    resolution_m: float
    origin_xy_m: np.ndarray


class GridReplica:
    """The tiles of one robot's live grid, kept from its ``map/grid`` messages."""

    def __init__(self) -> None:
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.resolution_m = 0.0
        self.tile_cells = 0
        self.stamp_ns = 0
        self.keyframes = 0
        self.pending = 0

    def apply(self, msg: t.MapGrid) -> list[tuple[int, int]]:
        """Take one message; returns the tiles it changed (all of them after a whole one)."""
        if msg.whole or msg.resolution_m != self.resolution_m or msg.tile_cells != self.tile_cells:
            self.tiles.clear()
        self.resolution_m, self.tile_cells = float(msg.resolution_m), int(msg.tile_cells)
        self.stamp_ns, self.keyframes, self.pending = msg.stamp_ns, msg.keyframes, msg.pending
        changed = [(int(r), int(c)) for r, c in msg.tiles.tolist()]
        for tile, cells in zip(changed, msg.cells):
            self.tiles[tile] = cells
        return changed

    def frame(self) -> tuple[np.ndarray, tuple[int, int]] | None:
        """The lower-left corner (2,) m and the (H, W) cells of the tiles' bounding box; None before the first tile."""
        if not self.tiles:
            return None
        keys = np.array(list(self.tiles))
        (r0, c0), (r1, c1) = keys.min(axis=0), keys.max(axis=0)
        side = self.tile_cells
        return np.array([c0, r0], float) * side * self.resolution_m, ((r1 - r0 + 1) * side, (c1 - c0 + 1) * side)

    def image(self) -> GridImage | None:
        """Every tile in one array over their bounding box (:meth:`frame`); None before the first tile."""
        frame = self.frame()
        if frame is None:
            return None
        origin, shape = frame
        side = self.tile_cells
        r0, c0 = np.round(origin[::-1] / (side * self.resolution_m)).astype(int)
        out = np.full(shape, UNKNOWN, np.int8)
        for (r, c), cells in self.tiles.items():
            out[(r - r0) * side:(r - r0 + 1) * side, (c - c0) * side:(c - c0 + 1) * side] = cells
        return GridImage(out, self.resolution_m, origin)
