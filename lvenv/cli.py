"""Command line: ``lvenv presets | simulate | reach | fit | cohort | train | oracle | campaign | bench | report`` (``lvenv --help``), on Click with rich output.

Exit codes (also in ``lvenv --help``):

====  ======================================================================================
0     everything computed and usable
1     a computation failed: a member's status is not ``ok`` / ``not_converged``, or ``reach``
      missed its targets by more than 1 %; or the command was interrupted (Ctrl-C ends it
      within a second or two, :mod:`lvenv.interrupt`)
2     a usage error: an unknown option or parameter, or a value outside what is allowed
      (the message names the field, the value and what is allowed), or an output path that
      cannot be written (checked before computing; a write that fails all the same is
      reported after the result is printed)
3     an internal error (a bug): the traceback is printed
====  ======================================================================================

Tables go to a terminal with units in every header and ``—`` for the metrics of a failed
member; ``--json`` prints machine-readable output (internal units; a failed member's metrics
are ``null``). Anything longer than a moment shows progress on stderr when it is a terminal.

``cohort`` exits 0 when every good row was fitted with a usable status; bad rows are reported
(line and reason, also under ``bad_rows`` in ``--json``) and skipped without changing the code.

Every command turns on JAX's persistent compilation cache (:mod:`lvenv.jitcache`, default
``~/.cache/lvenv/jax``) unless given ``lvenv --no-jit-cache``, so a second process does not
recompile the model.

The CLI is the application layer: it may import :mod:`optim` (``reach``, ``fit``, ``cohort``);
the rest of :mod:`lvenv` never does.

Why the imports of :mod:`optim` and :mod:`fe_oracle` sit inside the commands: :mod:`lvenv` is
the ground floor that :mod:`optim` and :mod:`fe_oracle` build on, so a module-level import here
would make the package import its own users (a cycle through ``lvenv.cli``), and every
``lvenv --help`` or ``lvenv simulate`` would pay for loading the optimisers, flowjax and the FE
backend it never uses. The lazy import in each command is the seam: the dependency points
upwards only where the application needs it, at call time.

Length: over 600 lines because it is one Click application whose commands share the option
checks, tables, exit codes and progress display above; each command is a thin shell over
:mod:`optim` or :mod:`fe_oracle`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
import traceback
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import click
import numpy as np
from rich.console import Console
from rich.table import Table

from fe_oracle.api import BACKENDS, DEFAULT_MESH_SIZE
from lvenv import interrupt, jitcache, plots, presets
from lvenv.presets import LO_MODELS, MULTI_ELEMENT_MODELS
from lvenv.geometry import cavity_volume
from lvenv.identification import ACTION_BOUNDS
from lvenv.metrics import METRICS, SUMMARY_NAMES, display, header
from lvenv.params import field_names
from lvenv.patients import BUILTIN, Patient, builtin
from lvenv.plausibility import report as plausibility_report
from lvenv.env.core import ENV_SCHEME
from lvenv.simulation import MAX_BEATS, MAX_STEPS_PER_BEAT, MIN_STEPS_PER_BEAT, SCHEMES, Traces, simulate
from lvenv.status import is_usable
from lvenv.validation import InputError, writable

__all__ = ["main", "app", "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "EXIT_INTERNAL"]

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3
_EPILOG = "Exit codes: 0 ok; 1 a computation failed; 2 usage error (bad option or value); 3 internal error."

_err = Console(stderr=True, highlight=False)


def _out() -> Console:
    """Standard output: the terminal's width, or wide enough for every column when piped."""
    return Console(highlight=False, width=None if sys.stdout.isatty() else 300)


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
    table.add_column("case", no_wrap=True)
    for key in SUMMARY_NAMES:
        table.add_column(header(key), justify="right")
    table.add_column("status")
    for name, metrics, status in rows:
        style = None if is_usable(status) else "red"
        table.add_row(name, *(display(k, metrics[k]) for k in SUMMARY_NAMES), status, style=style)
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


def _model_option(command):
    return click.option("--model", type=click.Choice(tuple(LO_MODELS)), default=None,
                        help="LO heart model of a built-in patient (lvenv.presets.LO_MODELS) [default: single]")(command)


def _plot_suffix(ctx, param, value):
    """A --plot path must end in .png or .pdf and be writable (checked before any long computation)."""
    if value is not None and not value.lower().endswith(plots.SUFFIXES):
        raise click.BadParameter(f"{value!r} must end in one of {plots.SUFFIXES}")
    return _writable_file(ctx, param, value)


def _writable_file(ctx, param, value):
    """An output file's path, checked writable before any long computation (a usage error, exit 2)."""
    if value is not None:
        try:
            writable(f"--{param.name.replace('_path', '').replace('_', '-')}", value)
        except InputError as err:
            raise click.BadParameter(str(err)) from None
    return value


def _writable_folder(ctx, param, value):
    """An output folder's path, checked writable before any long computation."""
    if value is not None:
        try:
            writable(f"--{param.name.replace('_dir', '')}", value, folder=True)
        except InputError as err:
            raise click.BadParameter(str(err)) from None
    return value


def _save(unsaved: list[str], option: str, path, write) -> None:
    """Run ``write()``; if it fails all the same (the disk filled up, the folder went away), keep a
    message naming the option and path for :func:`_finish`, so that the result is still printed."""
    try:
        write()
    except OSError as err:
        unsaved.append(f"lvenv: error: cannot write {option} {str(path)!r}: {err.strerror or err}")


def _finish(code: int, unsaved: Sequence[str]) -> int:
    """The exit code after the result is printed: a usage error (2) if an output was not written."""
    for message in unsaved:
        _err.print(message, markup=False, soft_wrap=True)
    return EXIT_USAGE if unsaved else code


@click.group(context_settings={"help_option_names": ["-h", "--help"]}, epilog=_EPILOG)
@click.option("--no-jit-cache", is_flag=True, help="do not use JAX's persistent compilation cache ($LVENV_JIT_CACHE, default ~/.cache/lvenv/jax)")
def app(no_jit_cache: bool) -> None:
    """Low-order LV heart (Di Achille et al. 2020) in JAX: simulate, fit patients and cohorts."""
    if not no_jit_cache:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", jitcache.JitCacheWarning)
            jitcache.enable()
        for warning in caught:
            _err.print(f"lvenv: warning: {warning.message}", markup=False, soft_wrap=True)


