"""The command line: help, distinct exit codes, errors that name the field, NaN shown as such."""

import json

import pytest
from rich.console import Console

from lvenv import cli
from lvenv.identification import ACTION_BOUNDS
from lvenv.patients import builtin
from optim.congruency import FIDELITY_TOLERANCE, MAP_NAMES


def test_presets_command_prints_both_tables(capsys):
    assert cli.main(["presets", "--max-beats", "60"]) == cli.EXIT_OK
    out = capsys.readouterr().out
    assert "normal" in out and "heart_failure (3)" in out and "EF (%)" in out and "IVRT (ms)" in out


@pytest.mark.parametrize("argv", [["--help"], *([c, "--help"] for c in ("presets", "simulate", "reach", "fit", "cohort", "train", "oracle", "bench", "report")), ["-h"]])
def test_help_of_every_command_works(argv, capsys):
    assert cli.main(argv) == cli.EXIT_OK
    out = capsys.readouterr().out
    assert "Usage: lvenv" in out and "Exit codes" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "--set", "tau2=5"], "cell.tau2 = 5 s is outside the allowed range"),
        (["simulate", "--set", "foo=1"], "unknown parameter 'foo'"),
        (["simulate", "--set", "tau2=abc"], "tau2 = 'abc' is not a number"),
        (["simulate", "--set", "tau2"], "expected NAME=VALUE"),
        (["simulate", "--set", "tau2=nan"], "must be finite"),
        (["simulate", "--set", "closed_loop=0.5"], "closed_loop = 0.5 must be one of 0, 1"),
        (["simulate", "--beats", "1.5"], "1.5"),
        (["simulate", "--condition", "4"], "4"),
        (["simulate", "--preset", "nobody"], "nobody"),
        (["simulate", "--patient", "/no/such/file.json"], "file.json"),
        (["simulate", "--steps-per-beat", "5"], "5"),
        (["frobnicate"], "frobnicate"),
        (["fit", "normal", "--refine"], "--refine applies to a posterior: give --posterior amortised"),
        (["fit", "normal", "--samples", "100"], "--samples applies to a posterior"),
        (["fit", "normal", "--map-draws", "4"], "the maps of 'normal' do not come from the anatomy regression"),
        (["fit", "normal", "--map-draws", "1"], "--map-draws needs at least 2 draws"),
        (["fit", "normal", "--retune-maps"], "--retune-maps refits the maps on the oracle's beat: it needs --fidelity"),
        (["fit", "normal", "--retune-maps", "--correct-maps", "2"], "--correct-maps refits them at every round but the last"),
        (["fit", "normal", "--correct-maps", "11"], "11"),
        (["fit", "normal", "--fidelity", "--refit-passive"], "--refit-passive refits the passive maps with the others: it needs --retune-maps"),
        (["fit", "normal", "--fidelity", "--aortic-weight", "1"], "--aortic-weight weighs the aortic pressure into the refits of the maps"),
        (["fit", "normal", "--correct-maps", "1", "--aortic-weight", "-1"], "-1"),
        (["cohort", "r.csv", "--out", "o.csv", "--maps", "gp"], "'gp' is not one of"),
        (["fit", "normal", "--posterior", "mcmc"], "'mcmc' is not one of 'amortised', 'importance'"),
        (["fit", "p.json", "--model", "series3"], "--model series3: a patient record carries its own LO heart model"),
        (["fit", "normal", "--model", "series3", "--scheme", "adaptive"], "scheme = 'adaptive' is not available for a multi-element heart"),
        (["simulate", "--model", "series2"], "'series2' is not one of 'single', 'series3'"),
        (["cohort", "r.csv", "--out", "o.csv", "--model", "series2"], "'series2' is not one of 'single', 'series3'"),
    ],
)
def test_usage_errors_exit_2_and_name_the_problem(argv, message, capsys):
    assert cli.main(argv) == cli.EXIT_USAGE
    captured = capsys.readouterr()
    assert message in captured.err and "Traceback" not in captured.err


def test_a_failed_simulation_exits_1_with_its_status_and_no_numbers(capsys):
    argv = ["simulate", "--set", "Sa=10", "--set", "Cmax=10", "--set", "Tref=1000", "--beats", "2"]
    assert cli.main(argv + ["--json"]) == cli.EXIT_FAILED
    payload = json.loads(capsys.readouterr().out)
    assert payload["status"] == "non_physical" and all(v is None for v in payload["metrics"].values())
    assert cli.main(argv) == cli.EXIT_FAILED
    out = capsys.readouterr().out
    assert "non_physical" in out and "—" in out and "0.0 " not in out


