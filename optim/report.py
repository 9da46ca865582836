"""`lvenv report`: the results of every experiment the project reproduces, rebuilt from what the
experiments left under ``out/`` (and the trained records shipped in the package).

Nothing is recomputed. Each section states the command that produces its results and the date
of their run (the file's modification time, or the record's own date). A section whose results
are missing says so and gives that command; it never shows a number of its own. Two forms, with
the same sections: one markdown report (:func:`build_report`, ``lvenv report``), and one page per
section for the documentation site (:func:`build_pages`, called by ``docs/conf.py``). Sources:

=================  =====================================================  ===============================================
section            read from                                              written by
=================  =====================================================  ===============================================
training           ``lvenv/data/trained_*.json``                          ``python scripts/train_presets.py [--model series3]``
generalisation     ``out/generalisation/generalisation.{md,png}``         ``python scripts/generalisation.py``
multi-element      ``out/multielement/multielement.md``                   ``python scripts/multielement_study.py``
fidelity           ``out/diagnosis/diagnosis.md``;                        ``python scripts/congruency_diagnosis.py``;
                   ``out/diagnosis/wall.{md,png}``;                       ``python scripts/wall_diagnosis.py``;
                   ``out/diagnosis/candidates_dataset.md``,               ``python scripts/candidate_study.py dataset``,
                   ``candidates_hearts.{md,png}``,                        ``python scripts/candidate_study.py hearts``,
                   ``candidates_hearts_dt2.5ms.md``,                      ``… hearts --dt 0.0025 --no-unseen``,
                   ``candidates_hearts_h4.5mm.md``,                       ``… hearts --mesh-size 4.5 --candidates single series3-onsets --no-unseen``,
                   ``candidates_retune.md``                               ``python scripts/candidate_study.py retune``
inverse problem    ``out/fit/fits.txt``, ``out/fit/pv_*.png``;            ``make run``;
                   ``out/fit/fidelity_<patient>_<model>[_passive]``       ``python scripts/fit_patients.py --fidelity``
                   ``[_aorticW].md`` (:func:`fidelity_file`);             (or ``--correct-maps K [--refit-passive]
                                                                          [--aortic-weight W]``);
                   ``out/identify/posterior_patients.json`` and           ``python scripts/posterior_patients.py``;
                   ``posterior_pairs.png``;
                   ``out/cohort/*.csv`` with its ``.json``                ``lvenv cohort REPORTS --out out/cohort/…``
calibration        ``out/identify/calibration.json``;                     ``python scripts/calibration.py``;
                   ``out/bench/amortised.json``;                          ``lvenv bench amortised``;
                   ``out/compare/compare.json``                           ``python scripts/compare_amortised.py``
benchmarks         ``out/bench/*.json``                                   ``lvenv bench NAME``
anatomy            ``out/anatomy/anatomy.md`` and its figures;            ``python scripts/anatomy_study.py``;
                   ``out/anatomy/anatomy_series3.md``                     ``… --model series3``
=================  =====================================================  ===============================================
"""

from __future__ import annotations

import csv
import datetime
import json
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lvenv import presets, trained
from lvenv.identification import ACTION_BOUNDS
from lvenv.plots import histogram_figure
from optim.cohort import summarise

__all__ = ["build_report", "build_pages", "SECTIONS", "TITLES"]

#: Section keys, in report order; also the page names of :func:`build_pages` (spaces → hyphens).
SECTIONS = ("training", "generalisation", "multi-element", "fidelity", "inverse problem", "calibration", "benchmarks", "anatomy")
#: The heading of each section.
TITLES = {"training": "Training (congruency)", "generalisation": "Generalisation", "multi-element": "Multi-element models",
          "fidelity": "Where the LO heart misses the FE wall",
          "inverse problem": "Inverse problem", "calibration": "Calibration of the posteriors", "benchmarks": "Benchmarks",
          "anatomy": "Anatomy"}
