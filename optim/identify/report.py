"""A per-patient identifiability report: the measurement model, sensitivity, profiles and
posterior at a fit, as markdown with PNG figures and JSON (``lvenv fit PATIENT --report DIR``)."""

from __future__ import annotations

import json
import pathlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.patients import Patient
from optim.cohort import CohortOptions
from optim.identify.noise import NOISE, Relative, chi2, measurement_sd
from optim.identify.profiles import DELTA_95, profile
from optim.identify.sampler import posterior

__all__ = ["write_report"]


def _bound_text(value: float | None, side: str) -> str:
    return f"{value:.4g}" if value is not None else f"({side} bound)"


def write_report(
    patient: Patient,
    fit: Mapping[str, float],
    observation: Mapping[str, float],
    out_dir: str | pathlib.Path,
    *,
    grid: int = 7,
    options: CohortOptions | None = None,
    posterior_options: Mapping[str, Any] | None = None,
    noise: Mapping[str, float | Relative] = NOISE,
) -> pathlib.Path:
    """Per-patient identifiability report at the fit ``fit`` (parameters by name, physical units),
    whose steady-state metrics are ``observation`` (by name, internal units: a fit result's
    ``observation``; the report gives χ² at the fit from it).

    Writes to ``out_dir``: ``identifiability.md`` (targets and their σ, the fit, the sensitivity's
    singular values and null directions, each parameter's profile class and 95 % interval, the
    posterior's medians, 90 % intervals and diagnostics), ``profiles.png``
    (:func:`lvenv.plots.profile_figure`), ``posterior_pairs.png`` (:func:`lvenv.plots.pairs_figure`)
    and ``identifiability.json`` (every number, internal units). ``grid`` and ``options``: of
    :func:`profile`; ``posterior_options``: keywords of :func:`posterior`. Returns the markdown's
    path. Takes a few minutes on 2 cores with the defaults (mostly the posterior).
    """
    from lvenv.plots import pairs_figure, profile_figure

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    fit = {n: float(fit[n]) for n in space.names}
    log = dict(zip(space.names, space.log))
    prof = profile(patient, grid=grid, fit=fit, noise=noise, options=options)
    post = posterior(patient, start=fit, noise=noise, **dict(posterior_options or {}))
    profile_figure(prof.grid, prof.chi2, prof.chi2_min, out / "profiles.png", DELTA_95, log=log, best=fit)
    pairs_figure({patient.name: post.samples}, out / "posterior_pairs.png", log=log)
    sigma = dict(zip(patient.targets, measurement_sd(patient.targets, noise)))
    lines = [f"# Identifiability of {patient.name}", "",
             "Internal units (s, ml, kPa). Measurement model, priors and methods: `optim.identify`.", "",
             "| target | value | σ |", "|---|---|---|",
             *(f"| {k} | {v:.4g} | {sigma[k]:.3g} |" for k, v in patient.targets.items()), "",
             "## Fit", "", "| parameter | value | units |", "|---|---|---|",
             *(f"| {n} | {fit[n]:.4g} | {ACTION_BOUNDS[n].units} |" for n in space.names), "",
             f"χ² at the fit: {chi2(patient, observation, noise):.3g}", "",
             "## Sensitivity at the fit", ""]
    sens = prof.sensitivity
    if sens is None:
        lines += ["No usable steady state at the fit: no sensitivity.", ""]
    else:
        lines += ["Singular values of diag(1/σ) dM/du (χ per unit-cube step): " + ", ".join(f"{v:.3g}" for v in sens.singular_values), ""]
        lines += [f"* null direction {j + 1}: " + ", ".join(f"{n} {v:+.2f}" for n, v in d.items()) for j, d in enumerate(sens.null_directions)]
        lines += [""]
    lines += ["## Profile likelihoods", "",
              f"{grid} constrained fits per parameter over its bound; Δχ² = {DELTA_95} marks the 95 % interval. ![profiles](profiles.png)", "",
              "| parameter | class | 95 % interval (outer grid points) | profile range (Δχ²) |", "|---|---|---|---|"]
    for n in space.names:
        lo, hi = prof.interval[n]
        values = prof.chi2[n]
        spread = f"{np.nanmax(values) - np.nanmin(values):.3g}" if np.isfinite(values).any() else "—"
        lines.append(f"| {n} | {prof.classification[n]} | [{_bound_text(lo, 'lower')}, {_bound_text(hi, 'upper')}] | {spread} |")
    lines += ["", "## Posterior", "",
              f"{post.evaluations} evaluations ({post.failed} failed), acceptance {post.acceptance:.2f}. ![posterior pairs](posterior_pairs.png)", "",
              "| parameter | median | 90 % interval | split R-hat | ESS |", "|---|---|---|---|---|"]
    for n in space.names:
        lo, hi = post.interval_90[n]
        lines.append(f"| {n} | {post.median[n]:.4g} | [{lo:.4g}, {hi:.4g}] | {post.rhat[n]:.3f} | {post.ess[n]:.0f} |")
    if max(post.rhat.values()) >= 1.01:
        lines += ["", f"**Not converged**: split R-hat up to {max(post.rhat.values()):.3f} (≥ 1.01); run longer chains (`chain_steps`)."]
    path = out / "identifiability.md"
    path.write_text("\n".join(lines) + "\n")
    sens_dict = None if sens is None else {"singular_values": sens.singular_values.tolist(), "null_directions": sens.null_directions}
    (out / "identifiability.json").write_text(json.dumps({"patient": patient.name, "targets": patient.targets, "noise": sigma, "fit": fit,
                                                          "sensitivity": sens_dict, "profiles": prof.to_dict(), "posterior": post.to_dict()},
                                                         indent=2, default=float))
    return path
