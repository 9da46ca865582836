"""The inverse problem end to end (`optim.fit`): fits, table, plots, synthetic recovery."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

import lvenv
from lvenv import presets
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import builtin
from optim.congruency import MAP_NAMES
from optim.fit import corrected_fit, fit_patients, null_directions, synthetic_recovery
from scripts import fit_patients as script

TARGETS = ("EF", "ET", "IVRT", "P_ao_pulse")


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit")
    result = fit_patients(("normal",), ("mads", "cma"), num_envs=8, budget=64, seed=0, out_dir=out,
                          options={"mads": {"n_candidates": 64}})
    return result, out


def test_fit_drops_the_mismatch_and_writes_a_pv_plot(rows):
    result, out = rows
    assert [(r.patient, r.method) for r in result] == [("normal", "mads"), ("normal", "cma")]
    mads = result[0]
    own = mads.history.mismatch[0]  # MADS evaluates the patient's own parameters first
    for r in result:
        assert r.mismatch < own, (r.method, r.mismatch, own)
        assert r.evaluations == 64 and r.wall_time > 0
        assert set(r.mismatch_per_target) == set(TARGETS) and set(r.parameters) == set(DEFAULT_ACTION_PARAMS)
    assert min(r.mismatch for r in result) < 0.7 * own, [r.mismatch for r in result]
    png = out / "pv_normal.png"
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_script_prints_the_table_in_mmhg_and_ms(rows, capsys):
    script.print_fits(rows[0])
    text = capsys.readouterr().out
    assert "tau2 (ms)" in text and "ET (ms)" in text and "P_ao pulse (mmHg)" in text
    assert "P_at mean (mmHg)" in text and "EDP (mmHg)" in text and "P_at_mean 4–25 mmHg" in text, "the plausibility columns"
    assert "60.0" in text  # EF target of the normal patient, in %
    assert "300.0" in text  # ET target, in ms


def test_lm_rows_sit_beside_the_env_methods_warm_and_as_fit_lm_alone_gives_them(capsys):
    """`fit_patients(..., methods=("lm",))`: the least-squares fit in the same table, with its own
    budget; the warm-up run that takes its compilation out of the wall time leaves the result
    bit-identical to `fit_lm` called alone."""
    from optim.lm import fit_lm

    options = {"lm": {"budget": 6, "starts": 2}}
    (row,) = fit_patients(("normal",), ("lm",), num_envs=8, budget=64, seed=0, steps_per_beat=1000, options=options)
    alone = fit_lm("normal", budget=6, starts=2, seed=0, steps_per_beat=1000)
    assert row.method == "lm" and row.evaluations == alone.evaluations <= 6
    np.testing.assert_array_equal(row.history.x, alone.history.x)
    np.testing.assert_array_equal(row.history.f, alone.history.f)
    assert row.mismatch < row.history.mismatch[0], "it improved on the patient's own values (start 0's first point)"
    assert row.compile_time > 0 and row.wall_time > 0
    script.print_fits([row])
    text = capsys.readouterr().out
    assert re.search(r"^normal +lm +\d", text, re.M), "the lm row of the parameter table"
    assert "normal lm " in text and "lm: each evaluation is a steady state and its tangents" in text, "its compilation and footnote"


def test_targets_move_less_along_the_null_directions_than_across_them():
    # the Table 3 heart: at the trained preset IVRT jumps by about a step (2 ms at 500 steps per
    # beat) between neighbouring parameter sets here, which central differences cannot see past
    heart = lvenv.presets.normal(lo="table3")
    truth = np.array([[0.17, 1.0, 0.025, 0.2, 15.0, 2.0]])
    sigmas, null = null_directions(heart, truth, TARGETS)
    assert sigmas.shape == (1, 4) and null.shape == (1, 6, 2)
    np.testing.assert_allclose(null[0].T @ null[0], np.eye(2), atol=1e-12)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    u0 = space.to_unit(truth[0])
    row_dir = np.linalg.svd(np.eye(6) - null[0] @ null[0].T)[0][:, 0]  # a direction across the null space
    hearts = [heart.replace(**dict(zip(space.names, map(float, space.from_unit(u0 + 0.02 * d)))))
              for d in (np.zeros(6), null[0][:, 0], null[0][:, 1], row_dir)]
    hearts += hearts[-1:] * 9  # 13 members, like null_directions' own batch: no second compilation
    m = lvenv.simulate(hearts, steps_per_beat=500, max_beats=60, traces=False).metrics
    change = [max(abs(m[t][i] / m[t][0] - 1) for t in TARGETS) for i in (1, 2, 3)]
    assert max(change[:2]) < 0.1 * change[2], change


def test_synthetic_recovery_matches_the_observations():
    rep = synthetic_recovery(n_sets=1, method="cma", num_envs=8, budget=320, seed=5)
    assert rep.truths.shape == rep.fits.shape == (1, 6)
    assert rep.max_error[0] < 0.03, rep.max_error
    assert rep.null_share.shape == (1, 6) and set(rep.identifiable) == set(DEFAULT_ACTION_PARAMS)


@pytest.mark.slow
def test_synthetic_recovery_of_ten_truths_within_one_percent():
    rep = synthetic_recovery(n_sets=10, method="cma", num_envs=16, budget=1600, seed=0)
    assert np.all(rep.max_error < 0.01), rep.max_error


def test_make_env_takes_a_patient_record_path_and_picks_the_scheme_of_its_model(tmp_path):
    """A JSON path (as the env takes it) gets the env's default scheme for the record's LO heart
    model: adaptive for the single cell, fixed for the 3-cell series heart."""
    from optim.fit import make_env

    for model, scheme in (("single", "adaptive"), ("series3", "fixed")):
        path = tmp_path / f"{model}.json"
        builtin("heart_failure", model).to_json(path)
        venv = make_env(str(path), num_envs=2)
        assert venv.unwrapped.config.scheme == scheme and venv.unwrapped.patients[0].heart.elements == builtin("heart_failure", model).heart.elements
        venv.close()


def test_corrected_fit_with_passive_refits_the_passive_maps_inside_their_boxes_and_the_cli_shows_them(tmp_path):
    """``passive``: every round carries the nine maps, and round 1's passive maps, refitted on
    round 0's beat (with ``aortic_weight``, which that refit records and the last round, which
    refits nothing, leaves out), stay within the patient's own ÷ and × `PASSIVE_FREEDOM` (the
    oracle is the patient's own LO heart; a passive map found again is `check_fidelity`'s test);
    `lvenv fit --correct-maps`'s table gets a column per passive map."""
    from rich.console import Console

    from lvenv import cli
    from optim.congruency import PASSIVE_FREEDOM, PASSIVE_NAMES

    truth = dataclasses.replace(presets.N_LO, mu1=0.0945, mu2=0.2, gamma=2.5, delay=0.03)
    normal = builtin("normal")
    patient = dataclasses.replace(normal, heart=normal.heart.replace(lo=truth))
    rounds = corrected_fit(patient, ("cma",), 1, backend="multielement", beats=5, retune_budget=32, num_envs=8, budget=64,
                           steps_per_beat=500, passive=True, aortic_weight=0.5, arrangement="parallel", n_elements=1, lo=truth, cache_dir=tmp_path)
    assert all(tuple(r.maps) == (*MAP_NAMES, *PASSIVE_NAMES) for r in rounds)
    assert rounds[0].fidelity.retuned["aortic_weight"] == 0.5 and rounds[1].fidelity.retuned is None
    assert rounds[1].maps == rounds[0].fidelity.retuned["lo"]
    for name in PASSIVE_NAMES:
        low, high = sorted((getattr(truth, name) / PASSIVE_FREEDOM, getattr(truth, name) * PASSIVE_FREEDOM))
        assert low <= rounds[1].maps[name] <= high, name
    payload = [{"round": r, "maps": step.maps, "mismatch": step.fit.mismatch, "fidelity": step.fidelity.to_dict()} for r, step in enumerate(rounds)]
    console = Console(record=True, width=400)
    console.print(cli._correction_table(payload, "multielement", 6.0))
    lines = console.export_text().splitlines()
    head = next(line for line in lines if line.startswith("┃"))
    assert [c.strip() for c in head.split("┃")[1:-1]][:10] == ["round", "mu1", "mu2", "gamma", "delay (ms)", *PASSIVE_NAMES]
    row = next(line for line in lines if line.startswith("│") and line.split("│")[1].strip() == "1")
    assert row.split("│")[10].strip() == f"{rounds[1].maps['c']:.4g}"