def test_a_patient_file_is_simulated(tmp_path, capsys):
    from lvenv.patients import builtin

    path = tmp_path / "hf.json"
    builtin("heart_failure").to_json(path)
    assert cli.main(["simulate", "--patient", str(path), "--beats", "1", "--json"]) == cli.EXIT_OK
    assert json.loads(capsys.readouterr().out)["status"] == "ok"


def test_simulate_runs_the_model_asked_for(capsys):
    import lvenv
    from lvenv import presets

    assert cli.main(["simulate", "--model", "series3", "--beats", "1", "--steps-per-beat", "200", "--json"]) == cli.EXIT_OK
    payload = json.loads(capsys.readouterr().out)
    expected = lvenv.simulate(presets.normal(model="series3"), beats=1, steps_per_beat=200)
    assert payload["status"] == "ok" and payload["metrics"]["EF"] == pytest.approx(float(expected.metrics["EF"]), rel=1e-12)


def test_an_internal_error_exits_3_with_the_traceback(monkeypatch, capsys):
    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(cli, "simulate", broken)
    assert cli.main(["simulate"]) == cli.EXIT_INTERNAL
    err = capsys.readouterr().err
    assert "internal error" in err and "RuntimeError: boom" in err and "Traceback" in err


def test_long_commands_show_progress_on_a_terminal(monkeypatch, capsys):
    import io

    from rich.console import Console

    screen = io.StringIO()
    monkeypatch.setattr(cli, "_err", Console(file=screen, force_terminal=True, width=120))
    assert cli.main(["simulate", "--beats", "1", "--json"]) == cli.EXIT_OK
    assert "simulating" in screen.getvalue()
    capsys.readouterr()
    monkeypatch.setattr(cli, "_err", Console(file=io.StringIO(), force_terminal=False))
    assert cli.main(["simulate", "--beats", "1", "--json"]) == cli.EXIT_OK
    assert "simulating" not in capsys.readouterr().err  # nothing but the result when piped


def test_fit_command_reports_parameters_targets_and_compile_time_and_plots_the_fit(tmp_path, capsys):
    """The fit with every report it can add; the map correction (`optim.fit.corrected_fit`) runs
    against the multielement oracle, whose own test is in test_optim_fit."""
    plot, convergence = tmp_path / "fit.png", tmp_path / "convergence.pdf"
    argv = ["fit", "normal", "--method", "cma", "--budget", "16", "--num-envs", "8", "--steps-per-beat", "250", "--plot", str(plot),
            "--convergence", str(convergence), "--identifiability", "--posterior", "importance", "--samples", "200",
            "--fidelity-backend", "multielement", "--correct-maps", "1", "--retune-budget", "16", "--json"]
    assert cli.main(argv) == cli.EXIT_OK
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and convergence.read_bytes()[:5] == b"%PDF-"
    payload = json.loads(capsys.readouterr().out)
    assert set(payload["parameters"]) == {"tau2", "Sa", "R2", "R3", "C", "Cat"}
    assert payload["evaluations"] == 16 and payload["status"] in ("ok", "not_converged")
    assert set(payload["mismatch_per_target"]) == set(payload["targets"]) and payload["compile_time_s"] > 0
    bands = payload["plausibility"]
    assert set(bands) == {"P_ao_mean", "P_at_mean", "EDP"}
    for name, check in bands.items():
        assert check["inside"] == (check["low"] <= check["value"] <= check["high"]), name
        assert check["value"] == pytest.approx(7.50062 * payload["observation"][name]), "mmHg"
    ident = payload["identifiability"]
    assert len(ident["singular_values"]) == 4 and len(ident["null_directions"]) == 2, "4 targets, 6 parameters"
    post = payload["posterior"]
    assert post["sampler"] == "importance" and not post["refined"] and not post["out_of_distribution"] and post["reason"] == ""
    assert 0 < post["ess"] <= 400 and post["pareto_k"] < 0.7, "400 proposals (2 per draw), reliable weights for the built-in patient"
    for name, median in post["median"].items():
        lo, hi = post["interval_90"][name]
        assert ACTION_BOUNDS[name].lo <= lo < median < hi <= ACTION_BOUNDS[name].hi, name
    first, second = payload["correction"]
    assert first["round"] == 0 and second["round"] == 1 and payload["fidelity"] == first["fidelity"]
    assert first["parameters"] == payload["parameters"] and first["maps"] == {n: getattr(builtin("normal").heart.lo, n) for n in MAP_NAMES}
    assert second["maps"] == first["fidelity"]["retuned"]["lo"] != first["maps"], "round 1 fits with the maps refitted on round 0's beat"
    assert first["fidelity"]["retuned"]["C"] <= first["fidelity"]["C"], "the refit starts from the maps it improves on"
    assert second["fidelity"]["retuned"] is None and second["evaluations"] == 16 and second["parameters"] != first["parameters"]
    assert set(second["fidelity"]["rows"]) == set(FIDELITY_TOLERANCE) and second["fidelity"]["provenance"]["backend"] == "multielement"
    console = Console(record=True, width=300)
    console.print(cli._correction_table(payload["correction"], "multielement", 6.0))
    rows = [line for line in console.export_text().splitlines() if line.startswith("│")]
    assert [row.split("│")[1].strip() for row in rows] == ["0", "1"]
    for row, step in zip(rows, payload["correction"]):
        cells = [c.strip() for c in row.split("│")[1:-1]]
        assert cells[6] == f"{100 * step['fidelity']['C']:.2f}" and sum(c.endswith("OUT") for c in cells) == list(step["fidelity"]["within"].values()).count(False)
    console.print(cli._fidelity_table(first["fidelity"], "multielement", 6.0))
    text = console.export_text()
    assert f"C {100 * first['fidelity']['C']:.2f} %" in text and f"C {100 * first['fidelity']['retuned']['C']:.2f} %" in text
    rows = [line for line in text.splitlines() if line.startswith("│")]
    assert len(rows) == len(FIDELITY_TOLERANCE) and all(len(row.split("│")) == 9 for row in rows), "LO, oracle, then both differences"
    assert cli.main(["fit", "nobody"]) == cli.EXIT_USAGE
    assert "nobody" in capsys.readouterr().err