BENCH_ROWS = 60  # rows of one benchmark's table at most; the rest stay in its JSON, which the page names


def _stamp(path: Path) -> str:
    return datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def _missing(command: str) -> list[str]:
    return [f"Not run yet. Command: `{command}`", ""]


def _image(path: Path, report_dir: Path) -> str:
    return f"![{path.stem}]({os.path.relpath(path, report_dir)})"


def _training() -> list[str]:
    lines = ["Command: `python scripts/train_presets.py` (or `lvenv train HEART --out FILE`; the 3-cell series heart: "
             "`python scripts/train_presets.py --model series3`); read from the records shipped in `lvenv/data/`, each trained on "
             "the date in its row.", "",
             "| heart | C ① | C ② | C ③ | C | C without the delay | delay (ms) | backend, mesh | trained |", "|---|---|---|---|---|---|---|---|---|"]
    for name in (presets.record_name(heart, model) for model in presets.LO_MODELS for heart in ("normal", "heart_failure")):
        record = trained.builtin(name)
        c, without = record.congruency, record.congruency_without_delay or {}
        cells = [f"{100 * c[k]:.2f} %" for k in ("1", "2", "3", "C")]
        cells.append(f"{100 * without['C']:.2f} %" if "C" in without else "—")
        cells.append(f"{1000 * record.lo.delay:.0f}")
        cells.append(f"{record.provenance.get('backend')}, h = {record.provenance.get('mesh_size_mm', '—')} mm")
        cells.append(str(record.provenance.get("created", "—"))[:10])
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines + [""]


def _markdown_file(path: Path, command: str, report_dir: Path, images: tuple[Path, ...] = ()) -> list[str]:
    if not path.exists():
        return _missing(command)
    lines = [f"Command: `{command}`; results of {_stamp(path)} (`{path}`).", "", path.read_text().strip(), ""]
    return lines + [line for image in images if image.exists() for line in (_image(image, report_dir), "")]


#: The fidelity section's parts: heading, results file, the command that writes it, its figure.
FIDELITY_PARTS = (
    ("By phase of the beat, over the campaign's anatomies", "diagnosis.md", "python scripts/congruency_diagnosis.py", None),
    ("The wall's tension and stretch against the LO cells", "wall.md", "python scripts/wall_diagnosis.py", "wall.png"),
    ("Candidate low-order hearts on the campaign's anatomies", "candidates_dataset.md", "python scripts/candidate_study.py dataset", None),
    ("Candidate low-order hearts on N and HF, training and unseen scenarios", "candidates_hearts.md", "python scripts/candidate_study.py hearts",
     "candidates_hearts.png"),
    ("The same, trained on the oracle at dt = 2.5 ms", "candidates_hearts_dt2.5ms.md",
     "python scripts/candidate_study.py hearts --dt 0.0025 --no-unseen", None),
    ("The same, trained on the oracle at h = 4.5 mm", "candidates_hearts_h4.5mm.md",
     "python scripts/candidate_study.py hearts --mesh-size 4.5 --candidates single series3-onsets --no-unseen", None),
    ("Maps frozen against maps refitted in each unseen scenario", "candidates_retune.md", "python scripts/candidate_study.py retune", None),
)


def _fidelity(folder: Path, report_dir: Path, level: int) -> list[str]:
    lines = []
    for title, name, command, image in FIDELITY_PARTS:
        images = () if image is None else (folder / image,)
        lines += ["#" * level + f" {title}", "", *_markdown_file(folder / name, command, report_dir, images)]
    return lines


def _inverse(root: Path, report_dir: Path, level: int) -> list[str]:
    return ["#" * level + " Built-in patients", "", *_fits(root, report_dir),
            "#" * level + " Fidelity of the fits against the FE oracle", "", *_fit_fidelity(root),
            "#" * level + " Posteriors of the built-in patients", "", *_posteriors(root, report_dir),
            "#" * level + " Cohorts", "", *_cohorts(root, report_dir)]