@app.command("presets", epilog=_EPILOG)
@click.option("--max-beats", type=click.IntRange(1, MAX_BEATS), default=200, show_default=True, help="beats to reach steady state, at most")
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
@click.option("--beats", type=click.IntRange(1, MAX_BEATS), default=None, help="fixed number of beats (default: to steady state)")
@click.option("--max-beats", type=click.IntRange(1, MAX_BEATS), default=200, show_default=True, help="beats to reach steady state, at most")
@click.option("--steps-per-beat", type=click.IntRange(MIN_STEPS_PER_BEAT, MAX_STEPS_PER_BEAT), default=1000, show_default=True, help="ROS2 steps per cardiac cycle")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None, callback=_plot_suffix, help="write the PV loop and traces of the last beat (.png or .pdf)")
@_model_option
@click.option("--json", "as_json", is_flag=True, help="print JSON (internal units) instead of a table")
def simulate_command(preset, patient_file, condition, settings, beats, max_beats, steps_per_beat, plot_path, model, as_json) -> int:
    """Simulate one heart with parameters changed by --set NAME=VALUE."""
    if preset is not None and patient_file is not None:
        raise click.UsageError("give --preset or --patient, not both")
    name = patient_file or preset or "normal"
    heart = _patient_arg(preset or "normal", model).heart if patient_file is None else _patient_arg(patient_file, model).heart
    if model not in (None, "single"):
        name = f"{name} ({model})"
    if condition:
        heart = presets.training_condition(condition, heart)
    heart = heart.replace(**_parse_settings(settings))
    with _working("simulating"):
        res = simulate(heart, beats=beats, max_beats=max_beats, steps_per_beat=steps_per_beat, traces=plot_path is not None)
    unsaved: list[str] = []
    if plot_path is not None and is_usable(res.status):
        _save(unsaved, "--plot", plot_path, lambda: plots.beat_figure(res.traces, plot_path, f"{name}: EF {100 * res.metrics['EF']:.0f} %"))
    if as_json:
        _print_json({"metrics": res.metrics, "status": res.status, "converged": bool(res.converged), "beats": int(res.beats)})
    else:
        _out().print(_metrics_table(f"{name}: {res.beats} beats", [(name, res.metrics, res.status)]))
    return _finish(EXIT_OK if is_usable(res.status) else EXIT_FAILED, unsaved)


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


def _patient_arg(text: str, model: str | None = None) -> Patient:
    """A built-in patient name (its heart of the LO heart ``model``, default the single cell) or
    the path of a patient JSON record (which carries its own model: ``model`` must be None)."""
    if text in BUILTIN:
        return builtin(text, model or "single")
    if model is not None:
        raise click.UsageError(f"--model {model}: a patient record carries its own LO heart model (its \"elements\" field); --model is for built-in patients")
    return Patient.from_json(text)


def _parameter_table(parameters: dict[str, float]) -> Table:
    table = Table(title_justify="left")
    for col in ("parameter", "value", "units", "bounds"):
        table.add_column(col)
    for pname, value in parameters.items():
        b = ACTION_BOUNDS[pname]
        table.add_row(pname, f"{value:.4g}", b.units, f"[{b.lo:g}, {b.hi:g}]")
    return table


#: --posterior importance: flow draws per patient reweighted by the exact posterior, per posterior draw.
IMPORTANCE_PER_SAMPLE = 2


def _posterior_options(command):
    """``--posterior``, ``--samples`` and ``--refine`` of ``fit`` and ``cohort``."""
    command = click.option("--refine", is_flag=True,
                           help="for patients flagged (out of distribution, unreliable importance weights, or not covered by the "
                                "estimator), run the MCMC posterior (optim.identify.posterior, minutes each) instead, started from the "
                                "amortised median (the sampler takes one start point, not the samples); needs --posterior")(command)
    command = click.option("--samples", "n_samples", type=click.IntRange(min=8), default=None,
                           help="posterior draws per patient [default: 1000]; needs --posterior")(command)
    return click.option("--posterior", type=click.Choice(("amortised", "importance")), default=None,
                        help="also the posterior of every fitted parameter: median and 90 % interval from the shipped amortised "
                             "estimator (optim.amortised), with its out-of-distribution flag; 'importance' reweights "
                             f"{IMPORTANCE_PER_SAMPLE} flow draws per posterior draw by the exact posterior (one simulation each, "
                             "about 1-2 s per patient), flagging unreliable weights")(command)


def _check_posterior_options(posterior, n_samples, refine) -> tuple[int, int]:
    """A usage error naming the option for --samples or --refine without --posterior; the draws per
    patient and the importance proposals per patient (0 unless --posterior importance)."""
    for given, option in ((n_samples is not None, "--samples"), (refine, "--refine")):
        if given and posterior is None:
            raise click.UsageError(f"{option} applies to a posterior: give --posterior amortised or importance with it")
    n_samples = 1000 if n_samples is None else n_samples
    return n_samples, IMPORTANCE_PER_SAMPLE * n_samples if posterior == "importance" else 0


def _refining(done: int, total: int, name: str) -> None:
    """Progress of --refine on stderr (on a terminal): one line per MCMC posterior."""
    if _err.is_terminal:
        _err.print(f"refining {name} by MCMC ({done + 1} of {total}; about 100 s each on 2 cores)", markup=False)


def _map_table(spread: dict, fitted: dict[str, float]) -> Table:
    """The fit's parameters beside their spread over the refits at map draws (optim.map_uncertainty)."""
    table = Table(title=f"uncertainty from the maps: {spread['usable']} of {spread['draws']} refits at draws of the anatomy regression's maps",
                  title_justify="left")
    for col in ("parameter", "fit", "sd over draws", "90 % of draws", "sd (% of fit)"):
        table.add_column(col, justify="right")
    for name, s in spread["summary"].items():
        table.add_row(name, f"{fitted[name]:.4g}", f"{s['sd']:.3g}", f"{s['q05']:.4g}–{s['q95']:.4g}", f"{100 * s['sd'] / abs(fitted[name]):.1f}")
    return table


def _posterior_payload(identified) -> dict:
    """JSON of one :class:`optim.amortised.Identified` (internal units); an importance-weighted
    posterior adds its weights' effective sample size and Pareto k."""
    post = identified.posterior
    payload = {"sampler": None if post is None else post.sampler, "refined": identified.refined, "out_of_distribution": bool(identified.flag),
               "reason": identified.flag, "median": None if post is None else post.median, "interval_90": None if post is None else post.interval_90}
    if post is not None and post.sampler == "importance":
        payload.update(ess=next(iter(post.ess.values())), pareto_k=post.pareto_k)
    return payload


def _posterior_table(identified) -> Table:
    post = identified.posterior
    what = ("no posterior" if post is None else f"MCMC ({post.sampler}), refined" if identified.refined
            else f"amortised, importance-weighted (ESS {post.weights_ess:.0f} of {post.evaluations}, Pareto k {post.pareto_k:.2f})"
            if post.sampler == "importance" else "amortised")
    flag = f"; FLAGGED: {identified.flag}" if identified.flag else ""
    table = Table(title=f"posterior of {identified.patient}: {what}{flag}", title_justify="left")
    for col in ("parameter", "median", "5 %", "95 %", "units"):
        table.add_column(col)
    if post is not None:
        for name, median in post.median.items():
            lo, hi = post.interval_90[name]
            table.add_row(name, f"{median:.4g}", f"{lo:.4g}", f"{hi:.4g}", ACTION_BOUNDS[name].units)
    return table


@app.command("fit", epilog=_EPILOG)
@click.argument("patient")
@click.option("--method", type=click.Choice(("mads", "cma", "kriging", "lm")), default="mads", show_default=True,
              help="lm: multi-start least squares with autodiff Jacobians (optim.lm)")
