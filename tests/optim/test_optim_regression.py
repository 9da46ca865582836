"""The anatomy regression: cross-validation on a known smooth map, the artefact's round trip to
`lvenv.anatomy.from_geometry` (predictions equal scikit-learn's own), the warning outside the box
and clear errors for malformed artefacts; a multi-element heart's regression with its cells'
onsets, and the records that take it."""

import csv
import dataclasses
import json
import warnings

import numpy as np
import pytest

from lvenv import anatomy
from lvenv.anatomy import ExtrapolationWarning, Regression
from lvenv.geometry import Geometry
from lvenv.validation import InputError
from optim import campaign, regression
from optim.campaign import Settings
from optim.cohort import GEOMETRY_COLUMNS

N = 40


def _truth(g: dict) -> dict:
    """A smooth map from geometry to trained values, of the size the FE campaign gives."""
    return {"mu1": 0.15 + 0.004 * (g["Rb"] - 37) - 0.006 * (g["L"] - 10), "mu2": 0.16 + 0.01 * np.sin((g["Z"] - 53) / 10),
            "gamma": 2.0 + 0.05 * (g["H"] - 9) ** 2 / 4, "alpha": 0.7, "beta": 3.0 + 2.0 * (g["e"] - 0.7), "a": 2.2 + 0.01 * (g["C0"] + 60),
            "b": -1.6 + 0.02 * (g["Rb"] - 37), "c": 2.3 - 0.03 * (g["L"] - 10), "delay": 0.04 + 0.001 * (g["Z"] - 53), "C": 0.05 + 0.002 * (g["L"] - 10)}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A campaign folder whose anatomies carry trained values from :func:`_truth` plus 0.5 % noise,
    except α, which training keeps fixed."""
    directory = tmp_path_factory.mktemp("anatomy")
    campaign.run(directory, n=N, held_out=3, seed=2, settings=Settings(backend="multielement", budget=16), limit=0)
    rows = campaign.read_index(directory)
    rng = np.random.default_rng(0)
    for row in rows:
        g = {name: row[col] for col, name in GEOMETRY_COLUMNS.items()}
        row.update({k: v * (1 + 0.005 * rng.standard_normal()) for k, v in _truth(g).items()}, alpha=0.7, status="accepted", reason="", oracle_code="x")
    with (directory / "anatomies.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, campaign.COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    return directory


@pytest.fixture(scope="module")
def fitted(dataset):
    return regression.fit(dataset, restarts=0, folds=5)


def test_cross_validation_recovers_a_smooth_map_with_calibrated_intervals(fitted):
    assert set(fitted.outputs) == set(regression.OUTPUTS)
    for name in ("mu1", "mu2", "b", "c", "delay", "C"):
        cv = fitted.outputs[name]["cv"]
        assert cv["r2"] > 0.9, (name, cv)
        assert 0.75 <= cv["coverage_2sd"] <= 1.0, (name, cv)
    assert fitted.ids == tuple(f"A{i:03d}" for i in range(N))  # the held-out anatomies stay out


def test_an_output_training_kept_fixed_is_predicted_exactly_with_no_spread(fitted, tmp_path):
    """α is 0.7 on every anatomy: no GP, no cross-validation figures, the value with sd 0 and
    every map draw at it, through the saved artefact too."""
    from lvenv.anatomy import map_draws

    assert fitted.outputs["alpha"] == {"mean": 0.7, "fixed": True}
    assert "alpha" not in fitted.provenance["cv_predictions"]
    geometry = Geometry(35.0, 9.6, 54.0, 12.0, 0.70, -53.0)
    loaded = Regression.load(regression.save(fitted, tmp_path / "regression.json"))
    mean, sd = loaded.predict([geometry, Geometry(40.0, 12.0, 60.0, 8.0, 0.6, -70.0)], ["alpha", "mu1"])
    assert mean["alpha"].tolist() == [0.7, 0.7] and sd["alpha"].tolist() == [0.0, 0.0] and np.all(sd["mu1"] > 0)
    draws = map_draws(geometry, 5, regression=loaded)
    assert {d.alpha for d in draws} == {0.7} and len({d.mu1 for d in draws}) == 5
    # a log output's draws are log-normal around its predicted median
    mean, sd = loaded.latent([geometry], ["mu1"])
    z = (np.log([d.mu1 for d in map_draws(geometry, 400, regression=loaded, seed=1)]) - mean["mu1"][0]) / sd["mu1"][0]
    assert abs(z.mean()) < 0.2 and 0.85 < z.std() < 1.15


def test_artefact_round_trip_predicts_what_scikit_learn_predicts(fitted, dataset, tmp_path):
    path = regression.save(fitted, tmp_path / "regression.json")
    loaded = Regression.load(path)
    ids, x, y = regression.training_set(dataset, split="heldout")
    geometries = [Geometry(*row) for row in x]
    mean, sd = loaded.predict(geometries)
    latent_mean, latent_sd = loaded.latent(geometries)
    # the reference: scikit-learn fitted afresh on the same standardised data with the same restarts
    xs = (x - fitted.x_mean) / fitted.x_scale
    for name in ("mu1", "b", "delay", "C"):
        spec = fitted.outputs[name]
        gp = regression.fit_gp(fitted.x, fitted.y[name], restarts=0, seed=0)
        m, s = gp.predict(xs, return_std=True)
        np.testing.assert_allclose(latent_mean[name], m * spec["scale"] + spec["mean"], rtol=1e-6)
        np.testing.assert_allclose(latent_sd[name], s * spec["scale"], rtol=1e-4)
    # positive outputs are regressed in log and predicted as the log-normal's median and sd; b (negative) is not
    assert {n for n, spec in fitted.outputs.items() if spec.get("log")} == set(regression.OUTPUTS) - {"alpha", "b"}
    np.testing.assert_allclose(mean["mu1"], np.exp(latent_mean["mu1"]), rtol=1e-12)
    np.testing.assert_allclose(sd["mu1"], mean["mu1"] * np.sqrt(np.expm1(latent_sd["mu1"] ** 2)), rtol=1e-12)
    assert mean["b"].tolist() == latent_mean["b"].tolist() and np.all(mean["b"] < 0)
    trained = anatomy.from_geometry(geometries[0], loaded)
    assert trained.lo.mu1 == pytest.approx(mean["mu1"][0]) and trained.provenance["sd"]["mu1"] == pytest.approx(sd["mu1"][0])
    assert trained.congruency["C"] == pytest.approx(mean["C"][0]) and not trained.provenance["outside_box"]
    assert trained.heart().geometry == geometries[0]


def test_a_geometry_outside_the_box_is_predicted_with_a_warning_naming_the_parameter(fitted):
    with pytest.warns(ExtrapolationWarning, match=r"geometry.Rb = 55 outside the sampled range \[28, 46\]"):
        trained = anatomy.from_geometry(Geometry(55.0, 10.0, 55.0, 10.0, 0.7, -60.0), fitted)
    assert trained.provenance["outside_box"] and np.isfinite(trained.lo.mu1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        anatomy.from_geometry(Geometry(35.0, 9.6, 54.0, 12.0, 0.70, -53.0), fitted)


def test_malformed_or_missing_artefacts_are_refused_naming_the_problem(fitted, tmp_path):
    record = fitted.to_dict()
    cases = {
        "format": (record | {"format": 7}, "has format 7"),
        "length": (record | {"outputs": record["outputs"] | {"mu1": record["outputs"]["mu1"] | {"length_scale": [1.0]}}}, "outputs.mu1.length_scale has 1"),
        "noise": (record | {"outputs": record["outputs"] | {"mu1": record["outputs"]["mu1"] | {"noise": None}}}, "outputs.mu1.noise"),
        "log": (record | {"outputs": record["outputs"] | {"mu1": record["outputs"]["mu1"] | {"log": "yes"}}}, "outputs.mu1.log = 'yes'"),
        "missing": ({k: v for k, v in record.items() if k != "x"}, "KeyError: 'x'"),
        "ids": (record | {"ids": record["ids"][:-1]}, "one entry per anatomy"),
    }
    for name, (bad, message) in cases.items():
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=message):
            Regression.load(path)
    (tmp_path / "junk.json").write_bytes(b"\xff\xfe not json")
    with pytest.raises(InputError, match="cannot read the anatomy regression"):
        Regression.load(tmp_path / "junk.json")
    with pytest.raises(InputError, match="lvenv campaign regress"):
        Regression.load(tmp_path / "absent.json")
    with pytest.raises(InputError, match="no output 'zeta'"):
        fitted.predict([Geometry(35.0, 9.6, 54.0, 12.0, 0.70, -53.0)], ["zeta"])


def _onsets(g: dict) -> tuple[float, float, float]:
    """Cells' onsets (s) that follow the geometry smoothly: a longer, thicker wall activates over longer."""
    spread = 0.02 + 0.0004 * (g["Z"] - 53) + 0.001 * (g["L"] - 10)
    return -spread, 0.0, 1.4 * spread


