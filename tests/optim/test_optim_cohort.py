"""Cohort fitting from echo reports: parsing and bad rows, the cuff mapping, fits that do not
depend on their neighbours, resume after a kill, and the Dask split giving the same fits."""

import csv
import dataclasses
import json

import numpy as np
import pytest

import lvenv
from lvenv.metrics import OBS_NAMES
from lvenv.validation import InputError
from lvenv.units import mmhg_to_kpa
from optim import cohort
from optim.cohort import CohortError, CohortOptions, cuff_from_central, cuff_targets, fit_reports, read_reports, run_cohort
from scripts import make_cohort

#: Small but real: two CMA-ES generations of 8, the confirmation, streaming through 2 slots.
SMALL = CohortOptions(budget=16, slots=2, confirm_steps=3, steps_per_beat=250)
HEADER = ["id", "EF_pct", "ET_ms", "IVRT_ms", "SBP_mmHg", "DBP_mmHg", "HR_bpm", "site"]
GOOD = ["A", "58", "290", "85", "124", "78", "64", "north"]


def _write(path, rows, header=HEADER):
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


@pytest.fixture(scope="module")
def reports_csv(tmp_path_factory):
    """Four synthetic reports (known truths) with the generator's own columns."""
    rows, _ = make_cohort.draw(4, seed=5, batch=64)
    path = tmp_path_factory.mktemp("cohort") / "reports.csv"
    make_cohort.write(rows, path)
    return path


def test_cuff_pressures_map_to_central_diastolic_and_mean_and_back():
    dia, mean = cuff_targets(120.0, 80.0)
    assert dia == pytest.approx(float(mmhg_to_kpa(80.0)))
    assert mean == pytest.approx(float(mmhg_to_kpa(80.0 + 0.412 * 40.0)))
    sbp, dbp = cuff_from_central(dia, mean)
    assert (sbp, dbp) == pytest.approx((120.0, 80.0))


def test_good_rows_become_patients_with_the_report_targets_and_heart_rate(tmp_path):
    path = _write(tmp_path / "r.csv", [GOOD, ["B", "35", "320", "110", "140", "90", "88", "south"]])
    parsed = read_reports(path)
    assert not parsed.bad and parsed.extra_columns == ["site"]
    a, b = parsed.rows
    assert (a.line, a.id, a.extra) == (2, "A", {"site": "north"})
    assert a.patient.targets == pytest.approx({"EF": 0.58, "ET": 0.29, "IVRT": 0.085, "P_ao_dia": cuff_targets(124, 78)[0],
                                               "P_ao_mean": cuff_targets(124, 78)[1]})
    assert float(a.patient.heart.circulation.HR) == 64.0 and float(b.patient.heart.circulation.HR) == 88.0


def test_a_row_with_a_geometry_gets_its_anatomys_maps_unless_told_to_keep_the_base_ones(tmp_path, monkeypatch):
    """The maps come from the anatomy regression (the shipped artefact) for rows with geometry
    columns, the output's maps cell says so and names an extrapolated column; --maps base keeps
    the base heart's; an artefact that cannot be loaded is refused before any fit."""
    from lvenv import presets
    from lvenv.anatomy import ARTEFACT_ENV, from_geometry

    base = presets.normal()
    header = [*HEADER, "Rb_mm", "L_mm"]
    path = _write(tmp_path / "r.csv", [[*GOOD, "40", "12"], ["B", *GOOD[1:], "60", ""], ["C", *GOOD[1:], "", ""]], header)
    a, b, c = read_reports(path).rows
    assert (a.patient.heart.geometry.Rb, a.patient.heart.geometry.L, a.patient.heart.geometry.Z) == (40.0, 12.0, base.geometry.Z)
    assert a.patient.heart.lo == from_geometry(a.patient.heart.geometry).lo != base.lo
    assert cohort.maps_label(a.patient) == "regression"
    assert cohort.maps_label(b.patient).startswith("regression (Rb_mm = 60 outside the sampled range")
    assert c.patient.heart.lo == base.lo and cohort.maps_label(c.patient) == "base"
    assert all(r.patient.heart.lo == base.lo and cohort.maps_label(r.patient) == "base" for r in read_reports(path, maps="base").rows)
    (result,) = fit_reports([a], dataclasses.replace(SMALL, budget=8))
    assert result["maps"] == cohort._row(result)["maps"] == "regression" and "maps" in cohort.output_columns([])
    monkeypatch.setenv(ARTEFACT_ENV, str(tmp_path / "absent.json"))
    with pytest.raises(CohortError, match=r"has geometry columns.*absent.json.*--maps base"):
        read_reports(path)
    assert len(read_reports(path, maps="base").rows) == 3
    with pytest.raises(CohortError, match=r"has geometry columns"):
        run_cohort(path, tmp_path / "out.csv", SMALL)
    assert not (tmp_path / "out.csv").exists()


