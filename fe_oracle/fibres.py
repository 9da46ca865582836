"""Rule-based myocardial fibres (DESIGN §4); needs the ``fe`` extra.

1. Transmural coordinate φ (0 on the endocardium, 1 on the epicardium): the P2 solution of
   Laplace's equation Δφ = 0 with those Dirichlet values, zero flux through the base.
2. Local basis at each point: transmural e_t = ∇φ/‖∇φ‖; longitudinal e_l = the long axis ẑ
   (apex → base) projected onto the plane ⊥ e_t; circumferential e_c = e_l × e_t
   (counter-clockwise seen from the base).
3. Helix angle α(φ) = α_endo + (α_epi − α_endo) φ, α_endo = +60°, α_epi = −60°::

       f = cos α e_c + sin α e_l,   s = e_t (sheet, transmural),   n = f × s

Bayer JD et al. (2012) Ann Biomed Eng 40:2243 (rule-based fibres); the linear helix rule with
±60° is the one used by the Land et al. 2015 benchmark.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import dolfinx_solver  # noqa: F401
import dolfinx
import dolfinx.fem.petsc
import ufl
from petsc4py import PETSc

from fe_oracle.mechanics import interpolate_at_quadrature, quadrature_function
from fe_oracle.mesh import ENDO, EPI, TaggedMesh

__all__ = ["FibreField", "transmural_coordinate", "fibre_basis", "fibre_field"]

HELIX_ENDO_DEG = 60.0
HELIX_EPI_DEG = -60.0


@dataclasses.dataclass
class FibreField:
    """Fibre, sheet and normal unit vectors at the quadrature points, and φ there."""

    f0: dolfinx.fem.Function
    s0: dolfinx.fem.Function
    n0: dolfinx.fem.Function
    phi: dolfinx.fem.Function
    transmural: dolfinx.fem.Function  # the P2 Laplace solution

    def vectors(self):
        return self.f0, self.s0, self.n0


def transmural_coordinate(tm: TaggedMesh) -> dolfinx.fem.Function:
    """φ ∈ [0, 1] in P2: Δφ = 0, φ = 0 on ENDO, φ = 1 on EPI."""
    mesh = tm.mesh
    space = dolfinx.fem.functionspace(mesh, ("Lagrange", 2))
    trial, test = ufl.TrialFunction(space), ufl.TestFunction(space)
    fdim = mesh.topology.dim - 1
    bcs = [
        dolfinx.fem.dirichletbc(PETSc.ScalarType(value), dolfinx.fem.locate_dofs_topological(space, fdim, tm.facet_tags.find(tag)), space)
        for tag, value in ((ENDO, 0.0), (EPI, 1.0))
    ]
    zero = dolfinx.fem.Constant(mesh, PETSc.ScalarType(0.0))
    problem = dolfinx.fem.petsc.LinearProblem(
        ufl.inner(ufl.grad(trial), ufl.grad(test)) * ufl.dx,
        zero * test * ufl.dx,
        bcs=bcs,
        petsc_options_prefix="transmural_",
        petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
    )
    phi = problem.solve()
    phi.name = "transmural"
    return phi


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def fibre_basis(grad_phi: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f, s, n), each shape (N, 3), from ∇φ (N, 3) and φ (N,) by the rule in the module docstring."""
    e_t = _unit(grad_phi)
    axis = np.array([0.0, 0.0, 1.0])
    e_l = axis - (e_t @ axis)[:, None] * e_t
    degenerate = np.linalg.norm(e_l, axis=1) < 1e-6
    if np.any(degenerate):  # exactly at the apex: any direction ⊥ e_t will do
        x = np.array([1.0, 0.0, 0.0])
        e_l[degenerate] = x - (e_t[degenerate] @ x)[:, None] * e_t[degenerate]
    e_l = _unit(e_l)
    e_c = np.cross(e_l, e_t)
    alpha = np.deg2rad(HELIX_ENDO_DEG + (HELIX_EPI_DEG - HELIX_ENDO_DEG) * np.clip(phi, 0.0, 1.0))
    f = _unit(np.cos(alpha)[:, None] * e_c + np.sin(alpha)[:, None] * e_l)
    s = e_t
    n = np.cross(f, s)
    return f, s, n


def fibre_field(tm: TaggedMesh) -> FibreField:
    """Solve for φ and build the fibre basis at the quadrature points."""
    mesh = tm.mesh
    transmural = transmural_coordinate(tm)
    phi_q = quadrature_function(mesh)
    grad_q = quadrature_function(mesh, (3,))
    phi_vals = interpolate_at_quadrature(phi_q, transmural).copy()
    grad_vals = interpolate_at_quadrature(grad_q, ufl.grad(transmural)).reshape(-1, 3)
    f, s, n = fibre_basis(grad_vals, phi_vals)
    out = []
    for vec in (f, s, n):
        fn = quadrature_function(mesh, (3,))
        fn.x.array[:] = vec.ravel()
        out.append(fn)
    return FibreField(*out, phi_q, transmural)
