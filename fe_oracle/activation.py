"""Activation times from an anisotropic eikonal equation (DESIGN §4); needs the ``fe`` extra.

    √(∇t · D ∇t) = 1,   D = v_f² f⊗f + v_s² s⊗s + v_n² n⊗n,   t = 0 at the foci

Conduction velocities fibre : sheet : normal = 4 : 2 : 1. The fibre velocity v_f = 0.9 m/s
(900 mm/s) is ours, an effective value. Myocardium conducts at ≈ 0.67 : 0.30 : 0.17 m/s
(Caldwell et al. 2009, Circ Arrhythm Electrophysiol 2:433), but the model has no Purkinje network
beyond its four foci, and at v_f = 0.6 m/s the N ventricle would take 125 ms to activate. At
0.9 m/s it activates in 82 ms, the total left-ventricular activation time of the normal human
heart (≈ 80 ms, Durrer et al. 1970, Circulation 41:899), so the spread of activation, and with it
the isovolumic contraction time, is of physiological size.

Four endocardial foci (DESIGN §4), given as (normalised height z̄ from the base, angle θ from the
free-wall centre): (0.6, 70°), (0.3, 140°), (0.6, 150°), (0.05, 50°); z̄ = 0 at the base, 1 at
the endocardial apex, the free-wall centre is the +x direction, θ counter-clockwise seen from the
base.

Discretisation (ours): every curved P2 tetrahedron is split into its 8 straight sub-tetrahedra on
the 10 P2 nodes, the metric D⁻¹ of each is built from φ and ∇φ at its centroid
(:mod:`fe_oracle.fibres`), and the Hopf–Lax fixed point is found by
:func:`fe_oracle.eikonal.solve`, whose local solver is exact on each tetrahedron (a plane front
comes out exact; from a point focus the error is first order in h). The arrival times live on
the P2 nodes and are interpolated to the quadrature points.
"""

from __future__ import annotations

import math

import numpy as np

import dolfinx_solver  # noqa: F401
import dolfinx
import ufl

from fe_oracle import eikonal
from fe_oracle.fibres import FibreField, fibre_basis
from fe_oracle.mechanics import interpolate_at_quadrature, quadrature_function
from fe_oracle.mesh import ENDO, TaggedMesh
from lvenv.geometry import Geometry, surfaces

__all__ = ["FOCI", "FIBRE_VELOCITY", "VELOCITY_RATIO", "activation_times", "activation_quantiles"]

FOCI = ((0.6, 70.0), (0.3, 140.0), (0.6, 150.0), (0.05, 50.0))
FIBRE_VELOCITY = 900.0  # mm/s
VELOCITY_RATIO = (4.0, 2.0, 1.0)


def _focus_point(geometry: Geometry, zbar: float, theta_deg: float) -> np.ndarray:
    s = surfaces(geometry)
    z = s.z_base + zbar * (-s.b_inner - s.z_base)
    r = s.a_inner * max(0.0, 1.0 - (abs(z) / s.b_inner) ** (2 * s.e)) ** (1.0 / (2 * s.e))
    th = math.radians(theta_deg)
    return np.array([r * math.cos(th), r * math.sin(th), z])


def activation_times(tm: TaggedMesh, geometry: Geometry, fibres: FibreField, fibre_velocity: float = FIBRE_VELOCITY):
    """(t_act at the quadrature points (s), the P2 Function of t_act, the focus nodes' coordinates).

    Under MPI every rank contributes its cells and nodes (global node numbers); rank 0 solves
    the eikonal equation on the whole mesh and broadcasts the arrival times.
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
    velocities = fibre_velocity * np.asarray(VELOCITY_RATIO) / VELOCITY_RATIO[0]

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

    phi = np.column_stack([fibres.transmural.x.array, grad.x.array.reshape(-1, 3)])
    parts = comm.gather((global_ids[space.dofmap.list], global_ids, x, phi), root=0)
    times = None
    if comm.rank == 0:
        size = index_map.size_global
        nodes, node_phi = np.empty((size, 3)), np.empty((size, 4))
        for _, ids, xs, ph in parts:
            nodes[ids], node_phi[ids] = xs, ph
        tets = eikonal.split_p2_tetrahedra(np.concatenate([cells for cells, *_ in parts]))
        centre = node_phi[tets].mean(axis=1)  # φ and ∇φ at each sub-tetrahedron's centroid
        metric = eikonal.metric_tensors(np.stack(fibre_basis(centre[:, 1:], centre[:, 0]), axis=1), velocities)
        times = eikonal.solve(nodes, tets, metric, sources)
    times = comm.bcast(times, root=0)
    t_fn = dolfinx.fem.Function(space, name="activation_time")
    t_fn.x.array[:] = times[global_ids]
    t_q = quadrature_function(mesh)
    values = interpolate_at_quadrature(t_q, t_fn).copy()
    return values, t_fn, np.array(source_x)


def activation_quantiles(geometry: Geometry, mesh_size: float, quantiles) -> np.ndarray:
    """The ``quantiles`` (fractions) of the activation times (s) over the quadrature points of
    ``geometry``'s oracle mesh at ``mesh_size`` (mm), as an FE beat has them; meshing and the
    eikonal solve only, no mechanics. Serial."""
    from fe_oracle.fibres import fibre_field
    from fe_oracle.mesh import lv_mesh

    tm = lv_mesh(geometry, mesh_size)
    return np.quantile(activation_times(tm, geometry, fibre_field(tm))[0], quantiles)
