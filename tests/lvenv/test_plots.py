"""`lvenv.plots`: the generalisation panel (the paper's Fig. 7) draws every scenario, in PNG and PDF."""

import pytest

import lvenv
from lvenv import plots, presets


def test_generalisation_panel_draws_each_scenario_in_png_and_pdf(tmp_path):
    hearts = [presets.normal().replace(tau2=t) for t in (0.12, 0.18)]
    sim = lvenv.simulate(hearts, beats=1, steps_per_beat=100)
    rows = [{"heart": "normal", "scenario": f"tau2 {t}", "C": 0.01 * (i + 1), "lo": sim[i].traces,
             "oracle": {"t": sim[i].traces.t, "V": sim[i].traces.V * 1.02, "P_lv": sim[i].traces.P_lv}} for i, t in enumerate((0.12, 0.18))]
    png = plots.generalisation_figure(rows, tmp_path / "g.png", columns=2)
    pdf = plots.generalisation_figure(rows, tmp_path / "g.pdf", columns=2)
    assert png.read_bytes()[:4] == b"\x89PNG" and pdf.read_bytes()[:5] == b"%PDF-"
    with pytest.raises(ValueError, match="must end in one of"):
        plots.generalisation_figure(rows, tmp_path / "g.svg", columns=2)
