"""The command line: help, distinct exit codes, errors that name the field, NaN shown as such."""

import json

import pytest

from lvenv import cli


def test_presets_command_prints_both_tables(capsys):
    assert cli.main(["presets", "--max-beats", "60"]) == cli.EXIT_OK
    out = capsys.readouterr().out
    assert "normal" in out and "heart_failure (3)" in out and "EF (%)" in out and "IVRT (ms)" in out


@pytest.mark.parametrize("argv", [["--help"], ["presets", "--help"], ["simulate", "--help"], ["reach", "--help"], ["-h"]])
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