def test_cohort_command_skips_bad_rows_naming_their_lines_and_fits_the_rest(tmp_path, capsys):
    reports = tmp_path / "reports.csv"
    reports.write_text("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm\n"
                       "A,58,290,85,124,78,64\nB,58,,85,124,78,64\nC,160,290,85,124,78,64\n")
    fits = tmp_path / "out" / "cohort" / "fits.csv"
    argv = ["cohort", str(reports), "--out", str(fits), "--budget", "8", "--candidates", "8"]
    assert cli.main(argv + ["--json"]) == cli.EXIT_OK
    captured = capsys.readouterr()
    assert "line 3 (id B): ET_ms is missing; skipped" in captured.err and "line 4 (id C): EF_pct = 160" in captured.err
    summary = json.loads(captured.out)
    assert summary["fitted"] == 1 and [b["line"] for b in summary["bad_rows"]] == [3, 4]
    header = fits.read_text().splitlines()[0]
    assert header.startswith("id,tau2_s,Sa,R2_kPa_s_per_ml,R3_kPa_s_per_ml,C_ml_per_kPa,Cat_ml_per_kPa,mismatch,")
    no_hr = tmp_path / "no_hr.csv"
    no_hr.write_text("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg\nA,58,290,85,124,78\n")
    assert cli.main(["cohort", str(no_hr), "--out", str(tmp_path / "x.csv")]) == cli.EXIT_USAGE
    assert "lacks the required column(s) ['HR_bpm']" in capsys.readouterr().err
    assert cli.main(["report", "--root", str(tmp_path / "out")]) == cli.EXIT_OK
    report = (tmp_path / "out" / "report" / "report.md").read_text()
    assert "| normal | " in report and "| heart_failure | " in report, "congruency from the shipped records"
    assert f"--out {fits}" in report and "| 1 | ok 1 |" in report, "the cohort's summary with its command"
    assert "Not run yet. Command: `make run`" in report and "Not run yet. Command: `lvenv bench lo" in report
    assert (tmp_path / "out" / "report" / "cohort_fits.png").stat().st_size > 0