BAD = [
    (["C", "58", "", "85", "124", "78", "64", "x"], "ET_ms is missing"),
    (["D", "58", "290", "85", "high", "78", "64", "x"], "SBP_mmHg = 'high' is not a number"),
    (["E", "160", "290", "85", "124", "78", "64", "x"], "EF_pct = 160 must lie in (2, 100]"),
    (["F", "0.6", "290", "85", "124", "78", "64", "x"], "0.6 would be 0.6 %"),
    (["G", "58", "290", "-85", "124", "78", "64", "x"], r"IVRT_ms = -85.0 must be a finite real number in (0, 3000]"),
    (["H", "58", "290", "85", "78", "124", "64", "x"], "DBP_mmHg = 124 must be below SBP_mmHg = 78"),
    (["A", "58", "290", "85", "124", "78", "64", "x"], "id 'A' repeats the row on line 2"),
    (["I", "58", "290", "85", "124", "78", "400", "x"], "HR_bpm = 400"),
    (["J", "58", "900", "300", "124", "78", "100", "x"], "ET_ms + IVRT_ms = 1200 ms must not exceed one beat, 600 ms at HR_bpm = 100"),
    (["N", "58", "290", "85", "700", "500", "64", "x"], "SBP_mmHg = 700.0 must be a finite real number in (0, 300.025]"),
    (["O", "58", "4000", "85", "124", "78", "20", "x"], "ET_ms = 4000.0 must be a finite real number in (0, 3000]"),
    (["K", "58", "290"], "3 fields for 8 columns"),
    (["L", "58", "290", "85", "124", "78", "64", "x", "surplus"], "9 fields for 8 columns"),
    (["", "58", "290", "85", "124", "78", "64", "x"], "id is missing"),
]


def test_each_bad_row_is_reported_with_its_line_and_reason_and_the_rest_are_kept(tmp_path):
    path = _write(tmp_path / "r.csv", [GOOD] + [row for row, _ in BAD] + [["M", *GOOD[1:]]])
    parsed = read_reports(path)
    assert [r.id for r in parsed.rows] == ["A", "M"]
    assert [b.line for b in parsed.bad] == list(range(3, 3 + len(BAD)))
    for bad, (_, reason) in zip(parsed.bad, BAD):
        assert reason in bad.reason, (bad, reason)
        assert "patient" not in bad.reason and "kPa" not in bad.reason, "the CSV's own columns and units"


def test_a_file_without_a_required_column_is_refused_naming_it(tmp_path):
    path = _write(tmp_path / "r.csv", [GOOD[:6] + GOOD[7:]], header=[c for c in HEADER if c != "HR_bpm"])
    with pytest.raises(CohortError, match=r"lacks the required column\(s\) \['HR_bpm'\]"):
        read_reports(path)


def test_a_weight_for_a_target_the_row_lacks_is_a_bad_row(tmp_path):
    path = _write(tmp_path / "r.csv", [["A", *GOOD[1:7], "2", ""], ["B", *GOOD[1:7], "", "3"]],
                  header=HEADER[:7] + ["w_ET", "w_EDV"])
    parsed = read_reports(path)
    assert parsed.rows[0].patient.weights == {"ET": 2.0}
    assert parsed.bad[0].line == 3 and "w_EDV = 3 weights a target the row does not give (EDV_ml)" in parsed.bad[0].reason


def _check_reported_fit_against_an_independent_simulation(result, patient, options):
    heart = patient.heart.replace(**result["parameters"])
    sim = lvenv.simulate(heart, steps_per_beat=options.steps_per_beat, scheme=options.scheme, max_beats=400, traces=False)
    assert sim.status == "ok"
    obs = result["observation"]
    assert result["mismatch"] == pytest.approx(np.mean([abs(obs[k] - t) / t for k, t in patient.targets.items()]), rel=1e-12)
    # the same steady state, reached from another start: the adaptive step sequence differs, so
    # event times agree to a fraction of a millisecond (the scheme's specification is 2 ms)
    for k in patient.targets:
        tol = dict(abs=5e-4) if k in ("ET", "IVRT") else dict(rel=1e-3)
        assert obs[k] == pytest.approx(float(sim.metrics[k]), **tol), k


def test_fits_report_the_confirmed_steady_state_and_do_not_depend_on_their_neighbours(reports_csv):
    reports = read_reports(reports_csv).rows
    together = {r["id"]: r for r in fit_reports(reports, SMALL)}
    assert set(together) == {r.id for r in reports}
    for report in reports:
        result = together[report.id]
        assert result["status"] == "ok" and result["evaluations"] <= SMALL.budget
        assert result["stop"] in ("tolerance", "budget", "optimiser")
        _check_reported_fit_against_an_independent_simulation(result, report.patient, SMALL)
    alone = fit_reports([reports[2], reports[0]], dataclasses.replace(SMALL, slots=1))
    for result in alone:
        assert result == together[result["id"]], "a fit must not depend on the other patients or its slot"
    other_seed = fit_reports([reports[0]], dataclasses.replace(SMALL, seed=1))[0]
    assert other_seed["parameters"] != together[reports[0].id]["parameters"]


def _rows(path):
    with path.open(newline="") as handle:
        return sorted(csv.DictReader(handle), key=lambda r: r["id"])


