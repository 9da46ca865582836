"""Trained-LO records read from disk: a round trip, and every damaged field refused by name."""

import json

import pytest

from lvenv import trained
from lvenv.trained import TrainedLO
from lvenv.validation import InputError


def test_the_shipped_records_round_trip(tmp_path):
    for name in ("normal", "heart_failure", "normal_series3", "heart_failure_series3"):
        record = trained.builtin(name)
        record.to_json(tmp_path / f"{name}.json")
        assert TrainedLO.from_json(tmp_path / f"{name}.json") == record
        assert record.heart().elements == record.elements


def test_the_series3_records_carry_their_wall_and_the_single_cells_passive_maps():
    """Each 3-cell record: the single-cell record's wall, cell and passive maps (train_model
    refits the active ones only), and its own onsets, increasing, with the median cell at 0."""
    for name in ("normal", "heart_failure"):
        single, series = trained.builtin(name), trained.builtin(f"{name}_series3")
        assert single.elements is None and series.elements.kind == "series" and series.elements.n_elements == 3
        assert (series.geometry, series.cell, series.passive_rmse_ml) == (single.geometry, single.cell, single.passive_rmse_ml)
        assert all(getattr(series.lo, n) == getattr(single.lo, n) for n in ("alpha", "beta", "a", "b", "c"))
        early, median, late = series.elements.onsets
        assert early < median == 0.0 < late


def test_a_record_without_elements_is_the_single_cell():
    record = trained.builtin("normal").to_dict()
    record.pop("elements")
    assert TrainedLO.from_dict(record).elements is None


def _drop(part, field):
    return lambda r: r[part].pop(field)


def _set(part, field, value):
    return lambda r: r[part].__setitem__(field, value)


@pytest.mark.parametrize(
    "damage, message",
    [
        (_drop("lo", "mu1"), r"lo lacks the field\(s\) \['mu1'\]"),
        (_drop("cell", "tau2"), r"cell lacks the field\(s\) \['tau2'\]"),
        (_drop("geometry", "Rb"), r"geometry lacks the field\(s\) \['Rb'\]"),
        (lambda r: r.pop("congruency"), r"record lacks the field\(s\) \['congruency'\]"),
        (_set("lo", "mu1", "0.2"), r"lo.mu1 = '0.2' must be a finite real number"),
        (_set("lo", "mu1", None), r"lo.mu1 = None must be a finite real number"),
        (_set("cell", "Sa", [1.0, 2.0]), r"cell.Sa = \[1.0, 2.0\] must be a finite real number"),
        (_set("cell", "Sa", True), r"cell.Sa = True must be a finite real number"),
        (_set("lo", "mu1", 5.0), r"lo.mu1 = 5 is outside the allowed range \[0.001, 1\]"),
        (_set("lo", "extra", 1.0), r"lo has the unknown field\(s\) \['extra'\]"),
        (lambda r: r.__setitem__("lo", [0.1, 0.2]), r"lo = \[0.1, 0.2\] must be an object"),
        (lambda r: r.__setitem__("passive_rmse_ml", "small"), r"passive_rmse_ml = 'small' must be a finite real number ≥ 0"),
        (_set("congruency", "C", "good"), r"congruency\['C'\] = 'good' must be a finite real number ≥ 0"),
        (lambda r: r.__setitem__("elements", "series"), r"elements = 'series' must be null \(the single-cell heart\) or an object"),
        (lambda r: r.__setitem__("elements", {"kind": "series", "n_elements": 3, "onsets": [0.0]}), r"elements: onsets = \(0.0,\) must give one onset"),
        (lambda r: r.__setitem__("elements", {"kind": "ring"}), r"arrangement = 'ring' is not one of 'parallel', 'series'"),
    ],
)
def test_a_damaged_record_is_refused_naming_the_field(tmp_path, damage, message):
    record = trained.builtin("normal").to_dict()
    damage(record)
    path = tmp_path / "damaged.json"
    path.write_text(json.dumps(record))
    with pytest.raises(InputError, match=message) as err:
        TrainedLO.from_json(path)
    assert str(path) in str(err.value)


def test_a_file_that_is_not_json_text_is_refused_naming_it(tmp_path):
    for content in (b"\x89PNG\r\n\x1a\n\x00\x00", b"{\"lo\": "):
        path = tmp_path / "bad.json"
        path.write_bytes(content)
        with pytest.raises(InputError, match="cannot read the trained-LO record"):
            TrainedLO.from_json(path)