def _fits(root: Path, report_dir: Path) -> list[str]:
    table = root / "fit" / "fits.txt"
    if not table.exists():
        return _missing("make run")
    lines = [f"Command: `make run`; results of {_stamp(table)}.", "", "```", table.read_text().rstrip(), "```", ""]
    lines += [_image(p, report_dir) for p in sorted((root / "fit").glob("pv_*.png"))]
    return lines + [""]


def fidelity_file(patient: str, model: str, passive: bool = False, aortic_weight: float = 0.0) -> str:
    """The name of the table ``scripts/fit_patients.py`` writes of a patient's fidelity checks with
    the LO heart ``model``: ``fidelity_<patient>_<model>[_passive][_aortic<W>].md``, marked where the
    refits moved the passive maps too or weighed the aortic pressure in (:func:`_fit_fidelity`)."""
    return f"fidelity_{patient}_{model}{'_passive' if passive else ''}{f'_aortic{aortic_weight:g}' if aortic_weight else ''}.md"


_FIDELITY_STEM = re.compile(rf"fidelity_(?P<patient>.+)_(?P<model>{'|'.join(map(re.escape, presets.LO_MODELS))})"
                            r"(?P<passive>_passive)?(?:_aortic(?P<weight>[^_]+))?")


def _fit_fidelity(root: Path) -> list[str]:
    """Each table ``fit_patients.py`` wrote of a patient's fidelity checks (one per patient, LO
    model and how the refits moved the maps, :func:`fidelity_file`; each headed by its command)."""
    files = sorted((root / "fit").glob("fidelity_*.md"))
    if not files:
        return _missing("python scripts/fit_patients.py --fidelity")
    lines = []
    for path in files:
        name = _FIDELITY_STEM.fullmatch(path.stem)
        if name is None:  # not a name the script gives
            title = path.stem
        else:
            refits = (", passive maps refitted too" if name["passive"] else "") + (
                f", aortic pressure weighed in (weight {name['weight']})" if name["weight"] else "")
            title = f"{name['patient']}, {name['model']} heart{refits}"
        lines += [f"**{title}**, results of {_stamp(path)} (`{path}`).", "", path.read_text().strip(), ""]
    return lines


def _posteriors(root: Path, report_dir: Path) -> list[str]:
    """Medians and 90 % intervals (physical units, :data:`lvenv.identification.ACTION_BOUNDS`)
    of ``scripts/posterior_patients.py``, its two probabilities and its pairs plot."""
    path = root / "identify" / "posterior_patients.json"
    if not path.exists():
        return _missing("python scripts/posterior_patients.py")
    result = json.loads(path.read_text())
    posteriors = {name: value["posterior"] for name, value in result.items() if isinstance(value, Mapping) and "posterior" in value}
    lines = [f"Command: `python scripts/posterior_patients.py` (sampler {next(iter(posteriors.values()))['sampler']}); "
             f"results of {_stamp(path)}. Median and 90 % credible interval per parameter:", ""]
    lines += _per_parameter({name: {n: f"{m:.3g} ({post['interval_90'][n][0]:.3g}–{post['interval_90'][n][1]:.3g})" for n, m in post["median"].items()}
                             for name, post in posteriors.items()}, units=True)
    lines += ["; ".join(f"{key} = {value:.3f}" for key, value in result.items() if key.startswith("P(")), ""]
    figure = path.with_name("posterior_pairs.png")
    return lines + ([_image(figure, report_dir), ""] if figure.exists() else [])


