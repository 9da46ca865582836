"""`optim.studies.retune`: maps refitted on each unseen scenario's own oracle beat, against an oracle
that is the LO heart itself with known maps (the multi-element backend with one element), so the
retuned maps must come back to those maps and C to zero, whatever the frozen maps were."""

import dataclasses

import pytest

from lvenv import presets
from optim import studies

#: The oracle's maps: Table 3 with μ1 at the one-element value of the parallel arrangement.
TRUTH = dataclasses.replace(presets.N_LO, mu1=0.0945, mu2=0.2, gamma=2.5, delay=0.03)


def test_retune_recovers_the_maps_of_the_scenario_beat_that_frozen_maps_miss(tmp_path):
    heart = dataclasses.replace(presets.normal(lo="table3"), lo=dataclasses.replace(TRUTH, mu1=0.08, mu2=0.24, delay=0.04))
    scenarios = {"n0_0.9": studies.UNSEEN["n0_0.9"]}
    rows = studies.retune(heart, scenarios, "multielement", names=("mu1", "mu2", "delay"), budget=96, progress=False,
                          arrangement="parallel", n_elements=1, lo=TRUTH, cache_dir=tmp_path)
    (row,) = rows
    assert row["scenario"] == "n0_0.9" and row["change"] == {"n0": 0.9}
    assert row["C_frozen"] > 0.05
    assert row["C_retuned"] < 1e-4
    for name in ("mu1", "mu2", "delay"):
        assert row["retuned"][name] == pytest.approx(getattr(TRUTH, name), rel=1e-3), name
        assert row["frozen"][name] == getattr(heart.lo, name)
    assert set(row["retuned"]) == {"mu1", "mu2", "delay"}