@click.option("--budget", type=click.IntRange(min=16), default=480, show_default=True, help="steady-state simulations, at most")
@click.option("--num-envs", type=click.IntRange(min=1), default=16, show_default=True, help="members of the vector env (points per round)")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--steps-per-beat", type=click.IntRange(MIN_STEPS_PER_BEAT, MAX_STEPS_PER_BEAT), default=500, show_default=True,
              help="ROS2 steps per cardiac cycle of the fixed-step simulations (lm, the fitted beat, --scheme fixed)")
@click.option("--scheme", type=click.Choice(SCHEMES), default=None,
              help=f"integration scheme of the optimisers' env: step-size control, or --steps-per-beat equal steps "
                   f"[default: {ENV_SCHEME}; fixed for a multi-element heart]")
@_model_option
@click.option("--plausibility/--no-plausibility", default=True, show_default=True,
              help="keep mean atrial pressure and EDP within 4–25 mmHg in the objective (lvenv.plausibility)")
@click.option("--identifiability", is_flag=True, help="also report the sensitivity at the fit (autodiff): singular values and null directions")
@click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None, callback=_writable_folder,
              help="write the identifiability report at the fit to this folder: profiles, posterior, markdown and PNG (minutes)")
@click.option("--map-draws", type=click.IntRange(min=0, max=1000), default=0, show_default=True,
              help="refit at this many draws of the LO maps from the anatomy regression (a record with \"lo\": \"regression\") "
                   "and report the spread they give each parameter (optim.map_uncertainty)")
@click.option("--fidelity", is_flag=True, help="also run the 3-D FE oracle at the fit (needs the `fe` extra; minutes)")
@click.option("--fidelity-mesh", type=click.FloatRange(min=1.0), default=DEFAULT_MESH_SIZE, show_default=True, help="FE mesh size h (mm) of the dolfinx oracle of --fidelity and --correct-maps")
@click.option("--fidelity-backend", type=click.Choice(BACKENDS), default="dolfinx", show_default=True,
              help="the oracle of --fidelity and --correct-maps (multielement: the multi-element LO heart of DESIGN §1.4, seconds instead of minutes)")
@click.option("--retune-maps", is_flag=True,
              help="with --fidelity: also refit {mu1, mu2, gamma, delay} on the oracle's beat and compare again (the model's own floor there)")
@click.option("--correct-maps", type=click.IntRange(min=0, max=10), default=0, show_default=True, metavar="K",
              help="K rounds of: the maps refitted on the oracle's beat at the fit, the patient fitted again with them (optim.fit.corrected_fit); "
                   "then the oracle at the last fit. Implies --fidelity; each round costs an oracle run, a refit and a fit (minutes)")
@click.option("--refit-passive", is_flag=True,
              help="with --retune-maps or --correct-maps: refit the passive maps {alpha, beta, a, b, c} too, each within the heart's own value "
                   "÷ and × optim.congruency.PASSIVE_FREEDOM")
@click.option("--aortic-weight", type=click.FloatRange(min=0.0), default=0.0, show_default=True, metavar="W",
              help="with --retune-maps or --correct-maps: the refits minimise C^2 + W A^2, A the aortic pressure's misfit on the oracle's beat")
@click.option("--retune-budget", type=click.IntRange(min=16), default=480, show_default=True,
              help="MADS evaluations of each refit of the maps (--retune-maps, --correct-maps), before least squares")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None, callback=_plot_suffix, help="write the fitted beat against the targets (.png or .pdf)")
@click.option("--convergence", "convergence_path", type=click.Path(dir_okay=False), default=None, callback=_plot_suffix,
              help="write the best mismatch against evaluations (.png or .pdf)")