def _cohorts(root: Path, report_dir: Path) -> list[str]:
    fits = [p for p in sorted((root / "cohort").glob("*.csv")) if p.with_name(p.name + ".json").exists()]
    if not fits:
        return _missing("lvenv cohort REPORTS.csv --out out/cohort/fits.csv")
    lines = []
    for path in fits:
        meta = json.loads(path.with_name(path.name + ".json").read_text())
        s = summarise(path)
        m = s["mismatch"]
        lines += [f"Command: `lvenv cohort REPORTS --out {path}` (input SHA-256 {meta['reports_sha256'][:12]}…); results of {_stamp(path)}.", "",
                  "| patients | status | median mismatch | 95th percentile | max |", "|---|---|---|---|---|",
                  f"| {s['fitted']} | " + ", ".join(f"{k} {v}" for k, v in s["status"].items())
                  + (f" | {100 * m['median']:.2f} % | {100 * m['p95']:.2f} % | {100 * m['max']:.2f} % |" if m else " | — | — | — |"), ""]
        figure = report_dir / f"cohort_{path.stem}.png"
        _mismatch_histogram(path, figure)
        lines += [_image(figure, report_dir), ""]
    return lines


def _mismatch_histogram(path: Path, figure: Path) -> None:
    with path.open(newline="") as handle:
        values = np.array([float(r["mismatch"]) for r in csv.DictReader(handle) if r["mismatch"]])
    histogram_figure(100 * values, figure, "mismatch (%)", f"{path.name}: {len(values)} fits")


def _per_parameter(rows: Mapping[str, Mapping[str, str]], units: bool = False) -> list[str]:
    """A table with one column per parameter: ``rows`` maps a row label to {parameter: cell};
    ``units``: each column's heading gives its parameter's unit."""
    names = list(next(iter(rows.values())))
    head = [f"{n} ({ACTION_BOUNDS[n].units})" if units and ACTION_BOUNDS[n].units != "1" else n for n in names]
    lines = ["| | " + " | ".join(head) + " |", "|---|" + "---|" * len(names)]
    return lines + [f"| {label} | " + " | ".join(cells.get(n, "—") for n in names) + " |" for label, cells in rows.items()] + [""]


def _calibration(root: Path, level: int) -> list[str]:
    """Coverage of the 90 % intervals on synthetic truths: the MCMC posterior
    (``scripts/calibration.py``) and the amortised one (``scripts/bench_amortised.py``);
    subsection headings at ``level``."""
    lines = ["#" * level + " MCMC posterior (`optim.identify.posterior`)", ""]
    path = root / "identify" / "calibration.json"
    if path.exists():
        result = json.loads(path.read_text())
        options = result["options"]
        tail = result["binomial_tail"]
        lines += [f"Command: `python scripts/calibration.py --truths {options['truths']} --draw {options['draw']} --seed {options['seed']}` "
                  f"(other settings: {', '.join(f'{k} {v}' for k, v in options.items() if k not in ('truths', 'draw', 'seed', 'out'))}); "
                  f"results of {_stamp(path)}.", "",
                  f"Fraction of {len(result['runs'])} noisy truths inside their 90 % interval (calibrated: about 0.9), with P, the binomial "
                  "probability of so few hits or fewer if the intervals were calibrated, and the interval's median width (fraction of the bound):", ""]
        lines += _per_parameter({
            "equal-tailed": {n: f"{c:.2f} (P {tail['inside'][n]:.2f})" for n, c in result["coverage"].items()},
            "highest-density": {n: f"{c:.2f} (P {tail['inside_hdi'][n]:.2f})" for n, c in result["coverage_hdi"].items()},
            "median width": {n: f"{w:.2f}" for n, w in result["median_width"].items()},
        })
    else:
        lines += _missing("python scripts/calibration.py")
    lines += ["#" * level + " Amortised posterior (`optim.identify.amortised`)", ""]
    path = root / "bench" / "amortised.json"
    if not path.exists():
        lines += _missing("lvenv bench amortised")
    else:
        result = json.loads(path.read_text())
        kinds = f" over the heart kinds {', '.join(result['bases'])}" if "bases" in result else ""
        lines += [f"Command: `lvenv bench amortised`; results of {_stamp(path)}.", "",
                  f"On {result['truths']} held-out truths from the prior{kinds}: the fraction inside their 90 % interval, and the "
                  "Kolmogorov–Smirnov p-value of the truths' ranks among the samples against uniform (simulation-based calibration, "
                  f"Talts S et al., arXiv:1804.06788, 2018); {100 * result['out_of_distribution']:.1f} % flagged out of distribution.", ""]
        lines += _per_parameter({"90 % coverage": {n: f"{c:.2f}" for n, c in result["coverage_90"].items()},
                                 "rank KS p": {n: f"{p:.3g}" for n, p in result["rank_ks_p"].items()}})
    return lines + _against_mcmc(root / "compare" / "compare.json", level)


