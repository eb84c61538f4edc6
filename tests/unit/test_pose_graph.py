"""Pose graph: a noisy loop is recovered, the gauge does not matter, an outlier closure is down-weighted."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import compose, relative, wrap_angle
from lrfslam.algo.pose_graph import PoseGraph
from lrfslam.errors import InputError

SIGMA = np.array([0.02, 0.02, 0.01])  # odometry noise per edge (m, m, rad)


def square_loop(laps: int = 1, side: int = 10, step_m: float = 0.5) -> np.ndarray:
    """True poses (K, 3) driving round a square, ``side`` steps a side."""
    poses = [np.zeros(3)]
    for _ in range(laps):
        for _ in range(4):
            for k in range(side):
                turn = np.pi / 2 if k == side - 1 else 0.0
                poses.append(compose(poses[-1], (step_m, 0.0, turn)))
    return np.array(poses)


def noisy_graph(truth: np.ndarray, rng: np.random.Generator, loops: list[tuple[int, int]]) -> PoseGraph:
    graph = PoseGraph()
    info = np.diag(1.0 / SIGMA**2)
    pose = truth[0].copy()
    graph.add_node(pose)
    for k in range(1, len(truth)):
        z = relative(truth[k - 1], truth[k]) + rng.normal(0.0, SIGMA)
        pose = compose(pose, z)
        graph.add_node(pose)
        graph.add_edge(k - 1, k, z, info)
    for a, b in loops:
        z = relative(truth[a], truth[b]) + rng.normal(0.0, SIGMA / 2)
        graph.add_edge(a, b, z, np.diag(4.0 / SIGMA**2), robust=True)
    return graph


def position_error(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Distance of each pose from the truth after aligning the first poses (m), shape (K,)."""
    aligned = np.array([compose(truth[0], relative(poses[0], p)) for p in poses])
    return np.hypot(*(aligned[:, :2] - truth[:, :2]).T)


def test_noisy_loop_is_recovered():
    rng = np.random.default_rng(1)
    truth = square_loop(laps=2)
    n = len(truth)
    loops = [(k, k + 40) for k in range(0, n - 40, 3)]
    graph = noisy_graph(truth, rng, loops)
    before = position_error(graph.poses, truth)
    report = graph.optimize()
    after = position_error(graph.poses, truth)
    assert report.final_cost < report.initial_cost
    assert before.max() > 0.3  # the chain alone drifts
    assert after.max() < 0.1
    # The χ² of a consistent graph is about its degrees of freedom.
    chi2 = graph.chi2()
    dof = 3 * graph.edge_count() - 3 * (n - 1)
    assert 0.5 * dof < chi2.sum() < 2.0 * dof


@settings(max_examples=10, deadline=None)
@given(st.floats(-20, 20), st.floats(-20, 20), st.floats(-np.pi, np.pi))
def test_solution_is_invariant_to_the_gauge(tx, ty, th):
    rng = np.random.default_rng(2)
    truth = square_loop()
    loops = [(0, len(truth) - 1), (5, 35)]
    plain = noisy_graph(truth, np.random.default_rng(2), loops)
    plain.optimize()
    moved = noisy_graph(truth, rng, loops)
    offset = np.array([tx, ty, th])
    for k, p in enumerate(moved.poses.copy()):
        moved.set_pose(k, compose(offset, p))
    moved.optimize()
    back = np.array([relative(offset, p) for p in moved.poses])
    assert np.allclose(back[:, :2], plain.poses[:, :2], atol=1e-6)
    assert np.allclose(wrap_angle(back[:, 2] - plain.poses[:, 2]), 0.0, atol=1e-8)