def test_a_multi_element_models_regression_predicts_its_maps_and_its_cells_onsets(dataset, tmp_path):
    """A 3-cell table (trained values and onsets that follow the geometry, for some of the
    anatomies): its regression predicts the onsets (the median cell's, 0 on every anatomy,
    exactly), leaves the anatomies the table lacks out, and a record from it carries the cells;
    it is refused where the single cell's is asked for, and a table of other columns is refused."""
    import shutil

    from lvenv.cli import main

    dataset = shutil.copytree(dataset, tmp_path / "dataset")
    columns = campaign.model_columns("series3")
    rows = [r for r in campaign.read_index(dataset) if r["id"] != "A005"]
    table = campaign.model_table_path(dataset, "series3")
    table.parent.mkdir()
    with table.open("w", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(columns)
        for r in rows:
            g = {name: r[col] for col, name in GEOMETRY_COLUMNS.items()}
            values = {**r, "gamma": 0.5 * r["gamma"], "C_1": r["C"], "C_2": r["C"], "C_3": r["C"], **dict(zip(("onset_1", "onset_2", "onset_3"), _onsets(g))), "train_s": 1.0, "finished": "x"}
            writer.writerow([values[c] for c in columns])
    path = tmp_path / "series3.json"
    assert main(["campaign", "regress", str(dataset), "--model", "series3", "--out", str(path), "--restarts", "0", "--folds", "3", "--json"]) == 0
    fitted3 = Regression.load(path)
    assert fitted3.model == "series3" and set(fitted3.outputs) == set(regression.outputs_of("series3"))
    assert "A005" not in fitted3.ids and len(fitted3.ids) == N - 1
    assert fitted3.outputs["onset_2"] == {"mean": 0.0, "fixed": True} and fitted3.outputs["onset_1"]["cv"]["r2"] > 0.9
    geometry = Geometry(35.0, 9.6, 54.0, 12.0, 0.70, -53.0)
    trained = anatomy.from_geometry(geometry, fitted3)
    truth = _onsets(dataclasses.asdict(geometry))
    assert trained.elements.model_key() == ("series", 3, (1.0, 1.0)) and trained.elements.onsets[1] == 0.0
    np.testing.assert_allclose(trained.elements.onsets, truth, atol=0.1 * truth[2])
    assert trained.lo.gamma == pytest.approx(0.5 * _truth(dataclasses.asdict(geometry))["gamma"], rel=0.05)
    assert anatomy.from_geometry(geometry, fitted3, model="series3").elements == trained.elements
    with pytest.raises(InputError, match="predicts the maps of model 'series3', not of model 'single'"):
        anatomy.from_geometry(geometry, fitted3, model="single")
    with pytest.raises(InputError, match="needs \\['onset_1', 'onset_2', 'onset_3'\\] too"):
        regression.fit(dataset, restarts=0, model="series3", outputs=anatomy.LO_OUTPUTS)
    record = fitted3.to_dict()
    del record["outputs"]["onset_3"], record["y"]["onset_3"]
    (tmp_path / "bad.json").write_text(json.dumps(record))
    with pytest.raises(InputError, match=r"predicts its cells' onsets, and \['onset_3'\] are missing"):
        Regression.load(tmp_path / "bad.json")
    table.write_text("id,split,mu1\nA000,train,0.1\n")
    with pytest.raises(campaign.CampaignError, match=r"series3.csv' has the wrong columns \(missing \['mu2'"):
        regression.fit(dataset, restarts=0, model="series3")


def test_too_few_anatomies_make_no_regression(tmp_path):
    campaign.run(tmp_path, n=3, settings=Settings(backend="multielement", budget=16), limit=0)
    with pytest.raises(InputError, match="has 0 accepted training anatomies; a regression needs at least 10"):
        regression.fit(tmp_path)


def test_held_out_anatomies_compare_predicted_trained_and_baseline_maps_on_their_own_traces(dataset, fitted, tmp_path):
    """A held-out anatomy with real oracle traces (the multielement oracle, in-process) and maps
    trained on them: its C is reproduced from the dataset, and the N record's maps do worse."""
    import shutil

    from lvenv import archive
    from lvenv.trained import builtin
    from optim import congruency

    dataset = shutil.copytree(dataset, tmp_path / "dataset")  # the module fixture stays as it was
    rows = campaign.read_index(dataset)
    row = next(r for r in rows if r["id"] == "H000")
    geometry = Geometry(**{name: row[col] for col, name in GEOMETRY_COLUMNS.items()})
    data = congruency.oracle_data(geometry, "multielement", n_elements=4, cache_dir=tmp_path / "cache", progress=False)
    archive.save(dataset / "traces" / "H000.npz", *campaign.trace_archive(data))
    trained = congruency.train_on(campaign.oracle_data(dataset, "H000"), start=builtin("normal").lo, budget=16, progress=False)
    row.update(dataclasses.asdict(trained.lo), C=trained.congruency["C"])
    others = [r for r in rows if r["split"] == "heldout" and r["id"] != "H000"]
    for r in others:
        r["status"] = "failed_fe"
    with (dataset / "anatomies.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, campaign.COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in r.items()} for r in rows)
    (result,) = regression.held_out(fitted, dataset)
    assert result["id"] == "H000"
    assert result["C_trained"] == pytest.approx(trained.congruency["C"], rel=1e-12)
    assert result["C_baseline"] > 3 * result["C_trained"] and np.isfinite(result["C_predicted"])


def test_anatomy_figures_are_drawn_from_the_regression(fitted, tmp_path):
    from lvenv import plots

    cv = fitted.provenance["cv_predictions"]
    truth = {k: fitted.y[k] * fitted.outputs[k]["scale"] + fitted.outputs[k]["mean"] for k in cv}
    paths = [plots.anatomy_scatter_figure(fitted, tmp_path / "scatter.png"), plots.anatomy_contour_figure(fitted, tmp_path / "contours.pdf"),
             plots.parity_figure(truth, {k: np.array(v["predicted"]) for k, v in cv.items()}, {k: np.array(v["sd"]) for k, v in cv.items()},
                                 tmp_path / "parity.png")]
    assert all(p.stat().st_size > 10_000 for p in paths)
    with pytest.raises(InputError, match="must end in one of"):
        plots.parity_figure(truth, truth, truth, tmp_path / "parity.svg")


def test_a_prediction_outside_a_parameters_range_is_clipped_with_a_warning(fitted):
    from lvenv.params import LOParams

    ranges = {f.name: f.metadata["range"] for f in dataclasses.fields(LOParams)}
    # b (regressed as it is) below its range; the delay (regressed in log) above it
    shifted = dataclasses.replace(fitted, outputs={**fitted.outputs, "b": fitted.outputs["b"] | {"mean": -100.0},
                                                   "delay": fitted.outputs["delay"] | {"mean": 0.0}}, _gps={})
    with pytest.warns(ExtrapolationWarning) as caught:
        trained = anatomy.from_geometry(Geometry(35.0, 9.6, 54.0, 12.0, 0.70, -53.0), shifted)
    messages = [str(w.message) for w in caught]
    assert any(m.startswith("lo.b = -10") and m.endswith("clipped to its allowed range [-50, 50]") for m in messages), messages
    assert any(m.startswith("lo.delay = 1.0") and m.endswith("clipped to its allowed range [0, 0.3]") for m in messages), messages
    assert trained.lo.b == ranges["b"][0] and trained.lo.delay == ranges["delay"][1] and len(trained.provenance["clipped"]) == 2


def test_a_patient_imaged_at_end_diastole_is_unloaded_and_gets_its_anatomys_maps(fitted, tmp_path, monkeypatch):
    """`lvenv fit PATIENT.json`'s record path: an imaged geometry is unloaded (the paper's rule or
    the passive-curve search), the maps come from the regression the environment names, the
    record says what was done and reads back without unloading twice."""
    from lvenv import presets
    from lvenv.anatomy import ARTEFACT_ENV, inflate, map_draws
    from lvenv.coupling import passive_volume
    from lvenv.geometry import cavity_volume
    from lvenv.patients import Patient, builtin

    path = regression.save(fitted, tmp_path / "regression.json")
    monkeypatch.setenv(ARTEFACT_ENV, str(path))
    unloaded = Geometry(36.0, 9.0, 52.0, 10.0, 0.70, -60.0)
    imaged = inflate(unloaded, 0.12)
    record = {**builtin("normal").to_dict(), "geometry": dataclasses.asdict(imaged), "unload": {"strain": 0.12}, "lo": "regression"}
    patient = Patient.from_dict(record)
    assert patient.heart.geometry.as_tuple() == pytest.approx(unloaded.as_tuple(), rel=1e-9)
    assert patient.heart.lo == anatomy.from_geometry(patient.heart.geometry, fitted).lo
    maps = patient.anatomy["maps"]
    assert maps["source"] == "regression" and set(maps["sd"]) == set(regression.OUTPUTS)
    assert maps["sd"]["alpha"] == 0.0 and all(v > 0 for k, v in maps["sd"].items() if k != "alpha")
    assert patient.anatomy["unloading"] == {"imaged": dataclasses.asdict(imaged), "how": {"strain": 0.12}, "strain": 0.12}
    assert Patient.from_json(patient.to_json()) == patient
    # by the end-diastolic pressure: the unloaded shape's predicted passive curve reaches the imaged volume
    searched = Patient.from_dict({**record, "unload": {"edp": 1.5}})
    heart = searched.heart
    assert float(passive_volume(1.5, cavity_volume(heart.geometry), heart.lo)) == pytest.approx(cavity_volume(imaged), rel=1e-7)
    assert heart.lo == anatomy.from_geometry(heart.geometry, fitted).lo and 0 < searched.anatomy["unloading"]["strain"] < 0.6
    # the maps' uncertainty: draws scatter by the predictive sd around the predicted maps
    draws = map_draws(patient.heart.geometry, 400, seed=1)
    mu1 = np.array([d.mu1 for d in draws])
    assert abs(mu1.mean() - patient.heart.lo.mu1) < 4 * maps["sd"]["mu1"] / 20 and mu1.std() == pytest.approx(maps["sd"]["mu1"], rel=0.15)
    # bad records name the field
    for bad, match in (({"strain": 2.0}, r"patient.unload.strain = 2"), ({"group": "X"}, r"patient.unload.group = 'X'"),
                       ({"width": 1}, r"one of the fields \('strain', 'group', 'edp'\)")):
        with pytest.raises(InputError, match=match):
            Patient.from_dict({**record, "unload": bad})
    with pytest.raises(InputError, match=r"patient.lo must be an object of named numbers or \"regression\", got 'gp'"):
        Patient.from_dict({**record, "lo": "gp"})
    monkeypatch.setenv(ARTEFACT_ENV, str(tmp_path / "missing.json"))
    with pytest.raises(InputError, match=ARTEFACT_ENV):
        Patient.from_dict(record)
    assert presets.N_UNLOADED == Patient.from_dict({**record, "geometry": dataclasses.asdict(presets.N_UNLOADED), "unload": None, "lo": None}).heart.geometry


def test_refits_at_map_draws_carry_the_maps_uncertainty_into_the_fitted_parameters(fitted, tmp_path, monkeypatch):
    """`lvenv fit --map-draws`: a record with the regression's maps, fitted by least squares, then
    refitted from that fit at draws of its maps. Every refit reaches the targets again; the control
    (the predicted maps) stays at the fit; the draws move the parameters."""
    from lvenv.anatomy import ARTEFACT_ENV
    from lvenv.patients import Patient, builtin
    from optim.lm import fit_lm
    from optim.map_uncertainty import refit

    monkeypatch.setenv(ARTEFACT_ENV, str(regression.save(fitted, tmp_path / "regression.json")))
    patient = Patient.from_dict({**builtin("normal").to_dict(), "lo": "regression"})
    first = fit_lm(patient, budget=24, starts=1, steps_per_beat=500)
    assert first.mismatch < 1e-6
    seen = []
    spread = refit(patient, first.parameters, 3, budget=10, steps_per_beat=500, regression=fitted, progress=lambda d, t: seen.append((d, t)))
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)] and spread.usable == 3
    assert np.all(spread.mismatch < 1e-4) and spread.control_mismatch < 1e-6
    assert spread.control == pytest.approx(first.parameters, rel=1e-6)
    summary = spread.summary()
    for name, values in spread.parameters.items():
        assert summary[name]["sd"] == pytest.approx(np.std(values, ddof=1))
    assert summary["Sa"]["sd"] > 0 and len(set(spread.parameters["Sa"])) == 3
    with pytest.raises(InputError, match="do not come from the anatomy regression"):
        refit(builtin("normal"), first.parameters, 3)


