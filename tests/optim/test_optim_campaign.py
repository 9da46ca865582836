"""Anatomy campaigns: the Latin-hypercube design, a killed campaign resumed without recomputing,
a real Dask cluster on which one anatomy's FE solve crashes while the others finish, the
dataset's traces retraining without FE, and clear errors for folders that cannot be used."""

import json
import os
import pathlib
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from scipy.stats import qmc

from lvenv.geometry import Geometry
from lvenv.trained import builtin
from lvenv.validation import InputError
from optim import campaign, congruency
from optim.campaign import BOX, CampaignError, Settings

#: Small but real: the multielement oracle with 4 elements and a short training search.
TINY = Settings(backend="multielement", n_elements=4, budget=16, timeout_s=300.0)
CLI = [sys.executable, "-m", "lvenv.cli", "campaign", "run"]


def _tiny_args(directory, cache, n):
    return [*CLI, str(directory), "--n", str(n), "--seed", "3", "--backend", "multielement", "--n-elements", "4", "--budget", "16",
            "--timeout", "300", "--workers", "1", "--cache-dir", str(cache)]


def _log(directory):
    path = pathlib.Path(directory) / "log.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_design_is_a_latin_hypercube_inside_the_box_and_reproducible():
    rows = campaign.design(20, held_out=4, seed=1)
    assert [r["id"] for r in rows] == [f"H{i:03d}" for i in range(4)] + [f"A{i:03d}" for i in range(20)]
    names = list(BOX)
    train = np.array([[r[k] for k in names] for r in rows if r["split"] == "train"])
    lower, upper = np.array([BOX[k] for k in names]).T
    assert np.all((train >= lower) & (train <= upper))
    # one point in each of the 20 strata of every parameter: the j-th smallest lies in the j-th
    # stratum, up to the rounding of the stored values (half a unit of their last decimal)
    edges = lower + np.arange(21)[:, None] / 20 * (upper - lower)
    rounding = np.array([0.5 * 10.0 ** -campaign.DECIMALS[k] for k in names])
    ordered = np.sort(train, axis=0)
    assert np.all((ordered >= edges[:-1] - rounding) & (ordered <= edges[1:] + rounding))
    assert qmc.discrepancy((train - lower) / (upper - lower)) < 0.1
    assert rows == campaign.design(20, held_out=4, seed=1) and rows != campaign.design(20, held_out=4, seed=2)