def test_outlier_loop_edge_is_down_weighted():
    rng = np.random.default_rng(3)
    truth = square_loop()
    n = len(truth)
    graph = noisy_graph(truth, rng, [])
    good = [graph.add_edge(0, n - 1, relative(truth[0], truth[n - 1]), np.diag(4.0 / SIGMA**2), robust=True),
            graph.add_edge(2, n - 3, relative(truth[2], truth[n - 3]), np.diag(4.0 / SIGMA**2), robust=True)]
    # A closure 3 m and 60° wrong, as sure of itself as the good ones.
    wrong = compose(relative(truth[10], truth[30]), (3.0, 0.0, 1.0))
    bad = graph.add_edge(10, 30, wrong, np.diag(4.0 / SIGMA**2), robust=True)
    graph.optimize()
    w = graph.loop_weights()
    assert w[bad] < 0.01
    assert all(w[g] > 0.5 for g in good)
    assert position_error(graph.poses, truth).max() < 0.15
    # Removed, the rest fits without it.
    graph.remove_edge(bad)
    graph.optimize()
    assert np.isnan(graph.chi2()[bad])
    assert position_error(graph.poses, truth).max() < 0.15


def test_relative_covariance_of_a_chain_adds_up():
    graph = PoseGraph()
    cov = np.diag([0.01, 0.02, 0.001])
    graph.add_node(np.zeros(3))
    for k in range(1, 6):
        graph.add_node((k, 0.0, 0.0))
        graph.add_edge(k - 1, k, (1.0, 0.0, 0.0), np.linalg.inv(cov))
    rel = graph.relative_covariance(2, 5)
    # Three straight unit steps: heading variance adds up, lateral picks up the lever arms 1, 2 (and 0).
    assert rel[2, 2] == pytest.approx(3 * 0.001)
    assert rel[0, 0] == pytest.approx(3 * 0.01)
    assert rel[1, 1] == pytest.approx(3 * 0.02 + 0.001 * (1 + 4))


def edge_error_xy(xi, xj, z):
    """An edge's position error, (2,): node j in node i's frame less the measurement, in the
    measurement's frame; written with numpy ufuncs only, so complex steps differentiate it."""
    ci, si, cz, sz = np.cos(xi[2]), np.sin(xi[2]), np.cos(z[2]), np.sin(z[2])
    dx, dy = xj[0] - xi[0], xj[1] - xi[1]
    a0, a1 = ci * dx + si * dy - z[0], -si * dx + ci * dy - z[1]
    return np.array([cz * a0 + sz * a1, -sz * a0 + cz * a1])


def edge_jacobian(xi, xj, z):
    """(3, 6) Jacobian of an edge's error with respect to (x_i, x_j), by complex steps (exact to
    rounding, and independent of the graph's own analytic Jacobians)."""
    jac = np.zeros((3, 6))
    for k in range(6):
        x = np.concatenate((xi, xj)).astype(complex)
        x[k] += 1e-30j
        jac[:2, k] = edge_error_xy(x[:3], x[3:], z).imag / 1e-30
    jac[2, 2], jac[2, 5] = -1.0, 1.0   # the heading error is θ_j − θ_i − θ_z
    return jac