def test_a_multi_element_patient_record_takes_its_maps_and_onsets_from_its_models_regression():
    """A 3-cell record with ``"lo": "regression"`` gets the maps and the cells' onsets of the
    3-cell heart's shipped regression, not the single cell's maps; a record whose cells are no
    named model is refused, naming them."""
    from lvenv.patients import Patient, builtin

    geometry = Geometry(36.0, 9.0, 52.0, 10.0, 0.70, -60.0)
    cells = {"kind": "series", "n_elements": 3, "spread": [1.0, 1.0]}
    record = {**builtin("normal").to_dict(), "geometry": dataclasses.asdict(geometry), "elements": cells, "lo": "regression"}
    patient = Patient.from_dict(record)
    predicted = anatomy.from_geometry(geometry, model="series3")
    assert patient.heart.lo == predicted.lo != anatomy.from_geometry(geometry).lo
    assert patient.heart.elements == predicted.elements and len(set(predicted.elements.onsets)) == 3
    assert patient.anatomy["maps"]["model"] == "series3" and Patient.from_json(patient.to_json()) == patient
    # the maps' uncertainty is the 3-cell regression's: draws scatter around its maps, not the single cell's
    gamma = np.array([d.gamma for d in anatomy.map_draws(geometry, 200, model="series3")])
    sd = predicted.provenance["sd"]["gamma"]
    assert abs(np.median(gamma) - predicted.lo.gamma) < sd / 2 < abs(np.median(gamma) - anatomy.from_geometry(geometry).lo.gamma)
    with pytest.raises(InputError, match=r"elements \('series', 4, \(1.0, 1.0\)\) are no LO heart model"):
        Patient.from_dict({**record, "elements": {**cells, "n_elements": 4}})

