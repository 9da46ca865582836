"""The anatomy campaign's results: status, throughput, the regression's cross-validation, the held-out check and the figures; prints one JSON object.

    python scripts/anatomy_study.py [--dataset lvenv/data/anatomy] [--out out/anatomy] [--restarts 5] [--artefact PATH]
    python scripts/anatomy_study.py --model series3 [...]

Reads the campaign's dataset (`optim.campaign`; no FE run), counts the anatomies by status with
every reason for leaving one out, and the throughput per session and worker count from the
campaign's own log, and the paper's unloading rule (`lvenv.anatomy.unload`) on the Table 1
end-diastolic anatomies against their unloaded ones and, through the oracle's passive curves of
the accepted anatomies, against the FE wall (`optim.unloading.check`: the rule's EDV and V0
errors, the strain the wall has at EDP, and V0 recovered by the passive-curve search
`lvenv.anatomy.unload_to_volume` with each anatomy's trained maps and with the GP's). With at least `optim.regression.MIN_ANATOMIES` accepted training anatomies
it fits the regression (`optim.regression.fit`, 5-fold cross-validation), writes the artefact
(default: the package's, which `lvenv.anatomy.from_geometry` loads), compares C of the
GP-predicted, the directly trained and the N record's maps on each held-out anatomy
(`optim.regression.held_out`), and draws the Fig. 9-style scatter and contour plots and the
parity plot under ``--out``. ``<out>/anatomy.md`` holds the tables, the command and the date for
``lvenv report``.

``--model series3``: the regression of a multi-element LO heart's maps and cells' onsets over
the anatomies its table holds (``lvenv campaign train-model``, `optim.campaign.train_model_table`),
its cross-validation and held-out check (each heart with its own cells' onsets), written to its
artefact (default `lvenv.anatomy.artefact`) and ``<out>/anatomy_<model>.md``; no unloading check.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from lvenv import plots, presets  # noqa: E402
from lvenv.anatomy import ED_STRAIN, artefact, unload  # noqa: E402
from lvenv.geometry import cavity_volume  # noqa: E402
from optim import campaign, regression, unloading  # noqa: E402


def _markdown(summary: dict, command: str) -> str:
    lines = [f"Made by `{command}` on {summary['date']}.", "", "| Table 1 anatomy | unloaded by the rule: V0 (ml) | paper's unloaded V0 (ml) | error |", "|---|---|---|---|"]
    lines += [f"| {k} (strain {100 * v['strain']:.0f} %) | {v['V0_rule_ml']:.1f} | {v['V0_table1_ml']:.1f} | {100 * v['V0_error']:+.1f} % |"
              for k, v in summary["unloading_rule"].items()]
    lines += ["", "| status | anatomies |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in summary["counts"].items() if v]
    if summary["throughput"]:
        lines += ["", "| session | workers | anatomies | per hour | median min per anatomy |", "|---|---|---|---|---|"]
        lines += [f"| {s['session']} | {s['workers']} | {s['anatomies']} | {s['per_hour']:.2f} | {s['median_anatomy_min']:.1f} |" for s in summary["throughput"]]
    if summary["unloading_fe"]:
        gp = "V0_error_gp_median_abs" in next(iter(summary["unloading_fe"].values()))
        lines += ["", "Unloading against the FE wall (`optim.unloading`), median / largest absolute error over the accepted anatomies:", "",
                  "| rule | EDP (kPa) | anatomies | EDV error | V0 error, rule | V0 error, trained maps | " + ("V0 error, GP maps | " if gp else "")
                  + "strain of the FE wall at EDP |", "|---|---|---|---|---|---|---|" + ("---|" if gp else "")]
        for group, f in summary["unloading_fe"].items():
            pair = lambda key: f"{100 * f[key + '_median_abs']:.1f} / {100 * f[key + '_max_abs']:.1f} %"
            lines.append(f"| {group}: strain {100 * ED_STRAIN[group]:.0f} % | {f['EDP_kPa']:.2f} | {f['anatomies']} | {pair('EDV_error')} | {pair('V0_error_rule')} | "
                         f"{pair('V0_error_fit')} | " + (f"{pair('V0_error_gp')} | " if gp else "")
                         + f"{100 * f['strain_fe_median']:.1f} % ({100 * f['strain_fe_min']:.1f}–{100 * f['strain_fe_max']:.1f} %) |")
    return "\n".join(lines + _regression_lines(summary)) + "\n"


def _regression_lines(summary: dict) -> list[str]:
    """The cross-validation and held-out tables of ``summary``."""
    lines = []
    if "cv" in summary:
        lines += ["", f"Cross-validation ({summary['folds']}-fold, {summary['training_anatomies']} anatomies):", "",
                  "| output | regressed | R² | RMSE | within 2 sd |", "|---|---|---|---|---|"]
        lines += [f"| {k} | fixed by training | | | |" if v == "fixed" else
                  f"| {k} | {'in log' if v['log'] else 'as is'} | {v['r2']:.3f} | {v['rmse']:.4g} | {100 * v['coverage_2sd']:.0f} % |"
                  for k, v in summary["cv"].items()]
    if summary.get("held_out"):
        lines += ["", "| held-out anatomy | C trained (%) | C GP-predicted (%) | C N maps (%) |", "|---|---|---|---|"]
        lines += [f"| {r['id']} | {100 * r['C_trained']:.2f} | {100 * r['C_predicted']:.2f} | {100 * r['C_baseline']:.2f} |" for r in summary["held_out"]]
    return lines


def _unloading_rule() -> dict:
    """The paper's unloading rule (`lvenv.anatomy.unload`) on the Table 1 end-diastolic
    anatomies, against the paper's own unloaded ones: V0 in ml and its relative error."""
    out = {}
    for name, ed, unloaded in (("N", presets.N_END_DIASTOLE, presets.N_UNLOADED), ("HF", presets.HF_END_DIASTOLE, presets.HF_UNLOADED)):
        rule = unload(ed, ED_STRAIN[name])
        out[name] = {"strain": ED_STRAIN[name], "geometry": rule.as_tuple(), "V0_rule_ml": cavity_volume(rule), "V0_table1_ml": cavity_volume(unloaded),
                     "V0_error": cavity_volume(rule) / cavity_volume(unloaded) - 1.0}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=pathlib.Path, default=campaign.DATASET)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("out/anatomy"))
    parser.add_argument("--restarts", type=int, default=5)
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--model", choices=tuple(presets.LO_MODELS), default="single", help="the LO heart whose maps to regress")
    parser.add_argument("--artefact", type=pathlib.Path, default=None, help="default: the package's artefact of --model")
    args = parser.parse_args()
    args.artefact = artefact(args.model) if args.artefact is None else args.artefact
    command = "python " + " ".join(sys.argv)
    if args.model != "single":
        fitted = regression.fit(args.dataset, restarts=args.restarts, folds=args.folds, model=args.model)
        regression.save(fitted, args.artefact)
        summary = {"date": datetime.date.today().isoformat(), "model": args.model, "training_anatomies": len(fitted.ids), "folds": args.folds,
                   "artefact": str(args.artefact), "cv": {k: v["cv"] | {"log": v["log"]} if "cv" in v else "fixed" for k, v in fitted.outputs.items()},
                   "held_out": regression.held_out(fitted, args.dataset)}
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"anatomy_{args.model}.md").write_text("\n".join([f"Made by `{command}` on {summary['date']}.", *_regression_lines(summary)]) + "\n")
        print(json.dumps(summary, indent=2, default=float))
        return
    rows = campaign.read_index(args.dataset)
    summary: dict = {
        "date": datetime.date.today().isoformat(),
        "counts": {s: sum(r["status"] == s for r in rows) for s in campaign.STATUSES},
        "left_out": {r["id"]: f"{r['status']}: {r['reason']}" for r in rows if r["status"] not in ("pending", "accepted")},
        "throughput": campaign.throughput(args.dataset),
        "settings": json.loads((args.dataset / "campaign.json").read_text())["settings"],
        "unloading_rule": _unloading_rule(),
    }
    ids, _, trained = regression.training_set(args.dataset)
    fitted = None
    if len(ids) >= regression.MIN_ANATOMIES:
        fitted = regression.fit(args.dataset, restarts=args.restarts, folds=args.folds)
        regression.save(fitted, args.artefact)
        cv_predictions = fitted.provenance["cv_predictions"]
        summary.update(training_anatomies=len(ids), folds=args.folds, artefact=str(args.artefact),
                       cv={k: v["cv"] | {"log": v["log"]} if "cv" in v else "fixed" for k, v in fitted.outputs.items()}, held_out=regression.held_out(fitted, args.dataset))
        args.out.mkdir(parents=True, exist_ok=True)
        summary["figures"] = [str(p) for p in (
            plots.anatomy_scatter_figure(fitted, args.out / "anatomy_scatter.png"),
            plots.anatomy_contour_figure(fitted, args.out / "anatomy_contours.png"),
            plots.parity_figure({k: trained[k] for k in cv_predictions}, {k: np.array(v["predicted"]) for k, v in cv_predictions.items()},
                                {k: np.array(v["sd"]) for k, v in cv_predictions.items()}, args.out / "anatomy_parity.png"),
        )]
    else:
        summary["regression"] = f"not fitted: {len(ids)} accepted training anatomies, {regression.MIN_ANATOMIES} needed"
    edp = unloading.reference_edp()
    rows = unloading.check(args.dataset, edp, fitted)
    summary["unloading_fe"] = {group: {"EDP_kPa": edp[group], **figures} for group, figures in unloading.summary(rows).items()}
    summary["unloading_fe_rows"] = rows
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "anatomy.md").write_text(_markdown(summary, command))
    print(json.dumps(summary, indent=2, default=float))


if __name__ == "__main__":
    main()
