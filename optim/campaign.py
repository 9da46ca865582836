"""Virtual-cohort campaigns (DESIGN §5): many anatomies through the FE oracle and congruency training.

A campaign samples anatomies by Latin hypercube over :data:`BOX`, and for each one runs the
oracle's passive curve and the three Table 2 training beats (`optim.congruency.oracle_data`),
then trains the LO maps on them (`optim.congruency.train_on`, the activation delay included).
It sits in ``optim`` rather than ``fe_oracle`` because it drives both the oracle and the
training, and ``optim`` already imports ``fe_oracle``.

**Execution.** Anatomies are tasks on Dask distributed (`optim.cluster.client`: a
``LocalCluster`` sized to the machine by default, or an existing scheduler by address). A
worker runs each FE solve in a subprocess of its own (``python -m fe_oracle.solve``) with a
timeout, so a crash, a hang or a runaway mesh cannot take the worker down; the solve writes its
result into the oracle's content-hash cache (`fe_oracle.cache`) and the worker reads it back by
its key. Solves and workers use JAX's persistent compilation cache (`lvenv.jitcache`, as every
``lvenv`` command does), so the LO programs compile once per machine, not once per solve.

**Screening.** An anatomy that `lvenv.geometry` refuses (a wall too thick for the radius, an
endocardium that crosses the epicardium, no cavity) is ``rejected_geometry``; one whose FE solve
fails or times out (a mesh that fails included) is ``failed_fe``; one whose volume under ② never
falls below :data:`CONTRACTION_LIMIT` × V0 is ``no_contraction`` (the paper's rule: γ, the
compression map, needs it) and is not trained; a training that fails is ``failed_training``; a
task that dies otherwise (its worker killed, an error outside the solves) is ``failed_task``.
Only ``accepted`` anatomies enter the regression. Every reason is written down.

**The dataset** (a folder, by default :data:`DATASET`, the package's ``lvenv/data/anatomy``):

* ``campaign.json``: format version, the box, the sampling (size, held-out size, seed), the
  settings (backend, mesh size h, time step, training budget, solve timeout) and the code
  versions it was written with;
* ``anatomies.csv``: the index, one row per sampled anatomy: ``id``, ``split`` (``train`` or
  ``heldout``), ``key`` (content hash of the geometry and the settings), the six geometric
  parameters (the cohort CSV's columns ``Rb_mm`` … ``C0_deg``), V0, ``status`` and ``reason``,
  the trained parameters (μ1, μ2, γ, α, β, a, b, c, delay), C per training beat, the passive
  fit's residual, ESV② / V0, the FE and training times and the oracle code version;
* ``traces/<id>.npz`` (safe `lvenv.archive` format, no pickle): the oracle's passive curve
  (P, V) and the three beats (t, V, P_lv, P_ao, P_at, P_c at the oracle's time step), with each
  run's metadata (cache key, mesh, timings). :func:`oracle_data` rebuilds a
  :class:`~optim.congruency.OracleData` from it, so any later LO model retrains on the whole
  cohort without an FE run;
* ``log.jsonl``: one line per finished anatomy (worker count, start, end, FE seconds per case,
  whether each run came from the cache), from which :func:`throughput` computes anatomies per
  hour;
* ``models/<model>.csv``: a multi-element LO heart (`lvenv.presets.LO_MODELS`) trained on every
  accepted anatomy's traces, no FE run (:func:`train_model_table`, resumable): its maps, C per
  training beat and its cells' onsets, which `optim.regression.fit` regresses with ``model=``.

**Resuming.** Rows are written as anatomies finish (atomically), and the oracle keeps every
finished FE run by content hash, so a killed campaign resumes with the same command: finished
anatomies are skipped, finished FE runs of an unfinished one are read back, nothing is
recomputed. A folder written by another oracle code version is refused (naming both versions)
unless ``allow_code_change`` (finished anatomies keep their results and their recorded version).
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import hashlib
import io
import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from scipy.stats import qmc

import fe_oracle
from fe_oracle import cache as oracle_cache
from lvenv import archive, jitcache, presets
from lvenv.geometry import Geometry, GeometryError, cavity_volume
from lvenv.params import CellParams, LOParams
from lvenv.trained import TrainedLO, builtin
from lvenv.validation import InputError, choice, integer, real, writable
from optim import congruency
from optim.cluster import client
from optim.cohort import GEOMETRY_COLUMNS

__all__ = [
    "BOX", "DECIMALS", "DATASET", "FORMAT_VERSION", "CONTRACTION_LIMIT", "STATUSES", "COLUMNS", "Settings", "CampaignError", "Interrupted",
    "design", "run", "solve_anatomy", "trace_archive", "read_index", "oracle_data", "throughput",
    "model_columns", "model_table_path", "read_model_table", "single_record", "train_model_table",
]

#: Sampling box of the unloaded geometry (mm; e dimensionless; C0 degrees): the two Table 1
#: unloaded anatomies (N 35, 9.6, 54, 12, 0.70, −53; HF 38, 10, 49, 7.7, 0.66, −64) with a clinical
#: margin on each side (docs, "Anatomy").
BOX = {"Rb": (28.0, 46.0), "L": (6.0, 14.0), "Z": (40.0, 66.0), "H": (5.0, 14.0), "e": (0.55, 0.85), "C0": (-80.0, -45.0)}
#: Decimals each sampled parameter is rounded to (0.01 mm, 0.001, 0.01°), so the CSV is exact.
DECIMALS = {"Rb": 2, "L": 2, "Z": 2, "H": 2, "e": 3, "C0": 2}
DATASET = pathlib.Path(__file__).resolve().parent.parent / "lvenv" / "data" / "anatomy"
FORMAT_VERSION = 1
#: An anatomy must contract below this fraction of V0 under condition ② (Di Achille et al. 2020).
CONTRACTION_LIMIT = 0.85
#: Oracle cases per anatomy, in order.
CASES = ("passive", 1, 2, 3)
STATUSES = ("pending", "accepted", "rejected_geometry", "failed_fe", "no_contraction", "failed_training", "failed_task")
_FINAL = frozenset(STATUSES) - {"pending"}
TRAINED = tuple(f.name for f in dataclasses.fields(LOParams))
COLUMNS = ("id", "split", "key", *GEOMETRY_COLUMNS, "V0_ml", "status", "reason", *TRAINED, "C", "C_1", "C_2", "C_3", "C_without_delay",
           "passive_rmse_ml", "ESV2_over_V0", "fe_s", "train_s", "oracle_code", "finished")
_TRACE_NAMES = ("t", "V", "P_lv", "P_ao", "P_at", "P_c")


class CampaignError(InputError):
    """A campaign folder that cannot be used as asked: malformed, of another format or code
    version, or of other settings. Names the file and what differs."""


class Interrupted(Exception):
    """An FE solve stopped by Ctrl-C: the anatomy is not finished, and stays pending."""


@dataclasses.dataclass(frozen=True)
class Settings:
    """What every anatomy of a campaign is run with.

    ``backend``: the oracle (``"dolfinx"``; ``"multielement"`` for tests and dry runs);
    ``mesh_size``: h (mm, dolfinx only); ``dt``: the oracle's time step (s; None: its default);
    ``budget``: MADS evaluations per active fit; ``timeout_s``: wall-clock limit of one FE solve
    (s); ``n_elements``: elements of the multielement backend (None: its default).
    """

    backend: str = "dolfinx"
    mesh_size: float = fe_oracle.DEFAULT_MESH_SIZE
    dt: float | None = None
    budget: int = 960
    timeout_s: float = 3600.0
    n_elements: int | None = None

    def __post_init__(self) -> None:
        choice("settings.backend", self.backend, fe_oracle.BACKENDS)
        real("settings.mesh_size", self.mesh_size, 1.0, 50.0)
        if self.dt is not None:
            real("settings.dt", self.dt, 0.0, 0.05, lo_open=True)
        integer("settings.budget", self.budget, 16)
        real("settings.timeout_s", self.timeout_s, 1.0)
        if self.n_elements is not None:
            integer("settings.n_elements", self.n_elements, 1)
            if self.backend != "multielement":
                raise InputError(f"settings.n_elements = {self.n_elements} applies to backend 'multielement' only, not {self.backend!r}")

    def oracle_options(self) -> dict[str, Any]:
        """Keyword arguments of :func:`fe_oracle.run` (and of `congruency.oracle_data`)."""
        options: dict[str, Any] = {} if self.dt is None else {"dt": self.dt}
        if self.backend == "dolfinx":
            options["mesh_size"] = self.mesh_size
        elif self.n_elements is not None:
            options["n_elements"] = self.n_elements
        return options


# ---------------------------------------------------------------------------- design
def design(n: int, held_out: int = 0, seed: int = 0, box: Mapping[str, tuple[float, float]] = BOX) -> list[dict[str, Any]]:
    """Latin-hypercube anatomies: ``n`` for training (ids ``A000``…) and ``held_out`` more from an
    independent hypercube (``H000``…), rounded to :data:`DECIMALS`. Each row: ``id``, ``split``
    and the six parameters by their `Geometry` names."""
    n, held_out, seed = integer("n", n, 1), integer("held_out", held_out, 0), integer("seed", seed, 0)
    names = tuple(f.name for f in dataclasses.fields(Geometry))
    lower = np.array([box[k][0] for k in names])
    upper = np.array([box[k][1] for k in names])
    rng = np.random.default_rng(seed)
    rows = []
    for split, prefix, count in (("heldout", "H", held_out), ("train", "A", n)):
        if not count:
            continue
        unit = qmc.LatinHypercube(d=len(names), seed=rng).random(count)
        for i, x in enumerate(lower + unit * (upper - lower)):
            rows.append({"id": f"{prefix}{i:03d}", "split": split, **{k: round(float(v), DECIMALS[k]) for k, v in zip(names, x)}})
    return rows


def _anatomy_key(geometry: Mapping[str, float], settings: Settings) -> str:
    blob = json.dumps({"geometry": dict(geometry), "settings": dataclasses.asdict(settings), "cell": dataclasses.asdict(CellParams())}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _geometry_of(row: Mapping[str, Any]) -> dict[str, float]:
    return {name: float(row[column]) for column, name in GEOMETRY_COLUMNS.items()}


# ---------------------------------------------------------------------------- one anatomy (on a worker)
def _solve(geometry: Geometry, case, settings: Settings, cache_dir: str | None) -> tuple[str | None, str, float, bool]:
    """One oracle run in a subprocess (module docstring): (its cache key, or None and the
    reason it failed; seconds; whether it was read back from the cache rather than computed)."""
    request = {"geometry": dataclasses.asdict(geometry), "case": case, "backend": settings.backend,
               "options": settings.oracle_options(), "cache_dir": cache_dir}
    t0 = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, "-m", "fe_oracle.solve", json.dumps(request)], capture_output=True, text=True, timeout=settings.timeout_s)
    except subprocess.TimeoutExpired:
        return None, f"case {case}: the FE solve timed out after {settings.timeout_s:g} s", time.perf_counter() - t0, False
    seconds = time.perf_counter() - t0
    if done.returncode == 0:
        how, key = done.stdout.split()[-2:]
        return key, "", seconds, how == "cached"
    if done.returncode == -signal.SIGINT:
        raise Interrupted(f"case {case}: the FE solve was interrupted (Ctrl-C)")
    if done.returncode < 0:
        return None, f"case {case}: the FE solve was killed by signal {-done.returncode}", seconds, False
    last = [line for line in done.stderr.strip().splitlines() if line.strip()]
    return None, f"case {case}: {last[-1] if last else f'the FE solve exited with code {done.returncode}'}", seconds, False


def solve_anatomy(task: Mapping[str, Any]) -> dict[str, Any]:
    """Run one anatomy (FE solves, screening, training); the row's new fields, its traces and
    its log entry. ``task``: ``id``, ``geometry`` (by `Geometry` names), ``settings`` (a
    :class:`Settings` as a dict), ``cache_dir``. Runs on a Dask worker; never raises for a failed
    anatomy, which comes back with its status and reason."""
    jitcache.enable()
    settings = Settings(**task["settings"])
    geometry = Geometry(**task["geometry"])
    start = time.time()
    fe_s: dict[str, float] = {}
    cached: dict[str, bool] = {}
    keys: dict[str, str] = {}
    out: dict[str, Any] = {"id": task["id"], "fields": {}, "traces": None, "log": {}}
    for case in CASES:
        key, reason, seconds, cached[str(case)] = _solve(geometry, case, settings, task["cache_dir"])
        fe_s[str(case)] = seconds
        if key is None:
            out["fields"] = {"status": "failed_fe", "reason": reason, "fe_s": sum(fe_s.values())}
            out["log"] = {"start": start, "end": time.time(), "fe_s": fe_s, "from_cache": cached}
            return out
        keys[str(case)] = key
    # read back by the keys the solves wrote (this worker's code version may differ from theirs)
    directory = oracle_cache.default_dir() if task["cache_dir"] is None else pathlib.Path(task["cache_dir"])
    runs = {case: oracle_cache.load(directory, key) for case, key in keys.items()}
    if lost := [case for case, run in runs.items() if run is None]:
        out["fields"] = {"status": "failed_fe", "reason": f"cases {lost}: the solves finished but their cache entries are gone from {directory}"}
        out["log"] = {"start": start, "end": time.time(), "fe_s": fe_s, "from_cache": cached}
        return out
    data = congruency.OracleData(geometry, CellParams(), runs["passive"], {k: runs[str(k)] for k in congruency.CONDITIONS}, settings.backend,
                                 settings.oracle_options())
    out["traces"] = trace_archive(data)
    v0 = cavity_volume(geometry)
    ratio = float(np.min(data.beats[2].traces["V"]) / v0)
    fields: dict[str, Any] = {"ESV2_over_V0": ratio, "fe_s": sum(fe_s.values()), "oracle_code": data.passive.metadata["code_version"]}
    if not ratio < CONTRACTION_LIMIT:
        fields.update(status="no_contraction", reason=f"smallest volume under condition 2 is {ratio:.3f} of V0, not below {CONTRACTION_LIMIT}")
    else:
        t0 = time.perf_counter()
        try:
            trained = congruency.train_on(data, start=builtin("normal").lo, budget=settings.budget, progress=False)
        except (RuntimeError, ValueError, FloatingPointError) as err:
            fields.update(status="failed_training", reason=f"{type(err).__name__}: {err}")
        else:
            c = trained.congruency
            without = trained.congruency_without_delay
            fields.update(status="accepted", reason="", **{name: float(getattr(trained.lo, name)) for name in TRAINED}, C=c["C"],
                          **{f"C_{k}": c[str(k)] for k in congruency.CONDITIONS}, C_without_delay=None if without is None else without["C"],
                          passive_rmse_ml=trained.passive_rmse_ml)
        fields["train_s"] = time.perf_counter() - t0
    out["fields"] = fields
    out["log"] = {"start": start, "end": time.time(), "fe_s": fe_s, "from_cache": cached,
                  "oracle_total_s": {k: r.metadata.get("total_s") for k, r in runs.items()}}
    return out


def trace_archive(data: congruency.OracleData) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The arrays and metadata of an anatomy's ``traces/<id>.npz``."""
    arrays = {"passive_P": data.passive.traces["P_lv"], "passive_V": data.passive.traces["V"], "passive_t": data.passive.traces["t"]}
    for k, result in data.beats.items():
        arrays.update({f"beat{k}_{name}": result.traces[name] for name in _TRACE_NAMES})
    meta = {"geometry": dataclasses.asdict(data.geometry), "cell": dataclasses.asdict(data.cell), "backend": data.backend,
            "options": {k: v for k, v in data.options.items() if k != "cache_dir"},
            "metadata": {"passive": data.passive.metadata, **{str(k): r.metadata for k, r in data.beats.items()}}}
    return arrays, json.loads(json.dumps(meta, default=float))


