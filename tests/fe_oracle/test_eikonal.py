"""The anisotropic eikonal solver (pure NumPy) against exact solutions in a homogeneous medium."""

import itertools

import numpy as np
import pytest
from scipy import sparse
from scipy.sparse import csgraph

from fe_oracle import eikonal


def box_mesh(n: int, length: float = 10.0):
    """Cube [0, length]³, n³ sub-cubes of 6 (Kuhn) tetrahedra each: (nodes, tets)."""
    g = np.linspace(0.0, length, n + 1)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    tets = []
    for perm in itertools.permutations(range(3)):
        for corner in itertools.product(range(n), repeat=3):
            p = np.array(corner)
            path = [idx[tuple(p)]]
            for axis in perm:
                p[axis] += 1
                path.append(idx[tuple(p)])
            tets.append(path)
    return x, np.array(tets)


def oblique_metric():
    """D⁻¹ for velocities 4 : 2 : 1 (mm/s, scaled) along an oblique orthonormal basis."""
    f = np.array([np.cos(0.5), np.sin(0.5), 0.3])
    f /= np.linalg.norm(f)
    s = np.cross(f, [0.0, 0.0, 1.0])
    s /= np.linalg.norm(s)
    return eikonal.metric_tensors(np.array([f, s, np.cross(f, s)])[None], (4.0, 2.0, 1.0))[0]


def point_source_error(n: int):
    x, tets = box_mesh(n)
    m = oblique_metric()
    src = int(np.argmin(np.linalg.norm(x - 5.0, axis=1)))
    d = x - x[src]
    exact = np.sqrt(np.einsum("na,ab,nb->n", d, m, d))
    far = exact > 0.5 * exact.max()
    t = eikonal.solve(x, tets, np.broadcast_to(m, (len(tets), 3, 3)), [src])
    return np.abs(t - exact)[far] / exact[far], x, tets, m, src, exact, far


def test_a_plane_front_is_exact():
    """t linear with |∇t|_D = 1 is a discrete solution: boundary data in, exact interior out."""
    x, tets = box_mesh(8)
    m = oblique_metric()
    d_tensor = np.linalg.inv(m)
    direction = np.array([1.0, 0.4, -0.2])
    slowness = direction / np.sqrt(direction @ d_tensor @ direction)
    exact = x @ slowness
    exact -= exact.min()
    boundary = np.flatnonzero(np.any((x == 0.0) | (x == 10.0), axis=1))
    t = eikonal.solve(x, tets, np.broadcast_to(m, (len(tets), 3, 3)), boundary, exact[boundary])
    np.testing.assert_allclose(t, exact, atol=1e-12 * exact.max())


def test_point_source_converges_and_beats_shortest_paths():
    coarse = point_source_error(6)[0]
    err, x, tets, m, src, exact, far = point_source_error(12)
    assert err.mean() < 0.7 * coarse.mean()  # converges with h
    assert err.mean() < 0.03
    i, j = np.triu_indices(4, 1)
    edges = np.unique(np.sort(np.stack([tets[:, i].ravel(), tets[:, j].ravel()], 1), 1), axis=0)
    e = x[edges[:, 1]] - x[edges[:, 0]]
    w = np.sqrt(np.einsum("na,ab,nb->n", e, m, e))
    graph = sparse.coo_matrix((w, (edges[:, 0], edges[:, 1])), shape=(len(x),) * 2).tocsr()
    t_graph = csgraph.dijkstra(graph, directed=False, indices=[src], min_only=True)
    assert np.all(t_graph[far] >= exact[far] * (1 - 1e-12))  # paths along edges never undercut
    assert err.mean() < 0.25 * (np.abs(t_graph - exact)[far] / exact[far]).mean()


def test_p2_split_tiles_the_tetrahedron():
    """8 sub-tetrahedra on the 10 nodes of a straight P2 tetrahedron (basix order) fill it exactly."""
    v = np.array([[0.0, 0, 0], [2.0, 0.1, 0], [0.3, 1.5, 0], [0.2, 0.4, 1.8]])
    edges = [(2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1)]
    x = np.vstack([v, [(v[a] + v[b]) / 2 for a, b in edges]])
    sub = eikonal.split_p2_tetrahedra(np.arange(10)[None])
    assert sub.shape == (8, 4)
    vol = lambda t: abs(np.linalg.det(x[t[1:]] - x[t[0]])) / 6.0  # noqa: E731
    volumes = np.array([vol(t) for t in sub])
    np.testing.assert_allclose(volumes, vol(np.arange(4)) / 8.0, rtol=1e-12)  # red refinement: equal volumes
    with pytest.raises(ValueError, match=r"\(n, 10\)"):
        eikonal.split_p2_tetrahedra(np.arange(4)[None])


def test_unreached_nodes_stay_infinite():
    x, tets = box_mesh(2)
    x2 = np.vstack([x, x + 100.0])
    t = eikonal.solve(x2, np.vstack([tets, tets + len(x)]), np.broadcast_to(np.eye(3), (2 * len(tets), 3, 3)), [0])
    assert np.all(np.isfinite(t[: len(x)])) and np.all(np.isinf(t[len(x):]))