def test_cohort_posterior_adds_medians_intervals_and_flags_per_row(tmp_path, capsys):
    """--posterior amortised: every parameter's median inside its 90 % interval inside its bound;
    a row far from every simulated heart is flagged with the density reason, a row with a target
    the estimator does not take (EDV) is flagged with that reason and has empty cells; a row with
    a geometry (its anatomy's regression maps) is answered, one outside the anatomy box flagged."""
    import csv

    from optim.cohort import parameter_column

    reports = tmp_path / "reports.csv"
    reports.write_text("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm,EDV_ml,Rb_mm,H_mm\n"
                       "A,58,290,85,124,78,64,,,\nB,55,300,90,120,80,70,130,,\nC,10,80,300,230,42,64,,,\n"
                       "D,58,290,85,124,78,64,,31,8\nE,58,290,85,124,78,64,,60,8\n")
    fits = tmp_path / "fits.csv"
    argv = ["cohort", str(reports), "--out", str(fits), "--budget", "8", "--candidates", "8", "--posterior", "amortised", "--samples", "400"]
    assert cli.main(argv + ["--json"]) == cli.EXIT_OK
    assert json.loads(capsys.readouterr().out)["posterior"] == {"flagged": 3, "refined": 0}
    rows = {r["id"]: r for r in csv.DictReader(fits.open())}
    header = fits.read_text().splitlines()[0].split(",")
    assert header[-5:] == ["post_sampler", "post_refined", "post_ood", "post_ood_reason", "line"]
    assert header.index("tau2_s_post_median") + 1 == header.index("tau2_s_post_q05") and "Cat_ml_per_kPa_post_q95" in header
    for rid in "ACD":
        assert rows[rid]["post_sampler"] == "amortised" and rows[rid]["post_refined"] == "0"
        for name, bound in ACTION_BOUNDS.items():
            column = parameter_column(name)
            lo, median, hi = (float(rows[rid][f"{column}_post_{s}"]) for s in ("q05", "median", "q95"))
            assert bound.lo <= lo < median < hi <= bound.hi, (rid, name)
    assert (rows["A"]["post_ood"], rows["A"]["post_ood_reason"]) == (rows["D"]["post_ood"], rows["D"]["post_ood_reason"]) == ("0", "")
    assert rows["E"]["post_ood"] == "1" and "Rb = 60 outside" in rows["E"]["post_ood_reason"] and rows["E"]["post_sampler"] == ""
    assert rows["C"]["post_ood"] == "1" and "log density" in rows["C"]["post_ood_reason"]
    assert rows["B"]["post_ood"] == "1" and "['EDV']" in rows["B"]["post_ood_reason"] and rows["B"]["post_sampler"] == ""
    assert rows["B"]["tau2_s_post_median"] == rows["B"]["Sa_post_q95"] == ""
    assert float(rows["C"]["tau2_s_post_q95"]) < float(rows["A"]["tau2_s_post_q05"]), "the rows' own posteriors, not one shared"
    assert cli.main(argv[:-1] + ["800"]) == cli.EXIT_USAGE, "a resumed output of other posterior options is refused"
    assert "other options" in capsys.readouterr().err


def test_the_persistent_jit_cache_stores_compiled_programs_unless_turned_off(tmp_path):
    import os
    import subprocess
    import sys

    env = {**os.environ, "LVENV_JIT_CACHE": str(tmp_path / "jax")}
    argv = [sys.executable, "-m", "lvenv.cli", "simulate", "--beats", "1", "--steps-per-beat", "100", "--json"]
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert list((tmp_path / "jax").iterdir()), "the process stored its compiled programs"
    off = subprocess.run(argv[:3] + ["--no-jit-cache"] + argv[3:], env={**os.environ, "LVENV_JIT_CACHE": str(tmp_path / "other")},
                         capture_output=True, text=True, timeout=300)
    assert off.returncode == 0, off.stderr
    assert not (tmp_path / "other").exists()


def test_simulate_plot_writes_a_pdf_and_refuses_other_suffixes_before_simulating(tmp_path, capsys):
    pdf = tmp_path / "beat.pdf"
    assert cli.main(["simulate", "--steps-per-beat", "250", "--plot", str(pdf)]) == cli.EXIT_OK
    assert pdf.read_bytes()[:5] == b"%PDF-"
    assert cli.main(["simulate", "--plot", str(tmp_path / "beat.txt")]) == cli.EXIT_USAGE
    assert "must end in one of ('.png', '.pdf')" in capsys.readouterr().err


