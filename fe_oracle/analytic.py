"""Exact inflation of an incompressible thick-walled sphere (isotropic Guccione law); pure SciPy.

Reference radii A (inner) < B (outer), deformed inner radius a. Incompressibility maps a
material sphere R to r(R) = (R³ + a³ − A³)^(1/3); principal stretches λ_θ = r/R, λ_r = (R/r)².
With E_i = (λ_i² − 1)/2, Q = b (E_r² + 2 E_θ²) and W = C/2 (e^Q − 1), the Cauchy stress
difference is σ_θ − σ_r = C b e^Q (λ_θ² E_θ − λ_r² E_r), and radial equilibrium with a
traction-free outer surface gives the cavity pressure::

    p(a) = ∫_a^b 2 (σ_θ − σ_r) / r dr,    b = (B³ + a³ − A³)^(1/3)

Cavity volume V = 4/3 π a³. Used to check the FE solid (Ogden, *Non-linear elastic
deformations*, §5.3.2, specialised to this law).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import integrate, optimize

__all__ = ["sphere_pressure", "sphere_volume"]

_MM3_PER_ML = 1000.0


def sphere_pressure(a: float, A: float, B: float, C: float, b: float) -> float:
    """Cavity pressure (kPa) holding the inner radius at ``a`` (mm); C in kPa."""
    shift = a**3 - A**3

    def integrand(r: float) -> float:
        R = (r**3 - shift) ** (1.0 / 3.0)
        lt, lr = r / R, (R / r) ** 2
        et, er = 0.5 * (lt**2 - 1.0), 0.5 * (lr**2 - 1.0)
        q = b * (er**2 + 2.0 * et**2)
        return 2.0 * C * b * math.exp(q) * (lt**2 * et - lr**2 * er) / r

    outer = (B**3 + shift) ** (1.0 / 3.0)
    value, _ = integrate.quad(integrand, a, outer, epsabs=1e-12, epsrel=1e-12)
    return value


def sphere_volume(p: float, A: float, B: float, C: float, b: float) -> float:
    """Cavity volume (ml) of the sphere at pressure ``p`` (kPa)."""
    if p == 0.0:
        a = A
    else:
        hi = 1.05 * A
        while sphere_pressure(hi, A, B, C, b) < p:
            hi = A + 2.0 * (hi - A)
        a = optimize.brentq(lambda x: sphere_pressure(x, A, B, C, b) - p, A, hi, xtol=1e-12)
    return 4.0 / 3.0 * math.pi * a**3 / _MM3_PER_ML


def sphere_volumes(pressures, A: float, B: float, C: float, b: float) -> np.ndarray:
    """:func:`sphere_volume` at each pressure."""
    return np.array([sphere_volume(float(p), A, B, C, b) for p in pressures])
