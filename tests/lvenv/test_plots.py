"""`lvenv.plots`: the generalisation panel (the paper's Fig. 7) draws every scenario, in PNG and PDF."""

import pytest

import lvenv
from lvenv import plots, presets


def test_generalisation_panel_draws_each_scenario_in_png_and_pdf(tmp_path):
    hearts = [presets.normal().replace(tau2=t) for t in (0.12, 0.18)]
    sim = lvenv.simulate(hearts, beats=1, steps_per_beat=100)
    traces = [{"t": sim[i].traces.t, "V": sim[i].traces.V, "P_lv": sim[i].traces.P_lv} for i in range(2)]
    rows = [{"heart": "normal", "scenario": f"tau2 {t}", "C": 0.01 * (i + 1), "lo": traces[i], "candidates": {"other": traces[1 - i]},
             "oracle": {"t": traces[i]["t"], "V": traces[i]["V"] * 1.02, "P_lv": traces[i]["P_lv"]}} for i, t in enumerate((0.12, 0.18))]
    png = plots.generalisation_figure(rows, tmp_path / "g.png", columns=2)
    pdf = plots.generalisation_figure(rows, tmp_path / "g.pdf", columns=2)
    assert png.read_bytes()[:4] == b"\x89PNG" and pdf.read_bytes()[:5] == b"%PDF-"
    with pytest.raises(ValueError, match="must end in one of"):
        plots.generalisation_figure(rows, tmp_path / "g.svg", columns=2)


def test_pairs_figure_draws_every_pair_of_each_posterior_on_the_requested_axes(tmp_path):
    import numpy as np
    from matplotlib.image import imread

    rng = np.random.default_rng(0)
    samples = {label: {"tau2": np.exp(rng.normal(np.log(0.2), 0.2, 500)), "Sa": rng.normal(1.0, 0.1, 500), "R2": rng.uniform(0.0, 0.05, 500)}
               for label in ("normal", "heart_failure")}
    png = plots.pairs_figure(samples, tmp_path / "pairs.png", log={"tau2": True}, max_points=100)
    image = imread(png)
    assert image.shape[0] == image.shape[1] > 300, "a square grid, one panel per pair"
    assert len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 10, "something was drawn"
    with pytest.raises(ValueError, match="must end in one of"):
        plots.pairs_figure(samples, tmp_path / "pairs.svg")