def _against_mcmc(path: Path, level: int) -> list[str]:
    """The amortised posteriors, the flow's draws and the importance-weighted ones, beside the
    MCMC posterior of the same patients (``scripts/compare_amortised.py``)."""
    lines = ["#" * level + " Amortised against MCMC", ""]
    if not path.exists():
        return lines + _missing("python scripts/compare_amortised.py --out out/compare")
    result = json.loads(path.read_text())
    methods = [m for m in ("amortised", "importance") if m in result]
    lines += [f"Command: `{result.get('command', 'python scripts/compare_amortised.py')}`; results of {_stamp(path)}.", "",
              f"{result['patients']} patients (the built-in ones and {result['truths']} held-out truths), {result['samples']} draws each; "
              f"MCMC {result['mcmc_seconds_per_patient']:.0f} s per patient (largest split R-hat {result['mcmc_rhat_max']:.3f}). "
              "Per parameter, over the patients: the largest |median − MCMC median| in MCMC posterior sd (acceptance ≤ 0.3) and the "
              "range of the 90 % interval's width over MCMC's (acceptance 0.75–1.25), in the unit-cube coordinate of the parameter's "
              "bound. *amortised*: the flow's draws; *importance*: "
              f"{result.get('importance_draws', 0)} flow draws per patient reweighted by the exact posterior.", ""]
    rows = {}
    for m in methods:
        rows[f"{m}: median shift (sd)"] = {n: f"{v:.2f}" for n, v in result[m]["worst_median_shift_sd"].items()}
        rows[f"{m}: width ratio"] = {n: f"{lo:.2f}–{hi:.2f}" for n, (lo, hi) in result[m]["width_ratio_range"].items()}
    lines += _per_parameter(rows)
    for m in methods:
        within = result[m]["within_acceptance"]
        lines += [f"* {m}: medians within 0.3 sd in {100 * within['median']:.1f} % of the (patient, parameter) pairs, widths within 25 % in "
                  f"{100 * within['width']:.1f} %; {within['patients_all_parameters']} of {result['patients']} patients within both on every "
                  f"parameter; {result[m]['seconds']:.1f} s for all of them."]
    return lines + [""]


def _leaves(value: Any, key: str = "") -> Iterator[tuple[str, str]]:
    """(dotted key, text) of every number, string or short list in a JSON value."""
    if isinstance(value, Mapping):
        for k, v in value.items():
            yield from _leaves(v, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list) and not all(isinstance(v, (int, float, str, bool)) or v is None for v in value):
        for i, v in enumerate(value):
            yield from _leaves(v, f"{key}[{i}]")
    elif isinstance(value, float):
        yield key, f"{value:.4g}"
    else:
        yield key, ", ".join(map(str, value)) if isinstance(value, list) else str(value)


