"""`lvenv report` as documentation pages (optim.report.build_pages): one page per results kind,
each with its command and the date of its run, numbers only from the results under ``out/``."""

import json
import os
import re

from optim import report


def _results(root):
    """A small ``out/`` tree: a calibration run, a benchmark and a `make run` table."""
    params = ("tau2", "Sa")
    (root / "identify").mkdir(parents=True)
    (root / "identify" / "calibration.json").write_text(json.dumps({
        "coverage": {"tau2": 0.85, "Sa": 0.95}, "coverage_hdi": {"tau2": 0.8, "Sa": 0.9},
        "binomial_tail": {"inside": {"tau2": 0.32, "Sa": 0.88}, "inside_hdi": {"tau2": 0.13, "Sa": 0.61}},
        "median_width": {"tau2": 0.27, "Sa": 0.41}, "runs": [{}] * 20,
        "options": {"truths": 20, "draw": "prior", "seed": 3, "walkers": 64, "out": "x.json"}}))
    (root / "identify" / "posterior_patients.json").write_text(json.dumps({
        name: {"fit": {"mismatch": 0.001}, "posterior": {"sampler": "ensemble", "median": {"tau2": tau2, "Sa": 1.0},
                                                         "interval_90": {"tau2": [0.9 * tau2, 1.1 * tau2], "Sa": [0.5, 1.5]}}}
        for name, tau2 in (("normal", 0.15), ("heart_failure", 0.2))} | {"P(Sa_HF < Sa_N)": 0.9876, "posterior_wall_s_total": 12.0}))
    (root / "bench").mkdir()
    (root / "bench" / "amortised.json").write_text(json.dumps({
        "truths": 300, "out_of_distribution": 0.02, "coverage_90": {n: 0.9 for n in params}, "rank_ks_p": {"tau2": 0.25, "Sa": 0.0081},
        "training": {"pairs": 18802, "seconds": 11.068963}, "targets": ["EF", "ET"], "mcmc": [{"patient": "truth0", "seconds": 962.74}],
        "rows": {f"r{i}": i for i in range(report.BENCH_ROWS)}}))
    (root / "compare").mkdir()
    method = lambda shift, ratio, share, agree: {
        "seconds": 2.0, "worst_median_shift_sd": {"tau2": shift, "Sa": shift / 2}, "width_ratio_range": {n: [1 - ratio, 1 + ratio] for n in params},
        "within_acceptance": {"median": share, "width": 1.0, "patients_all_parameters": agree}}
    (root / "compare" / "compare.json").write_text(json.dumps({
        "patients": 22, "truths": 20, "samples": 4000, "importance_draws": 8000, "mcmc_seconds_per_patient": 110.0, "mcmc_rhat_max": 1.037,
        "amortised": method(0.65, 0.3, 0.833, 9), "importance": method(0.09, 0.1, 1.0, 22), "command": "python scripts/compare_amortised.py --truths 20"}))
    (root / "fit").mkdir()
    (root / "fit" / "fits.txt").write_text("patient  method  mismatch\nnormal   mads    0.42 %\n")
    os.utime(root / "fit" / "fits.txt", (0, 86400 * 365))  # 1971-01-01
    (root / "fit" / "fidelity_heart_failure_series3.md").write_text("Command: `python scripts/fit_patients.py --correct-maps 3`.\n\n"
                                                                     "| maps | C |\n|---|---|\n| round 3 | 3.04 % |\n")
    (root / "fit" / "fidelity_heart_failure_series3_passive.md").write_text(
        "Command: `python scripts/fit_patients.py --correct-maps 3 --refit-passive`.\n\n| maps | C |\n|---|---|\n| round 3 | 2.62 % |\n")
    (root / "fit" / report.fidelity_file("heart_failure", "series3", passive=True, aortic_weight=0.5)).write_text(
        "Command: `python scripts/fit_patients.py --correct-maps 3 --refit-passive --aortic-weight 0.5`.\n\n| maps | C |\n|---|---|\n"
        "| round 3 | 2.71 % |\n")