def gauge_a_covariance(graph: PoseGraph, a: int, b: int) -> np.ndarray:
    """The oracle: dense normal equations built from the graph's public edges (each weighted by its
    Cauchy weight), node ``a`` held fixed (left out), ``b``'s covariance in ``a``'s frame."""
    n, poses, weights = len(graph), graph.poses, graph.loop_weights()
    h = np.zeros((3 * n, 3 * n))
    for edge in range(len(weights)):   # every edge added; removed ones are NaN
        if np.isnan(weights[edge]):
            continue
        i, j = graph.edge_nodes(edge)
        jac = edge_jacobian(poses[i], poses[j], graph.edge_measurement(edge))
        cols = np.r_[3 * i: 3 * i + 3, 3 * j: 3 * j + 3]
        h[np.ix_(cols, cols)] += jac.T @ (weights[edge] * graph.edge_information(edge)) @ jac
    kept = np.r_[0: 3 * a, 3 * a + 3: 3 * n]
    cov = np.linalg.inv(h[np.ix_(kept, kept)])
    rb = 3 * b - (3 if b > a else 0)
    cov_world = cov[rb: rb + 3, rb: rb + 3]
    c, s = np.cos(poses[a, 2]), np.sin(poses[a, 2])
    rot_t = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot_t @ cov_world @ rot_t.T


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_relative_covariance_equals_holding_the_first_node_fixed(seed, optimised):
    # Computed with the first node as the gauge (one factorisation per graph state), it must
    # equal the covariance with node a held fixed, for any pair, loops and robust weights included.
    rng = np.random.default_rng(seed)
    truth = square_loop(laps=2, side=5)
    graph = noisy_graph(truth, rng, [(0, 20), (3, 24), (7, 38)])
    if optimised:
        graph.optimize()
    for a, b in rng.integers(0, len(truth), size=(4, 2)).tolist() + [[0, 40], [40, 0], [17, 3]]:
        got = graph.relative_covariance(a, b)
        if a == b:
            assert np.all(got == 0.0)
            continue
        want = gauge_a_covariance(graph, a, b)
        assert np.allclose(got, want, rtol=1e-7, atol=1e-12 * np.abs(want).max())


def test_relative_covariance_follows_the_graph_as_it_changes():
    # The factorisation is cached per state of the graph: a new edge, node or estimate must not
    # be answered from the old one.
    rng = np.random.default_rng(3)
    truth = square_loop(side=5)
    graph = noisy_graph(truth, rng, [])
    before = graph.relative_covariance(2, 19)
    graph.add_edge(0, 19, relative(truth[0], truth[19]), np.diag(4.0 / SIGMA**2))
    after = graph.relative_covariance(2, 19)
    assert np.trace(after) < 0.5 * np.trace(before)
    assert np.allclose(after, gauge_a_covariance(graph, 2, 19), rtol=1e-7)
    # New nodes hung off the graph one edge each (the loop search's new keyframes) are carried
    # from the factorisation along their edges: they must equal a fresh solve, in either order.
    for step in ((0.5, 0.0, 0.1), (0.4, 0.1, -0.3), (0.5, -0.2, 0.2)):
        graph.add_node(compose(graph.poses[-1], np.add(step, 0.01)))
        graph.add_edge(len(graph) - 2, len(graph) - 1, step, np.diag(1.0 / SIGMA**2))
        last = len(graph) - 1
        for a, b in ((2, last), (last, 7), (0, last), (last - 1, last)):
            assert np.allclose(graph.relative_covariance(a, b), gauge_a_covariance(graph, a, b), rtol=1e-7)
    graph.add_edge(3, len(graph) - 1, relative(graph.poses[3], graph.poses[-1]), np.eye(3), robust=True)
    assert np.allclose(graph.relative_covariance(2, len(graph) - 1),
                       gauge_a_covariance(graph, 2, len(graph) - 1), rtol=1e-7)
    graph.set_pose(10, graph.poses[10] + (0.3, -0.2, 0.1))
    assert np.allclose(graph.relative_covariance(2, 19), gauge_a_covariance(graph, 2, 19), rtol=1e-7)


def test_bad_input_is_refused():
    graph = PoseGraph()
    graph.add_node(np.zeros(3))
    with pytest.raises(InputError):
        graph.add_edge(0, 1, np.zeros(3), np.eye(3))
    with pytest.raises(InputError):
        graph.add_node((np.nan, 0.0, 0.0))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 4))
def test_a_restored_snapshot_optimises_to_the_same_poses(seed, removed):
    rng = np.random.default_rng(seed)
    truth = square_loop()
    n = len(truth)
    graph = noisy_graph(truth, rng, [(k, n - 1 - k) for k in range(0, 10, 2)])
    loop_edges = range(n - 1, n - 1 + 5)
    for e in list(loop_edges)[:removed]:
        graph.remove_edge(e)
    buffer = io.BytesIO()
    np.savez(buffer, **graph.snapshot())   # as the mapper's checkpoint stores it
    buffer.seek(0)
    with np.load(buffer) as data:
        again = PoseGraph.restore({k: data[k] for k in data.files})
    assert again.edge_count() == graph.edge_count() == n - 1 + 5 - removed
    graph.optimize()
    again.optimize()
    np.testing.assert_array_equal(again.poses, graph.poses)
    np.testing.assert_array_equal(again.chi2(), graph.chi2())
    # It grows on as the original does.
    assert again.add_node(np.zeros(3)) == graph.add_node(np.zeros(3)) == n


