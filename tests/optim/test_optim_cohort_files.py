"""Cohort CSV files as people write them: byte-order marks, other separators and encodings,
binary files, awkward column names and quoting, torn output; the output parses back whole.

The fits are replaced by a stand-in (the reports' own targets as the fit) so that many files
run in seconds: what is tested is the reading, the writing and the resume, not the fitting
(tests/optim/test_optim_cohort.py fits for real)."""

import csv
import io
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from optim import cohort
from optim.cohort import CohortError, output_columns, read_reports, run_cohort

REQUIRED = list(cohort.REQUIRED)
GOOD = {"EF_pct": "58", "ET_ms": "290", "IVRT_ms": "85", "SBP_mmHg": "124", "DBP_mmHg": "78", "HR_bpm": "64"}
#: Values that make a row bad, with a word its reason must contain.
BAD = [("ET_ms", "", "ET_ms is missing"), ("EF_pct", "160", "EF_pct = 160"), ("SBP_mmHg", "high", "SBP_mmHg = 'high'"),
       ("DBP_mmHg", "200", "DBP_mmHg"), ("HR_bpm", "0", "HR_bpm")]


def _stand_in(reports, options=None, *, on_done=None):
    """A 'fit' of each report at its own targets (the output's every column filled)."""
    results = []
    for report in reports:
        observation = dict.fromkeys(cohort.OBS_NAMES, math.nan) | dict(report.patient.targets) | {"P_ao_sys": 16.0, "EDP": 1.0, "P_at_mean": 1.2}
        result = {"id": report.id, "line": report.line, "extra": report.extra, "targets": dict(report.patient.targets),
                  "parameters": {n: float(report.patient.heart.get(n)) for n in cohort.DEFAULT_ACTION_PARAMS},
                  "observation": observation, "mismatch": 0.0, "evaluations": 8, "stop": "tolerance", "status": "ok", "maps": "base"}
        results.append(result)
        if on_done is not None:
            on_done(result)
    return results


def _encode(rows, quoting, line_end, encoding):
    """The rows as a CSV file; a cell with a line break is quoted whatever the line ending (the
    csv module's minimal quoting only looks for the characters of its own line ending)."""
    if any("\n" in cell or "\r" in cell for row in rows for cell in row):
        quoting = csv.QUOTE_ALL
    text = io.StringIO(newline="")
    csv.writer(text, quoting=quoting, lineterminator=line_end).writerows(rows)
    return text.getvalue().encode(encoding)


_NAME = st.text(st.sampled_from(list('ab, ;"\'é→\t\n')), min_size=1, max_size=8).map(str.strip).filter(
    lambda n: n and n not in output_columns(()) and n not in cohort._KNOWN)
_CELL = st.text(st.sampled_from(list('x1, ;"é\n')), max_size=6)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(extra=st.lists(_NAME, max_size=3, unique=True), n=st.integers(1, 6), data=st.data(),
       quoting=st.sampled_from([csv.QUOTE_MINIMAL, csv.QUOTE_ALL]), line_end=st.sampled_from(["\n", "\r\n", "\r"]),
       encoding=st.sampled_from(["utf-8", "utf-8-sig", "utf-16"]))
def test_every_row_of_any_file_is_fitted_or_reported_and_the_output_parses_back(tmp_path_factory, monkeypatch, extra, n, data, quoting,
                                                                               line_end, encoding):
    monkeypatch.setattr(cohort, "fit_reports", _stand_in)
    header = [*REQUIRED, *extra]
    rows, good, bad = [], {}, {}
    for i in range(n):
        values = dict(GOOD, id=f"p{i}", **{c: data.draw(_CELL) for c in extra})
        if data.draw(st.booleans()):
            column, value, reason = data.draw(st.sampled_from(BAD))
            values[column] = value
            bad[f"p{i}"] = reason
        else:
            good[f"p{i}"] = {c: values[c] for c in extra}
        rows.append([values[c] for c in header])
    folder = tmp_path_factory.mktemp("cohort")
    reports = folder / "reports.csv"
    reports.write_bytes(_encode([header, *rows], quoting, line_end, encoding))
    out = folder / "fits.csv"
    summary = run_cohort(reports, out)
    assert {b["id"]: b["reason"] for b in summary["bad_rows"]}.keys() == bad.keys()
    for row in summary["bad_rows"]:
        assert bad[row["id"]] in row["reason"] and row["line"] >= 2
    with out.open(newline="", encoding="utf-8") as handle:
        text = handle.read()
    assert "\r" not in text, "one line ending, whatever the input's"
    written = list(csv.DictReader(io.StringIO(text, newline="")))
    assert list(csv.reader(io.StringIO(text, newline="")))[0] == output_columns(extra)
    assert {r["id"]: {c: r[c] for c in extra} for r in written} == good, "carried-through cells unchanged"
    again = run_cohort(reports, out)
    assert again["resumed"] == len(good) and again["fitted"] == len(good), "the resume reads the file back"


