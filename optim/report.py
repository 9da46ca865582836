"""`lvenv report`: one markdown report of every experiment the project reproduces, rebuilt from
the results the experiments left under ``out/`` (and the trained records shipped in the package).

Nothing is recomputed. Each section states the command that produces its results. A section
whose results are missing says so and gives that command. Sources:

=================  ==============================================  ==============================================
section            read from                                       written by
=================  ==============================================  ==============================================
congruency         ``lvenv/data/trained_*.json``                   ``python scripts/train_presets.py``
generalisation     ``out/generalisation/generalisation.{md,png}``     ``python scripts/generalisation.py``
multi-element      ``out/multielement/multielement.md``            ``python scripts/multielement_study.py``
inverse problem    ``out/fit/fits.txt``, ``out/fit/pv_*.png``      ``make run``
cohort             ``out/cohort/*.csv`` with its ``.json``         ``lvenv cohort REPORTS --out out/cohort/…``
performance        ``out/bench/*.json``                            ``lvenv bench NAME``
anatomy            ``out/anatomy/anatomy.md`` and its figures      ``python scripts/anatomy_study.py``
=================  ==============================================  ==============================================
"""

from __future__ import annotations

import csv
import datetime
import json
import os
from pathlib import Path

import numpy as np

from lvenv import trained
from lvenv.plots import histogram_figure
from optim.cohort import summarise

__all__ = ["build_report", "SECTIONS"]

SECTIONS = ("congruency", "generalisation", "multi-element", "inverse problem", "cohort", "performance", "anatomy")


def _stamp(path: Path) -> str:
    return datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def _missing(command: str) -> list[str]:
    return [f"Not run yet. Command: `{command}`", ""]


def _image(path: Path, report_dir: Path) -> str:
    return f"![{path.stem}]({os.path.relpath(path, report_dir)})"


def _congruency() -> list[str]:
    lines = ["Command: `python scripts/train_presets.py` (or `lvenv train HEART --out FILE`); "
             "read from the records shipped in `lvenv/data/`.", "",
             "| heart | C ① | C ② | C ③ | C | C without the delay | delay (ms) | backend, mesh |", "|---|---|---|---|---|---|---|---|"]
    for name in ("normal", "heart_failure"):
        record = trained.builtin(name)
        c, without = record.congruency, record.congruency_without_delay or {}
        cells = [f"{100 * c[k]:.2f} %" for k in ("1", "2", "3", "C")]
        cells.append(f"{100 * without['C']:.2f} %" if "C" in without else "—")
        cells.append(f"{1000 * record.lo.delay:.0f}")
        cells.append(f"{record.provenance.get('backend')}, h = {record.provenance.get('mesh_size_mm', '—')} mm")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines + [""]


def _markdown_file(path: Path, command: str, report_dir: Path, images: tuple[Path, ...] = ()) -> list[str]:
    if not path.exists():
        return _missing(command)
    lines = [f"Command: `{command}`; results of {_stamp(path)} (`{path}`).", "", path.read_text().strip(), ""]
    return lines + [line for image in images if image.exists() for line in (_image(image, report_dir), "")]


def _inverse(root: Path, report_dir: Path) -> list[str]:
    table = root / "fit" / "fits.txt"
    if not table.exists():
        return _missing("make run")
    lines = [f"Command: `make run`; results of {_stamp(table)}.", "", "```", table.read_text().rstrip(), "```", ""]
    lines += [_image(p, report_dir) for p in sorted((root / "fit").glob("pv_*.png"))]
    return lines + [""]


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


def _performance(root: Path) -> list[str]:
    benches = sorted((root / "bench").glob("*.json"))
    if not benches:
        return _missing("lvenv bench lo   (and env, optim, kriging, fe, cohort, cold_start)")
    lines = []
    for path in benches:
        lines += [f"### {path.stem}", "", f"Command: `lvenv bench {path.stem}`; results of {_stamp(path)}.", "",
                  "```json", json.dumps(json.loads(path.read_text()), indent=1)[:4000], "```", ""]
    return lines


def build_report(root: str | os.PathLike[str] = "out", path: str | os.PathLike[str] | None = None) -> Path:
    """Write the report (default ``<root>/report/report.md``) and its figures; returns its path."""
    root = Path(root)
    path = Path(path) if path is not None else root / "report" / "report.md"
    report_dir = path.parent
    report_dir.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# lvenv report ({now})", "", f"Rebuilt by `lvenv report` from the results under `{root}/`; nothing recomputed.", ""]
    sections = {
        "congruency": _congruency(),
        "generalisation": _markdown_file(root / "generalisation" / "generalisation.md", "python scripts/generalisation.py", report_dir,
                                         (root / "generalisation" / "generalisation.png",)),
        "multi-element": _markdown_file(root / "multielement" / "multielement.md", "python scripts/multielement_study.py", report_dir),
        "inverse problem": _inverse(root, report_dir),
        "cohort": _cohorts(root, report_dir),
        "performance": _performance(root),
        "anatomy": _markdown_file(root / "anatomy" / "anatomy.md", "python scripts/anatomy_study.py", report_dir,
                                  tuple(root / "anatomy" / f"anatomy_{name}.png" for name in ("scatter", "contours", "parity"))),
    }
    for title, body in sections.items():
        lines += [f"## {title.capitalize()}", "", *body]
    path.write_text("\n".join(lines).rstrip() + "\n")
    return path
