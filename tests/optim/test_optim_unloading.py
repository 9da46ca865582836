"""The unloading check over a campaign's dataset (`optim.unloading`), on a real tiny campaign of
the multi-element oracle."""

import pytest

from lvenv.anatomy import ED_STRAIN, inflate
from lvenv.geometry import cavity_volume
from optim import campaign, unloading
from optim.campaign import Settings

EDP = {"N": 1.6, "HF": 2.0}  # kPa


def test_unloading_check_reads_the_oracles_passive_curve_and_scores_the_rule(tmp_path):
    directory = tmp_path / "anatomy"
    campaign.run(directory, n=1, held_out=0, seed=3, settings=Settings(backend="multielement", n_elements=4, budget=16, timeout_s=300.0),
                 workers=1, cache_dir=tmp_path / "cache")
    accepted = [r for r in campaign.read_index(directory) if r["status"] == "accepted"]
    rows = unloading.check(directory, EDP)
    assert accepted and len(rows) == 2 * len(accepted)
    for row in rows:
        data = campaign.oracle_data(directory, row["id"])
        g0 = data.geometry
        assert row["strain"] == ED_STRAIN[row["group"]] and row["EDP_kPa"] == EDP[row["group"]]
        # the oracle-consistent imaged shape holds the oracle's volume at EDP, which lies on its passive curve
        assert cavity_volume(inflate(g0, row["strain_fe"])) == pytest.approx(row["V_fe_ml"], rel=1e-8)
        assert min(data.passive.traces["V"]) < row["V_fe_ml"] < max(data.passive.traces["V"])
        assert row["EDV_ml"] == pytest.approx(cavity_volume(inflate(g0, row["strain"])), rel=1e-12)
        # the rule unloads too little (V0 too large) exactly when the wall is strained more than it assumes
        assert (row["V0_error_rule"] > 0) == (row["strain_fe"] > row["strain"]) and abs(row["V0_error_rule"]) > 1e-3
        # the trained maps' passive curve is a fit to the oracle's: it recovers V0 far better than the fixed strain
        assert abs(row["V0_error_fit"]) < 0.02 and abs(row["V0_error_fit"]) < abs(row["V0_error_rule"])
    summary = unloading.summary(rows)
    assert set(summary) == set(ED_STRAIN) and all(s["anatomies"] == len(accepted) for s in summary.values())
