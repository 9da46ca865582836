"""Command line: ``lvenv presets | simulate | reach`` (``lvenv --help``), on Click with rich output.

Exit codes (also in ``lvenv --help``):

====  ======================================================================================
0     everything computed and usable
1     a computation failed: a member's status is not ``ok`` / ``not_converged``, or ``reach``
      missed its targets by more than 1 %
2     a usage error: an unknown option or parameter, or a value outside what is allowed
      (the message names the field, the value and what is allowed)
3     an internal error (a bug): the traceback is printed
====  ======================================================================================

Tables go to a terminal with units in every header and ``—`` for the metrics of a failed
member; ``--json`` prints machine-readable output (internal units; a failed member's metrics
are ``null``). Anything longer than a moment shows progress on stderr when it is a terminal.

The CLI is the application layer: it may import :mod:`optim` (``reach``); the rest of
:mod:`lvenv` never does.
"""

from __future__ import annotations

import json
import math
import sys
import time
import traceback
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import click
import numpy as np
from rich.console import Console
from rich.table import Table

from lvenv import presets
from lvenv.geometry import cavity_volume
from lvenv.identification import ACTION_BOUNDS
from lvenv.metrics import METRIC_NAMES, display, header
from lvenv.params import field_names
from lvenv.patients import BUILTIN, Patient, builtin
from lvenv.simulation import simulate
from lvenv.status import is_usable
from lvenv.validation import InputError

__all__ = ["main", "app", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "EXIT_INTERNAL"]

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3
_EPILOG = "Exit codes: 0 ok; 1 a computation failed; 2 usage error (bad option or value); 3 internal error."

_err = Console(stderr=True, highlight=False)


def _out() -> Console:
    """Standard output: the terminal's width, or wide enough for every column when piped."""
    return Console(highlight=False, width=None if sys.stdout.isatty() else 240)


@contextmanager
def _working(message: str) -> Iterator[None]:
    """A spinner with elapsed time on stderr while a long call runs (only on a terminal)."""
    if not _err.is_terminal:
        yield
        return
    with _err.status(f"{message} (the first call of a session also compiles the model)"):
        yield


