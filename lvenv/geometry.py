"""Truncated prolate-spheroid LV geometry (DESIGN §1.3), shared by the LO heart and the FE mesher.

Pure NumPy/SciPy: no JAX, no DOLFINx, so the FE oracle can import it too.

The six parameters (lengths in mm, angle in degrees):

* ``Rb`` outer radius at the base,
* ``L``  wall thickness at the base,
* ``Z``  long-axis length including the apical wall (base plane to outer apex),
* ``H``  apical wall thickness,
* ``e``  meridian shape, 0.5 = cone ... 1.0 = ellipse,
* ``C0`` parametric latitude of the basal cut on the outer surface (negative: below the equator).

Each wall surface is a surface of revolution about the long (z) axis whose meridian is a
superellipse with exponent ``2e`` (our reading of the paper's ``e``)::

    (r / a)^(2e) + (|z| / b)^(2e) = 1,
    r(θ) = a |cos θ|^(1/e),   z(θ) = b sgn(sin θ) |sin θ|^(1/e),   θ ∈ [−90°, C0].

``e = 1`` gives an ellipse (a sphere when a = b); ``e = 0.5`` gives the straight line
``r/a + |z|/b = 1``, i.e. a cone. Both surfaces share the centre (z = 0) and the basal plane.

Outer surface (a_o, b_o) from Rb, Z, C0::

    a_o = Rb / |cos C0|^(1/e)
    b_o = Z / (1 + sgn(C0) |sin C0|^(1/e))
    z_base = b_o sgn(C0) |sin C0|^(1/e)

Inner (endocardial) surface (a_i, b_i) from L, H::

    b_i = b_o − H                                   (apical wall thickness H)
    r_i(z_base) = Rb − L                            (basal wall thickness L)
    ⇒ a_i = (Rb − L) / (1 − (|z_base| / b_i)^(2e))^(1/(2e))

Unloaded cavity volume, the solid of revolution of the inner meridian below the basal plane::

    V0 = π ∫_{−b_i}^{z_base} r_i(z)² dz,   r_i(z) = a_i (1 − (|z|/b_i)^(2e))^(1/(2e))

Values (this reading): N unloaded V0 = 35.81 ml, HF unloaded V0 = 40.83 ml (docs, "The model").
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from scipy import integrate

from lvenv.validation import InputError, real

__all__ = ["Geometry", "GeometryError", "cavity_volume", "wall_volume", "surfaces", "meridian"]

_MM3_PER_ML = 1000.0


class GeometryError(InputError):
    """An impossible geometry (e.g. a wall thicker than the radius)."""


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Six-parameter truncated prolate spheroid. Lengths in mm, ``C0`` in degrees."""

    Rb: float
    L: float
    Z: float
    H: float
    e: float
    C0: float

    def __post_init__(self) -> None:
        validate(self)

    def as_tuple(self) -> tuple[float, ...]:
        return tuple(float(getattr(self, f.name)) for f in dataclasses.fields(self))


@dataclasses.dataclass(frozen=True)
class Surfaces:
    """Semi-axes (mm) of the outer and inner superellipse meridians, and the basal plane z (mm)."""

    a_outer: float
    b_outer: float
    a_inner: float
    b_inner: float
    z_base: float
    e: float


def _ranged(name: str, value: float, lo: float, hi: float, *, lo_open: bool = False) -> None:
    try:
        real(f"geometry.{name}", value, lo, hi, lo_open=lo_open)
    except ValueError as err:
        raise GeometryError(str(err)) from None


