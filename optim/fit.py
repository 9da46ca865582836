"""The inverse problem of the paper (DESIGN §2–3, issue 4): fit patients with every optimiser.

`fit_patients` fits (τ2, Sa, R2, R3, C, Cat) of each patient to its targets (built-ins: EF, ET,
IVRT, aortic pulse pressure) with each method through one vector env per patient
(`optim.minimize`), and returns one `FitRow` per (patient, method). With `out_dir` it writes
`pv_<patient>.png`: the fitted PV loops against the target end-systolic volume, and every
method's observation / target ratio per target.

`corrected_fit` fits a patient, runs the oracle at its best fit (`optim.congruency.check_fidelity`),
refits the heart's maps {μ1, μ2, γ, delay} on that oracle beat and fits the patient again with
them, for a number of rounds, then checks the last fit against the oracle: maps trained where the
fit lands instead of at the training beats, since maps trained on the training beats do not carry
over to other cells and circulations (`optim.studies.retune`).

`synthetic_recovery` draws ground-truth parameter sets inside the bounds, uses their simulated
observations as a patient's targets, fits them back, and reports per parameter how far the fits
land from the truth (identifiability).

Defaults (ours) are sized for the README main job on a 2-core CPU: num_envs = 16, the env's
adaptive integration scheme (per-member step-size control, within the accuracy specification
against Radau: EF 0.5 points, phase durations 2 ms, pressures 1 %), a budget of 480 evaluations
(30 env steps), and per-method options in `DEFAULT_OPTIONS`. ``steps_per_beat`` (500, h = 2 ms
at 60 bpm) sets the fixed-step simulations that draw the PV loops and synthetic truths.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

import lvenv
from lvenv.env.core import ENV_ACCELERATION, ENV_SCHEME
from lvenv.identification import DEFAULT_ACTION_PARAMS, ParameterSpace
from lvenv.metrics import METRICS
from lvenv.params import Heart
from lvenv.patients import Patient, builtin
from lvenv.plausibility import Band, inside_bands
from lvenv.validation import integer, real
from optim.congruency import Fidelity, check_fidelity, map_refit
from optim.minimize import MinimizeResult, minimize

__all__ = [
    "FitRow", "DEFAULT_OPTIONS", "make_env", "warm_up", "fit_patients", "CorrectionRound", "corrected_fit", "plot_fits", "null_directions",
    "synthetic_recovery", "RecoveryReport", "draw_truths", "Truths", "ENV_SIMULATION",
]

#: Per-method options used by `fit_patients` unless overridden (see `optim.minimize`).
DEFAULT_OPTIONS: dict[str, dict[str, Any]] = {
    "mads": {},
    "cma": {},
    "kriging": {"n_restarts": 0, "n_candidates": 1024},  # trust region + Thompson sampling (optim.kriging)
    # optim.lm.fit_lm: its own budget, since each of its evaluations is a steady state and its tangents
    "lm": {"budget": 120, "starts": 4},
}


@dataclasses.dataclass(frozen=True)
class FitRow(MinimizeResult):
    """One (patient, method) fit: the `MinimizeResult` of `minimize` (of `optim.lm.fit_lm` for
    ``"lm"``), plus the evaluations and wall time (s) until the mismatch first fell below 3 % (None
    if never), and the one-off JIT compilation `compile_time` (s, not in wall_time): the env's,
    shared by all env methods of the patient, or for ``"lm"`` that of a short warm-up run of it."""

    evaluations_to_3pct: int | None
    wall_time_to_3pct: float | None
    compile_time: float

    @classmethod
    def of(cls, res: MinimizeResult, compile_time: float) -> FitRow:
        """The row of the fit ``res``, which compiled for ``compile_time`` s."""
        evals, wall = res.history.to_target(0.03)
        fields = {f.name: getattr(res, f.name) for f in dataclasses.fields(res)}
        return cls(**fields, evaluations_to_3pct=evals, wall_time_to_3pct=wall, compile_time=compile_time)


def make_env(patient: str | Patient | Sequence[Patient], num_envs: int = 16, steps_per_beat: int = 500, max_beats: int = 60,
             rtol: float = 1e-4, scheme: str | None = None, plausibility: bool | Sequence[Band] = True) -> Any:
    """A vector env set up for optimisation (autoreset Disabled, no tolerance, no truncation).

    ``scheme``: the env's integration scheme (:data:`lvenv.simulation.SCHEMES`; ``None``: the
    env's default for the patient's LO heart model, :func:`lvenv.env.core.default_scheme`);
    ``steps_per_beat`` applies to ``scheme="fixed"`` only. ``plausibility``: the objective's
    physiological bands (:mod:`lvenv.plausibility`; default on)."""
    return gymnasium.make_vec(
        "lvenv/LVHeart-v0", num_envs=num_envs, patient=patient, max_episode_steps=None, tolerance=0.0,
        autoreset_mode="Disabled", steps_per_beat=steps_per_beat, max_beats=max_beats, rtol=rtol, scheme=scheme,
        plausibility=plausibility,
    )


def warm_up(venv: Any) -> float:
    """Compile the env's step, which also resets, once (s); later runs on this env pay no JIT cost."""
    start = time.perf_counter()
    _, info = venv.reset(seed=0)
    values = np.stack([info["parameters"][n] for n in venv.unwrapped.action_names], axis=1)
    venv.step(values if venv.unwrapped.config.actions.mode == "physical" else np.zeros_like(values))
    return time.perf_counter() - start