def _benchmarks(root: Path, level: int) -> list[str]:
    benches = sorted((root / "bench").glob("*.json"))
    if not benches:
        return _missing("lvenv bench lo   (and env, optim, kriging, fe, cohort, cold_start, amortised)")
    lines = []
    for path in benches:
        rows = list(_leaves(json.loads(path.read_text())))
        lines += ["#" * level + f" {path.stem}", "", f"Command: `lvenv bench {path.stem}`; results of {_stamp(path)}.", "",
                  "| quantity | value |", "|---|---|", *(f"| `{k}` | {v} |" for k, v in rows[:BENCH_ROWS]), ""]
        if len(rows) > BENCH_ROWS:
            lines += [f"{len(rows) - BENCH_ROWS} more values in `{path}`.", ""]
    return lines


def _sections(root: Path, report_dir: Path, level: int) -> dict[str, list[str]]:
    """Each section's markdown lines, figures written to (or linked from) ``report_dir``, its
    subsection headings at ``level`` (3 in the report, 2 on a page of its own)."""
    return {
        "training": _training(),
        "generalisation": _markdown_file(root / "generalisation" / "generalisation.md", "python scripts/generalisation.py", report_dir,
                                         (root / "generalisation" / "generalisation.png",)),
        "multi-element": _markdown_file(root / "multielement" / "multielement.md", "python scripts/multielement_study.py", report_dir),
        "fidelity": _fidelity(root / "diagnosis", report_dir, level),
        "inverse problem": _inverse(root, report_dir, level),
        "calibration": _calibration(root, level),
        "benchmarks": _benchmarks(root, level),
        "anatomy": _anatomy(root / "anatomy", report_dir, level),
    }


def _anatomy(folder: Path, report_dir: Path, level: int) -> list[str]:
    """The single cell's regression with its figures, then each multi-element model's that has been fitted."""
    lines = _markdown_file(folder / "anatomy.md", "python scripts/anatomy_study.py", report_dir,
                           tuple(folder / f"anatomy_{name}.png" for name in ("scatter", "contours", "parity")))
    for model in presets.MULTI_ELEMENT_MODELS:
        if (folder / f"anatomy_{model}.md").exists():
            lines += ["#" * level + f" The regression of the {model} heart's maps", "",
                      *_markdown_file(folder / f"anatomy_{model}.md", f"python scripts/anatomy_study.py --model {model}", report_dir)]
    return lines


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def build_report(root: str | os.PathLike[str] = "out", path: str | os.PathLike[str] | None = None) -> Path:
    """Write the report (default ``<root>/report/report.md``) and its figures; returns its path."""
    root = Path(root)
    path = Path(path) if path is not None else root / "report" / "report.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [f"# lvenv report ({_now()})", "", f"Rebuilt by `lvenv report` from the results under `{root}/`; nothing recomputed.", ""]
    for key, body in _sections(root, path.parent, 3).items():
        lines += [f"## {TITLES[key]}", "", *body]
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path


def build_pages(root: str | os.PathLike[str], folder: str | os.PathLike[str]) -> list[Path]:
    """Write the report as pages for the documentation site: ``<folder>/index.md`` (a MyST
    toctree) and one ``<folder>/<section>.md`` per section (:data:`SECTIONS`, spaces → hyphens),
    figures beside them; returns the pages' paths, the index first."""
    root, folder = Path(root), Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    now = _now()
    pages = {key.replace(" ", "-"): body for key, body in _sections(root, folder, 2).items()}
    index = folder / "index.md"
    index.write_text("\n".join([
        "# Results", "",
        f"Rebuilt on {now} by `lvenv report` ({{mod}}`optim.report`) from the results under `{root.name}/` and the trained "
        "records shipped in `lvenv/data/`; nothing is recomputed, and nothing here is kept by hand. Each page names the "
        "command that produces its results and the date they were made; a page whose results are missing gives that command.",
        "", "```{toctree}", ":maxdepth: 1", "", *pages, "```", ""]))
    paths = [index]
    for (name, body), key in zip(pages.items(), SECTIONS):
        paths.append(folder / f"{name}.md")
        paths[-1].write_text("\n".join([f"# {TITLES[key]}", "", *body]).rstrip() + "\n")
    return paths