@pytest.fixture(scope="module")
def jit_cache(tmp_path_factory):
    """A compilation cache of this module's own for the campaigns' processes (module docstring of
    `optim.campaign`): the solves compile the LO programs once, and a later test's processes read
    them, as a user's second campaign does."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("LVENV_JIT_CACHE", str(tmp_path_factory.mktemp("jax")))
        yield


def test_killed_campaign_resumes_with_identical_results_and_recomputes_nothing(tmp_path, jit_cache):
    directory, cache = tmp_path / "camp", tmp_path / "cache"
    proc = subprocess.Popen(_tiny_args(directory, cache, 2), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 240
    # kill the whole process tree once the first anatomy is written and the second has a finished FE run
    while time.monotonic() < deadline and not (_log(directory) and len(list(cache.glob("*.npz"))) > 4):
        assert proc.poll() is None, proc.stderr.read().decode()
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = campaign.read_index(directory)
    first = _log(directory)
    assert [r["status"] for r in before].count("accepted") == 1 and len(first) == 1
    entries = {p.name: p.stat().st_mtime_ns for p in cache.glob("*.npz")}
    assert len(entries) > 4

    done = subprocess.run(_tiny_args(directory, cache, 2), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    after = campaign.read_index(directory)
    assert all(r["status"] == "accepted" for r in after)
    finished_before = next(r for r in before if r["status"] == "accepted")
    assert next(r for r in after if r["id"] == finished_before["id"]) == finished_before  # untouched, timestamp included
    resumed = _log(directory)[1:]
    assert [line["id"] for line in resumed] == [r["id"] for r in before if r["status"] == "pending"]
    # the FE runs that had finished were read back, not recomputed; no finished entry was rewritten
    assert sum(resumed[0]["from_cache"].values()) >= 1
    assert {name: p.stat().st_mtime_ns for name, p in ((p.name, p) for p in cache.glob("*.npz")) if name in entries} == entries
    assert len(list(cache.glob("*.npz"))) == 8
    # identical results: the interrupted anatomy, retrained from its dataset traces (no FE run), gives its row
    for row in (r for r in after if r["id"] != finished_before["id"]):
        data = campaign.oracle_data(directory, row["id"])
        trained = congruency.train_on(data, start=builtin("normal").lo, budget=TINY.budget, progress=False)
        assert {k: getattr(trained.lo, k) for k in campaign.TRAINED} == {k: row[k] for k in campaign.TRAINED}
        assert trained.congruency["C"] == row["C"]


def test_local_cluster_runs_the_campaign_and_a_crashed_fe_solve_fails_only_its_anatomy(tmp_path, jit_cache):
    from dask.distributed import LocalCluster

    directory = tmp_path / "camp"
    victim = next(r for r in campaign.design(3, seed=4) if r["id"] == "A001")
    marker = f'"Rb": {victim["Rb"]}'
    stop, killed = threading.Event(), []

    def crash_the_victims_solve():
        while not stop.is_set() and not killed:
            for proc in pathlib.Path("/proc").glob("[0-9]*"):
                try:
                    cmdline = (proc / "cmdline").read_bytes().decode(errors="replace")
                except OSError:
                    continue
                if "fe_oracle.solve" in cmdline and marker in cmdline:
                    os.kill(int(proc.name), signal.SIGKILL)
                    killed.append(int(proc.name))
                    break
            time.sleep(0.02)

    watcher = threading.Thread(target=crash_the_victims_solve, daemon=True)
    watcher.start()
    events = []
    try:
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=":0") as cluster:
            counts = campaign.run(directory, n=3, seed=4, settings=TINY, scheduler=cluster.scheduler_address, cache_dir=tmp_path / "cache",
                                  on_event=events.append)
    finally:
        stop.set()
        watcher.join()
    assert killed
    rows = {r["id"]: r for r in campaign.read_index(directory)}
    assert rows["A001"]["status"] == "failed_fe" and "killed by signal 9" in rows["A001"]["reason"]
    assert rows["A000"]["status"] == rows["A002"]["status"] == "accepted"
    assert counts["accepted"] == 2 and counts["failed_fe"] == 1 and counts["pending"] == 0
    assert {line["workers"] for line in _log(directory)} == {2}
    assert events[-1]["pending"] == 0 and not (directory / "traces" / "A001.npz").exists()
    assert campaign.throughput(directory)[0]["anatomies"] == 3


def test_unwritable_folders_are_refused_before_any_work(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("")
    with pytest.raises(InputError, match="directory = .*afile/camp.* cannot be made: .*afile' is a file"):
        campaign.run(blocker / "camp", n=1, settings=TINY)
    with pytest.raises(InputError, match="cache_dir = .*afile' must be a folder"):
        campaign.run(tmp_path / "camp", n=1, settings=TINY, cache_dir=blocker)
    assert not (tmp_path / "camp").exists()


def test_unknown_scheduler_address_is_named(tmp_path):
    with pytest.raises(InputError, match=r"tcp://127\.0\.0\.1:9"):
        campaign.run(tmp_path / "c", n=1, settings=TINY, scheduler="tcp://127.0.0.1:9")
    with pytest.raises(InputError, match="not a Dask scheduler address"):
        campaign.run(tmp_path / "d", n=1, settings=TINY, scheduler="localhost")


def _finished_folder(tmp_path):
    """A campaign folder whose one anatomy is marked finished without running it (``limit=0``
    writes the design only)."""
    directory = tmp_path / "camp"
    campaign.run(directory, n=2, seed=0, settings=TINY, limit=0)
    return directory


def test_folders_that_cannot_be_used_are_refused_naming_the_problem(tmp_path):
    directory = _finished_folder(tmp_path)
    assert [r["status"] for r in campaign.read_index(directory)] == ["pending", "pending"]
    with pytest.raises(CampaignError, match="n = 2, not 5"):
        campaign.run(directory, n=5, settings=TINY, limit=0)
    with pytest.raises(CampaignError, match="was run with settings"):
        campaign.run(directory, settings=Settings(backend="multielement", budget=32), limit=0)
    config = json.loads((directory / "campaign.json").read_text())
    (directory / "campaign.json").write_text(json.dumps(config | {"oracle_code": ["0123456789abcdef"]}))
    with pytest.raises(CampaignError, match="written by oracle code 0123456789abcdef and this is"):
        campaign.run(directory, limit=0)
    campaign.run(directory, limit=0, allow_code_change=True)
    assert json.loads((directory / "campaign.json").read_text())["oracle_code"][0] == "0123456789abcdef"
    (directory / "campaign.json").write_text(json.dumps(config | {"format": 99}))
    with pytest.raises(CampaignError, match="format 99"):
        campaign.run(directory, limit=0)
    (directory / "campaign.json").write_text("{not json")
    with pytest.raises(CampaignError, match="not a campaign file"):
        campaign.run(directory, limit=0)
    with pytest.raises(CampaignError, match="no campaign"):
        campaign.run(tmp_path / "empty", limit=0)


def test_a_malformed_index_is_refused_naming_line_and_column(tmp_path):
    directory = _finished_folder(tmp_path)
    path = directory / "anatomies.csv"
    text = path.read_text()
    lines = text.splitlines()
    cells = lines[1].split(",")
    cells[3] = "abc"
    path.write_text("\n".join([lines[0], ",".join(cells), *lines[2:]]) + "\n")
    with pytest.raises(CampaignError, match=r"line 2: column Rb_mm = 'abc' is not a number"):
        campaign.read_index(directory)
    path.write_text(text.replace(",pending,", ",done,", 1))
    with pytest.raises(CampaignError, match="status = 'done'"):
        campaign.read_index(directory)
    path.write_text(text.replace("Rb_mm,", "", 1))
    with pytest.raises(CampaignError, match=r"missing \['Rb_mm'\]"):
        campaign.read_index(directory)
    path.write_text(text.replace(lines[1].split(",")[2], "0" * 16, 1))
    with pytest.raises(CampaignError, match="ids or keys differ"):
        campaign.run(directory, limit=0)
    with pytest.raises(InputError, match="trace"):
        campaign.oracle_data(directory, "A000")


def test_settings_are_validated_naming_the_field():
    with pytest.raises(InputError, match="settings.backend"):
        Settings(backend="fem")
    with pytest.raises(InputError, match="settings.n_elements = 8 applies to backend 'multielement' only"):
        Settings(n_elements=8)
    with pytest.raises(InputError, match="settings.timeout_s"):
        Settings(timeout_s=0.0)
    assert Geometry(**{k: v for k, v in campaign.design(1)[0].items() if k in BOX})  # the design's rows are geometries


@pytest.mark.fe
def test_a_multi_element_model_is_trained_on_the_datasets_traces_and_resumes(tmp_path):
    """The 3-cell heart on two anatomies of the package dataset (their FE traces, no FE run;
    the onsets from the wall's eikonal), one of them already in the table (the package table's
    row): only the other is trained, the row already there is kept as written, and a further
    call has nothing left to train. The new row's C is what its maps and onsets give on the
    anatomy's traces, and its onsets rise from the earliest cell with the median cell's at 0."""
    import shutil

    from lvenv.params import Arrangement, LOParams

    directory = tmp_path / "dataset"
    (directory / "traces").mkdir(parents=True)
    shutil.copy(campaign.DATASET / "campaign.json", directory)
    campaign._write_index(directory, [r for r in campaign.read_index(campaign.DATASET) if r["id"] in ("A000", "A001")])
    for name in ("A000", "A001"):
        shutil.copy(campaign.DATASET / "traces" / f"{name}.npz", directory / "traces")
    table = campaign.model_table_path(directory, "series3")
    table.parent.mkdir()
    header, *lines = campaign.model_table_path(campaign.DATASET, "series3").read_text().splitlines()
    table.write_text("\n".join([header, next(line for line in lines if line.startswith("A001,"))]) + "\n")
    written = table.read_text()
    seen = []
    rows = campaign.train_model_table(directory, "series3", budget=16, steps_per_beat=500, progress=lambda row, done, total: seen.append((row["id"], done, total)))
    assert [r["id"] for r in rows] == ["A001", "A000"] and seen == [("A000", 1, 1)] and table.read_text().startswith(written)
    assert campaign.read_model_table(directory, "series3") == rows
    new = rows[1]
    onsets = (new["onset_1"], new["onset_2"], new["onset_3"])
    assert onsets[0] < onsets[1] == 0.0 < onsets[2]
    data = campaign.oracle_data(directory, "A000")
    c = congruency.run_congruency(data, [LOParams(**{name: new[name] for name in campaign.TRAINED})], 500, Arrangement("series", 3, (1.0, 1.0), onsets=onsets))[0]
    assert congruency.overall(c) == pytest.approx(new["C"], rel=1e-9)
    assert campaign.train_model_table(directory, "series3", budget=16, steps_per_beat=500) == rows  # nothing left to train
    done = subprocess.run([sys.executable, "-m", "lvenv.cli", "campaign", "train-model", str(directory), "--model", "series3"], capture_output=True, text=True)
    assert done.returncode == 0 and "2 anatomies trained for series3" in done.stdout
    with pytest.raises(InputError, match="model = 'single' is not one of"):
        campaign.train_model_table(directory, "single")