def test_pages_give_each_results_kind_its_command_date_and_numbers_from_out(tmp_path):
    root = tmp_path / "out"
    _results(root)
    pages = report.build_pages(root, tmp_path / "docs" / "results")
    names = [p.stem for p in pages]
    assert names == ["index", "training", "generalisation", "multi-element", "fidelity", "inverse-problem", "calibration", "benchmarks", "anatomy"]
    index = pages[0].read_text()
    assert index.startswith("# Results") and all(f"\n{name}\n" in index for name in names[1:]), "the index's toctree lists every page"
    text = {p.stem: p.read_text() for p in pages[1:]}
    for key, (name, page) in zip(report.SECTIONS, text.items(), strict=True):
        assert page.startswith(f"# {report.TITLES[key]}\n"), name
        assert "Command: `" in page, f"{name} names its command"
        assert re.search(r"#{3,} ", page) is None, f"{name}: subsections are H2 on a page of their own"
    assert "| normal | " in text["training"] and re.search(r"\| \d{4}-\d\d-\d\d \|", text["training"]), "the record's training date"
    assert "Not run yet. Command: `python scripts/generalisation.py`" in text["generalisation"]
    assert "Not run yet. Command: `python scripts/multielement_study.py`" in text["multi-element"]
    assert all(f"## {title}\n\nNot run yet. Command: `{command}`" in text["fidelity"] for title, _, command, _ in report.FIDELITY_PARTS)
    inverse = text["inverse-problem"]
    assert "## Built-in patients" in inverse and "results of 1971-01-01 00:00 UTC" in inverse and "normal   mads    0.42 %" in inverse
    assert "## Fidelity of the fits against the FE oracle\n\n**heart_failure, series3 heart**, results of " in inverse
    assert "Command: `python scripts/fit_patients.py --correct-maps 3`." in inverse and "| round 3 | 3.04 % |" in inverse
    assert "\n\n**heart_failure, series3 heart, passive maps refitted too**, results of " in inverse and "| round 3 | 2.62 % |" in inverse
    assert ("\n\n**heart_failure, series3 heart, passive maps refitted too, aortic pressure weighed in (weight 0.5)**, results of "
            in inverse and "| round 3 | 2.71 % |" in inverse)
    assert "Not run yet. Command: `lvenv cohort REPORTS.csv --out out/cohort/fits.csv`" in inverse
    assert "`python scripts/posterior_patients.py` (sampler ensemble)" in inverse and "| | tau2 (s) | Sa |" in inverse
    assert "| heart_failure | 0.2 (0.18–0.22) | 1 (0.5–1.5) |" in inverse and "P(Sa_HF < Sa_N) = 0.988" in inverse
    calibration = text["calibration"]
    assert "`python scripts/calibration.py --truths 20 --draw prior --seed 3` (other settings: walkers 64)" in calibration
    assert "| equal-tailed | 0.85 (P 0.32) | 0.95 (P 0.88) |" in calibration and "| median width | 0.27 | 0.41 |" in calibration
    assert "On 300 held-out truths" in calibration and "2.0 % flagged" in calibration and "| rank KS p | 0.25 | 0.0081 |" in calibration
    assert "## Amortised against MCMC\n\nCommand: `python scripts/compare_amortised.py --truths 20`" in calibration
    assert "| amortised: median shift (sd) | 0.65 | 0.33 |" in calibration and "| importance: width ratio | 0.90–1.10 | 0.90–1.10 |" in calibration
    assert "* importance: medians within 0.3 sd in 100.0 %" in calibration and "22 of 22 patients within both" in calibration
    bench = text["benchmarks"]
    assert "Command: `lvenv bench amortised`" in bench
    assert "| `training.seconds` | 11.07 |" in bench and "| `targets` | EF, ET |" in bench and "| `mcmc[0].patient` | truth0 |" in bench
    rows = len(re.findall(r"^\| `", bench, re.M))
    assert rows == report.BENCH_ROWS and "more values in" in bench, "a long benchmark is cut, and the page says where the rest is"


def test_report_holds_the_same_sections_one_level_down(tmp_path):
    root = tmp_path / "out"
    _results(root)
    text = report.build_report(root).read_text()
    assert [line[3:] for line in text.splitlines() if line.startswith("## ")] == [report.TITLES[s] for s in report.SECTIONS]
    assert "### MCMC posterior" in text and "### amortised" in text and "### Built-in patients" in text


def test_a_results_tree_without_results_gives_only_commands(tmp_path):
    pages = report.build_pages(tmp_path / "nothing", tmp_path / "pages")
    for page in pages[2:]:  # the training page reads the records shipped in the package
        body = page.read_text()
        assert "Not run yet. Command: `" in body, page.stem
        assert not re.search(r"\d+(\.\d+)? ?%", body), f"{page.stem}: no number without a result behind it"