def test_a_bad_snapshot_is_refused():
    graph = noisy_graph(square_loop(), np.random.default_rng(0), [(0, 30)])
    snap = graph.snapshot()
    for broken in ({k: v for k, v in snap.items() if k != "graph_edge_alive"},
                   {**snap, "graph_edge_nodes": snap["graph_edge_nodes"] + len(graph)},
                   {**snap, "graph_edge_measurement": snap["graph_edge_measurement"][:-1]},
                   {**snap, "graph_poses": np.full_like(snap["graph_poses"], np.nan)}):
        with pytest.raises(InputError, match="pose graph snapshot"):
            PoseGraph.restore(broken)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_leaves_are_left_out_of_the_factorisation_and_change_no_covariance(seed):
    # Leaves (one edge each: the mapper's folded revisits) hang off a loop. The factorisation
    # leaves them out; the covariance of any pair, leaves included, and after edges to a leaf and
    # new nodes, must still be the dense oracle's.
    rng = np.random.default_rng(seed)
    truth = square_loop(side=5)
    graph = noisy_graph(truth, rng, [(0, 15)])
    hosts = rng.choice(np.arange(1, len(truth) - 1), size=6, replace=False).tolist()
    leaves = []
    for host in hosts:
        offset = rng.normal(scale=(0.3, 0.3, 0.2))
        leaves.append(graph.add_node(compose(graph.poses[host], offset)))
        graph.add_edge(host, leaves[-1], offset + rng.normal(scale=0.01, size=3), np.diag(1.0 / SIGMA**2),
                       robust=bool(rng.integers(2)))
    pairs = [(int(a), int(b)) for a, b in rng.integers(0, len(truth), size=(3, 2))]
    for a, b in pairs + [(hosts[0], leaves[0]), (leaves[1], 3), (leaves[2], leaves[3])]:
        if a != b:
            want = gauge_a_covariance(graph, a, b)
            assert np.allclose(graph.relative_covariance(a, b), want, rtol=1e-7, atol=1e-12 * np.abs(want).max())
    assert graph.factorised_through == len(graph)
    # A new node joined to a leaf: the leaf is one no more.
    graph.add_node(compose(graph.poses[leaves[4]], (0.5, 0.0, 0.1)))
    graph.add_edge(leaves[4], len(graph) - 1, (0.5, 0.0, 0.1), np.diag(1.0 / SIGMA**2))
    for a, b in ((2, len(graph) - 1), (leaves[4], 7)):
        want = gauge_a_covariance(graph, a, b)
        assert np.allclose(graph.relative_covariance(a, b), want, rtol=1e-7, atol=1e-12 * np.abs(want).max())


def test_the_factorisation_leaves_the_leaves_out():
    rng = np.random.default_rng(2)
    truth = square_loop(side=5)
    graph = noisy_graph(truth, rng, [(0, 15)])
    for host in range(1, 15):
        graph.add_node(compose(graph.poses[host], (0.1, 0.2, 0.0)))
        graph.add_edge(host, len(graph) - 1, (0.1, 0.2, 0.0), np.diag(1.0 / SIGMA**2), robust=True)
    graph.relative_covariance(2, 9)
    # Left out: the gauge, the leaves but the newest node (the next one's edge will join it), and
    # the first lap's last node, whose only edge is the one from its predecessor.
    assert graph.factorised_through == len(graph)
    left_out = sorted(set(range(len(graph))) - set(graph.factorised_nodes.tolist()))
    assert left_out == [0, len(truth) - 1, *range(len(truth), len(graph) - 1)]