def _patient(p: str | Patient) -> Patient:
    return builtin(p) if isinstance(p, str) else p


def fit_patients(
    patients: Sequence[str | Patient] = ("normal", "heart_failure"),
    methods: Sequence[str] = ("mads", "cma", "kriging"),
    num_envs: int = 16,
    budget: int = 480,
    seed: int = 0,
    out_dir: str | Path | None = None,
    steps_per_beat: int = 500,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    progress: bool | None = False,
    plausibility: bool | Sequence[Band] = True,
    scheme: str | None = None,
) -> list[FitRow]:
    """Fit every patient with every method; rows in (patient, method) order. See module docstring.
    ``plausibility``: the objective's physiological bands (:mod:`lvenv.plausibility`); ``scheme``:
    the env's integration scheme (:func:`make_env`).

    ``"lm"`` (:func:`optim.lm.fit_lm`) does not use the env: it runs at ``steps_per_beat`` fixed
    steps with its own budget and starts (`DEFAULT_OPTIONS`; an ``options["lm"]`` budget overrides
    it), after a warm-up run of 2 evaluations a start that compiles the same batched functions,
    so its wall time is warm like the others'."""
    rows: list[FitRow] = []
    for p in patients:
        patient = _patient(p)
        venv = make_env(patient, num_envs, steps_per_beat, scheme=scheme, plausibility=plausibility) if set(methods) - {"lm"} else None
        compile_time = warm_up(venv) if venv is not None else 0.0
        for method in methods:
            opts = {**DEFAULT_OPTIONS.get(method, {}), **dict((options or {}).get(method, {}))}
            if method == "lm":
                res, compiled = _fit_lm(patient, seed, steps_per_beat, plausibility, {"budget": budget, **opts})
            else:
                res, compiled = minimize(venv, method, budget=budget, seed=seed, progress=progress, **opts), compile_time
            rows.append(FitRow.of(res, compiled))
        if venv is not None:
            venv.close()
    if out_dir is not None:
        plot_fits(rows, {_patient(p).name: _patient(p) for p in patients}, out_dir, steps_per_beat)
    return rows


@dataclasses.dataclass(frozen=True)
class CorrectionRound:
    """One round of :func:`corrected_fit`: the maps the patient's heart carried (``maps``, name →
    value), the best fit with them (``fit``) and the oracle's check at that fit (``fidelity``;
    ``fidelity.retuned`` holds the maps refitted on its beat, for the next round)."""

    maps: dict[str, float]
    fit: FitRow
    fidelity: Fidelity


