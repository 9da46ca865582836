"""Unloading an imaged (end-diastolic) ventricle: by the paper's assumed mid-wall strain, and by
the strain at which the LO passive curve reaches the imaged volume."""

import dataclasses

import pytest
from scipy.optimize import brentq

from lvenv import presets
from lvenv.anatomy import ED_STRAIN, inflate, unload, unload_to_volume
from lvenv.coupling import passive_volume
from lvenv.trained import builtin
from lvenv.geometry import Geometry, GeometryError, cavity_volume, wall_volume
from lvenv.validation import InputError


def test_unloading_by_mid_wall_strain_keeps_the_wall_volume_and_shrinks_the_mid_wall():
    ed = presets.HF_END_DIASTOLE
    assert unload(ed, 0.0) == ed
    volumes = []
    for strain in (0.05, ED_STRAIN["N"], ED_STRAIN["HF"], 0.25):
        g = unload(ed, strain)
        assert wall_volume(g) == pytest.approx(wall_volume(ed), rel=1e-9)
        assert (g.Rb - g.L / 2) * (1 + strain) == pytest.approx(ed.Rb - ed.L / 2, rel=1e-12)
        assert (g.Z - g.H / 2) * (1 + strain) == pytest.approx(ed.Z - ed.H / 2, rel=1e-12)
        assert g.L / ed.L == pytest.approx(g.H / ed.H, rel=1e-12) and g.L > ed.L
        assert (g.e, g.C0) == (ed.e, ed.C0)
        volumes.append(cavity_volume(g))
    assert volumes == sorted(volumes, reverse=True) and volumes[-1] < cavity_volume(ed)
    with pytest.raises(InputError, match="strain"):
        unload(ed, -0.1)
    with pytest.raises(GeometryError, match="keeps the wall volume"):
        unload(Geometry(Rb=20.0, L=9.0, Z=30.0, H=8.0, e=0.7, C0=-60.0), 0.9)


def test_inflation_is_the_inverse_of_unloading_and_keeps_the_wall_volume():
    for g, strain in ((presets.N_UNLOADED, ED_STRAIN["N"]), (presets.HF_UNLOADED, ED_STRAIN["HF"]), (presets.N_UNLOADED, 0.3)):
        ed = inflate(g, strain)
        assert cavity_volume(ed) > cavity_volume(g) and ed.L < g.L and ed.H < g.H
        assert wall_volume(ed) == pytest.approx(wall_volume(g), rel=1e-9)
        back = unload(ed, strain)
        assert back.as_tuple() == pytest.approx(g.as_tuple(), rel=1e-9)
    assert inflate(presets.N_UNLOADED, 0.0) == presets.N_UNLOADED


def test_unloading_to_the_imaged_volume_recovers_the_strain_the_passive_curve_implies():
    """An imaged ventricle built as the N anatomy inflated to where the trained N maps' passive
    curve puts it at 1.5 kPa: the search returns that strain and that unloaded shape, and the
    fixed 10 % rule does not; a stiffer passive curve gives a smaller strain."""
    lo, g0, edp = builtin("normal").lo, presets.N_UNLOADED, 1.5
    target = float(passive_volume(edp, cavity_volume(g0), lo))
    strain = brentq(lambda s: cavity_volume(inflate(g0, s)) - target, 0.0, 0.6, xtol=1e-12)
    imaged = inflate(g0, strain)
    unloaded, found = unload_to_volume(imaged, edp, lo=lo)
    assert found == pytest.approx(strain, abs=1e-8) and abs(found - ED_STRAIN["N"]) > 0.01
    assert unloaded.as_tuple() == pytest.approx(g0.as_tuple(), rel=1e-7)
    assert float(passive_volume(edp, cavity_volume(unloaded), lo)) == pytest.approx(cavity_volume(imaged), rel=1e-8)
    stiffer = dataclasses.replace(lo, c=2 * lo.c, b=2 * lo.b, a=2 * lo.a)
    assert unload_to_volume(imaged, edp, lo=stiffer)[1] < found
    with pytest.raises(InputError, match="edp"):
        unload_to_volume(imaged, -1.0, lo=lo)