@_posterior_options
@click.option("--json", "as_json", is_flag=True, help="print JSON (internal units) instead of tables")
def fit_command(patient, method, budget, num_envs, seed, steps_per_beat, scheme, model, plausibility, identifiability, report_dir, map_draws,
                fidelity, fidelity_mesh, fidelity_backend, retune_maps, correct_maps, refit_passive, aortic_weight, retune_budget, plot_path,
                convergence_path, posterior, n_samples, refine, as_json) -> int:
    """Fit (tau2, Sa, R2, R3, C, Cat) of PATIENT (a built-in name or a patient JSON file) to its targets.
    A record may give an imaged geometry to unload and take its maps from the anatomy regression
    (lvenv.patients); --map-draws then carries the maps' uncertainty into the fit."""
    from optim.fit import DEFAULT_OPTIONS, make_env, warm_up
    from optim.minimize import minimize

    n_samples, importance = _check_posterior_options(posterior, n_samples, refine)
    record = _patient_arg(patient, model)
    if map_draws == 1:
        raise click.UsageError("--map-draws needs at least 2 draws (0: no refits)")
    if retune_maps and (correct_maps or not fidelity):
        raise click.UsageError("--retune-maps refits the maps on the beat of --fidelity; --correct-maps refits them at every round but the last"
                               if correct_maps else "--retune-maps refits the maps on the oracle's beat: it needs --fidelity")
    if refit_passive and not (retune_maps or correct_maps):
        raise click.UsageError("--refit-passive refits the passive maps with the others: it needs --retune-maps or --correct-maps")
    if aortic_weight and not (retune_maps or correct_maps):
        raise click.UsageError("--aortic-weight weighs the aortic pressure into the refits of the maps: it needs --retune-maps or --correct-maps")
    if map_draws:
        from optim.map_uncertainty import require_regression_maps

        try:
            require_regression_maps(record)
        except InputError as err:
            raise click.UsageError(f"--map-draws: {err}") from None
    if method == "lm":
        from optim.lm import fit_lm

        compile_time = 0.0  # compiled during the first evaluation, inside wall_time
        with _working("fitting by least squares"):
            res = fit_lm(record, budget=budget, seed=seed, steps_per_beat=steps_per_beat, plausibility=plausibility)
    else:
        venv = make_env(record, num_envs, steps_per_beat, scheme=scheme, plausibility=plausibility)
        with _working("compiling the model"):
            compile_time = warm_up(venv)
        res = minimize(venv, method, budget=budget, seed=seed, progress=_err.is_terminal, **DEFAULT_OPTIONS.get(method, {}))
        venv.close()
    ok = is_usable(res.status) and math.isfinite(res.mismatch)
    payload = {"patient": record.name, "method": method, "parameters": res.parameters, "targets": res.targets,
               "observation": res.observation, "mismatch": res.mismatch, "mismatch_per_target": res.mismatch_per_target,
               "status": res.status, "evaluations": res.evaluations, "wall_time_s": res.wall_time, "compile_time_s": compile_time,
               "plausibility": plausibility_report(res.observation, plausibility)}
    heart = record.heart.replace(**res.parameters) if ok else None
    unsaved: list[str] = []
    if convergence_path is not None:
        _save(unsaved, "--convergence", convergence_path,
              lambda: plots.convergence_figure({method: res.history.best_mismatch_so_far()}, convergence_path, f"{record.name}: {method}, {num_envs} envs"))
    if plot_path is not None and ok:
        beat = simulate(heart, steps_per_beat=steps_per_beat)
        _save(unsaved, "--plot", plot_path,
              lambda: plots.fit_figure(beat.traces, beat.metrics, res.targets, plot_path, f"{record.name}: {method} fit, mismatch {100 * res.mismatch:.2f} %"))
    if identifiability and ok:
        from optim.identify import sensitivity

        sens = sensitivity(record, res.parameters, steps_per_beat=steps_per_beat)
        payload["identifiability"] = {"singular_values": sens.singular_values, "null_directions": sens.null_directions}
    if report_dir is not None and not ok:
        _err.print(f"no identifiability report: the fit has no usable steady state (status {res.status})", markup=False)
    if report_dir is not None and ok:
        from optim.cohort import CohortOptions
        from optim.identify import write_report

        options = CohortOptions(budget=480, stop_mismatch=0.0, plausibility=plausibility, seed=seed)
        with _working("profiles and posterior for the identifiability report"):
            _save(unsaved, "--report", report_dir, lambda: payload.update(report=str(write_report(
                record, res.parameters, res.observation, report_dir, options=options, posterior_options={"plausibility": plausibility, "seed": seed}))))
    if map_draws and ok:
        from optim.map_uncertainty import refit

        with _working(f"refitting at {map_draws} draws of the maps"):
            spread = refit(record, res.parameters, map_draws, seed=seed, steps_per_beat=max(steps_per_beat, 1000), plausibility=plausibility)
        payload["map_uncertainty"] = spread.to_dict()
    if posterior is not None:
        from optim.identify import identify_patients

        with _working("amortised posterior" + (", importance-weighted" if importance else "")):
            identified = identify_patients([record], n_samples, seed=seed, refine=refine, mcmc_options={"plausibility": plausibility}, progress=_refining,
                                           importance=importance)[0]
        payload["posterior"] = _posterior_payload(identified)
    oracle_failed = False
    if (fidelity or correct_maps) and not ok:
        _err.print(f"no check against the oracle: the fit has no usable steady state (status {res.status})", markup=False)
    if (fidelity or correct_maps) and ok:
        oracle_failed = _check_against_oracle(payload, record, res, heart, method, compile_time, correct_maps, retune_maps, refit_passive,
                                              aortic_weight, retune_budget, fidelity_backend, fidelity_mesh, num_envs, budget, seed, steps_per_beat, scheme, plausibility)
    code = EXIT_OK if ok and not oracle_failed else EXIT_FAILED
    if as_json:
        _print_json(payload)
        return _finish(code, unsaved)
    out = _out()
    out.print(f"{record.name}: {method}, {res.evaluations} evaluations in {res.wall_time:.1f} s "
              f"(+ {compile_time:.1f} s compiling); mismatch {100 * res.mismatch:.2f} %, status {res.status}")
    out.print(_parameter_table(res.parameters))
    targets = Table(title_justify="left")
    for col in ("target", "value", "fit", "error (%)"):
        targets.add_column(col, justify="right")
    for key, target in res.targets.items():
        targets.add_row(header(key), display(key, target), display(key, res.observation[key]), f"{100 * res.relative_error[key]:+.2f}")
    out.print(targets)
    bands = Table(title="plausibility (unmeasured)", title_justify="left")
    for col in ("quantity", "fit", "band", ""):
        bands.add_column(col, justify="right")
    for key, check in payload["plausibility"].items():
        bands.add_row(header(key), display(key, res.observation[key]), f"{check['low']:g}–{check['high']:g}",
                      "inside" if check["inside"] else "OUTSIDE", style=None if check["inside"] else "red")
    out.print(bands)
    if "identifiability" in payload:
        ident = payload["identifiability"]
        out.print("singular values of the noise-scaled sensitivity (optim.identify; χ per unit-cube step): " + ", ".join(f"{v:.3g}" for v in ident["singular_values"]))
        for j, direction in enumerate(ident["null_directions"]):
            out.print(f"null direction {j + 1} (targets unchanged to first order): " + ", ".join(f"{n} {v:+.2f}" for n, v in direction.items()))
    if "map_uncertainty" in payload:
        out.print(_map_table(payload["map_uncertainty"], res.parameters))
    if posterior is not None:
        out.print(_posterior_table(identified))
    if "report" in payload:
        out.print(f"identifiability report: {payload['report']}")
    if "correction" in payload:
        last = payload["correction"][-1]
        out.print(_correction_table(payload["correction"], fidelity_backend, fidelity_mesh))
        out.print(f"the fit of round {last['round']}, with the corrected maps: mismatch {100 * last['mismatch']:.2f} %, status {last['status']}")
        out.print(_parameter_table(last["parameters"]))
    elif "fidelity" in payload:
        out.print(_fidelity_table(payload["fidelity"], fidelity_backend, fidelity_mesh))
    if "fidelity_error" in payload:
        _err.print(f"lvenv: the oracle failed: {payload['fidelity_error']}", markup=False, soft_wrap=True)
    return _finish(code, unsaved)


def _check_against_oracle(payload: dict, record: Patient, res, heart, method: str, compile_time: float, correct_maps: int, retune_maps: bool,
                          refit_passive: bool, aortic_weight: float, retune_budget: int, backend: str, mesh_size: float, num_envs: int,
                          budget: int, seed: int, steps_per_beat: int, scheme: str | None, plausibility: bool) -> bool:
    """``fit --fidelity`` / ``--correct-maps``: the oracle at the fit ``res`` into ``payload``
    (``fidelity``; with ``correct_maps`` also ``correction``, a record per round; ``refit_passive``:
    the refits move the passive maps too; ``aortic_weight``: they weigh the aortic pressure in).
    Returns True if the oracle failed (``payload["fidelity_error"]`` says how); the fit is kept
    either way."""
    from fe_oracle import OracleDidNotConverge
    from optim.congruency import check_fidelity, map_refit
    from optim.fit import FitRow, corrected_fit

    oracle = {"mesh_size": mesh_size} if backend == "dolfinx" else {}
    try:
        if not correct_maps:
            names, bounds = map_refit(heart.lo, refit_passive)
            payload["fidelity"] = check_fidelity(heart, backend, progress=_err.is_terminal, retune=names if retune_maps else (),
                                                 retune_budget=retune_budget, bounds=bounds, aortic_weight=aortic_weight, **oracle).to_dict()
            return False
        _err.print(f"correcting the maps: {correct_maps} round(s) of an oracle run, a refit of the maps and a fit, then the oracle "
                   "at the last fit (minutes)", markup=False)
        rounds = corrected_fit(record, (method,), correct_maps, first=FitRow.of(res, compile_time), backend=backend, retune_budget=retune_budget,
                               num_envs=num_envs, budget=budget, seed=seed, steps_per_beat=steps_per_beat, plausibility=plausibility,
                               scheme=scheme, options={"lm": {"budget": budget}}, progress=_err.is_terminal, passive=refit_passive,
                               aortic_weight=aortic_weight, **oracle)
    except ImportError as err:
        raise click.UsageError(f"--fidelity needs the FE oracle (pip install 'lvenv[fe]'): {err}") from None
    except OracleDidNotConverge as err:
        payload["fidelity_error"] = str(err)
        return True
    payload["fidelity"] = rounds[0].fidelity.to_dict()
    payload["correction"] = [{"round": r, "maps": step.maps, "parameters": step.fit.parameters, "mismatch": step.fit.mismatch,
                              "status": step.fit.status, "evaluations": step.fit.evaluations, "fidelity": step.fidelity.to_dict()}
                             for r, step in enumerate(rounds)]
    return False