def test_corrected_fit_refits_the_maps_on_the_oracle_beat_and_the_next_fit_matches_the_oracle(tmp_path, capsys):
    """`corrected_fit` against an oracle that is the LO heart with other maps (the multi-element
    backend with one element): the maps refitted on the oracle's beat at the first fit come back
    to the oracle's, up to the oracle's own start (its closed loop starts from the LO heart's
    pressures with its own volume and has a few beats to settle), so the next fit, made with
    them, lands where the oracle agrees with the LO heart. The script prints both comparisons."""
    truth = dataclasses.replace(presets.N_LO, mu1=0.0945, mu2=0.2, gamma=2.5, delay=0.03)
    normal = builtin("normal")
    patient = dataclasses.replace(normal, heart=normal.heart.replace(lo=dataclasses.replace(truth, mu2=0.17, delay=0.045)))
    rounds = corrected_fit(patient, ("cma",), 1, backend="multielement", beats=5, retune_budget=32, num_envs=8, budget=64,
                           steps_per_beat=500, arrangement="parallel", n_elements=1, lo=truth, cache_dir=tmp_path)
    assert len(rounds) == 2 and all(r.fit.method == "cma" for r in rounds)
    assert rounds[0].maps == {n: getattr(patient.heart.lo, n) for n in MAP_NAMES}
    assert rounds[1].maps == rounds[0].fidelity.retuned["lo"] and rounds[1].fidelity.retuned is None
    for name in ("mu1", "mu2", "delay"):
        assert rounds[1].maps[name] == pytest.approx(getattr(truth, name), rel=0.02), name
    assert rounds[0].fidelity.C > 0.1 and rounds[0].fidelity.retuned["C"] < 0.02
    assert rounds[1].fidelity.C < min(0.02, rounds[0].fidelity.C / 10), (rounds[0].fidelity.C, rounds[1].fidelity.C)
    script.print_check("round 0", rounds[0].maps, rounds[0].fidelity)
    text = capsys.readouterr().out
    assert f"round 0: C {100 * rounds[0].fidelity.C:.2f} %, OUTSIDE tolerance" in text
    assert f"mu2 {rounds[1].maps['mu2']:.4g}" in text and f"C {100 * rounds[0].fidelity.retuned['C']:.2f} %" in text
    assert text.count("| refitted maps: FE − LO") == len(rounds[0].fidelity.rows)
    table = script.fidelity_markdown([script.Check(f"round {r}", step.fit, step.fidelity) for r, step in enumerate(rounds)],
                                     "python scripts/fit_patients.py --correct-maps 1", 6.0, 5)
    lines = table.splitlines()
    assert lines[0].startswith("Command: `python scripts/fit_patients.py --correct-maps 1`. FE − LO at each fit (h = 6 mm, the last of 5")
    head, rule, *body = [line for line in lines if line.startswith("|")]
    assert len(body) == 3, "round 0, round 0 with the maps refitted on its FE beat, round 1"
    assert all(len(row.split(" | ")) == len(head.split(" | ")) == rule.count("---") for row in body)
    for row, c, within in ((body[0], rounds[0].fidelity.C, rounds[0].fidelity.within),
                           (body[1], rounds[0].fidelity.retuned["C"], rounds[0].fidelity.retuned["within"]),
                           (body[2], rounds[1].fidelity.C, rounds[1].fidelity.within)):
        assert f" | {100 * c:.2f} % | " in row and row.count(" OUT") == list(within.values()).count(False), row
    assert body[1].startswith("| refitted on this FE beat | cma, mismatch ") and body[2].startswith("| round 1 | cma, mismatch ")
    assert f" | {1000 * rounds[1].fit.parameters['tau2']:.0f} | " in body[2]