def _jsonable(value):
    """NumPy scalars/arrays → Python; NaN and ±inf → ``None`` (JSON ``null``)."""
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in np.asarray(value).tolist()] if isinstance(value, np.ndarray) else [_jsonable(v) for v in value]
    if isinstance(value, (np.generic,)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _print_json(payload) -> None:
    click.echo(json.dumps(_jsonable(payload), indent=2, allow_nan=False))


def _metrics_table(title: str, rows: Sequence[tuple[str, dict[str, float], str]]) -> Table:
    table = Table(title=title, title_justify="left")
    table.add_column("case")
    for key in METRIC_NAMES:
        table.add_column(header(key), justify="right")
    table.add_column("status")
    for name, metrics, status in rows:
        style = None if is_usable(status) else "red"
        table.add_row(name, *(display(k, metrics[k]) for k in METRIC_NAMES), status, style=style)
    return table


def _member_rows(result, names):
    return [(name, {k: float(v[i]) for k, v in result.metrics.items()}, str(result.status[i])) for i, name in enumerate(names)]


def _parse_settings(items: Sequence[str]) -> dict[str, float]:
    """``NAME=VALUE`` pairs → {name: float}; unknown names and non-numbers are usage errors."""
    known = field_names()
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name or not text.strip():
            raise click.BadParameter(f"expected NAME=VALUE, got {item!r}", param_hint="--set")
        if name not in known:
            raise click.BadParameter(f"unknown parameter {name!r}; known: {', '.join(known)}", param_hint="--set")
        try:
            value = float(text)
        except ValueError:
            raise click.BadParameter(f"{name} = {text!r} is not a number", param_hint="--set") from None
        if not math.isfinite(value):
            raise click.BadParameter(f"{name} = {text!r} must be finite", param_hint="--set")
        out[name] = value
    return out


@click.group(context_settings={"help_option_names": ["-h", "--help"]}, epilog=_EPILOG)
def app() -> None:
    """Low-order LV heart (Di Achille et al. 2020) in JAX: simulate presets and patients."""


@app.command("presets", epilog=_EPILOG)
@click.option("--max-beats", type=click.IntRange(min=1), default=200, show_default=True, help="beats to reach steady state, at most")
@click.option("--json", "as_json", is_flag=True, help="print JSON (internal units) instead of tables")
def presets_command(max_beats: int, as_json: bool) -> int:
    """Simulate the built-in N and HF hearts: steady state and the training protocol."""
    t0 = time.perf_counter()
    names = list(BUILTIN)
    steady = [builtin(n).heart for n in names]
    train_names, train = [], []
    for name, heart in zip(names, steady):
        for k in sorted(presets.TRAINING_CONDITIONS):
            train_names.append(f"{name} ({k})")
            train.append(presets.training_condition(k, heart))
    with _working("simulating N and HF to steady state and under the training protocol"):
        res = simulate(steady, max_beats=max_beats, traces=False)
        res_train = simulate(train, beats=1, traces=False)
    v0 = {n: cavity_volume(h.geometry) for n, h in zip(names, steady)}
    failed = not all(is_usable(s) for s in [*res.status, *res_train.status])
    if as_json:
        _print_json({
            "steady_state": {n: {"metrics": r[1], "status": r[2], "beats": int(b)} for n, r, b in zip(names, _member_rows(res, names), res.beats)},
            "training_protocol": {n: {"metrics": r[1], "status": r[2]} for n, r in zip(train_names, _member_rows(res_train, train_names))},
            "V0_ml": v0,
        })
        return EXIT_FAILED if failed else EXIT_OK
    beats = ", ".join(f"{n} {b}" for n, b in zip(names, res.beats))
    _out().print(_metrics_table(f"Steady state, closed loop, 60 bpm (beats to steady state: {beats})", _member_rows(res, names)))
    _out().print(_metrics_table("Training protocol (Table 2, one beat from passive equilibrium, P_c(0) = 10 kPa)", _member_rows(res_train, train_names)))
    _out().print("Unloaded cavity volume V0: " + ", ".join(f"{n} {v:.2f} ml" for n, v in v0.items()))
    _out().print(f"wall time {time.perf_counter() - t0:.1f} s")
    return EXIT_FAILED if failed else EXIT_OK


@app.command("simulate", epilog=_EPILOG)
@click.option("--preset", type=click.Choice(BUILTIN), default=None, help="built-in heart (default: normal)")
@click.option("--patient", "patient_file", type=click.Path(exists=True, dir_okay=False), default=None, help="patient JSON record whose heart to simulate")
@click.option("--condition", type=click.IntRange(1, 3), default=None, help="apply Table 2 training condition 1, 2 or 3 (open loop)")
@click.option("--set", "settings", multiple=True, metavar="NAME=VALUE", help="change a parameter (internal units), e.g. --set tau2=0.2; repeatable")
@click.option("--beats", type=click.IntRange(min=1), default=None, help="fixed number of beats (default: to steady state)")
@click.option("--max-beats", type=click.IntRange(min=1), default=200, show_default=True, help="beats to reach steady state, at most")
@click.option("--steps-per-beat", type=click.IntRange(min=10), default=1000, show_default=True, help="ROS2 steps per cardiac cycle")
@click.option("--json", "as_json", is_flag=True, help="print JSON (internal units) instead of a table")
def simulate_command(preset, patient_file, condition, settings, beats, max_beats, steps_per_beat, as_json) -> int:
    """Simulate one heart with parameters changed by --set NAME=VALUE."""
    if preset is not None and patient_file is not None:
        raise click.UsageError("give --preset or --patient, not both")
    name = patient_file or preset or "normal"
    heart = Patient.from_json(patient_file).heart if patient_file else builtin(name).heart
    if condition:
        heart = presets.training_condition(condition, heart)
    heart = heart.replace(**_parse_settings(settings))
    with _working("simulating"):
        res = simulate(heart, beats=beats, max_beats=max_beats, steps_per_beat=steps_per_beat, traces=False)
    if as_json:
        _print_json({"metrics": res.metrics, "status": res.status, "converged": bool(res.converged), "beats": int(res.beats)})
    else:
        _out().print(_metrics_table(f"{name}: {res.beats} beats", [(name, res.metrics, res.status)]))
    return EXIT_OK if is_usable(res.status) else EXIT_FAILED


@app.command("reach", epilog=_EPILOG)
@click.option("--preset", type=click.Choice(BUILTIN), default="normal", show_default=True)
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--budget", type=click.IntRange(min=64), default=2048, show_default=True, help="steady-state simulations, at most")
@click.option("--json", "as_json", is_flag=True, help="print JSON (internal units) instead of a table")
def reach_command(preset: str, seed: int, budget: int, as_json: bool) -> int:
    """Search (tau2, Sa, R2, R3, C, Cat) for human resting values: EF 60 %, ET 300 ms, IVRT 80 ms, 120/75 mmHg."""
    from optim.reach import reach as search

    t0 = time.perf_counter()
    r = search(builtin(preset).heart, seed=seed, budget=budget, progress=_err.is_terminal)
    worst = max((abs(e) for e in r.relative_error.values()), default=math.inf)
    ok = math.isfinite(worst) and worst < 0.01
    if as_json:
        _print_json({"parameters": r.parameters, "targets": r.targets, "reached": {k: r.observation[k] for k in r.targets},
                     "relative_error": r.relative_error, "evaluations": r.evaluations, "ok": ok})
        return EXIT_OK if ok else EXIT_FAILED
    _out().print(f"Reachability search on {preset} ({r.evaluations} steady-state simulations, {time.perf_counter() - t0:.1f} s)")
    table = Table(title_justify="left")
    for col in ("parameter", "value", "units"):
        table.add_column(col)
    for pname, value in r.parameters.items():
        table.add_row(pname, f"{value:.4g}", ACTION_BOUNDS[pname].units)
    _out().print(table)
    targets = Table(title_justify="left")
    for col in ("metric", "target", "reached", "error (%)"):
        targets.add_column(col, justify="right")
    for key, target in r.targets.items():
        targets.add_row(header(key), display(key, target), display(key, r.observation[key]), f"{100 * r.relative_error[key]:+.2f}")
    _out().print(targets)
    return EXIT_OK if ok else EXIT_FAILED


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (see the module docstring)."""
    try:
        code = app.main(args=list(sys.argv[1:] if argv is None else argv), prog_name="lvenv", standalone_mode=False)
    except click.exceptions.Exit as done:
        return done.exit_code
    except click.ClickException as err:
        err.show()
        return EXIT_USAGE
    except click.exceptions.Abort:
        _err.print("lvenv: aborted")
        return EXIT_FAILED
    except InputError as err:
        _err.print(f"lvenv: error: {err}", markup=False)
        return EXIT_USAGE
    except Exception:  # noqa: BLE001 - the last line of defence: say it is our bug, show where
        _err.print("lvenv: internal error (please report it with the traceback below)", markup=False)
        traceback.print_exc()
        return EXIT_INTERNAL
    return EXIT_OK if code is None else int(code)


if __name__ == "__main__":
    sys.exit(main())