def corrected_fit(patient: str | Patient, methods: Sequence[str] = ("cma",), rounds: int = 1, *, first: FitRow | None = None,
                  backend: str = "dolfinx", beats: int = 2, retune_budget: int = 480, num_envs: int = 16, budget: int = 480,
                  seed: int = 0, steps_per_beat: int = 1000, plausibility: bool | Sequence[Band] = True, scheme: str | None = None,
                  options: Mapping[str, Mapping[str, Any]] | None = None, progress: bool | None = None, passive: bool = False,
                  aortic_weight: float = 0.0, **oracle_options: Any) -> list[CorrectionRound]:
    """``rounds`` + 1 rounds of: fit ``patient`` with ``methods`` (:func:`fit_patients`; the
    best fit), run the oracle ``backend`` at it for ``beats`` beats (`check_fidelity`), and, but
    in the last round, refit the maps :data:`~optim.congruency.MAP_NAMES` on that beat (MADS
    ``retune_budget`` evaluations, then least squares) for the next round's heart, whose fit
    starts from this round's fit. ``passive``: refit the passive maps
    :data:`~optim.congruency.PASSIVE_NAMES` too, each within the patient's own value ÷ and ×
    :data:`~optim.congruency.PASSIVE_FREEDOM` in every round (`optim.congruency.map_refit`).
    ``aortic_weight``: the refits weigh the aortic pressure trace in
    (`optim.congruency.fit_maps`). (The targets leave directions of the parameters free: fits
    from one start land at other points along them in each round, where the refitted maps need
    not hold.) ``first``: the first round's fit, if the patient was fitted already (with its own
    maps). ``scheme`` and ``options``: the fits' integration scheme and per-method options
    (:func:`fit_patients`); ``progress``: the oracle's and the refits' progress bars. Each round
    costs one oracle run (``beats`` beats; at h = 6 mm about 2 min a beat) and, but the last,
    one refit of the maps (minutes on one core)."""
    patient = _patient(patient)
    rounds = integer("rounds", rounds, 0)
    aortic_weight = real("aortic_weight", aortic_weight, 0.0)
    names, bounds = map_refit(patient.heart.lo, passive)
    out: list[CorrectionRound] = []
    for r in range(rounds + 1):
        if r == 0 and first is not None:
            best = first
        else:
            fits = fit_patients([patient], methods, num_envs, budget, seed, None, steps_per_beat, plausibility=plausibility, scheme=scheme,
                                options=options)
            best = min(fits, key=lambda row: row.mismatch)
        heart = patient.heart.replace(**best.parameters)
        refit = r < rounds
        report = check_fidelity(heart, backend, beats=beats, steps_per_beat=steps_per_beat, retune=names if refit else (),
                                retune_budget=retune_budget, bounds=bounds, aortic_weight=aortic_weight if refit else 0.0, progress=progress,
                                **oracle_options)
        out.append(CorrectionRound({n: float(getattr(heart.lo, n)) for n in names}, best, report))
        if refit:
            lo = dataclasses.replace(heart.lo, **report.retuned["lo"])
            patient = dataclasses.replace(patient, heart=dataclasses.replace(heart, lo=lo))
    return out


def _fit_lm(patient: Patient, seed: int, steps_per_beat: int, plausibility: bool | Sequence[Band],
            options: Mapping[str, Any]) -> tuple[MinimizeResult, float]:
    """`optim.lm.fit_lm` after a warm-up run (2 evaluations a start, the same batch shapes);
    returns its result and the warm-up's wall time (s)."""
    from optim.lm import fit_lm

    settings = {"seed": seed, "steps_per_beat": steps_per_beat, "plausibility": plausibility, **options}
    start = time.perf_counter()
    fit_lm(patient, **{**settings, "budget": 2 * settings["starts"]})
    compiled = time.perf_counter() - start
    return fit_lm(patient, **settings), compiled