def test_a_killed_run_resumes_without_refitting_and_gives_the_same_file(reports_csv, tmp_path):
    full = tmp_path / "full.csv"
    summary = run_cohort(reports_csv, full, SMALL)
    assert summary["fitted"] == 4 and summary["status"] == {"ok": 4} and summary["resumed"] == 0
    columns = next(csv.reader(full.open()))
    assert columns[:1] == ["id"] and "true_tau2_s" in columns and "tau2_s" in columns and "mismatch_MAP" in columns
    killed = tmp_path / "killed.csv"
    lines = full.read_text().splitlines(keepends=True)
    killed.write_text("".join(lines[:3]) + lines[3][:20])  # two rows done, a third torn mid-line
    (tmp_path / "killed.csv.json").write_text((tmp_path / "full.csv.json").read_text())
    resumed = run_cohort(reports_csv, killed, SMALL)
    assert resumed["resumed"] == 2 and resumed["fitted"] == 4
    assert _rows(killed) == _rows(full)
    with pytest.raises(CohortError, match="another report file or other options"):
        run_cohort(reports_csv, killed, dataclasses.replace(SMALL, budget=24))


def test_failed_values_are_empty_cells_never_zeros():
    result = {"id": "X", "line": 2, "extra": {}, "parameters": dict.fromkeys(cohort.DEFAULT_ACTION_PARAMS, float("nan")),
              "observation": dict.fromkeys(OBS_NAMES, float("nan")), "targets": {"EF": 0.5},
              "mismatch": float("nan"), "evaluations": 16, "stop": "failed", "status": "diverged", "maps": "base"}
    row = cohort._row(result)
    assert row["tau2_s"] == "" and row["mismatch"] == "" and row["mismatch_EF"] == "" and row["fit_EF_pct"] == ""
    assert row["status"] == "diverged" and row["stop"] == "failed"


def test_a_dask_local_cluster_gives_the_same_fits_as_one_process(reports_csv, tmp_path):
    single, split = tmp_path / "single.csv", tmp_path / "split.csv"
    options = dataclasses.replace(SMALL, slots=1)
    run_cohort(reports_csv, single, options)
    summary = run_cohort(reports_csv, split, options, workers=2)
    assert summary["fitted"] == 4
    assert _rows(split) == _rows(single)
    assert json.loads((tmp_path / "split.csv.json").read_text())["options"]["slots"] == 1
    with pytest.raises(InputError, match=r"scheduler = 'localhost:8786' is not a Dask scheduler address"):
        run_cohort(reports_csv, tmp_path / "elsewhere.csv", options, scheduler="localhost:8786")


def test_a_multi_element_base_heart_takes_a_rows_geometry_with_its_own_regressions_maps_and_onsets(tmp_path):
    """A cohort on the 3-cell series heart (``model``; the fixed scheme): a row without geometry
    fits that heart; a row with its own geometry gets the maps and cells' onsets the 3-cell
    regression predicts (the shipped artefact), or keeps the base heart's with ``maps="base"``;
    both rows fit in one batch, each reported fit being its own heart's steady state."""
    from lvenv.anatomy import from_geometry

    options = dataclasses.replace(SMALL, budget=8, scheme=None, model="series3")
    base = options.base_heart()
    assert base.elements is not None and options.scheme == "fixed"
    path = _write(tmp_path / "r.csv", [[*GOOD, ""], ["B", *GOOD[1:], "40"]], [*HEADER, "Rb_mm"])
    parsed = read_reports(path, base=base)
    own, other = parsed.rows
    assert not parsed.bad and own.patient.heart.elements == base.elements
    predicted = from_geometry(other.patient.heart.geometry, model="series3")
    assert other.patient.heart.geometry.Rb == 40.0 and other.patient.heart.lo == predicted.lo != base.lo
    assert other.patient.heart.elements == predicted.elements and predicted.elements.onsets != base.elements.onsets
    assert predicted.elements.model_key() == base.elements.model_key() and cohort.maps_label(other.patient) == "regression"
    kept = read_reports(path, base=base, maps="base").rows[1].patient.heart
    assert kept.lo == base.lo and kept.elements == base.elements and kept.geometry.Rb == 40.0
    results = fit_reports([own, other], options)
    for result, row in zip(results, (own, other)):
        _check_reported_fit_against_an_independent_simulation(result, row.patient, options)


def test_the_model_option_keeps_old_outputs_resumable_and_refuses_the_adaptive_scheme_for_cells_in_series():
    """The single cell's options record has no ``model`` entry (outputs written before the option
    resume); a multi-element model is recorded and takes the fixed scheme, and the adaptive
    scheme is refused for it."""
    assert "model" not in CohortOptions().to_dict() and CohortOptions().scheme == "adaptive"
    series = CohortOptions(model="series3")
    assert series.to_dict()["model"] == "series3" and series.scheme == "fixed"
    with pytest.raises(InputError, match="model = 'series2' is not one of"):
        CohortOptions(model="series2")
    with pytest.raises(InputError, match="scheme = 'adaptive' is not available for a multi-element heart"):
        CohortOptions(model="series3", scheme="adaptive")
