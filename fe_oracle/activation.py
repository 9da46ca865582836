"""Activation times from an anisotropic eikonal equation (DESIGN §4); needs the ``fe`` extra.

    √(∇t · D ∇t) = 1,   D = v_f² f⊗f + v_s² s⊗s + v_n² n⊗n,   t = 0 at the foci

Conduction velocities fibre : sheet : normal = 4 : 2 : 1 (v_f = 0.6 m/s = 600 mm/s, ours, a
typical human myocardial fibre velocity). Four endocardial foci (DESIGN §4), given as
(normalised height z̄ from the base, angle θ from the free-wall centre): (0.6, 70°),
(0.3, 140°), (0.6, 150°), (0.05, 50°); z̄ = 0 at the base, 1 at the endocardial apex, the
free-wall centre is the +x direction, θ counter-clockwise seen from the base.

Discretisation (ours): first arrival times on the graph whose nodes are the P2 nodes of the mesh
and whose edges join every pair of nodes of a cell, each edge e weighted by its travel time
√(eᵀ D⁻¹ e) with the fibre basis averaged over its ends (Dijkstra). With 10 nodes per tetrahedron
the graph offers many directions per node, which keeps the metrication error of shortest paths
small (a few per cent over the wall); an exact fast-marching solver would remove it.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

import dolfinx_solver  # noqa: F401
import dolfinx
import ufl

from fe_oracle.fibres import FibreField, fibre_basis
from fe_oracle.mechanics import interpolate_at_quadrature, quadrature_function
from fe_oracle.mesh import ENDO, TaggedMesh
from lvenv.geometry import Geometry, surfaces

__all__ = ["FOCI", "FIBRE_VELOCITY", "VELOCITY_RATIO", "activation_times"]

FOCI = ((0.6, 70.0), (0.3, 140.0), (0.6, 150.0), (0.05, 50.0))
FIBRE_VELOCITY = 600.0  # mm/s
VELOCITY_RATIO = (4.0, 2.0, 1.0)


def _focus_point(geometry: Geometry, zbar: float, theta_deg: float) -> np.ndarray:
    s = surfaces(geometry)
    z = s.z_base + zbar * (-s.b_inner - s.z_base)
    r = s.a_inner * max(0.0, 1.0 - (abs(z) / s.b_inner) ** (2 * s.e)) ** (1.0 / (2 * s.e))
    th = math.radians(theta_deg)
    return np.array([r * math.cos(th), r * math.sin(th), z])


def activation_times(tm: TaggedMesh, geometry: Geometry, fibres: FibreField, fibre_velocity: float = FIBRE_VELOCITY):
    """(t_act at the quadrature points (s), the P2 Function of t_act, the focus nodes' coordinates).

    Under MPI every rank contributes the edges of its cells (global node numbers); rank 0 runs
    Dijkstra on the whole graph and broadcasts the arrival times.
    """
    mesh = tm.mesh
    comm = mesh.comm
    space = dolfinx.fem.functionspace(mesh, ("Lagrange", 2))
    x = space.tabulate_dof_coordinates()
    index_map = space.dofmap.index_map
    global_ids = index_map.local_to_global(np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32))
    grad_space = dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))
    grad = dolfinx.fem.Function(grad_space)
    grad.interpolate(dolfinx.fem.Expression(ufl.grad(fibres.transmural), grad_space.element.interpolation_points))
    grad.x.scatter_forward()
    f, s, n = fibre_basis(grad.x.array.reshape(-1, 3), fibres.transmural.x.array)

    cells = space.dofmap.list
    k = cells.shape[1]
    i, j = np.triu_indices(k, 1)
    pairs = np.unique(np.sort(np.stack([cells[:, i].ravel(), cells[:, j].ravel()], axis=1), axis=1), axis=0)
    a, b = pairs[:, 0], pairs[:, 1]
    e = x[b] - x[a]
    v_f = fibre_velocity
    v_s = v_f * VELOCITY_RATIO[1] / VELOCITY_RATIO[0]
    v_n = v_f * VELOCITY_RATIO[2] / VELOCITY_RATIO[0]
    # Mean fibre direction of the two ends; f and −f are the same fibre, so align signs first.
    fm = f[a] + np.sign(np.sum(f[a] * f[b], axis=1, keepdims=True) + 1e-30) * f[b]
    sm = s[a] + s[b]
    fm /= np.linalg.norm(fm, axis=1, keepdims=True)
    sm -= np.sum(sm * fm, axis=1, keepdims=True) * fm
    sm /= np.maximum(np.linalg.norm(sm, axis=1, keepdims=True), 1e-300)
    nm = np.cross(fm, sm)
    cost = np.sqrt((np.sum(e * fm, 1) / v_f) ** 2 + (np.sum(e * sm, 1) / v_s) ** 2 + (np.sum(e * nm, 1) / v_n) ** 2)

    fdim = mesh.topology.dim - 1
    endo_dofs = dolfinx.fem.locate_dofs_topological(space, fdim, tm.facet_tags.find(ENDO))
    sources, source_x = [], []
    for zbar, theta in FOCI:
        target = _focus_point(geometry, zbar, theta)
        if len(endo_dofs):
            best = endo_dofs[np.argmin(np.linalg.norm(x[endo_dofs] - target, axis=1))]
            candidate = (float(np.linalg.norm(x[best] - target)), int(global_ids[best]), tuple(x[best]))
        else:
            candidate = (math.inf, -1, (math.nan,) * 3)
        dist, gid, where = min(comm.allgather(candidate))
        sources.append(gid)
        source_x.append(where)

    edges = comm.gather((global_ids[a], global_ids[b], cost), root=0)
    times = None
    if comm.rank == 0:
        ga, gb, gc = (np.concatenate(parts) for parts in zip(*edges))
        size = index_map.size_global
        lo, hi = np.minimum(ga, gb), np.maximum(ga, gb)
        _, first = np.unique(lo.astype(np.int64) * size + hi, return_index=True)  # edges shared by ranks once
        graph = sparse.coo_matrix((gc[first], (lo[first], hi[first])), shape=(size, size)).tocsr()
        times = csgraph.dijkstra(graph, directed=False, indices=np.array(sources), min_only=True)
    times = comm.bcast(times, root=0)
    t_fn = dolfinx.fem.Function(space, name="activation_time")
    t_fn.x.array[:] = times[global_ids]
    t_q = quadrature_function(mesh)
    values = interpolate_at_quadrature(t_q, t_fn).copy()
    return values, t_fn, np.array(source_x)
