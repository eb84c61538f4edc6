"""A 2-D pose graph (SE(2)) optimised by sparse Levenberg–Marquardt, robust on loop edges.

Symbols (inside this module only; public names are by role):

* node poses ``x_k = (x_m, y_m, theta_rad)`` in one world frame, shape (K, 3);
* an edge ``i -> j`` measures ``z = x_i ⊖ x_j`` (the pose of ``j`` in ``i``'s
  frame, ``lrfslam.algo.geometry.relative``) with information ``Ω`` (3, 3)
  (1/m², 1/(m·rad), 1/rad²);
* residual ``e = (R_zᵀ (R_iᵀ (t_j − t_i) − t_z), wrap(θ_j − θ_i − θ_z))`` and its
  squared Mahalanobis norm ``χ² = eᵀ Ω e``.

Design choices
--------------
* **Gauge.** The first node is held fixed: its three columns are dropped from the
  normal equations, so the solution is the unique one with that node where it
  was (any other gauge is a rigid motion of it, ``tests/unit/test_pose_graph.py``).
* **Sparse normal equations**, assembled from (E, 3, 3) Jacobian blocks with
  numpy and solved by ``scipy.sparse.linalg.splu``: a graph of thousands of
  keyframes solves in milliseconds; a chain plus a few loops stays banded.
* **Levenberg–Marquardt** with a diagonal damping ``λ diag(H)``: Gauss–Newton
  from a good initial guess converges in 2–3 steps, the damping only matters
  when a closure first pulls a long loop shut (tens of degrees of heading).
* **Robust loop edges.** Loop edges carry a Cauchy kernel
  ``ρ(χ²) = c² log(1 + χ²/c²)``, solved by iteratively reweighted least squares
  (weight ``1 / (1 + χ²/c²)``, recomputed each step, the step accepted on the
  robust cost). A wrong closure that disagrees with the rest of the graph ends
  with a small weight, which :meth:`PoseGraph.loop_weights` reports so the
  caller can remove it. Odometry edges are plain least squares: they are
  never outliers by construction (the chain they come from is continuous).
* **Relative covariance** (:meth:`PoseGraph.relative_covariance`): the
  covariance of node ``b`` seen from node ``a``, from the inverse of the
  normal equations linearised at the current estimate. The loop search asks
  for it for one or two candidates per new keyframe. The normal equations are
  factorised with the first node as the gauge and the factorisation kept until
  an estimate or a removal changes it (or ``_MAX_NEW_NODES`` nodes came since).
  What was added since, nodes and edges (the next keyframes, and the closures of a
  robot on its n-th round, one per keyframe), enters exactly but small: the
  factorisation gives the old graph's covariance of the old nodes the new edges
  touch, its inverse is their information, the new edges' information is added to
  it and that small dense matrix, old touched nodes plus new nodes, is inverted.
  The old graph's information about those nodes is all in their marginal, so this
  equals factorising everything again, which on a 3,000-keyframe graph with its
  revisits' closures takes ~80 ms (src/lrfslam/bench/mapper_growth.py). The
  factorisation leaves out the leaves (nodes with one edge: the mapper's folded
  revisits), whose edges say nothing about the rest of the graph. The relative pose's
  Jacobian carries the two nodes' joint covariance into ``a``'s frame: the
  relative pose does not depend on the gauge, so this equals holding ``a``
  fixed (``tests/unit/test_pose_graph.py``).

References
----------
G. Grisetti, R. Kümmerle, C. Stachniss, W. Burgard, "A tutorial on graph-based
SLAM", IEEE ITS Magazine 2(4), 2010. P. Agarwal, G. D. Tipaldi, L. Spinello,
C. Stachniss, W. Burgard, "Robust map optimization using dynamic covariance
scaling", ICRA 2013 (the same down-weighting idea as the kernel here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from lrfslam.algo.geometry import (
    compose,
    compose_with_covariance,
    inverse_with_covariance,
    relative,
    wrap_angle,
)
from lrfslam.errors import InputError

#: Levenberg–Marquardt steps at most in :meth:`PoseGraph.optimize`.
MAX_ITERATIONS = 10
#: ``c`` of the Cauchy kernel on loop edges, in units of the edge's Mahalanobis distance
#: (dimensionless): a loop edge with ``χ² = c²`` has half its weight.
CAUCHY_SCALE = 3.0
#: ``λ`` of the first step (dimensionless, relative to diag(H)).
INITIAL_DAMPING = 1e-4
#: The iteration stops once the largest step component is below ``CONVERGED_STEP`` (m and rad
#: alike), or a step lowered the cost by less than ``CONVERGED_COST`` of it.
CONVERGED_STEP = 1e-4
CONVERGED_COST = 1e-4


@dataclass(frozen=True)
class OptimizeReport:
    """What :meth:`PoseGraph.optimize` did.

    Attributes
    ----------
    iterations : int
        Steps tried (accepted or not).
    initial_cost, final_cost : float
        Robust cost ``½ Σ ρ(χ²)`` before and after (dimensionless).
    """

    iterations: int
    initial_cost: float
    final_cost: float


class PoseGraph:
    """Nodes (poses) and relative-pose edges; the poses are optimised in place (mutable).

    Attributes
    ----------
    poses : ndarray, shape (K, 3)
        Current estimate of every node, ``(x_m, y_m, theta_rad)``.
    """

    def __init__(self) -> None:
        self._poses = np.zeros((0, 3))
        self._n = 0
        # Edges in arrays grown by doubling (a list of small arrays costs ~4x the memory):
        # nodes (E, 2), measurement (E, 3), information (E, 3, 3), robust and alive (E,).
        self._m = 0
        self._nodes = np.zeros((0, 2), dtype=np.int64)
        self._z = np.zeros((0, 3))
        self._info = np.zeros((0, 3, 3))
        self._robust = np.zeros(0, dtype=bool)
        self._alive = np.zeros(0, dtype=bool)
        # For relative_covariance: the LU of the normal equations with node 0 as the gauge,
        # of the first ``covered`` nodes and the first ``edges`` edges (built when first
        # needed); dropped when an estimate changes or an edge is removed.
        self._factor: _Factor | None = None

    # -- building -------------------------------------------------------------------------------

    @property
    def poses(self) -> np.ndarray:
        return self._poses[: self._n]

    def __len__(self) -> int:
        return self._n

    def add_node(self, pose) -> int:
        """Append a node with initial estimate ``pose`` (3,); returns its index."""
        p = np.asarray(pose, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InputError(f"a node pose must be 3 finite numbers, got {pose!r}")
        if self._n == self._poses.shape[0]:
            grown = np.zeros((max(16, 2 * self._n), 3))
            grown[: self._n] = self._poses[: self._n]
            self._poses = grown
        self._poses[self._n] = p
        self._n += 1
        return self._n - 1

    def set_pose(self, node: int, pose) -> None:
        """Overwrite the estimate of ``node`` (3,), e.g. to re-seed a freshly added node."""
        self._poses[self._check_node(node)] = np.asarray(pose, dtype=float)
        self._factor = None

    def add_edge(self, i: int, j: int, measurement, information, robust: bool = False) -> int:
        """Add an edge measuring node ``j`` in node ``i``'s frame; returns its index.

        Parameters
        ----------
        i, j : int
            Node indices, different.
        measurement : array_like, shape (3,)
            ``(dx_m, dy_m, dtheta_rad)`` of ``j`` in ``i``'s frame.
        information : array_like, shape (3, 3)
            Inverse covariance, symmetric positive definite.
        robust : bool
            Put the Cauchy kernel on it (loop closures).
        """
        z, info = self._checked_edge(i, j, measurement, information)
        if self._m == self._z.shape[0]:
            size = max(16, 2 * self._m)
            self._nodes, self._z, self._info, self._robust, self._alive = (
                _grown(a, size) for a in (self._nodes, self._z, self._info, self._robust, self._alive))
        self._m += 1
        self._write_edge(self._m - 1, i, j, z, info, robust)
        return self._m - 1

    def set_edge(self, edge: int, i: int, j: int, measurement, information, robust: bool = False) -> None:
        """Replace edge ``edge`` (alive again if removed) by one between ``i`` and ``j``, as :meth:`add_edge`."""
        self._check_edge(edge)
        self._write_edge(edge, i, j, *self._checked_edge(i, j, measurement, information), robust)
        self._factor = None

    def _checked_edge(self, i: int, j: int, measurement, information) -> tuple[np.ndarray, np.ndarray]:
        self._check_node(i)
        self._check_node(j)
        z = np.asarray(measurement, dtype=float)
        info = np.asarray(information, dtype=float)
        if i == j or z.shape != (3,) or info.shape != (3, 3) or not (np.all(np.isfinite(z))
                                                                       and np.all(np.isfinite(info))):
            raise InputError("an edge needs two different nodes, a finite (3,) measurement and (3, 3) information")
        return z, info

    def _write_edge(self, m: int, i: int, j: int, z: np.ndarray, info: np.ndarray, robust: bool) -> None:
        self._nodes[m] = (i, j)
        self._z[m] = z
        self._info[m] = 0.5 * (info + info.T)
        self._robust[m] = bool(robust)
        self._alive[m] = True

    def remove_edge(self, edge: int) -> None:
        """Take an edge out of the problem (a closure found wrong); indices of the others stay."""
        self._alive[self._check_edge(edge)] = False
        self._factor = None

    def remove_nodes(self, nodes) -> tuple[np.ndarray, np.ndarray]:
        """Take ``nodes`` out with every edge that touches them, and drop the removed edges' rows.

        The graph is renumbered: the nodes and the edges in the problem keep their order.
        Returns the new index of every old node ((K,), −1: removed) and of every old edge
        ((E,), −1: removed, or removed before).

        Raises
        ------
        InputError
            If a node is not there, or is node 0 (the gauge).
        """
        gone = np.zeros(self._n, dtype=bool)
        for node in np.asarray(nodes, dtype=np.int64).reshape(-1).tolist():
            gone[self._check_node(node)] = True
        if gone[0] and self._n:
            raise InputError("node 0 holds the gauge: it cannot be removed")
        node_map = np.full(self._n, -1, dtype=np.int64)
        node_map[~gone] = np.arange(self._n - int(gone.sum()))
        ends = self._nodes[: self._m]
        kept = self._alive[: self._m] & ~(gone[ends[:, 0]] | gone[ends[:, 1]])
        edge_map = np.full(self._m, -1, dtype=np.int64)
        edge_map[kept] = np.arange(int(kept.sum()))
        self._poses = self.poses[~gone].copy()
        self._n = self._poses.shape[0]
        self._nodes = node_map[ends[kept]]
        self._z, self._info = self._z[: self._m][kept], self._info[: self._m][kept]
        self._robust, self._alive = self._robust[: self._m][kept], self._alive[: self._m][kept]
        self._m = self._nodes.shape[0]
        self._factor = None
        return node_map, edge_map

    def edges_of(self, node: int) -> np.ndarray:
        """Indices of the edges in the problem that touch ``node``, ascending, (D,)."""
        self._check_node(node)
        nodes = self._nodes[: self._m]
        return np.flatnonzero(self._alive[: self._m] & ((nodes[:, 0] == node) | (nodes[:, 1] == node)))

    def find_edge(self, i: int, j: int, robust: bool = False) -> int | None:
        """The first edge in the problem between ``i`` and ``j`` (either way round) of that kind, or None."""
        nodes = self._nodes[: self._m]
        found = np.flatnonzero(self._alive[: self._m] & (self._robust[: self._m] == robust)
                               & (((nodes[:, 0] == i) & (nodes[:, 1] == j)) | ((nodes[:, 0] == j) & (nodes[:, 1] == i))))
        return int(found[0]) if found.size else None

    def edge_information(self, edge: int) -> np.ndarray:
        """An edge's information (3, 3)."""
        return self._info[self._check_edge(edge)].copy()

    def edge_is_robust(self, edge: int) -> bool:
        """Whether an edge carries the Cauchy kernel (a loop closure)."""
        return bool(self._robust[self._check_edge(edge)])

    def edge_nodes(self, edge: int) -> tuple[int, int]:
        """The nodes ``(i, j)`` an edge joins."""
        i, j = self._nodes[self._check_edge(edge)]
        return int(i), int(j)

    def edge_measurement(self, edge: int) -> np.ndarray:
        """An edge's measurement (3,), node ``j`` in node ``i``'s frame."""
        return self._z[self._check_edge(edge)].copy()

    def edge_count(self) -> int:
        """Edges in the problem (removed ones not counted)."""
        return int(np.count_nonzero(self._alive[: self._m]))

    def fold(self, n: int, anchor_edge: int, weights: np.ndarray) -> list[int]:
        """Make node ``n`` a leaf on the node its robust edge ``anchor_edge`` comes from.

        ``n = k ⊕ z_L``: every other edge of ``n`` is re-expressed as an edge of ``k`` through
        ``z_L``, its covariance grown by the anchor's (``Σ_L / w``, its information as the last
        optimisation weighed it, ``weights`` (E,) as :meth:`loop_weights` gives), and merged with
        an edge already between the same nodes (:meth:`merge_measurement`). ``n`` keeps only
        ``anchor_edge``, so its pose follows ``k``'s. The anchor is set to where the optimisation
        put ``n``, not where the edge alone did: the optimum weighed it against the rest, and
        the re-expressed edges are to keep that optimum.

        Returns the edges that were ``n``'s other edges (now re-expressed, merged or removed).
        """
        k = self.edge_nodes(anchor_edge)[0]
        z_l = relative(self.poses[k], self.poses[n])
        info_l = self.edge_information(anchor_edge)
        self.set_edge(anchor_edge, k, n, z_l, info_l, robust=True)
        cov_l = np.linalg.inv(info_l) / max(float(weights[anchor_edge]), 1e-9)
        z_l_inv, cov_l_inv = inverse_with_covariance(z_l, cov_l)
        moved = [e for e in self.edges_of(n).tolist() if e != anchor_edge]
        for e in moved:
            i, j = self.edge_nodes(e)
            cov = np.linalg.inv(self.edge_information(e)) / max(float(weights[e]), 1e-9)
            if j == n:   # i -> n becomes i -> k
                a, b = i, k
                z, cov = compose_with_covariance(self.edge_measurement(e), cov, z_l_inv, cov_l_inv)
            else:        # n -> j becomes k -> j
                a, b = k, j
                z, cov = compose_with_covariance(z_l, cov_l, self.edge_measurement(e), cov)
            parallel = self.find_edge(a, b) if a != b else None
            if a == b or parallel is not None:
                self.remove_edge(e)
            if parallel is not None:
                self.merge_measurement(parallel, a, b, z, cov)
            elif a != b:
                self.set_edge(e, a, b, z, np.linalg.inv(cov))
        return moved

    def merge_measurement(self, edge: int, a: int, b: int, z: np.ndarray, cov: np.ndarray) -> None:
        """Fuse a measurement ``z`` (3,) of node ``b`` in node ``a``'s frame, covariance ``cov`` (3, 3),
        into ``edge`` (between the same two nodes, either way round).

        Information adds; the measurement moves from the edge's towards ``z`` by the new
        information's share, in the edge's own frame (the two differ by a correction, not a turn).
        """
        i, _ = self.edge_nodes(edge)
        if i != a:   # the edge runs b -> a
            z, cov = inverse_with_covariance(z, cov)
        old_z, old_info = self.edge_measurement(edge), self.edge_information(edge)
        info = np.linalg.inv(cov)
        fused_info = old_info + info
        step = np.linalg.solve(fused_info, info @ relative(old_z, z))
        self.set_edge(edge, *self.edge_nodes(edge), compose(old_z, step), fused_info)

    def snapshot(self) -> dict[str, np.ndarray]:
        """The graph as arrays (copies): ``graph_poses`` (K, 3); per edge, removed ones included so
        edge indices survive a restore, ``graph_edge_nodes`` (E, 2), ``graph_edge_measurement`` (E, 3),
        ``graph_edge_information`` (E, 3, 3), ``graph_edge_robust`` and ``graph_edge_alive`` (E,)."""
        return {
            "graph_poses": self.poses.copy(),
            "graph_edge_nodes": self._nodes[: self._m].copy(),
            "graph_edge_measurement": self._z[: self._m].copy(),
            "graph_edge_information": self._info[: self._m].copy(),
            "graph_edge_robust": self._robust[: self._m].copy(),
            "graph_edge_alive": self._alive[: self._m].copy(),
            # The nodes and edges the covariances' factorisation covers (0, 0: none), so a restored
            # graph computes them the same way to the last bit, as the graph it continues did.
            "graph_factor_extent": np.array([0, 0] if self._factor is None
                                            else [self._factor.covered, self._factor.edges], dtype=np.int64),
        }

    @classmethod
    def restore(cls, arrays) -> PoseGraph:
        """The graph :meth:`snapshot` gave ``arrays`` of (e.g. loaded from an ``.npz``).

        Raises
        ------
        InputError
            If the arrays are missing, of the wrong shapes, not finite, or name a node that is not there.
        """
        try:
            poses = np.array(arrays["graph_poses"], dtype=float)
            nodes = np.array(arrays["graph_edge_nodes"], dtype=np.int64)
            z = np.array(arrays["graph_edge_measurement"], dtype=float)
            info = np.array(arrays["graph_edge_information"], dtype=float)
            robust = np.array(arrays["graph_edge_robust"], dtype=bool)
            alive = np.array(arrays["graph_edge_alive"], dtype=bool)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"pose graph snapshot: {exc!r}") from None
        e = nodes.shape[0] if nodes.ndim == 2 else -1
        if poses.ndim != 2 or poses.shape[1:] != (3,) or nodes.shape != (e, 2) or z.shape != (e, 3) \
                or info.shape != (e, 3, 3) or robust.shape != (e,) or alive.shape != (e,):
            raise InputError("pose graph snapshot: arrays of inconsistent shapes")
        if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(z)) and np.all(np.isfinite(info))) \
                or np.any(nodes < 0) or np.any(nodes >= poses.shape[0]):
            raise InputError("pose graph snapshot: non-finite values or edges to missing nodes")
        graph = cls()
        graph._poses, graph._n = poses.copy(), poses.shape[0]
        graph._m = e
        graph._nodes, graph._z, graph._info, graph._robust, graph._alive = nodes, z, info, robust, alive
        # A snapshot written before the graph kept its factorisation's extent has none: factorised anew.
        if "graph_factor_extent" in arrays:
            covered, edges = (int(v) for v in np.array(arrays["graph_factor_extent"], dtype=np.int64).reshape(2))
            if covered:
                if not (2 <= covered <= graph._n and 0 < edges <= e):
                    raise InputError("pose graph snapshot: a factorisation of nodes or edges that are not there")
                graph._factor = _Factor(None, covered, edges)
        return graph

    def _check_edge(self, edge: int) -> int:
        if not 0 <= edge < self._m:
            raise InputError(f"no edge {edge} (graph has {self._m})")
        return edge

    def _check_node(self, node: int) -> int:
        if not 0 <= node < self._n:
            raise InputError(f"no node {node} (graph has {self._n})")
        return node

    # -- evaluation -----------------------------------------------------------------------------

    def _arrays(self):
        alive = np.flatnonzero(self._alive[: self._m])
        i, j = self._nodes[alive, 0], self._nodes[alive, 1]
        z, info, robust = self._z[alive], self._info[alive], self._robust[alive]
        return alive, i, j, z, info, robust

    @staticmethod
    def _residuals(poses, i, j, z, with_jacobians: bool):
        """Residuals (E, 3) and, if asked, their Jacobians (E, 3, 3) with respect to x_i and x_j."""
        xi, xj = poses[i], poses[j]
        ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
        cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
        dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
        # d = R_iᵀ (t_j − t_i): node j's position in node i's frame.
        d0, d1 = ci * dx + si * dy, -si * dx + ci * dy
        a0, a1 = d0 - z[:, 0], d1 - z[:, 1]
        e = np.column_stack((cz * a0 + sz * a1, -sz * a0 + cz * a1, wrap_angle(xj[:, 2] - xi[:, 2] - z[:, 2])))
        if not with_jacobians:
            return e, None, None
        n = len(i)
        rz_t = np.empty((n, 2, 2))
        rz_t[:, 0, 0], rz_t[:, 0, 1], rz_t[:, 1, 0], rz_t[:, 1, 1] = cz, sz, -sz, cz
        ri_t = np.empty((n, 2, 2))
        ri_t[:, 0, 0], ri_t[:, 0, 1], ri_t[:, 1, 0], ri_t[:, 1, 1] = ci, si, -si, ci
        # d(R_iᵀ)/dθ_i (t_j − t_i) = (d1, −d0).
        ddtheta = np.column_stack((d1, -d0))
        a = rz_t @ ri_t  # R_zᵀ R_iᵀ
        jac_i = np.zeros((n, 3, 3))
        jac_j = np.zeros((n, 3, 3))
        jac_i[:, :2, :2] = -a
        jac_i[:, :2, 2] = (rz_t @ ddtheta[:, :, None])[:, :, 0]
        jac_i[:, 2, 2] = -1.0
        jac_j[:, :2, :2] = a
        jac_j[:, 2, 2] = 1.0
        return e, jac_i, jac_j

    def _robust_terms(self, chi2: np.ndarray, robust: np.ndarray):
        """Per-edge robust cost ρ(χ²) and IRLS weight ρ'(χ²)."""
        c2 = CAUCHY_SCALE ** 2
        cost = np.where(robust, c2 * np.log1p(chi2 / c2), chi2)
        weight = np.where(robust, 1.0 / (1.0 + chi2 / c2), 1.0)
        return cost, weight

    def _cost(self, poses, i, j, z, info, robust) -> float:
        e, _, _ = self._residuals(poses, i, j, z, with_jacobians=False)
        chi2 = _mahalanobis2(e, info)
        return 0.5 * float(np.sum(self._robust_terms(chi2, robust)[0]))

    def chi2(self) -> np.ndarray:
        """``eᵀ Ω e`` of every edge at the current estimate, shape (edges added,); NaN for removed ones."""
        alive, i, j, z, info, _ = self._arrays()
        out = np.full(self._m, np.nan)
        if alive.size:
            e, _, _ = self._residuals(self.poses, i, j, z, with_jacobians=False)
            out[alive] = _mahalanobis2(e, info)
        return out

    def loop_weights(self) -> np.ndarray:
        """Cauchy weight in (0, 1] of every edge at the current estimate (1 for plain edges, NaN if removed)."""
        chi2 = self.chi2()
        robust = self._robust[: self._m]
        return np.where(np.isnan(chi2), np.nan, self._robust_terms(np.nan_to_num(chi2), robust)[1])

    # -- solving --------------------------------------------------------------------------------

    def _normal_equations(self, poses, i, j, z, info, robust, gauge: int, dropped: np.ndarray | None = None):
        """Sparse H and gradient b with node ``gauge`` eliminated, and with it the nodes ``dropped``
        ((K,) bool, None: none; their edges must not be among ``i, j``), K = len(poses); and each
        node's block in them (K,), −1 for those left out. H is 3(K−1) square without ``dropped``."""
        e, jac_i, jac_j = self._residuals(poses, i, j, z, with_jacobians=True)
        chi2 = _mahalanobis2(e, info)
        _, w = self._robust_terms(chi2, robust)
        winfo = info * w[:, None, None]
        # Stacked 3×3 products with matmul: einsum over three operands is several times slower here.
        jti_w = np.swapaxes(jac_i, 1, 2) @ winfo
        jtj_w = np.swapaxes(jac_j, 1, 2) @ winfo
        blocks = {(0, 0): jti_w @ jac_i, (0, 1): jti_w @ jac_j, (1, 0): jtj_w @ jac_i, (1, 1): jtj_w @ jac_j}
        grad_i = (jti_w @ e[:, :, None])[:, :, 0]
        grad_j = (jtj_w @ e[:, :, None])[:, :, 0]
        k = len(poses)
        # Map node -> reduced block index (the gauge node dropped, -1).
        kept = np.ones(k, dtype=bool) if dropped is None else ~dropped
        kept[gauge] = False
        reduced = np.full(k, -1)
        reduced[kept] = np.arange(np.count_nonzero(kept))
        ends = (reduced[i], reduced[j])
        rows, cols, vals = [], [], []
        off = np.arange(3)
        for (a, b), blk in blocks.items():
            ra, rb = ends[a], ends[b]
            keep = (ra >= 0) & (rb >= 0)
            r = (3 * ra[keep])[:, None, None] + off[None, :, None]
            c = (3 * rb[keep])[:, None, None] + off[None, None, :]
            rows.append(np.broadcast_to(r, blk[keep].shape).ravel())
            cols.append(np.broadcast_to(c, blk[keep].shape).ravel())
            vals.append(blk[keep].ravel())
        size = 3 * np.count_nonzero(kept)
        h = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(size, size)).tocsc()
        b = np.zeros(size)
        for rn, g in ((ends[0], grad_i), (ends[1], grad_j)):
            keep = rn >= 0
            np.add.at(b, ((3 * rn[keep])[:, None] + off).ravel(), g[keep].ravel())
        return h, b, reduced

    def optimize(self, robust: bool = True) -> OptimizeReport:
        """Levenberg–Marquardt on all nodes but the first; updates :attr:`poses`.

        With ``robust`` False the loop edges' kernel is off (plain least
        squares). The kernel needs a good start: a closure that moves a long
        loop by metres starts with a tiny weight and would stay an "outlier"
        however right it is, so a caller that trusts its closures solves
        without the kernel first and then with it.

        Raises
        ------
        InputError
            If a node other than the first is not reached by any edge (the
            problem is then singular).
        """
        _, i, j, z, info, robust_edges = self._arrays()
        robust_edges &= robust
        poses = self.poses.copy()
        if self._n < 2 or i.size == 0:
            return OptimizeReport(0, 0.0, 0.0)
        cost = self._cost(poses, i, j, z, info, robust_edges)
        initial = cost
        lam = INITIAL_DAMPING
        it = 0
        for it in range(1, MAX_ITERATIONS + 1):
            h, b, _ = self._normal_equations(poses, i, j, z, info, robust_edges, gauge=0)
            diag = h.diagonal()
            if np.any(diag <= 0):
                raise InputError("pose graph is not connected: a node has no edge")
            step = None
            previous = cost
            while lam < 1e8:
                damped = h + sp.diags(lam * diag, format="csc")
                dx = -_factorise(damped).solve(b)
                trial = poses.copy()
                trial[1:] += dx.reshape(-1, 3)
                trial[:, 2] = wrap_angle(trial[:, 2])
                trial_cost = self._cost(trial, i, j, z, info, robust_edges)
                if trial_cost <= cost:
                    step = dx
                    poses, cost = trial, trial_cost
                    lam = max(lam / 10.0, 1e-12)
                    break
                lam *= 10.0
            if step is None or np.max(np.abs(step)) < CONVERGED_STEP \
                    or previous - cost <= CONVERGED_COST * previous:
                break
        self._poses[: self._n] = poses
        self._factor = None
        return OptimizeReport(it, initial, cost)

    @property
    def factorised_through(self) -> int:
        """How many first nodes the covariances' factorisation was built over (0: none yet). Nodes
        added since enter :meth:`relative_covariance` exactly without a new factorisation, up to
        ``_MAX_NEW_NODES`` of them."""
        return 0 if self._factor is None else self._factor.covered

    @property
    def factorised_nodes(self) -> np.ndarray:
        """The nodes (K,) int that factorisation holds, ascending: the gauge (node 0) and leaves left out
        (a leaf adds a block and no fill; its covariance comes from its one edge). Empty before it is
        built (a restored graph builds it when first asked)."""
        if self._factor is None or self._factor.block is None:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self._factor.block >= 0)

    def relative_covariance(self, a: int, b: int) -> np.ndarray:
        """Covariance (3, 3) of node ``b``'s pose in node ``a``'s frame, at the current estimate.

        The uncertainty the graph leaves between the two (m², m·rad, rad²), loop-edge
        weights included: as if node ``a`` were held fixed.
        """
        self._check_node(a)
        self._check_node(b)
        if a == b:
            return np.zeros((3, 3))
        joint = self._joint_covariance(a, b)
        # Jacobian of relative(x_a, x_b) = (R_aᵀ (t_b − t_a), θ_b − θ_a) with respect to (x_a, x_b).
        xa, xb = self.poses[a], self.poses[b]
        c, s = np.cos(xa[2]), np.sin(xa[2])
        dx, dy = xb[0] - xa[0], xb[1] - xa[1]
        d0, d1 = c * dx + s * dy, -s * dx + c * dy
        jac = np.array([[-c, -s, d1, c, s, 0.0],
                        [s, -c, -d0, -s, c, 0.0],
                        [0.0, 0.0, -1.0, 0.0, 0.0, 1.0]])
        cov = jac @ joint @ jac.T
        return 0.5 * (cov + cov.T)

    def _factorised(self, covered: int, edges: int, drop_leaves: bool) -> _Factor:
        """The factorisation of the first ``covered`` nodes' and ``edges`` edges' normal equations.

        With ``drop_leaves``, without the nodes with a single edge (a folded revisit of
        lrfslam/algo/loop_closure/) and their edges: a leaf's edge fixes the leaf and tells the
        rest of the graph nothing (its Schur complement is zero), so the other nodes' covariance
        is the same, and the factorisation is the size of the graph without its leaves.
        """
        alive = np.flatnonzero(self._alive[:edges])
        i, j = self._nodes[alive, 0], self._nodes[alive, 1]
        dropped = None
        if drop_leaves:
            degree = np.bincount(i, minlength=covered) + np.bincount(j, minlength=covered)
            dropped = degree == 1
            # The gauge is left out anyway; the newest node is the end of the chain, which the
            # next node's edge will touch, not a leaf to stay one.
            dropped[[0, covered - 1]] = False
            alive = alive[~(dropped[i] | dropped[j])]
        h, _, block = self._normal_equations(self.poses[:covered], self._nodes[alive, 0], self._nodes[alive, 1],
                                             self._z[alive], self._info[alive], self._robust[alive], gauge=0,
                                             dropped=dropped)
        return _Factor(_factorise(h), covered, edges, block)

    def _joint_covariance(self, a: int, b: int) -> np.ndarray:
        """Covariance (6, 6) of nodes ``a`` and ``b`` (world frame) with the first node held fixed.

        Old nodes (those the cached factorisation covers) the new edges touch, and ``a`` and ``b``
        if old, are ``S``; the nodes added since are ``N``. The factorisation gives the old graph's
        covariance of ``S`` (the rows of ``H⁻¹``), its inverse is all the old graph says about
        ``S``; with the new edges' ``JᵀΩJ`` added (robust weights as in the optimisation) the
        information of ``S ∪ N`` is exact, and small enough to invert densely.
        """
        factor = self._factor
        if factor is None or self._n - factor.covered > _MAX_NEW_NODES:
            factor = _Factor(None, self._n, self._m)
        if factor.lu is None:
            factor = self._factorised(factor.covered, factor.edges, drop_leaves=True)
        new = factor.edges + np.flatnonzero(self._alive[factor.edges: self._m])
        i, j = self._nodes[new, 0], self._nodes[new, 1]
        ends = np.concatenate((i, j, [a, b]))
        old = np.unique(ends[(ends > 0) & (ends < factor.covered)])   # node 0, the gauge, has no variance
        if np.any(factor.block[old] < 0):   # a leaf left out is asked for, or has an edge since: all of it
            factor = self._factorised(factor.covered, factor.edges, drop_leaves=False)
        self._factor = factor
        covered = factor.covered
        nodes = np.concatenate((old, np.arange(covered, self._n)))
        index = np.full(self._n, -1)
        index[nodes] = np.arange(nodes.size)
        size = 3 * nodes.size
        # The information of S ∪ N is a dense block for S and a sparse chain of 3×3 blocks for N:
        # a sparse factorisation solves for a's and b's columns in time linear in |N|, where a
        # dense inverse of up to 3 × 200 unknowns cost milliseconds per search window.
        rows, cols, vals = [], [], []
        if old.size:
            block_rows = (3 * factor.block[old][:, None] + np.arange(3)).ravel()
            rhs = np.zeros((factor.lu.shape[0], block_rows.size))
            rhs[block_rows, np.arange(block_rows.size)] = 1.0
            old_cov = factor.lu.solve(rhs)[block_rows]
            dense = np.linalg.inv(0.5 * (old_cov + old_cov.T))
            k = np.arange(3 * old.size)
            rows.append(np.repeat(k, k.size))
            cols.append(np.tile(k, k.size))
            vals.append(dense.ravel())
        if new.size:
            e, jac_i, jac_j = self._residuals(self.poses, i, j, self._z[new], with_jacobians=True)
            _, w = self._robust_terms(_mahalanobis2(e, self._info[new]), self._robust[new])
            winfo = self._info[new] * w[:, None, None]
            three = np.arange(3)
            for r_nodes, jac_r in ((i, jac_i), (j, jac_j)):
                for c_nodes, jac_c in ((i, jac_i), (j, jac_j)):
                    blocks = np.swapaxes(jac_r, 1, 2) @ winfo @ jac_c
                    rn, cn = index[r_nodes], index[c_nodes]
                    keep = (rn >= 0) & (cn >= 0)
                    r = 3 * rn[keep, None, None] + three[None, :, None]
                    c = 3 * cn[keep, None, None] + three[None, None, :]
                    rows.append(np.broadcast_to(r, blocks[keep].shape).ravel())
                    cols.append(np.broadcast_to(c, blocks[keep].shape).ravel())
                    vals.append(blocks[keep].ravel())
        info = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(size, size)).tocsc()   # repeated entries summed
        wanted = [k for k in (a, b) if k > 0]
        want_rows = (3 * index[wanted][:, None] + np.arange(3)).ravel()
        unit = np.zeros((size, want_rows.size))
        unit[want_rows, np.arange(want_rows.size)] = 1.0
        try:
            cov = _factorise(info).solve(unit)[want_rows]
        except RuntimeError:   # SuperLU: "Factor is exactly singular"
            raise InputError("pose graph is not connected: a node added since has no edge") from None
        if not np.all(np.isfinite(cov)):
            raise InputError("pose graph is not connected: a node added since has no edge")
        joint = np.zeros((6, 6))
        at = {k: 3 * n for n, k in enumerate(wanted)}
        for x, kx in enumerate((a, b)):
            for y, ky in enumerate((a, b)):
                if kx > 0 and ky > 0:
                    joint[3 * x: 3 * x + 3, 3 * y: 3 * y + 3] = cov[at[kx]: at[kx] + 3, at[ky]: at[ky] + 3]
        return 0.5 * (joint + joint.T)