def _oracle_title(fid: dict, backend: str, mesh_size: float) -> str:
    return f"{backend} oracle" + (f", h = {mesh_size:g} mm" if backend == "dolfinx" else "") + f", {fid['provenance']['beats']} beats"


def _fidelity_table(fid: dict, backend: str, mesh_size: float) -> Table:
    """``fit --fidelity``: LO, oracle and oracle − LO per target, also with the maps refitted on
    the oracle's beat if ``fid`` (:meth:`Fidelity.to_dict`) has them."""
    from optim.congruency import format_difference

    again = fid["retuned"]
    title = f"fidelity against the {_oracle_title(fid, backend, mesh_size)}: C {100 * fid['C']:.2f} %, {'within' if fid['ok'] else 'OUTSIDE'} tolerance"
    if again is not None:
        title += f"; maps refitted on its beat ({', '.join(f'{n} {v:.4g}' for n, v in again['lo'].items())}): C {100 * again['C']:.2f} %"
    table = Table(title=title, title_justify="left")
    for col in ("target", "LO", "oracle", "oracle − LO", "", *(("refitted maps: oracle − LO", "") if again is not None else ())):
        table.add_column(col, justify="right")
    for name, (lo, fe, diff) in fid["rows"].items():
        cells = [header(name), display(name, lo), display(name, fe), format_difference(name, diff, unit=True),
                 "ok" if fid["within"][name] else "OUT"]
        if again is not None:
            cells += [format_difference(name, again["rows"][name][2], unit=True), "ok" if again["within"][name] else "OUT"]
        table.add_row(*cells)
    return table


def _correction_table(rounds: list[dict], backend: str, mesh_size: float) -> Table:
    """``fit --correct-maps``: per round, the maps, the fit's mismatch, C and oracle − LO per
    target (OUT: outside the tolerance); the parameters of the last round's fit follow it. The
    passive maps have columns too where the rounds refitted them (``--refit-passive``)."""
    from optim.congruency import ACTIVE_NAMES, FIDELITY_TOLERANCE, PASSIVE_NAMES, difference_unit, format_difference

    passive = tuple(n for n in PASSIVE_NAMES if n in rounds[0]["maps"])
    last = rounds[-1]["fidelity"]
    table = Table(title=f"maps corrected against the {_oracle_title(last, backend, mesh_size)}: round 0 has the heart's own maps, each next "
                        f"round the maps refitted on the last round's beat; last round C {100 * last['C']:.2f} %, "
                        f"{'within' if last['ok'] else 'OUTSIDE'} tolerance", title_justify="left")
    for col in ("round", *ACTIVE_NAMES, "delay (ms)", *passive, "mismatch (%)", "C (%)", *(f"{METRICS[t].label} ({difference_unit(t)})" for t in FIDELITY_TOLERANCE)):
        table.add_column(col, justify="right")
    for step in rounds:
        fid, maps = step["fidelity"], step["maps"]
        table.add_row(str(step["round"]), *(f"{maps[n]:.4g}" for n in ACTIVE_NAMES), f"{1000 * maps['delay']:.1f}",
                      *(f"{maps[n]:.4g}" for n in passive), f"{100 * step['mismatch']:.2f}", f"{100 * fid['C']:.2f}",
                      *(format_difference(t, fid["rows"][t][2]) + ("" if fid["within"][t] else " OUT") for t in FIDELITY_TOLERANCE))
    return table