def plot_fits(rows: Sequence[FitRow], patients: Mapping[str, Patient], out_dir: str | Path,
              steps_per_beat: int = 500) -> list[Path]:
    """`pv_<patient>.png` per patient: fitted PV loops (one per method) with the target
    end-systolic volume EDV·(1 − EF_target) marked at each loop's end-systolic pressure, and observation / target per target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lvenv.units import kpa_to_mmhg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, patient in patients.items():
        mine = [r for r in rows if r.patient == name and np.isfinite(r.mismatch)]
        fig, (ax_pv, ax_bar) = plt.subplots(1, 2, figsize=(11, 4.5))
        hearts = [patient.heart.replace(**r.parameters) for r in mine]
        sims = lvenv.simulate(hearts, steps_per_beat=steps_per_beat) if hearts else None
        targets = list(patient.targets)
        width = 0.8 / max(len(mine), 1)
        for j, r in enumerate(mine):
            tr = sims[j].traces
            (line,) = ax_pv.plot(tr.V, kpa_to_mmhg(tr.P_lv), label=f"{r.method} ({100 * r.mismatch:.2f} %)")
            if "EF" in patient.targets:
                edv = float(np.max(tr.V))
                esv_target = edv * (1.0 - patient.targets["EF"])
                p_es = kpa_to_mmhg(float(tr.P_lv[np.argmin(tr.V)]))  # end-systolic pressure of the fit
                ax_pv.plot([esv_target], [p_es], "x", ms=10, mew=2, color=line.get_color())
            ratios = [r.observation[t] / patient.targets[t] for t in targets]
            ax_bar.bar(np.arange(len(targets)) + (j - (len(mine) - 1) / 2) * width, ratios, width, label=r.method)
        ax_pv.set_xlabel("V (ml)")
        ax_pv.set_ylabel("P_lv (mmHg)")
        ax_pv.set_title(f"{name}: fitted PV loops; x = target ESV, EDV (1 − EF target)", fontsize=10)
        ax_pv.legend(fontsize=8)
        ax_bar.axhline(1.0, color="k", lw=1)
        ax_bar.set_xticks(np.arange(len(targets)))
        ax_bar.set_xticklabels([METRICS[t].label for t in targets])
        ax_bar.set_ylabel("fitted / target")
        ax_bar.set_ylim(0.9, 1.1)
        ax_bar.set_title("observation / target")
        ax_bar.legend(fontsize=8)
        fig.tight_layout()
        path = out / f"pv_{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def null_directions(
    heart: Any, truths: np.ndarray, targets: Sequence[str], steps_per_beat: int = 500, step: float = 0.002
) -> tuple[np.ndarray, np.ndarray]:
    """Local identifiability at each truth (rows of `truths`, physical, DEFAULT_ACTION_PARAMS).

    J_ij = ∂ ln o_i / ∂ u_j by central differences of ±`step` in the unit-cube coordinates u of
    `lvenv.identification.ParameterSpace` (log axes where marked), one batched simulation for all truths. The step is
    small because the metrics bend sharply in places (at the N preset, J at step 0.01 has
    σ_max a third of that at 0.002); the steady-state tolerance (1e-4) bounds its noise. With 4 targets
    and 6 parameters J has a null space of dimension ≥ 2: moving along it leaves every target
    unchanged to first order. Returns (singular values (m, n_targets), null basis (m, 6, 6 − r))
    where r is the numerical rank (σ > 1e-3 σ_max); parameter j is locally identifiable iff row
    j of the null basis is zero.
    """
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    k = space.dimension
    u0 = space.to_unit(truths)
    offsets = np.vstack([np.zeros(k), step * np.eye(k), -step * np.eye(k)])
    u = np.clip(u0[:, None, :] + offsets[None], 0.0, 1.0)  # (m, 2k + 1, k)
    x = space.from_unit(u.reshape(-1, k))
    sim = lvenv.simulate([heart.replace(**dict(zip(space.names, map(float, xi)))) for xi in x],
                         steps_per_beat=steps_per_beat, max_beats=60, traces=False)
    obs = np.log(np.stack([np.asarray(sim.metrics[t]) for t in targets], axis=1)).reshape(len(truths), 2 * k + 1, -1)
    du = (u[:, 1 : k + 1] - u[:, k + 1 :]).diagonal(axis1=1, axis2=2)  # actual central widths (m, k)
    jac = np.transpose((obs[:, 1 : k + 1] - obs[:, k + 1 :]) / du[:, :, None], (0, 2, 1))  # (m, n_t, k)
    sigmas, nulls = [], []
    for jm in jac:
        _, sv, vt = np.linalg.svd(jm)
        rank = int(np.sum(sv > 1e-3 * sv[0]))
        sigmas.append(sv)
        nulls.append(vt[rank:].T)
    width = max(n.shape[1] for n in nulls)
    padded = np.zeros((len(nulls), k, width))
    for i, n in enumerate(nulls):
        padded[i, :, : n.shape[1]] = n
    return np.array(sigmas), padded


@dataclasses.dataclass(frozen=True)
class RecoveryReport:
    """Synthetic recovery. truths / fits: (m, k) physical parameters (columns `names`);
    mismatch: (m,) refitted mean relative mismatch; max_error: (m,) largest abs(e_k) over targets;
    log_error: (m, k) abs(ln(fit / truth)) (abs(fit − truth) / range for linear parameters);
    identifiable[name]: median error below `tol_identifiable`. null_share: (m, k) norm of each
    parameter's row of the local null basis of ∂ ln(targets)/∂u at the truth (`null_directions`;
    0: locally identifiable, 1: free to first order); null_basis: (m, k, k − rank)."""

    names: tuple[str, ...]
    targets: tuple[str, ...]
    truths: np.ndarray
    fits: np.ndarray
    mismatch: np.ndarray
    max_error: np.ndarray
    log_error: np.ndarray
    identifiable: dict[str, bool]
    null_share: np.ndarray
    null_basis: np.ndarray
    singular_values: np.ndarray
    wall_time: float


@dataclasses.dataclass(frozen=True)
class Truths:
    """Synthetic ground truths (:func:`draw_truths`): ``parameters`` (n, 6), physical units,
    columns :data:`~lvenv.identification.DEFAULT_ACTION_PARAMS`; ``heart_rate`` (n,), 1/min;
    ``metrics``: every beat metric of each truth's steady state by name, (n,) each, internal
    units; ``tried``: how many parameter sets were simulated to find them."""

    parameters: np.ndarray
    heart_rate: np.ndarray
    metrics: dict[str, np.ndarray]
    tried: int

    def observations(self, names: Sequence[str]) -> np.ndarray:
        """(n, len(names)) metrics of the truths, columns ``names`` (internal units)."""
        return np.stack([self.metrics[k] for k in names], axis=1)


#: :func:`draw_truths`' default simulation: the env's scheme (adaptive, Anderson-accelerated), which will fit them.
ENV_SIMULATION = {"scheme": ENV_SCHEME, "acceleration": ENV_ACCELERATION, "max_beats": 60}


def draw_truths(
    n: int,
    rng: np.random.Generator,
    heart: Heart,
    *,
    ef: tuple[float, float] = (0.3, 0.75),
    heart_rate: tuple[float, float] | None = None,
    batch: int = 64,
    simulation: Mapping[str, Any] = ENV_SIMULATION,
) -> Truths:
    """``n`` random parameter sets of ``heart``, uniform in the unit cube of the identification
    bounds (log-uniform on log axes), whose hearts simulate cleanly (status ``ok``) with EF in
    ``ef`` and every plausibility band met (:mod:`lvenv.plausibility`), so that an exact fit
    exists. Drawn ``batch`` at a time from ``rng`` (for each batch the unit-cube points, then,
    with ``heart_rate`` = (low, high) 1/min, a heart rate uniform in it; otherwise ``heart``'s
    own), each batch one :func:`lvenv.simulate` call with the keywords ``simulation``; the first
    acceptable sets in draw order are kept. One home of the synthetic truths of
    :func:`synthetic_recovery`, the identification scripts and ``scripts/make_cohort.py``."""
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    kept: dict[str, list] = {"x": [], "hr": [], "metrics": []}
    tried = 0
    while len(kept["x"]) < n:
        x = space.from_unit(rng.random((batch, space.dimension)))
        rate = {"HR": rng.uniform(*heart_rate, batch)} if heart_rate is not None else {}
        hearts = [heart.replace(**{k: float(v[i]) for k, v in rate.items()}, **dict(zip(space.names, map(float, xi)))) for i, xi in enumerate(x)]
        sim = lvenv.simulate(hearts, traces=False, **simulation)
        m = sim.metrics
        good = (np.asarray(sim.status) == "ok") & (m["EF"] >= ef[0]) & (m["EF"] <= ef[1]) & inside_bands(m)
        chosen = np.flatnonzero(good)[: n - len(kept["x"])]
        kept["x"].extend(x[chosen])
        kept["hr"].extend(rate["HR"][chosen] if rate else np.full(len(chosen), float(heart.get("HR"))))
        kept["metrics"].append({k: np.asarray(v)[chosen] for k, v in m.items()})
        tried += batch
    metrics = {k: np.concatenate([part[k] for part in kept["metrics"]]) for k in kept["metrics"][0]}
    return Truths(np.array(kept["x"]), np.array(kept["hr"]), metrics, tried)


def synthetic_recovery(
    n_sets: int = 10,
    method: str = "cma",
    num_envs: int = 16,
    budget: int = 1600,
    seed: int = 0,
    steps_per_beat: int = 500,
    base: str | Patient = "normal",
    targets: Sequence[str] = ("EF", "ET", "IVRT", "P_ao_pulse"),
    tol_identifiable: float = 0.05,
    **options: Any,
) -> RecoveryReport:
    """Fit back `n_sets` synthetic patients whose targets are simulated from random truths.

    The fit starts from the base patient's own parameters, not from the truth. A parameter
    counts as identifiable when the median over sets of abs(ln(fit/truth)) (log axes) or
    abs(fit − truth) / (upper − lower) (linear axes) stays below `tol_identifiable`.
    """
    start = time.perf_counter()
    base_patient = _patient(base)
    rng = np.random.default_rng(seed)
    drawn = draw_truths(n_sets, rng, base_patient.heart)
    truths, obs = drawn.parameters, drawn.observations(targets)
    space = ParameterSpace.for_names(DEFAULT_ACTION_PARAMS)
    fits, mismatch, max_error = [], [], []
    opts = {**DEFAULT_OPTIONS.get(method, {}), **options}
    for i in range(n_sets):
        patient = Patient(f"synthetic_{i}", base_patient.heart, dict(zip(targets, map(float, obs[i]))))
        venv = make_env(patient, num_envs, steps_per_beat)
        res = minimize(venv, method, budget=budget, seed=seed + i, progress=False, **opts)
        venv.close()
        fits.append([res.parameters[n] for n in space.names])
        mismatch.append(res.mismatch)
        max_error.append(max(res.mismatch_per_target.values()))
    fits_arr = np.array(fits)
    err = np.where(space.log, np.abs(np.log(fits_arr / truths)), np.abs(fits_arr - truths) / (np.array(space.upper) - np.array(space.lower)))
    identifiable = {n: bool(np.median(err[:, j]) < tol_identifiable) for j, n in enumerate(space.names)}
    sigmas, null = null_directions(base_patient.heart, truths, targets, steps_per_beat)
    return RecoveryReport(space.names, tuple(targets), truths, fits_arr, np.array(mismatch), np.array(max_error),
                          err, identifiable, np.linalg.norm(null, axis=2), null, sigmas, time.perf_counter() - start)

