"""Unloading an imaged (end-diastolic) ventricle by the paper's assumed mid-wall strain."""

import pytest

from lvenv import presets
from lvenv.anatomy import ED_STRAIN, unload
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