@app.command("cohort", epilog=_EPILOG)
@click.argument("reports", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out_path", type=click.Path(dir_okay=False), required=True, callback=_writable_file, help="output CSV (resumed if it exists)")
@click.option("--budget", type=click.IntRange(min=8), default=None, help="evaluations per patient, at most [default: optim.cohort.CohortOptions]")
@click.option("--candidates", type=click.IntRange(min=2), default=None, help="env members per patient (CMA-ES population)")
@click.option("--slots", type=click.IntRange(min=1), default=None, help="patients fitted at once per process")
@click.option("--stop-mismatch", type=click.FloatRange(0.0, 1.0), default=None, help="a patient's search stops below this mismatch (fraction)")
@click.option("--seed", type=click.IntRange(min=0), default=None)
@click.option("--workers", type=click.IntRange(min=1), default=1, show_default=True, help="Dask LocalCluster processes (1: this process only)")
@click.option("--scheduler", default=None, metavar="ADDRESS", help="Dask scheduler address (e.g. tcp://host:8786) to split the cohort over")
@click.option("--maps", type=click.Choice(("regression", "base")), default="regression", show_default=True,
              help="LO maps of a row with geometry columns: its anatomy's, from the anatomy regression, or the base heart's")
@click.option("--model", type=click.Choice(tuple(LO_MODELS)), default="single", show_default=True,
              help="the base heart's LO heart model (lvenv.presets.LO_MODELS; rows with geometry columns take its anatomy regression); "
                   "a multi-element one's rows' posteriors need --refine (MCMC)")
@_posterior_options
@click.option("--json", "as_json", is_flag=True, help="print the summary as JSON")
def cohort_command(reports, out_path, budget, candidates, slots, stop_mismatch, seed, workers, scheduler, maps, model, posterior, n_samples, refine,
                   as_json) -> int:
    """Fit every echo report of the CSV REPORTS (columns: id, EF_pct, ET_ms, IVRT_ms, SBP_mmHg,
    DBP_mmHg, HR_bpm; see optim.cohort) together, writing one row per patient to --out. A row
    with geometry columns (Rb_mm ... C0_deg, unloaded) is fitted with its anatomy's LO maps
    (--maps; the output's maps column says which). With
    --posterior amortised (or importance) each row also gets every parameter's posterior median and 90 % interval
    (<column>_post_median, _post_q05, _post_q95) and its flag (post_ood, post_ood_reason)."""
    from optim.cohort import CohortOptions, PosteriorOptions, run_cohort

    n_samples, importance = _check_posterior_options(posterior, n_samples, refine)
    given = {"budget": budget, "candidates": candidates, "slots": slots, "stop_mismatch": stop_mismatch, "seed": seed, "maps": maps, "model": model}
    options = CohortOptions(**{k: v for k, v in given.items() if v is not None})
    posterior_options = None if posterior is None else PosteriorOptions(n_samples, refine, options.seed, {"plausibility": options.plausibility}, importance)

    def report_bad(bad) -> None:
        _err.print(f"{reports}: line {bad.line}{f' (id {bad.id})' if bad.id else ''}: {bad.reason}; skipped", markup=False, soft_wrap=True)
    bar = None
    if _err.is_terminal:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        bar = Progress(TextColumn("fitting"), BarColumn(), MofNCompleteColumn(), TextColumn("patients"), TimeElapsedColumn(),
                       TimeRemainingColumn(), TextColumn("{task.fields[last]}"), console=_err)
        task = bar.add_task("cohort", total=None, last="")

    def progress(done: int, total: int, result) -> None:
        if bar is not None:
            last = "" if result is None else f"last {result['id']}: {100 * result['mismatch']:.2f} % ({result['status']})"
            bar.update(task, completed=done, total=total, last=last)

    if bar is not None:
        bar.start()
    try:
        if posterior_options is not None and _err.is_terminal:
            _err.print("drawing the amortised posteriors of every row before the fits", markup=False)
        summary = run_cohort(reports, out_path, options, workers=workers, scheduler=scheduler, progress=progress, on_bad=report_bad,
                             posterior=posterior_options, posterior_progress=_refining)
    finally:
        if bar is not None:
            bar.stop()
    failed = sum(n for status, n in summary["status"].items() if not is_usable(status))
    if as_json:
        _print_json(summary)
        return EXIT_FAILED if failed else EXIT_OK
    m = summary["mismatch"]
    table = Table(title=f"Cohort {reports} → {out_path}", title_justify="left")
    for col in ("patients fitted", "resumed", "bad rows", "status", "median mismatch (%)", "95th pct (%)", "max (%)", "wall time (s)"):
        table.add_column(col, justify="right")
    pct = lambda key: f"{100 * m[key]:.2f}" if key in m and math.isfinite(m[key]) else "—"
    table.add_row(str(summary["fitted"]), str(summary["resumed"]), str(len(summary["bad_rows"])),
                  ", ".join(f"{k} {v}" for k, v in summary["status"].items()), pct("median"), pct("p95"), pct("max"), f"{summary['wall_time_s']:.1f}")
    _out().print(table)
    if "posterior" in summary:
        _out().print(f"posteriors: {summary['posterior']['flagged']} row(s) flagged (post_ood), {summary['posterior']['refined']} refined by MCMC")
    return EXIT_FAILED if failed else EXIT_OK


@app.command("train", epilog=_EPILOG)
@click.argument("heart", type=click.Choice(BUILTIN))
@click.option("--out", "out_path", type=click.Path(dir_okay=False), required=True, callback=_writable_file, help="the trained record (JSON; lvenv.trained.TrainedLO)")
@click.option("--backend", type=click.Choice(BACKENDS), default="dolfinx", show_default=True, help="the oracle to train against")
@click.option("--arrangement", type=click.Choice(("parallel", "series")), default=None, help="multi-element arrangement (backend multielement)")
@click.option("--mesh-size", type=click.FloatRange(min=1.0), default=None, help="FE mesh size h (mm; backend dolfinx) [default: the oracle's, 6]")
@click.option("--budget", type=click.IntRange(min=16), default=960, show_default=True, help="MADS evaluations per active fit")
@click.option("--delay", type=click.Choice(("auto", "never", "always")), default="auto", show_default=True, help="train the activation delay")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the trained record as JSON")
def train_command(heart, out_path, backend, arrangement, mesh_size, budget, delay, seed, as_json) -> int:
    """Congruency-train the LO maps of the built-in HEART's geometry against an oracle (optim.congruency.train)."""
    from optim.congruency import train

    oracle = {k: v for k, v in {"arrangement": arrangement, "mesh_size": mesh_size}.items() if v is not None}
    t0 = time.perf_counter()
    trained = train(builtin(heart).heart.geometry, backend, budget=budget, delay=delay, seed=seed, progress=_err.is_terminal, **oracle)
    unsaved: list[str] = []
    _save(unsaved, "--out", out_path, lambda: trained.to_json(out_path))
    c = trained.congruency.get("C", math.nan)
    if as_json or unsaved:  # the record itself, so that a failed write loses nothing
        click.echo(trained.to_json())
    else:
        table = Table(title=f"{heart} trained against {backend}: C = {100 * c:.2f} % ({time.perf_counter() - t0:.0f} s) → {out_path}", title_justify="left")
        for col in ("run", "C (%)", "C without delay (%)"):
            table.add_column(col, justify="right")
        without = trained.congruency_without_delay or {}
        for run, value in trained.congruency.items():
            table.add_row(str(run), f"{100 * value:.2f}", f"{100 * without[run]:.2f}" if run in without else "—")
        _out().print(table)
        _out().print(", ".join(f"{k} {v:.4g}" for k, v in dataclasses.asdict(trained.lo).items()))
    return _finish(EXIT_OK if math.isfinite(c) else EXIT_FAILED, unsaved)


@app.command("oracle", epilog=_EPILOG)
@click.argument("heart", type=click.Choice(BUILTIN))
@click.option("--case", type=click.Choice(("passive", "1", "2", "3", "closed")), default="2", show_default=True,
              help="passive inflation, Table 2 condition 1–3 (one beat), or the preset's closed loop")
@click.option("--backend", type=click.Choice(BACKENDS), default="dolfinx", show_default=True)
@click.option("--mesh-size", type=click.FloatRange(min=1.0), default=DEFAULT_MESH_SIZE, show_default=True, help="FE mesh size h (mm; dolfinx)")
@click.option("--beats", type=click.IntRange(min=1), default=1, show_default=True, help="beats of the closed loop")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None, callback=_plot_suffix,
              help="write FE (solid) against LO (dashed) traces (.png or .pdf; beat cases)")
@click.option("--json", "as_json", is_flag=True, help="print JSON (internal units) instead of a table")
def oracle_command(heart, case, backend, mesh_size, beats, plot_path, as_json) -> int:
    """Run one FE oracle case on a built-in HEART (cached) and compare its beat with the LO heart's."""
    import fe_oracle

    lo_heart = builtin(heart).heart
    options = {"mesh_size": mesh_size} if backend == "dolfinx" else {}
    t0 = time.perf_counter()
    if case == "passive":
        result = fe_oracle.run(lo_heart.geometry, "passive", backend, progress=_err.is_terminal, **options)
        tr = result.traces
        payload = {"case": case, "backend": backend, "P_lv": tr["P_lv"], "V": tr["V"], "from_cache": result.from_cache, "key": result.metadata.get("key")}
        if as_json:
            _print_json(payload)
            return EXIT_OK
        table = Table(title=f"{heart}: passive inflation ({backend}{', cached' if result.from_cache else ''}, {time.perf_counter() - t0:.1f} s)", title_justify="left")
        table.add_column("P_lv (mmHg)", justify="right")
        table.add_column("V (ml)", justify="right")
        for p, v in zip(tr["P_lv"], tr["V"]):
            table.add_row(display("P_lv_peak", p), f"{v:.2f}")
        _out().print(table)
        return EXIT_OK
    if case == "closed":
        circ, lo_case = lo_heart.circulation, lo_heart
        result = fe_oracle.run(lo_heart.geometry, circ, backend, cell=lo_heart.cell, beats=beats, progress=_err.is_terminal, **options)
    else:
        lo_case = presets.training_condition(int(case), lo_heart)
        result = fe_oracle.run(lo_heart.geometry, int(case), backend, cell=lo_heart.cell, progress=_err.is_terminal, **options)
        beats = 1
    fe_metrics = fe_oracle.beat_metrics(result)
    lo_run = simulate(lo_case, beats=beats)
    valid, fe_status = bool(fe_metrics.pop("valid")), fe_metrics.pop("status")
    unsaved: list[str] = []
    if plot_path is not None:
        period = float(result.metadata["period_s"])
        tr = result.traces
        last = tr["t"] >= tr["t"][-1] - period - 1e-9
        fe_traces = Traces(tr["t"][last] - tr["t"][last][0], tr["V"][last], tr["P_lv"][last], tr["P_ao"][last])
        _save(unsaved, "--plot", plot_path, lambda: plots.lo_fe_figure(lo_run.traces, fe_traces, plot_path, f"{heart}, case {case}: FE (solid) and LO (dashed)"))
    if as_json:
        _print_json({"case": case, "backend": backend, "fe": fe_metrics, "fe_valid": valid, "fe_status": fe_status, "lo": lo_run.metrics, "lo_status": lo_run.status,
                     "from_cache": result.from_cache, "key": result.metadata.get("key"), "wall_time_s": time.perf_counter() - t0})
        return _finish(EXIT_OK if valid else EXIT_FAILED, unsaved)
    rows = [(f"FE ({backend})", {k: float(fe_metrics.get(k, math.nan)) for k in SUMMARY_NAMES}, fe_status),
            ("LO", lo_run.metrics, lo_run.status)]
    cached = ", cached" if result.from_cache else ""
    _out().print(_metrics_table(f"{heart}, case {case}: last beat ({time.perf_counter() - t0:.1f} s{cached})", rows))
    return _finish(EXIT_OK if valid else EXIT_FAILED, unsaved)


