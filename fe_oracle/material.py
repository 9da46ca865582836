"""Passive myocardium: transversely isotropic Guccione law with a volumetric penalty (pure data).

Strain energy per unit reference volume (kPa), written with the isochoric Green–Lagrange strain
Ē = (J^(−2/3) FᵀF − I)/2 in the local fibre (f), sheet (s) and sheet-normal (n) basis::

    W(F) = C/2 (exp(Q) − 1) + κ/2 (J − 1)²
    Q = bf Ē_ff² + bt (Ē_ss² + Ē_nn² + 2 Ē_sn²) + 2 bfs (Ē_fs² + Ē_fn²)

The isochoric/volumetric split (ours) matters: with the full strain E and the same penalty the
Newton iteration of the N ventricle breaks down near 1.6 kPa, with the split it inflates to
4 kPa in three iterations per load step. At J = 1 both coincide with the incompressible law.

Guccione JM, Costa KD, McCulloch AD (1995) J Biomech 28:1167. Why Guccione rather than Usyk:
Usyk et al. (2000) is the orthotropic extension of the same exponential law (separate sheet and
normal stiffnesses); Guccione has one parameter set used by the cardiac-mechanics benchmark of
Land S et al. (2015) Proc R Soc A 471:20150641, so our implementation can be checked against a
published reference (problem 3: C = 2 kPa, bf = 8, bt = 2, bfs = 4). The isotropic version
(bf = bt = bfs = b; benchmark problem 2 uses C = 10 kPa, b = 1) has an exact thick-walled sphere
solution, used in the tests.

Near-incompressibility is a penalty κ (ours, κ = 1000 kPa ≈ 500 × the small-strain shear
modulus C·bt/2): with P2 displacements the wall volume changes by ≈ p/κ < 0.5 % at 4 kPa.
"""

from __future__ import annotations

import dataclasses

__all__ = ["Guccione"]


@dataclasses.dataclass(frozen=True)
class Guccione:
    """Guccione parameters: ``C``, ``kappa`` in kPa; ``bf``, ``bt``, ``bfs`` dimensionless."""

    C: float = 2.0
    bf: float = 8.0
    bt: float = 2.0
    bfs: float = 4.0
    kappa: float = 1000.0

    def __post_init__(self) -> None:
        for name in ("C", "bf", "bt", "bfs", "kappa"):
            value = getattr(self, name)
            if not value > 0.0:
                raise ValueError(f"Guccione.{name} = {value!r} must be positive")

    @classmethod
    def land_benchmark(cls) -> "Guccione":
        """Land et al. 2015 benchmark problem 3 (transversely isotropic): the default."""
        return cls()

    @classmethod
    def isotropic(cls, C: float = 10.0, b: float = 1.0, kappa: float = 1000.0) -> "Guccione":
        """Isotropic Guccione (bf = bt = bfs = b); default: Land et al. 2015 problem 2."""
        return cls(C=C, bf=b, bt=b, bfs=b, kappa=kappa)

    @property
    def is_isotropic(self) -> bool:
        return self.bf == self.bt == self.bfs
