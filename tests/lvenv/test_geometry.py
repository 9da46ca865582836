import math

import numpy as np
import pytest

from lvenv import presets
from lvenv.geometry import Geometry, GeometryError, cavity_volume, meridian, surfaces, wall_volume


def test_preset_volumes_are_tens_of_millilitres():
    assert cavity_volume(presets.N_UNLOADED) == pytest.approx(35.81, abs=0.01)
    assert cavity_volume(presets.HF_UNLOADED) == pytest.approx(40.83, abs=0.01)
    assert 20 < wall_volume(presets.N_UNLOADED) < 200


def test_surfaces_honour_the_six_parameters():
    g = presets.N_UNLOADED
    s = surfaces(g)
    outer, inner = meridian(g, "outer", 400), meridian(g, "inner", 400)
    # basal outer radius Rb, basal wall thickness L, long axis Z, apical wall H
    assert outer[-1, 0] == pytest.approx(g.Rb, rel=1e-9)
    assert outer[-1, 1] == pytest.approx(s.z_base, rel=1e-9)
    assert inner[-1, 0] == pytest.approx(g.Rb - g.L, rel=1e-9)
    assert inner[-1, 1] == pytest.approx(s.z_base, rel=1e-9)
    assert s.z_base - outer[0, 1] == pytest.approx(g.Z, rel=1e-9)
    assert inner[0, 1] - outer[0, 1] == pytest.approx(g.H, rel=1e-9)
    # every meridian point lies on its superellipse
    for pts, a, b in ((outer, s.a_outer, s.b_outer), (inner, s.a_inner, s.b_inner)):
        lhs = (pts[:, 0] / a) ** (2 * g.e) + (np.abs(pts[:, 1]) / b) ** (2 * g.e)
        np.testing.assert_allclose(lhs, 1.0, rtol=1e-9)


def test_volume_matches_closed_forms_for_ellipse_and_cone():
    # e = 1: ellipsoidal cap, V = π a²/b² ∫ (b² − z²) dz from −b to z_base
    g = Geometry(Rb=30.0, L=8.0, Z=60.0, H=10.0, e=1.0, C0=-20.0)
    s = surfaces(g)
    zb, a, b = s.z_base, s.a_inner, s.b_inner
    exact = math.pi * a**2 / b**2 * ((b**2 * zb - zb**3 / 3) - (-(b**3) + b**3 / 3)) / 1000.0
    assert cavity_volume(g) == pytest.approx(exact, rel=1e-9)
    # e = 0.5: cone with apex at −b, radius r(z) = a (1 − |z|/b)
    g = Geometry(Rb=30.0, L=8.0, Z=60.0, H=10.0, e=0.5, C0=-40.0)
    s = surfaces(g)
    height = s.b_inner - abs(s.z_base)
    r_base = s.a_inner * height / s.b_inner
    assert r_base == pytest.approx(g.Rb - g.L, rel=1e-9)
    assert cavity_volume(g) == pytest.approx(math.pi * r_base**2 * height / 3 / 1000.0, rel=1e-9)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(L=40.0), "geometry.L"),
        (dict(H=60.0), "geometry.H"),
        (dict(e=0.3), "geometry.e"),
        (dict(Rb=float("nan")), "geometry.Rb"),
        (dict(C0=-95.0), "geometry.C0"),
    ],
)
def test_impossible_geometries_are_rejected_with_the_field(kwargs, field):
    base = dict(Rb=35.0, L=9.6, Z=54.0, H=12.0, e=0.7, C0=-53.0)
    base.update(kwargs)
    with pytest.raises(GeometryError, match=field):
        Geometry(**base)


def test_endocardium_crossing_the_epicardium_is_rejected():
    # cut above the equator with a thin basal wall: the inner surface bulges through the outer
    with pytest.raises(GeometryError, match="crosses the epicardium"):
        Geometry(Rb=20.0, L=0.5, Z=20.0, H=0.2, e=0.7, C0=59.0)