#: Benchmarks of ``lvenv bench NAME``: scripts/bench_NAME.py of the source tree.
BENCHES = ("lo", "env", "optim", "kriging", "fe", "cohort", "cold_start", "amortised", "candidates")


@app.command("bench", epilog=_EPILOG, context_settings={"ignore_unknown_options": True})
@click.argument("name", type=click.Choice(BENCHES))
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def bench_command(name, args) -> int:
    """Run scripts/bench_NAME.py of the source checkout with ARGS (each prints JSON, kept in
    out/bench/NAME.json for `lvenv report`; see `lvenv bench NAME -- --help`)."""
    import subprocess
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / f"bench_{name}.py"
    if not script.is_file():
        raise click.UsageError(f"lvenv bench runs the benchmark scripts of a source checkout; {script} does not exist")
    done = subprocess.run([sys.executable, str(script), *args], cwd=script.parents[1], stdout=subprocess.PIPE, text=True)
    click.echo(done.stdout, nl=False)
    try:
        json.loads(done.stdout)
    except json.JSONDecodeError:
        pass  # --help or an error: nothing to keep for the report
    else:
        saved = script.parents[1] / "out" / "bench" / f"{name}.json"
        saved.parent.mkdir(parents=True, exist_ok=True)
        saved.write_text(done.stdout)
    return EXIT_OK if done.returncode == 0 else EXIT_FAILED


@app.command("report", epilog=_EPILOG)
@click.option("--root", type=click.Path(file_okay=False), default="out", show_default=True, help="where the experiments left their results")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), default=None, callback=_writable_file, help="the report [default: ROOT/report/report.md]")
@click.option("--json", "as_json", is_flag=True, help="print the report's path as JSON")
def report_command(root, out_path, as_json) -> int:
    """Rebuild one markdown report of every experiment (training, generalisation, multi-element,
    fidelity, inverse problem, calibration, benchmarks, anatomy: optim.report.SECTIONS) from the results the
    scripts left under ROOT; nothing is recomputed."""
    from optim.report import build_report

    path = build_report(root, out_path)
    if as_json:
        _print_json({"report": str(path)})
    else:
        _out().print(f"report written to {path}")
    return EXIT_OK


@app.group("campaign", epilog=_EPILOG)
def campaign_group() -> None:
    """Virtual-cohort campaigns: anatomies through the FE oracle and congruency training (optim.campaign)."""


@campaign_group.command("run", epilog=_EPILOG)
@click.argument("directory", type=click.Path(file_okay=False), required=False)
@click.option("--n", "n", type=click.IntRange(min=1), default=None, help="anatomies for the regression (a new campaign) [default: the folder's]")
@click.option("--held-out", type=click.IntRange(min=0), default=None, help="held-out anatomies from an independent hypercube (a new campaign)")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="sampling seed (a new campaign)")
@click.option("--backend", type=click.Choice(BACKENDS), default=None, help="the oracle (a new campaign) [default: dolfinx]")
@click.option("--mesh-size", type=click.FloatRange(min=1.0), default=None, help="FE mesh size h (mm; a new campaign) [default: 6]")
@click.option("--budget", type=click.IntRange(min=16), default=None, help="MADS evaluations per active fit (a new campaign) [default: 960]")
@click.option("--timeout", "timeout_s", type=click.FloatRange(min=1.0), default=None, help="wall-clock limit of one FE solve, s (a new campaign) [default: 3600]")
@click.option("--n-elements", type=click.IntRange(min=1), default=None, help="elements of the multielement backend (a new campaign)")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Dask LocalCluster processes [default: one per core]")
@click.option("--scheduler", default=None, metavar="ADDRESS", help="an existing Dask scheduler (e.g. tcp://host:8786) instead of a LocalCluster")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None, help="the FE oracle's cache [default: $LVENV_FE_CACHE or ~/.cache/lvenv/fe_oracle]")
@click.option("--limit", type=click.IntRange(min=0), default=None, help="stop after this many anatomies finish")
@click.option("--allow-code-change", is_flag=True, help="continue a folder written by another oracle code version")
@click.option("--json", "as_json", is_flag=True, help="print the counts as JSON")
def campaign_run_command(directory, n, held_out, seed, backend, mesh_size, budget, timeout_s, n_elements, workers, scheduler, cache_dir, limit,
                         allow_code_change, as_json) -> int:
    """Run or resume the campaign in DIRECTORY [default: the package dataset lvenv/data/anatomy]: each
    anatomy's passive curve and three training beats in the FE oracle, then congruency training.
    Finished anatomies and FE runs are kept; the same command resumes."""
    from optim import campaign

    chosen = {"backend": backend, "mesh_size": mesh_size, "budget": budget, "timeout_s": timeout_s, "n_elements": n_elements}
    settings = campaign.Settings(**{k: v for k, v in chosen.items() if v is not None}) if any(v is not None for v in chosen.values()) else None
    started = time.perf_counter()
    first: dict = {}

    def event(counts: dict) -> None:
        first.setdefault("pending", counts["pending"])
        done_now = first["pending"] - counts["pending"]
        elapsed = time.perf_counter() - started
        left_s = elapsed / done_now * counts["pending"] if done_now else math.nan
        eta = "" if not math.isfinite(left_s) or not counts["pending"] else f", about {left_s / 3600:.1f} h left" if left_s > 5400 else f", about {left_s / 60:.0f} min left"
        finished = ", ".join(f"{counts[s]} {s}" for s in campaign.STATUSES if s != "pending" and counts[s])
        last = f" [{counts['last']}: {counts['last_status']}]" if "last" in counts else ""
        _err.print(f"campaign {time.strftime('%H:%M:%S')}: {finished or 'nothing finished'}; {counts['running']} running, "
                   f"{counts['pending']} pending{eta}{last}", markup=False, soft_wrap=True)

    directory = campaign.DATASET if directory is None else directory
    try:
        counts = campaign.run(directory, n=n, held_out=held_out, seed=seed, settings=settings, workers=workers, scheduler=scheduler,
                              cache_dir=cache_dir, allow_code_change=allow_code_change, limit=limit, on_event=event)
    except KeyboardInterrupt:
        _err.print(f"campaign interrupted: every finished anatomy is kept in {directory}; run the same command to resume", markup=False)
        raise click.exceptions.Abort() from None
    if as_json:
        _print_json(counts)
    return EXIT_FAILED if any(counts[s] for s in ("failed_fe", "failed_training", "failed_task")) else EXIT_OK


