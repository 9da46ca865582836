from lvenv import cli


def test_presets_command_prints_both_tables(capsys):
    assert cli.main(["presets", "--max-beats", "60"]) == 0
    out = capsys.readouterr().out
    assert "normal" in out and "heart_failure (3)" in out and "EF (%)" in out


def test_simulate_command_reports_bad_input(capsys):
    assert cli.main(["simulate", "--set", "tau2=5"]) == 2
    assert "cell.tau2 = 5 s" in capsys.readouterr().err