def test_what_was_added_since_the_factorisation_enters_exactly():
    # A robot on its second round: every new node closes into the first lap. The graph is
    # factorised once; the new nodes and closures must give what factorising again gives.
    rng = np.random.default_rng(5)
    truth = square_loop(laps=2, side=5)
    lap = len(truth) // 2
    graph = noisy_graph(truth[: lap + 5], rng, [(0, lap)])
    graph.relative_covariance(2, lap)   # factorised here
    for k in range(lap + 5, len(truth)):
        graph.add_node(truth[k] + rng.normal(scale=0.02, size=3))
        graph.add_edge(k - 1, k, relative(truth[k - 1], truth[k]), np.diag(1.0 / SIGMA**2))
        graph.add_edge(k - lap, k, relative(truth[k - lap], truth[k]), np.diag(4.0 / SIGMA**2), robust=True)
        for a, b in ((k - lap, k), (2, k), (k, 7), (0, k)):
            assert np.allclose(graph.relative_covariance(a, b), gauge_a_covariance(graph, a, b), rtol=1e-7)
    assert graph.factorised_through == lap + 5   # not factorised again
    # A restored graph computes from the same factorisation: the same covariance to the last bit,
    # so a restarted mapper searches exactly the windows the one it continues would have.
    restored = PoseGraph.restore(graph.snapshot())
    last = len(graph) - 1
    np.testing.assert_array_equal(restored.relative_covariance(3, last), graph.relative_covariance(3, last))


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_taking_leaves_out_changes_no_other_pose_or_covariance(seed):
    # Leaves on a loop, some edges removed before: optimised with the leaves and then without
    # them, the other nodes sit where they did, their covariances are the same, and every
    # leaf sits on its one edge (so its pose is its host's composed with the edge, ever after).
    rng = np.random.default_rng(seed)
    truth = square_loop(side=5)
    graph = noisy_graph(truth, rng, [(0, 15), (3, 17)])
    graph.remove_edge(graph.edge_count() - 1)
    leaves, hosts = [], rng.choice(np.arange(1, len(truth)), size=5, replace=False).tolist()
    for host in hosts:
        offset = rng.normal(scale=(0.3, 0.3, 0.2))
        leaves.append(graph.add_node(compose(graph.poses[host], offset + rng.normal(scale=0.05, size=3))))
        graph.add_edge(host, leaves[-1], offset, np.diag(1.0 / SIGMA**2), robust=bool(rng.integers(2)))
    graph.optimize()
    before = graph.poses.copy()
    for host, leaf in zip(hosts, leaves, strict=True):
        z = graph.edge_measurement(int(graph.edges_of(leaf)[0]))
        assert np.allclose(relative(before[host], before[leaf]), z, atol=1e-6)
    with_leaves = PoseGraph.restore(graph.snapshot())
    covariance = graph.relative_covariance(2, 11)
    edges = graph.edge_count()
    node_map, edge_map = graph.remove_nodes(leaves)
    assert len(graph) == len(truth) and graph.edge_count() == edges - len(leaves)
    np.testing.assert_array_equal(node_map[: len(truth)], np.arange(len(truth)))
    assert np.all(node_map[len(truth):] == -1) and np.count_nonzero(edge_map >= 0) == graph.edge_count()
    np.testing.assert_array_equal(graph.poses, before[: len(truth)])
    np.testing.assert_allclose(graph.relative_covariance(2, 11), covariance, rtol=1e-7)
    # Optimised again, with and without them (the first optimisation stopped at its tolerance).
    graph.optimize()
    with_leaves.optimize()
    np.testing.assert_allclose(graph.poses, with_leaves.poses[: len(truth)], atol=1e-7)
    with pytest.raises(InputError):
        graph.remove_nodes([0])
    with pytest.raises(InputError):
        graph.remove_nodes([len(graph)])