@dataclass(frozen=True)
class _Factor:
    """The LU (None: not built yet) of the normal equations of the first ``covered`` nodes and ``edges``
    edges, and each node's block of rows in it ((covered,), −1: the gauge or a leaf left out)."""

    lu: object
    covered: int
    edges: int
    block: np.ndarray | None = None


#: Nodes added since the covariances' factorisation before it is built again: the dense
#: matrix of the nodes since grows with their square (3 × 200 unknowns: ~1 ms to invert).
_MAX_NEW_NODES = 200


def _grown(a: np.ndarray, rows: int) -> np.ndarray:
    """``a`` with room for ``rows`` rows, the first ``len(a)`` kept."""
    out = np.zeros((rows, *a.shape[1:]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


def _mahalanobis2(e: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``eᵀ Ω e`` per row: residuals (E, 3), information (E, 3, 3); shape (E,)."""
    return np.sum((info @ e[:, :, None])[:, :, 0] * e, axis=1)


def _factorise(h: sp.csc_matrix):
    """Sparse LU of the symmetric normal equations.

    The minimum-degree ordering of ``Hᵀ + H`` with symmetric pivoting halves the
    fill-in of the default column ordering on a chain with loops (4 ms instead
    of 13 ms for 1,400 nodes).
    """
    return splu(h, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