def oracle_data(directory: str | os.PathLike[str], anatomy: str) -> congruency.OracleData:
    """The oracle runs of one anatomy of a campaign's dataset as `optim.congruency.OracleData`,
    read from ``traces/<anatomy>.npz`` (no FE run): ``congruency.train_on`` retrains on it."""
    path = pathlib.Path(directory) / "traces" / f"{anatomy}.npz"
    arrays, meta = archive.load(path, f"FE traces of anatomy {anatomy!r}")
    try:
        passive = fe_oracle.OracleResult({"t": arrays["passive_t"], "V": arrays["passive_V"], "P_lv": arrays["passive_P"],
                                          "P_ao": np.full(len(arrays["passive_P"]), np.nan)}, meta["metadata"]["passive"], [], from_cache=True)
        beats = {k: fe_oracle.OracleResult({name: arrays[f"beat{k}_{name}"] for name in _TRACE_NAMES}, meta["metadata"][str(k)], [], from_cache=True)
                 for k in congruency.CONDITIONS}
        return congruency.OracleData(Geometry(**meta["geometry"]), CellParams(**meta["cell"]), passive, beats, meta["backend"], dict(meta["options"]))
    except (KeyError, TypeError) as err:
        raise CampaignError(f"{str(path)!r} is not a campaign trace file (missing or malformed {err})") from None