def test_oracle_and_train_commands_run_on_the_multielement_backend(tmp_path, capsys):
    plot = tmp_path / "lo_fe.png"
    argv = ["oracle", "normal", "--case", "2", "--backend", "multielement", "--plot", str(plot), "--json"]
    assert cli.main(argv) == cli.EXIT_OK
    payload = json.loads(capsys.readouterr().out)
    assert payload["fe_valid"] and payload["lo_status"] == "ok" and 0.3 < payload["fe"]["EF"] < 0.8
    assert plot.stat().st_size > 0
    out = tmp_path / "trained.json"
    assert cli.main(["train", "normal", "--backend", "multielement", "--budget", "16", "--delay", "never", "--out", str(out)]) == cli.EXIT_OK
    from lvenv.trained import TrainedLO

    trained = TrainedLO.from_json(out)
    assert trained.provenance["backend"] == "multielement" and 0.0 <= trained.congruency["C"] < 1.0
    assert cli.main(["bench", "nonsense"]) == cli.EXIT_USAGE


def test_an_unwritable_output_is_refused_before_any_computation(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    reports = tmp_path / "reports.csv"
    reports.write_text("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm\nA,58,290,85,124,78,64\n")
    cases = [
        ["simulate", "--plot", str(blocker / "beat.png")],
        ["fit", "normal", "--convergence", str(blocker / "c.pdf")],
        ["fit", "normal", "--report", str(blocker / "report")],
        ["cohort", str(reports), "--out", str(blocker / "fits.csv")],
        ["train", "normal", "--out", str(blocker / "trained.json")],
        ["oracle", "normal", "--plot", str(blocker / "o.png")],
        ["report", "--out", str(blocker / "report.md")],
    ]
    for argv in cases:
        assert cli.main(argv) == cli.EXIT_USAGE, argv
        captured = capsys.readouterr()
        assert "Traceback" not in captured.err and not captured.out, argv
        assert "is a file, not a folder" in captured.err or "must be a file, and it is a folder" in captured.err, (argv, captured.err)


def test_a_write_that_fails_anyway_prints_the_result_and_names_the_path(tmp_path, monkeypatch, capsys):
    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cli.plots, "beat_figure", full_disk)
    plot = tmp_path / "beat.png"
    assert cli.main(["simulate", "--beats", "1", "--steps-per-beat", "100", "--plot", str(plot), "--json"]) == cli.EXIT_USAGE
    captured = capsys.readouterr()
    assert json.loads(captured.out)["status"] == "ok", "the result is printed"
    assert f"cannot write --plot '{plot}': No space left on device" in captured.err and "Traceback" not in captured.err


def test_an_unusable_jit_cache_warns_and_the_command_runs(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    monkeypatch.setenv("LVENV_JIT_CACHE", str(blocker / "jax"))
    assert cli.main(["simulate", "--help"]) == cli.EXIT_OK
    captured = capsys.readouterr()
    assert "lvenv: warning: the JAX compilation cache" in captured.err and "running without it" in captured.err
    assert "Usage: lvenv simulate" in captured.out


def test_a_budget_below_one_batch_is_a_usage_error_naming_the_field(monkeypatch, capsys):
    import optim.fit

    monkeypatch.setattr(optim.fit, "warm_up", lambda venv: 0.0)  # the check needs no compiled model
    assert cli.main(["fit", "normal", "--budget", "16", "--num-envs", "32"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "budget = 16 evaluations is below one batch of 32" in err and "Traceback" not in err


def test_an_oracle_that_does_not_converge_keeps_the_fit_and_exits_1(monkeypatch, capsys):
    import fe_oracle

    def diverging(*args, **kwargs):
        raise fe_oracle.OracleDidNotConverge("Newton diverged", time=0.31, residual=2.5e3, log=[])

    monkeypatch.setattr(fe_oracle, "run", diverging)
    argv = ["fit", "normal", "--method", "cma", "--budget", "16", "--num-envs", "8", "--steps-per-beat", "250", "--fidelity", "--json"]
    assert cli.main(argv) == cli.EXIT_FAILED
    captured = capsys.readouterr()
    payload = json.loads(captured.out)
    assert set(payload["parameters"]) == {"tau2", "Sa", "R2", "R3", "C", "Cat"} and "fidelity" not in payload
    assert payload["fidelity_error"].startswith("Newton diverged (at t = 0.31") and "Traceback" not in captured.err