def validate(g: Geometry) -> None:
    """Raise :class:`GeometryError` naming the field, value and range if ``g`` is impossible."""
    _ranged("Rb", g.Rb, 0.0, 200.0, lo_open=True)
    _ranged("L", g.L, 0.0, 100.0, lo_open=True)
    _ranged("Z", g.Z, 0.0, 400.0, lo_open=True)
    _ranged("H", g.H, 0.0, 100.0, lo_open=True)
    _ranged("e", g.e, 0.5, 1.0)
    _ranged("C0", g.C0, -89.0, 60.0)
    if g.L >= g.Rb:
        raise GeometryError(f"geometry.L = {g.L} mm (basal wall) must be thinner than geometry.Rb = {g.Rb} mm (outer radius)")
    if g.H >= g.Z:
        raise GeometryError(f"geometry.H = {g.H} mm (apical wall) must be shorter than geometry.Z = {g.Z} mm (long axis)")
    s = _surfaces_unchecked(g)
    if s.b_inner <= abs(s.z_base) and s.z_base < 0:
        raise GeometryError(
            f"geometry.H = {g.H} mm leaves no cavity: the inner apex lies above the basal plane "
            f"(inner semi-axis {s.b_inner:.2f} mm ≤ |z_base| {abs(s.z_base):.2f} mm)"
        )
    z = np.linspace(-s.b_inner, s.z_base, 200)
    if np.any(_radius(z, s.a_inner, s.b_inner, s.e) >= _radius(z, s.a_outer, s.b_outer, s.e) - 1e-9):
        raise GeometryError(
            f"geometry (L={g.L}, H={g.H}, e={g.e}, C0={g.C0}) gives an endocardium that crosses the epicardium"
        )


def _surfaces_unchecked(g: Geometry) -> Surfaces:
    inv_e = 1.0 / g.e
    c0 = math.radians(g.C0)
    sin_term = math.copysign(abs(math.sin(c0)) ** inv_e, c0)
    a_o = g.Rb / abs(math.cos(c0)) ** inv_e
    b_o = g.Z / (1.0 + sin_term)
    z_base = b_o * sin_term
    b_i = b_o - g.H
    ratio = min(abs(z_base) / b_i, 1.0) if b_i > 0 else 1.0
    denom = (1.0 - ratio ** (2.0 * g.e)) ** (1.0 / (2.0 * g.e))
    a_i = (g.Rb - g.L) / denom if denom > 0 else math.inf
    return Surfaces(a_o, b_o, a_i, b_i, z_base, g.e)


def surfaces(g: Geometry) -> Surfaces:
    """Semi-axes of both wall surfaces and the basal plane (mm) for a validated geometry."""
    return _surfaces_unchecked(g)


def _radius(z: np.ndarray, a: float, b: float, e: float) -> np.ndarray:
    s = np.clip(np.abs(z) / b, 0.0, 1.0)
    return a * (1.0 - s ** (2.0 * e)) ** (1.0 / (2.0 * e))


def meridian(g: Geometry, which: str = "inner", n: int = 64) -> np.ndarray:
    """Points (r, z) in mm along the ``inner`` or ``outer`` meridian, apex to base, shape (n, 2).

    Sampled uniformly in the parametric latitude θ ∈ [−90°, θ_base], where θ_base is the
    latitude at which the surface meets the basal plane (C0 for the outer surface).
    """
    if which not in ("inner", "outer"):
        raise InputError(f"which must be 'inner' or 'outer', got {which!r}")
    s = surfaces(g)
    a, b = (s.a_inner, s.b_inner) if which == "inner" else (s.a_outer, s.b_outer)
    sin_base = math.copysign((abs(s.z_base) / b) ** g.e, s.z_base)
    theta = np.linspace(-math.pi / 2, math.asin(sin_base), n)
    r = a * np.abs(np.cos(theta)) ** (1.0 / g.e)
    z = b * np.sign(np.sin(theta)) * np.abs(np.sin(theta)) ** (1.0 / g.e)
    r[0] = 0.0
    return np.stack([r, z], axis=1)


def _volume_of_revolution(a: float, b: float, e: float, z_base: float) -> float:
    value, _ = integrate.quad(lambda z: math.pi * _radius(np.asarray(z), a, b, e) ** 2, -b, z_base, epsabs=1e-10, epsrel=1e-12, limit=200)
    return float(value)


@functools.lru_cache(maxsize=4096)
def _cavity_volume_cached(params: tuple[float, ...]) -> float:
    s = _surfaces_unchecked(Geometry(*params))
    return _volume_of_revolution(s.a_inner, s.b_inner, s.e, s.z_base) / _MM3_PER_ML


def cavity_volume(g: Geometry) -> float:
    """Unloaded cavity volume V0 in ml (module docstring for the formula)."""
    return _cavity_volume_cached(g.as_tuple())


def wall_volume(g: Geometry) -> float:
    """Myocardial wall volume in ml (outer solid minus cavity, both below the basal plane)."""
    s = surfaces(g)
    outer = _volume_of_revolution(s.a_outer, s.b_outer, s.e, s.z_base) / _MM3_PER_ML
    return outer - cavity_volume(g)