def _rows(text):
    return list(csv.reader(io.StringIO(text, newline="")))


def test_an_awkward_column_name_is_quoted_and_a_torn_quoted_row_is_dropped_on_resume(tmp_path, monkeypatch):
    monkeypatch.setattr(cohort, "fit_reports", _stand_in)
    reports = tmp_path / "r.csv"
    reports.write_text('id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm,"note, x"\n'
                       'A,58,290,85,124,78,64,"said ""hi"", then left"\nB,58,290,85,124,78,64,"two\nlines"\n', encoding="utf-8")
    out = tmp_path / "fits.csv"
    run_cohort(reports, out)
    text = out.read_text(encoding="utf-8")
    assert text.startswith('id,"note, x",tau2_s,') and "\r" not in text
    records = _rows(text)
    assert records[0] == output_columns(["note, x"]) and {r[0]: r[1] for r in records[1:]} == {"A": 'said "hi", then left', "B": "two\nlines"}
    cut = text.index("two\n") + 4  # killed inside B's quoted two-line cell
    out.write_text(text[:cut], encoding="utf-8")
    resumed = run_cohort(reports, out)
    assert resumed["resumed"] == 1 and _rows(out.read_text(encoding="utf-8")) == records


@pytest.mark.parametrize(
    "content, message",
    [
        ("id;EF_pct;ET_ms;IVRT_ms;SBP_mmHg;DBP_mmHg;HR_bpm\nA;58;290;85;124;78;64\n".encode(), "separates its fields by semicolons"),
        ("id\tEF_pct\tET_ms\tIVRT_ms\tSBP_mmHg\tDBP_mmHg\tHR_bpm\n".encode(), "separates its fields by tabs"),
        ("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm,site\nA,58,290,85,124,78,64,Zürich\n".encode("latin-1"),
         r"is not UTF-8 text: byte 0xfc on line 2"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "is not a text file"),
    ],
)
def test_a_file_in_another_format_is_refused_saying_why(tmp_path, content, message):
    path = tmp_path / "r.csv"
    path.write_bytes(content)
    with pytest.raises(CohortError, match=message):
        read_reports(path)


def test_a_byte_order_mark_is_read_past(tmp_path):
    path = tmp_path / "r.csv"
    path.write_bytes("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm\nA,58,290,85,124,78,64\n".encode("utf-8-sig"))
    parsed = read_reports(path)
    assert [r.id for r in parsed.rows] == ["A"] and not parsed.bad


def test_cohort_command_exits_2_without_a_traceback_for_such_files(tmp_path, capsys):
    from lvenv import cli

    path = tmp_path / "r.csv"
    path.write_bytes(b"\x00\x01\x02binary")
    assert cli.main(["cohort", str(path), "--out", str(tmp_path / "o.csv")]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "is not a text file" in err and "Traceback" not in err
    damaged = tmp_path / "o2.csv"
    damaged.write_text("id\n")
    (tmp_path / "o2.csv.json").write_bytes(b"\xff\xfe{")
    path.write_text("id,EF_pct,ET_ms,IVRT_ms,SBP_mmHg,DBP_mmHg,HR_bpm\nA,58,290,85,124,78,64\n")
    assert cli.main(["cohort", str(path), "--out", str(damaged)]) == cli.EXIT_USAGE
    assert "was written for another report file" in capsys.readouterr().err