# ---------------------------------------------------------------------------- the folder
def _config_path(directory: pathlib.Path) -> pathlib.Path:
    return directory / "campaign.json"


def _code() -> dict[str, str]:
    import importlib.metadata

    return {"lvenv": importlib.metadata.version("lvenv")}


def _open_config(directory: pathlib.Path, n, held_out, seed, settings: Settings | None, allow_code_change: bool) -> dict[str, Any]:
    """campaign.json of ``directory``, created from the arguments if absent, else checked against
    them (None: take the folder's)."""
    path = _config_path(directory)
    if not path.exists():
        if n is None:
            raise CampaignError(f"{str(directory)!r} holds no campaign (no campaign.json); give n to start one")
        settings = Settings() if settings is None else settings
        config = {"format": FORMAT_VERSION, "box": BOX, "n": integer("n", n, 1), "held_out": integer("held_out", 0 if held_out is None else held_out, 0),
                  "seed": integer("seed", 0 if seed is None else seed, 0), "settings": dataclasses.asdict(settings),
                  "oracle_code": [oracle_cache.code_version(settings.backend)], "code": _code(),
                  "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
        directory.mkdir(parents=True, exist_ok=True)
        archive.write_text(path, json.dumps(config, indent=2) + "\n")
        return config
    try:
        config = json.loads(path.read_text())
        stored = Settings(**config["settings"])
        if missing := [name for name in ("format", "box", "n", "held_out", "seed", "oracle_code") if name not in config]:
            raise KeyError(f"fields {missing}")
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise CampaignError(f"{str(path)!r} is not a campaign file ({type(err).__name__}: {err})") from None
    if config["format"] != FORMAT_VERSION:
        raise CampaignError(f"{str(path)!r} has format {config['format']!r}; this lvenv reads format {FORMAT_VERSION}")
    asked = {"n": n, "held_out": held_out, "seed": seed}
    for name, value in asked.items():
        if value is not None and value != config[name]:
            raise CampaignError(f"{str(path)!r} is a campaign with {name} = {config[name]}, not {value}; use another folder for another design")
    if settings is not None and settings != stored:
        raise CampaignError(f"{str(path)!r} was run with settings {dataclasses.asdict(stored)}, not {dataclasses.asdict(settings)}; use another folder")
    current = oracle_cache.code_version(stored.backend)
    if current != config["oracle_code"][-1]:
        if not allow_code_change:
            raise CampaignError(f"{str(path)!r} was written by oracle code {config['oracle_code'][-1]} and this is {current}: its finished FE runs would "
                                "not be reused. Finished anatomies keep their results either way; pass allow_code_change (CLI: --allow-code-change) to "
                                "continue with this code, or use another folder")
        config["oracle_code"].append(current)
        archive.write_text(path, json.dumps(config, indent=2) + "\n")
    return config


def _format(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _write_csv(path: pathlib.Path, columns: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> None:
    """``rows`` under the header ``columns``, written atomically."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows([_format(row.get(c)) for c in columns] for row in rows)
    archive.write_text(path, buffer.getvalue())


def _write_index(directory: pathlib.Path, rows: Sequence[Mapping[str, Any]]) -> None:
    _write_csv(directory / "anatomies.csv", COLUMNS, rows)


def _read_csv(path: pathlib.Path, columns: Sequence[str], text: frozenset[str]) -> list[dict[str, Any]]:
    """The rows of the CSV file ``path``, whose header must be ``columns``: the ``text``
    columns as strings, the others as floats (empty cells: None); a :class:`CampaignError`
    naming the file, line and column otherwise."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            header = tuple(reader.fieldnames or ())
            raw = list(reader)
    except FileNotFoundError:
        raise CampaignError(f"{str(path)!r} does not exist") from None
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise CampaignError(f"{str(path)!r} cannot be read ({type(err).__name__}: {err})") from None
    if header != tuple(columns):
        missing = [c for c in columns if c not in header]
        raise CampaignError(f"{str(path)!r} has the wrong columns (missing {missing}, extra {[c for c in header if c not in columns]})")
    rows = []
    for line, record in enumerate(raw, start=2):
        row: dict[str, Any] = {}
        for column in columns:
            cell = record[column]
            if column in text:
                row[column] = cell
            elif cell == "":
                row[column] = None
            else:
                try:
                    row[column] = float(cell)
                except ValueError:
                    raise CampaignError(f"{str(path)!r} line {line}: column {column} = {cell!r} is not a number") from None
        rows.append(row)
    return rows


def read_index(directory: str | os.PathLike[str] = DATASET) -> list[dict[str, Any]]:
    """The rows of ``anatomies.csv`` with numbers as floats (empty cells: None); a
    :class:`CampaignError` naming the file, row and column if it is malformed."""
    path = pathlib.Path(directory) / "anatomies.csv"
    rows = _read_csv(path, COLUMNS, frozenset({"id", "split", "key", "status", "reason", "oracle_code", "finished"}))
    for line, row in enumerate(rows, start=2):
        if row["status"] not in STATUSES:
            raise CampaignError(f"{str(path)!r} line {line}: status = {row['status']!r} is not one of {list(STATUSES)}")
    return rows


def _initial_rows(config: Mapping[str, Any]) -> list[dict[str, Any]]:
    settings = Settings(**config["settings"])
    rows = []
    for sample in design(config["n"], config["held_out"], config["seed"], config["box"]):
        row = {"id": sample["id"], "split": sample["split"], **{column: sample[name] for column, name in GEOMETRY_COLUMNS.items()}}
        geometry = _geometry_of(row)
        row["key"] = _anatomy_key(geometry, settings)
        try:
            row["V0_ml"] = cavity_volume(Geometry(**geometry))
            row.update(status="pending", reason="")
        except GeometryError as err:
            row.update(status="rejected_geometry", reason=str(err))
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------- the campaign
def run(directory: str | os.PathLike[str] = DATASET, *, n: int | None = None, held_out: int | None = None, seed: int | None = None,
        settings: Settings | None = None, workers: int | None = None, scheduler: str | None = None, cache_dir: str | None = None,
        allow_code_change: bool = False, limit: int | None = None, on_event: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Run (or resume) the campaign in ``directory`` (module docstring); returns the counts by
    status. ``n``, ``held_out``, ``seed``, ``settings`` start a new campaign, or must match the
    folder's. ``workers``/``scheduler``: see `optim.cluster.client`. ``cache_dir``: the oracle's
    cache (default its own). ``limit``: stop after that many anatomies finish (None: all).
    ``on_event``: called with the counts after each finished anatomy and before the first."""
    directory = writable("directory", directory, folder=True)
    cache_dir = None if cache_dir is None else str(writable("cache_dir", cache_dir, folder=True).resolve())
    config = _open_config(directory, n, held_out, seed, settings, allow_code_change)
    settings = Settings(**config["settings"])
    expected = _initial_rows(config)
    rows = read_index(directory) if (directory / "anatomies.csv").exists() else expected
    if [(r["id"], r["key"]) for r in rows] != [(r["id"], r["key"]) for r in expected]:
        raise CampaignError(f"{str(directory / 'anatomies.csv')!r} does not list the anatomies of {str(_config_path(directory))!r} (ids or keys differ)")
    _write_index(directory, rows)
    by_id = {r["id"]: r for r in rows}
    pending = [r for r in rows if r["status"] == "pending"]
    if limit is not None:
        pending = pending[: integer("limit", limit, 0)]
    counts = _counts(rows, running=0)
    if on_event is not None:
        on_event(counts)
    if not pending:
        return counts
    session = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    from dask.distributed import as_completed

    with client(workers, scheduler) as handle:
        n_workers = max(1, len(handle.scheduler_info()["workers"]))
        tasks = [{"id": r["id"], "geometry": _geometry_of(r), "settings": dataclasses.asdict(settings), "cache_dir": cache_dir} for r in pending]
        futures = {handle.submit(solve_anatomy, task, key=f"anatomy-{task['id']}-{by_id[task['id']]['key']}", pure=False): task["id"] for task in tasks}
        left = len(futures)
        for future in as_completed(futures):
            left -= 1
            try:
                result = future.result()
            except Interrupted:  # a Ctrl-C reached the solve before this process: the anatomy stays pending
                continue
            except Exception as err:  # noqa: BLE001 - a dead worker or a bug fails this anatomy, not the campaign
                now = time.time()
                result = {"id": futures[future], "fields": {"status": "failed_task", "reason": f"{type(err).__name__}: {err}"}, "traces": None,
                          "log": {"start": now, "end": now, "fe_s": {}, "from_cache": {}}}
            _record(directory, by_id[result["id"]], result, rows, session, n_workers)
            counts = _counts(rows, running=min(left, n_workers))
            if on_event is not None:
                on_event(counts | {"last": result["id"], "last_status": by_id[result["id"]]["status"], "workers": n_workers})
    return counts


def _record(directory: pathlib.Path, row: dict[str, Any], result: Mapping[str, Any], rows: Sequence[Mapping[str, Any]], session: str, workers: int) -> None:
    """Write one finished anatomy: its traces, its row (the whole index, atomically) and its log line."""
    if result["traces"] is not None:
        arrays, meta = result["traces"]
        archive.save(directory / "traces" / f"{row['id']}.npz", arrays, meta)
    row.update(result["fields"], finished=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
    _write_index(directory, rows)
    line = {"id": row["id"], "status": row["status"], "session": session, "workers": workers, **result["log"]}
    with (directory / "log.jsonl").open("a", encoding="utf-8") as handle:
        handle.write(json.dumps(line, default=float) + "\n")


def _counts(rows: Sequence[Mapping[str, Any]], running: int) -> dict[str, Any]:
    counts = {status: sum(r["status"] == status for r in rows) for status in STATUSES}
    return counts | {"total": len(rows), "running": running}


def throughput(directory: str | os.PathLike[str] = DATASET) -> list[dict[str, Any]]:
    """Anatomies per hour per session and worker count, from ``log.jsonl``: finished anatomies
    that ran their FE solves (not read back), over the span from the session's first start to
    its last end."""
    path = pathlib.Path(directory) / "log.jsonl"
    lines = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()] if path.exists() else []
    sessions: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for line in lines:
        if line.get("fe_s") and not all(line.get("from_cache", {}).values()):
            sessions.setdefault((line["session"], int(line["workers"])), []).append(line)
    out = []
    for (session, workers), group in sorted(sessions.items()):
        span = max(g["end"] for g in group) - min(g["start"] for g in group)
        out.append({"session": session, "workers": workers, "anatomies": len(group), "hours": span / 3600.0,
                    "per_hour": len(group) / (span / 3600.0) if span > 0 else math.nan,
                    "median_anatomy_min": float(np.median([(g["end"] - g["start"]) / 60.0 for g in group]))})
    return out



# ---------------------------------------------------------------------------- a multi-element model over the dataset
def model_columns(model: str) -> tuple[str, ...]:
    """The columns of the table of LO heart model ``model`` (:func:`train_model_table`): ``id``,
    ``split``, the trained LO parameters, C and C per beat, each cell's onset ``onset_<k>``
    (s, relative to the LO delay), the training time (s) and when it finished."""
    cells = presets.LO_MODELS[choice("model", model, presets.MULTI_ELEMENT_MODELS)][1]
    return ("id", "split", *TRAINED, "C", "C_1", "C_2", "C_3", *(f"onset_{k}" for k in range(1, cells + 1)), "train_s", "finished")


def model_table_path(directory: str | os.PathLike[str], model: str) -> pathlib.Path:
    """Where a dataset keeps the table of ``model``: ``models/<model>.csv``."""
    return pathlib.Path(directory) / "models" / f"{choice('model', model, presets.MULTI_ELEMENT_MODELS)}.csv"


def read_model_table(directory: str | os.PathLike[str], model: str) -> list[dict[str, Any]]:
    """The rows of ``model``'s table, numbers as floats (no table yet: none); a
    :class:`CampaignError` naming the file, line and column if it is malformed."""
    path = model_table_path(directory, model)
    return _read_csv(path, model_columns(model), frozenset({"id", "split", "finished"})) if path.exists() else []


def single_record(directory: str | os.PathLike[str], row: Mapping[str, Any], data: congruency.OracleData) -> TrainedLO:
    """The single-cell record of an accepted anatomy: its index ``row`` (trained maps, C) on its
    dataset traces ``data``."""
    c = {"C": row["C"], **{str(k): row[f"C_{k}"] for k in congruency.CONDITIONS}}
    return TrainedLO(data.geometry, LOParams(**{name: row[name] for name in TRAINED}), data.cell, c, None, row["passive_rmse_ml"],
                     {"dataset": str(directory), "id": row["id"]})


def train_model_table(directory: str | os.PathLike[str] = DATASET, model: str = "series3", *, budget: int = 480, steps_per_beat: int = 1000,
                      limit: int | None = None, progress: Callable[[dict[str, Any], int, int], None] | None = None) -> list[dict[str, Any]]:
    """Train LO heart model ``model`` (:data:`lvenv.presets.LO_MODELS`) on every accepted
    anatomy of the dataset, from its traces (no FE run): its cells' onsets from the anatomy's
    wall, {μ1, μ2, γ, delay} from its single-cell maps (`optim.congruency.train_model`, MADS
    ``budget``, the LO beats at ``steps_per_beat``). Each finished anatomy is written at once
    (the whole table, atomically), so an interrupted run resumes where it stopped, and an error
    names the anatomy it stopped at; ``limit``: at
    most this many anatomies this call. ``progress(row, done, total)`` is called with each new
    row and the counts of this call. Returns the whole table."""
    directory, columns = pathlib.Path(directory), model_columns(model)
    budget = integer("budget", budget, 16)
    path = model_table_path(directory, model)
    rows = read_model_table(directory, model)
    trained_ids = {r["id"] for r in rows}
    pending = [r for r in read_index(directory) if r["status"] == "accepted" and r["id"] not in trained_ids][:limit]
    for done, index_row in enumerate(pending, start=1):
        t0 = time.perf_counter()
        try:
            data = oracle_data(directory, index_row["id"])
            trained = congruency.train_model(data, single_record(directory, index_row, data), model, budget=budget, steps_per_beat=steps_per_beat,
                                             progress=False)
        except Exception as err:
            err.add_note(f"while training {model} on anatomy {index_row['id']} of {str(directory)!r}; the {len(rows)} rows before it are kept")
            raise
        rows.append({"id": index_row["id"], "split": index_row["split"], **dataclasses.asdict(trained.lo),
                     **{"C" if k == "C" else f"C_{k}": v for k, v in trained.congruency.items()},
                     **{f"onset_{k}": x for k, x in enumerate(trained.elements.onsets, start=1)}, "train_s": time.perf_counter() - t0,
                     "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})
        path.parent.mkdir(exist_ok=True)
        _write_csv(path, columns, rows)
        if progress is not None:
            progress(rows[-1], done, len(pending))
    return rows
