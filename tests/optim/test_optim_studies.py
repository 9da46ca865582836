"""`optim.studies.retune` and `map_transfer`: maps refitted on each unseen scenario's own oracle
beat, and carried along the scenario's axis, against an oracle that is the LO heart itself with
known maps (the multi-element backend with one element). Whatever the frozen maps were, the
retuned maps must come back to those maps and C to zero, at the scenario's end, at its interior
point and at the training beat, so the maps carried from them along the axis must fit too. The
smooth maps of scripts/smooth_maps.py are checked against the same oracle."""

import dataclasses

import numpy as np
import pytest

from lvenv import presets
from lvenv.validation import InputError
from optim import studies

#: The oracle's maps: Table 3 with μ1 at the one-element value of the parallel arrangement.
TRUTH = dataclasses.replace(presets.N_LO, mu1=0.0945, mu2=0.2, gamma=2.5, delay=0.03)
NAMES = ("mu1", "mu2", "delay")


def test_retuned_maps_recover_the_scenario_beats_maps_and_carry_along_its_axis(tmp_path):
    heart = dataclasses.replace(presets.normal(lo="table3"), lo=dataclasses.replace(TRUTH, mu1=0.08, mu2=0.24, delay=0.04))
    (row,) = studies.map_transfer(heart, {"n0_0.9": studies.UNSEEN["n0_0.9"]}, "multielement", names=NAMES, budget=96, progress=False,
                                  arrangement="parallel", n_elements=1, lo=TRUTH, cache_dir=tmp_path)
    _recovered(row, heart, NAMES)
    assert row["C_extrapolated"] < 1e-3 and row["interior"]["C_interpolated"] < 1e-3


def test_a_passive_map_is_retuned_within_its_box_and_carried_maps_that_fail_validation_get_no_c(tmp_path, monkeypatch):
    """A name outside ACTIVE_BOUNDS (the passive map's c) is refitted within the box given for
    it; a carried heart that `lvenv.params.validate` refuses (here: the interior point's) gets C =
    NaN, and the other carried beat its own C."""
    names = (*NAMES, "c")
    heart = dataclasses.replace(presets.normal(lo="table3"), lo=dataclasses.replace(TRUTH, mu1=0.08, mu2=0.24, delay=0.04, c=1.3 * TRUTH.c))
    monkeypatch.setattr(studies, "passes_validation", lambda h, real=studies.passes_validation: h.cell.n0 != 0.8 and real(h))
    (row,) = studies.map_transfer(heart, {"n0_0.9": studies.UNSEEN["n0_0.9"]}, "multielement", names=names, budget=160, progress=False,
                                  bounds={"c": (0.5 * TRUTH.c, 2.0 * TRUTH.c)}, arrangement="parallel", n_elements=1, lo=TRUTH, cache_dir=tmp_path)
    _recovered(row, heart, names)
    assert row["C_extrapolated"] < 1e-3 and np.isnan(row["interior"]["C_interpolated"])


def _recovered(row: dict, heart, names) -> None:
    """The retuned maps of ``row`` are the oracle's, at the scenario's end and its interior point."""
    assert row["scenario"] == "n0_0.9" and row["change"] == {"n0": 0.9}
    assert row["C_frozen"] > 0.05 and row["C_retuned"] < 1e-4
    assert row["P_error_frozen"] > 0.05 and row["P_error_retuned"] < 1e-3
    for name in names:
        assert row["retuned"][name] == pytest.approx(getattr(TRUTH, name), rel=1e-3), name
        assert row["frozen"][name] == getattr(heart.lo, name)
    for where in (row["where_frozen"], row["where_retuned"]):
        assert set(where["share"]) == {"upstroke", "ejection", "relaxation", "filling"}
        assert sum(where["share"].values()) == pytest.approx(1.0) and min(where["share"].values()) >= 0.0
    inner = row["interior"]
    assert inner["scenario"] == studies.INTERIOR["n0_0.9"][0] == "n0_0.8"
    assert inner["C_frozen"] > 0.02 and inner["C_retuned"] < 1e-4


def test_a_scenario_without_an_interior_point_is_refused_by_name():
    with pytest.raises(InputError, match=r"\['sa_x2'\] have no point inside their axis"):
        studies.map_transfer(presets.normal(), {"sa_x2": {"Sa": 2.0}}, "multielement")