@campaign_group.command("status", epilog=_EPILOG)
@click.argument("directory", type=click.Path(file_okay=False), required=False)
@click.option("--json", "as_json", is_flag=True, help="print JSON")
def campaign_status_command(directory, as_json) -> int:
    """Counts by status, the failures with their reasons, and the throughput per session."""
    from optim import campaign

    directory = campaign.DATASET if directory is None else directory
    rows = campaign.read_index(directory)
    counts = {s: sum(r["status"] == s for r in rows) for s in campaign.STATUSES}
    failures = [{"id": r["id"], "status": r["status"], "reason": r["reason"]} for r in rows if r["status"] not in ("pending", "accepted")]
    speed = campaign.throughput(directory)
    if as_json:
        _print_json({"counts": counts, "left_out": failures, "throughput": speed})
        return EXIT_OK
    _out().print(", ".join(f"{v} {k}" for k, v in counts.items() if v) or "no anatomies")
    for f in failures:
        _out().print(f"{f['id']}: {f['status']}: {f['reason']}", markup=False)
    for s in speed:
        _out().print(f"session {s['session']}: {s['anatomies']} anatomies on {s['workers']} worker(s), {s['per_hour']:.2f} per hour "
                     f"(median {s['median_anatomy_min']:.1f} min each)")
    return EXIT_OK


@campaign_group.command("train-model", epilog=_EPILOG)
@click.argument("directory", type=click.Path(file_okay=False), required=False)
@click.option("--model", type=click.Choice(MULTI_ELEMENT_MODELS), default=MULTI_ELEMENT_MODELS[0], show_default=True, help="the multi-element LO heart")
@click.option("--budget", type=click.IntRange(min=16), default=480, show_default=True, help="MADS evaluations per anatomy")
@click.option("--limit", type=click.IntRange(min=0), default=None, help="stop after this many anatomies")
def campaign_train_model_command(directory, model, budget, limit) -> int:
    """Train a multi-element LO heart on every accepted anatomy of the campaign in DIRECTORY
    [default: the package dataset], from its FE traces (no FE run), into DIRECTORY/models/MODEL.csv,
    which `lvenv campaign regress --model MODEL` regresses. Finished anatomies are kept; the same
    command resumes."""
    from optim import campaign

    directory = campaign.DATASET if directory is None else directory
    started = time.perf_counter()

    def progress(row: dict, done: int, total: int) -> None:
        left = (time.perf_counter() - started) / done * (total - done)
        _err.print(f"{model} {time.strftime('%H:%M:%S')}: {row['id']} C {100 * row['C']:.2f} % ({done}/{total}, about {left / 60:.0f} min left)", markup=False)

    try:
        rows = campaign.train_model_table(directory, model, budget=budget, limit=limit, progress=progress)
    except KeyboardInterrupt:
        _err.print(f"interrupted: every finished anatomy is kept in {campaign.model_table_path(directory, model)}; run the same command to resume", markup=False)
        raise click.exceptions.Abort() from None
    _out().print(f"{len(rows)} anatomies trained for {model} in {campaign.model_table_path(directory, model)}")
    return EXIT_OK


@campaign_group.command("regress", epilog=_EPILOG)
@click.argument("directory", type=click.Path(file_okay=False), required=False)
@click.option("--model", type=click.Choice(tuple(LO_MODELS)), default="single", show_default=True,
              help="the LO heart whose maps to regress (a multi-element one from `lvenv campaign train-model`)")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), default=None, help="the artefact [default: the package's lvenv/data/anatomy/regression[_MODEL].json]")
@click.option("--restarts", type=click.IntRange(min=0), default=5, show_default=True, help="optimiser restarts per Gaussian process")
@click.option("--folds", type=click.IntRange(min=2), default=5, show_default=True, help="cross-validation folds")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the cross-validation figures as JSON")
def campaign_regress_command(directory, model, out_path, restarts, folds, seed, as_json) -> int:
    """Fit the Gaussian-process regression from geometry to the trained maps over the campaign's
    accepted anatomies, cross-validate it and write the artefact lvenv.anatomy.from_geometry loads."""
    from optim import campaign, regression

    fitted = regression.fit(campaign.DATASET if directory is None else directory, restarts=restarts, folds=folds, seed=seed, model=model)
    path = regression.save(fitted, out_path)
    cv = {name: spec.get("cv", "fixed") for name, spec in fitted.outputs.items()}
    if as_json:
        _print_json({"artefact": str(path), "anatomies": len(fitted.ids), "cv": cv})
        return EXIT_OK
    table = Table(title=f"{len(fitted.ids)} anatomies, {folds}-fold cross-validation → {path}", title_justify="left")
    for col in ("output", "regressed", "R²", "RMSE", "within 2 sd"):
        table.add_column(col, justify="right")
    for name, figures in cv.items():
        if figures == "fixed":
            table.add_row(name, "fixed by training", "", "", "")
        else:
            table.add_row(name, "in log" if fitted.outputs[name].get("log") else "as is", f"{figures['r2']:.3f}", f"{figures['rmse']:.4g}",
                          f"{100 * figures['coverage_2sd']:.0f} %")
    _out().print(table)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (see the module docstring). A Ctrl-C ends the process
    within a second or two with exit code 1 (:mod:`lvenv.interrupt`)."""
    with interrupt.watchdog(EXIT_FAILED):
        return _run(argv)


def _run(argv: Sequence[str] | None) -> int:
    try:
        code = app.main(args=list(sys.argv[1:] if argv is None else argv), prog_name="lvenv", standalone_mode=False)
    except click.exceptions.Exit as done:
        return done.exit_code
    except click.ClickException as err:
        err.show()
        return EXIT_USAGE
    except (click.exceptions.Abort, KeyboardInterrupt):
        _err.print("lvenv: aborted")
        return EXIT_FAILED
    except InputError as err:
        _err.print(f"lvenv: error: {err}", markup=False, soft_wrap=True)
        return EXIT_USAGE
    except Exception:  # noqa: BLE001 - the last line of defence: say it is our bug, show where
        _err.print("lvenv: internal error (please report it with the traceback below)", markup=False)
        traceback.print_exc()
        return EXIT_INTERNAL
    return EXIT_OK if code is None else int(code)


if __name__ == "__main__":
    sys.exit(main())