def test_smooth_maps_are_the_trained_ones_at_the_training_beats_and_stay_in_their_boxes():
    """scripts/smooth_maps.py: x = 0 gives the trained maps at any position, second order adds x2
    f² to the exponent, and the x box of a position (order 1) puts its maps on the boxes' edges,
    on either side of the training beat."""
    from scripts.smooth_maps import DELAY_UNIT, Carry

    heart = presets.normal()
    carry = Carry(heart, ("mu1", "delay", "a"))
    np.testing.assert_array_equal(carry.maps(np.zeros(3), 2.0), [heart.lo.mu1, heart.lo.delay, heart.lo.a])
    assert carry.maps(np.array([np.log(2.0), 1.0, 0.0]), 1.5) == pytest.approx([heart.lo.mu1 * 2.0**1.5, heart.lo.delay + 1.5 * DELAY_UNIT, heart.lo.a])
    second = Carry(heart, ("mu1", "delay", "a"), order=2)
    assert second.maps(np.array([0.0, 0.0, 0.0, np.log(2.0), 1.0, 0.0]), 1.5) == pytest.approx([heart.lo.mu1 * 2.0**2.25, heart.lo.delay + 2.25 * DELAY_UNIT, heart.lo.a])
    for f in (2.0, -1.0):
        lower, upper = carry.x_box(f)
        assert np.all(lower < 0) and np.all(upper > 0)
        np.testing.assert_allclose(np.sort(np.stack([carry.maps(lower, f), carry.maps(upper, f)]), axis=0), [carry.lower, carry.upper], rtol=1e-12)


def test_smooth_maps_fit_the_inner_beats_and_a_large_ridge_keeps_the_trained_maps(tmp_path):
    """Against an oracle with other maps (the LO heart itself, one element), the carried maps fit
    the interior point's beat (from x = 0, least squares), and at second order the outer point's
    too, and are carried to the end (at first order, the outer point is held out); with a ridge far
    above C² they stay the trained ones, so the end's and the held-out point's C are the frozen
    maps'. ``check_dt`` measures the end against the oracle's beat at that time step too, which
    moves each C by no more than the oracle's own change."""
    from scripts.smooth_maps import study

    heart = dataclasses.replace(presets.normal(lo="table3"), lo=dataclasses.replace(TRUTH, mu1=0.08, mu2=0.24, delay=0.04))
    options = dict(arrangement="parallel", n_elements=1, lo=TRUTH, cache_dir=tmp_path)
    one = {"n0_0.9": studies.UNSEEN["n0_0.9"]}
    (fitted,) = study("N", heart, NAMES, 0.0, scenarios=one, backend="multielement", check_dt=0.0005, **options)
    (kept,) = study("N", heart, NAMES, 1e8, scenarios=one, backend="multielement", **options)
    (point,) = fitted["fitted"]
    (held,) = kept["held_out"]
    assert held["scenario"] == "n0_0.85" and fitted["held_out"][0]["scenario"] == "n0_0.85", "order 1 holds the outer point out"
    assert held["C_carried"] == pytest.approx(held["C_frozen"], rel=1e-3) and held["C_frozen"] > 0.02
    assert point["scenario"] == "n0_0.8" and fitted["w"] == pytest.approx((0.9 - heart.cell.n0) / (0.8 - heart.cell.n0))
    assert point["C_frozen"] > 0.02 and point["C_fitted"] < 1e-3, "the truth's maps are reachable at the interior point"
    assert fitted["x"][0][0] == pytest.approx(np.log(TRUTH.mu1 / heart.lo.mu1), rel=1e-2), "mu1"
    assert np.max(np.abs(kept["x"])) < 1e-4 and "end_check" not in kept
    check = fitted["end_check"]
    assert check["dt"] == 0.0005 and 0.0 < check["oracle_C"] < 0.01
    for k in ("frozen", "carried"):
        assert abs(check[f"{k}_C"] - fitted[f"end_C_{k}"]) <= 2.0 * check["oracle_C"], k
    (second,) = study("N", heart, NAMES, 0.0, order=2, scenarios=one, backend="multielement", **options)
    assert [p["scenario"] for p in second["fitted"]] == ["n0_0.8", "n0_0.85"] and len(second["x"]) == 2 and second["held_out"] == []
    assert all(p["C_frozen"] > 0.02 and p["C_fitted"] < 1e-3 for p in second["fitted"])
    assert kept["end_C_carried"] == pytest.approx(kept["end_C_frozen"], rel=1e-3) and kept["end_C_frozen"] == fitted["end_C_frozen"]


def test_the_pointwise_errors_skip_the_oracles_first_sample_only():
    """At t = 0 the FE wall carries no active tension yet while the LO pressure carries its resting
    cells' (`studies._errors`): a miss there alone counts in C but not in the largest pointwise
    error, while the same miss one sample later counts in both."""
    t = np.linspace(0.0, 0.8, 161)
    shape = np.sin(np.pi * t / 0.8) ** 2
    oracle = {"t": t, "V": 120.0 - 50.0 * shape, "P_lv": 0.66 + 12.0 * shape}
    first, second = oracle["P_lv"].copy(), oracle["P_lv"].copy()
    first[0] += 1.5
    second[1] += 1.5
    at_start, later = studies._errors(oracle, t, oracle["V"], first), studies._errors(oracle, t, oracle["V"], second)
    assert at_start["C"] > 0.0 and at_start["max_rel_error_P"] == 0.0 and at_start["max_rel_error_V"] == 0.0
    assert later["max_rel_error_P"] == pytest.approx(1.5 / oracle["P_lv"].max())
