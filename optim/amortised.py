"""Amortised identification: a neural posterior estimator of the six parameters, trained once.

A conditional normalising flow q(θ | c) learns :func:`optim.identify.posterior`'s posterior
from simulated pairs (Papamakarios G & Murray I, NeurIPS 2016; Greenberg D et al., ICML 2019):
θ is drawn from the same prior (:func:`optim.identify.prior_sample`: uniform in the unit cube of
the identification bounds times the plausibility factor, usable hearts only), the heart is
simulated by the same env, and the observation gets the same noise (:data:`optim.identify.NOISE`,
:func:`optim.identify.measurement_sd`). Training maximises E log q(θ | c) over the pairs, which
is minimised in expectation by the exact posterior; every later patient's posterior is one
batched pass through the flow.

Coordinates. θ enters as z = logit(u), u its unit-cube coordinate (log axes where marked), then
standardised by the training set's mean and standard deviation; samples map back through the
same steps, so they always lie inside the bounds. The condition vector c (:data:`CONDITION`) is

* the :data:`OBSERVED` targets, each standardised by the training set and multiplied by its
  mask bit (0 where missing), then the six mask bits: any subset of the targets may be missing.
  Training masks: a share :data:`COMMON_SHARE` of the rows carry one of the target sets
  patients carry (:data:`COMMON_MASKS`, drawn uniformly), the others drop each target
  independently with probability :data:`MISSING` (a row with none left keeps one at random).
  Under the independent drops alone the built-in patients' mask is one row in 46 (0.7⁴ 0.3²),
  too few for the flow to match the MCMC posterior on it (issue 33: 19 of 22 patients within
  the acceptance on every parameter; all 22 with a share 0.8 of common masks). Which masks are
  common is a choice of the training distribution only: the flow stays an estimate of the
  posterior for every mask. EDV and ESV are left out: adding them would need the volume noise
  model's relative errors and a larger training set for every mask; they can join the
  same way (a mask bit each) in a later artefact;
* the heart rate (1/min), drawn uniformly in the artefact's ``heart_rate`` range;
* the six unloaded-geometry parameters of :class:`lvenv.geometry.Geometry` (mm, degrees),
  standardised: each pair's own heart's (``PriorSample.geometry``).

Hearts. An artefact's ``bases`` are the heart kinds its pairs were drawn over (:data:`KINDS`):
the base presets (N and HF, each with its own trained maps) and :data:`ANATOMY`, hearts whose
geometry is uniform in the anatomy campaign's box and whose LO maps are the anatomy regression's
prediction for it (:func:`anatomy_heart`), as a cohort row or a patient record with a geometry
and ``"lo": "regression"`` gets them. :func:`covered_geometry` says whether a patient's heart is
one of them (up to the six parameters and the heart rate) and gives its geometry row; the
anatomy kind pins the regression (its dataset's hash) in the artefact's prior, so a refitted
regression asks for a retrained estimator.

Flow: a coupling flow of rational-quadratic splines (Durkan C et al., NeurIPS 2019;
``flowjax.flows.coupling_flow``), fast in both directions, trained by maximum likelihood with Adam
(optax), each epoch one jitted ``lax.scan`` over its minibatches. Every epoch draws fresh noise
and masks for the training rows, so the flow never learns one noise realisation. A held-out
fraction ``val_prop`` of the pairs (noise drawn once) gives the validation loss (mean −log q in
the standardised logit coordinates, nats); the learning rate is multiplied by ``decay`` after
every ``plateau`` epochs without improvement (Adam's step noise otherwise keeps the loss
0.02–0.05 nats above its floor), training stops after ``patience`` epochs without improvement
(or at a time budget) and keeps the best epoch's parameters.

Out-of-distribution check (:meth:`Estimator.out_of_distribution`). A patient is flagged when

* its heart rate lies outside the training range; or
* its observed targets are improbable under the training observations' density: a Gaussian
  mixture (:data:`OOD_COMPONENTS` components, full covariances) fitted to the standardised noisy
  training observations; for the patient's mask, its marginal log density (a Gaussian mixture
  too) is compared with the :data:`OOD_QUANTILE` quantile of the held-out pairs' log densities
  under the same marginal. So one in a thousand simulated patients is flagged (false alarms),
  and any observation farther from every simulated heart than they are is.

A flagged patient still gets samples, with ``Posterior.out_of_distribution`` set and the reason.

Artefact: an :mod:`lvenv.archive` ``.npz`` (never pickle) of the flow's arrays (``flow_000``, …,
in ``jax.tree.leaves`` order of the flow's arrays), the normalisation and the mixture, and JSON
metadata: :data:`FORMAT` and :data:`VERSION`, the prior (bounds, log flags, plausibility bands,
heart-rate range, base presets), the noise σ of each observed target, the training set (pairs,
uniform draws tried, those left out by reason, seconds), the architecture, the validation loss,
and the code version. :func:`load` rebuilds the flow from the architecture and checks every
array's shape and every recorded setting against this code: a malformed file, another format or
version, other bounds, noise, bands, bases or observation names give an
:class:`lvenv.archive.ArchiveError` that says what differs.

Length: over 800 lines, because the training pairs, the flow, its batched sampler and
the artefact that rebuilds it are one estimator: the artefact's checks must name every setting
the pairs and the flow were made with.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import pathlib
import subprocess
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from lvenv import archive, presets
from lvenv.archive import ArchiveError
from lvenv.geometry import Geometry
from lvenv.identification import ACTION_BOUNDS, DEFAULT_ACTION_PARAMS, LOGIT_EDGE, ParameterSpace, from_logit, to_logit
from lvenv.params import Heart
from lvenv.patients import Patient
from lvenv.plausibility import resolve as resolve_bands
from lvenv.validation import InputError, integer, real
from optim.identify.density import ARRAYS, PriorSample, prior_sample
from optim.identify.noise import NOISE, Relative, measurement_sd

__all__ = ["OBSERVED", "GEOMETRY", "CONDITION", "BASES", "HEART_RATE", "MISSING", "OOD_QUANTILE", "OOD_COMPONENTS", "OOD_FIT_ROWS", "COMMON_MASKS", "COMMON_SHARE", "FORMAT", "VERSION",
           "DEFAULT_ARTEFACT", "DRAWS_FORMAT", "SAMPLE_BLOCK", "Architecture", "Estimator", "training_patients", "simulate", "save_draws", "load_draws", "train", "save", "load", "covered_geometry", "anatomy_heart", "observations", "ANATOMY", "KINDS",
           "PAIRS_PER_ANATOMY", "ANATOMY_SEED", "heart_kinds",
           "HELD_OUT_TARGETS", "held_out_patients"]

#: The targets the estimator conditions on (internal units: EF fraction, times s, pressures kPa).
OBSERVED = ("EF", "ET", "IVRT", "P_ao_dia", "P_ao_mean", "P_ao_pulse")
#: The geometric columns of the condition (:class:`lvenv.geometry.Geometry`, unloaded: mm, degrees).
GEOMETRY = tuple(f.name for f in dataclasses.fields(Geometry))
#: Names of the condition vector's columns, in order (module docstring).
CONDITION = (*OBSERVED, *(f"mask_{k}" for k in OBSERVED), "HR", *GEOMETRY)
#: The base presets a default training set draws its hearts from (:mod:`lvenv.presets`).
BASES = ("normal", "heart_failure")
#: The heart kind drawn over anatomies: the N preset's cell and circulation with an unloaded
#: geometry uniform in the anatomy regression's box (the campaign's, :data:`optim.campaign.BOX`) and the LO maps the
#: anatomy regression predicts for it (:func:`lvenv.anatomy.predicted_maps`), as a cohort row or a
#: patient record with a geometry gets them.
ANATOMY = "anatomy"
#: Every heart kind a training set may draw from, in the order an estimator lists them; a pair's
#: ``base`` (:class:`optim.identify.PriorSample`) is its kind's index here.
KINDS = (*BASES, ANATOMY)
#: Pairs drawn per anatomy of the :data:`ANATOMY` kind (so a chunk of 5,000 pairs has 1,250 anatomies).
PAIRS_PER_ANATOMY = 4
#: Added to the seed of the :data:`ANATOMY` kind's draws, so that they never share a stream with the presets'.
ANATOMY_SEED = 1_000_000
#: Default heart-rate range of the training set (1/min).
HEART_RATE = (40.0, 120.0)
#: Probability that a training row's target is masked out (rows without a :data:`COMMON_MASKS` mask).
MISSING = 0.3
#: The targets of :func:`held_out_patients`: the built-in patients' own.
HELD_OUT_TARGETS = ("EF", "ET", "IVRT", "P_ao_pulse")
#: The target sets patients carry, each given to a share of the training rows (module docstring):
#: the built-in patients' (:data:`HELD_OUT_TARGETS`), a cohort report's (its required columns:
#: EF, ET, IVRT and the cuff's two, ``optim.cohort.REQUIRED``) and all six.
COMMON_MASKS = (HELD_OUT_TARGETS, ("EF", "ET", "IVRT", "P_ao_dia", "P_ao_mean"), OBSERVED)
#: Default share of the training rows whose mask is one of :data:`COMMON_MASKS`.
COMMON_SHARE = 0.8
#: Quantile of the held-out log densities below which an observation is flagged.
OOD_QUANTILE = 1e-3
#: Components of the observation density of the out-of-distribution check.
OOD_COMPONENTS = 8
#: At most this many pairs fit the out-of-distribution mixture (the rest add little).
OOD_FIT_ROWS = 200_000
#: Artefact format name and version (:func:`load` accepts only these).
FORMAT, VERSION = "lvenv-amortised-posterior", 1
#: The shipped artefact (``scripts/train_amortised.py``; provenance in its metadata and
#: ``optim/data/amortised.json``).
DEFAULT_ARTEFACT = pathlib.Path(__file__).parent / "data" / "amortised.npz"


@dataclasses.dataclass(frozen=True)
class Architecture:
    """The flow's shape: coupling layers, spline knots and interval (standardised units), and
    the conditioner MLP's width and depth."""

    flow_layers: int = 6
    knots: int = 8
    interval: float = 5.0
    nn_width: int = 128
    nn_depth: int = 2

    def build(self, seed: int = 0) -> Any:
        """A freshly initialised flow of this shape over the six parameters."""
        import jax
        import jax.numpy as jnp
        from flowjax.bijections import RationalQuadraticSpline
        from flowjax.distributions import Normal
        from flowjax.flows import coupling_flow

        return coupling_flow(jax.random.key(seed), base_dist=Normal(jnp.zeros(len(DEFAULT_ACTION_PARAMS))),
                             transformer=RationalQuadraticSpline(knots=self.knots, interval=self.interval), cond_dim=len(CONDITION),
                             flow_layers=self.flow_layers, nn_width=self.nn_width, nn_depth=self.nn_depth)


def _arrays_of(flow: Any) -> list[np.ndarray]:
    import equinox as eqx
    import jax

    return [np.asarray(a) for a in jax.tree.leaves(eqx.filter(flow, eqx.is_array))]


def _with_arrays(flow: Any, arrays: Sequence[np.ndarray]) -> Any:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    params, static = eqx.partition(flow, eqx.is_array)
    leaves, tree = jax.tree.flatten(params)
    return eqx.combine(jax.tree.unflatten(tree, [jnp.asarray(a, leaf.dtype) for a, leaf in zip(arrays, leaves)]), static)


def _code_version() -> str:
    """lvenv's package version (``unknown`` where it is not installed) and, in a git checkout,
    the commit (``-dirty`` with local changes)."""
    try:
        version = importlib.metadata.version("lvenv")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    try:
        root = pathlib.Path(__file__).parent
        commit = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=root, capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return f"{version}+{commit}" if commit else version


#: Placeholder targets of the training patients (only their names reach
#: :func:`optim.identify.prior_sample`).
_TARGETS = {"EF": 0.6, "ET": 0.3, "IVRT": 0.08, "P_ao_dia": 10.0, "P_ao_mean": 12.5, "P_ao_pulse": 6.0}


def training_patients(bases: Sequence[str] = BASES) -> list[Patient]:
    """One patient per base preset, targeting :data:`OBSERVED` (the target values are unused:
    only their names reach :func:`optim.identify.prior_sample`)."""
    return [Patient(name, _base_heart(name), _TARGETS) for name in bases]


def _base_heart(name: str) -> Heart:
    if name not in BASES:
        raise InputError(f"base {name!r} is not a preset the estimator knows; choose from {BASES}")
    return getattr(presets, name)()


@functools.lru_cache(maxsize=4096)
def anatomy_heart(geometry: Geometry) -> Heart:
    """The heart of the :data:`ANATOMY` kind with this unloaded ``geometry``: the N preset with
    the anatomy regression's LO maps for it (:func:`lvenv.anatomy.predicted_maps`; cached, since
    :func:`covered_geometry` asks again for every patient, 2.6 ms a prediction)."""
    from lvenv.anatomy import predicted_maps

    return presets.normal().replace(geometry=geometry, lo=predicted_maps(geometry)[0])


def heart_kinds(bases: Sequence[str]) -> tuple[str, ...]:
    """``bases`` checked, in :data:`KINDS` order: distinct heart kinds of :data:`KINDS`, at least one;
    :class:`InputError` otherwise."""
    bases = tuple(bases)
    if not bases or any(b not in KINDS for b in bases) or len(set(bases)) != len(bases):
        raise InputError(f"bases = {list(bases)}: give distinct heart kinds of {list(KINDS)}")
    return tuple(k for k in KINDS if k in bases)


def _anatomy_box() -> dict[str, tuple[float, float]]:
    """The box the anatomy regression's training anatomies were sampled in (the campaign's,
    :data:`optim.campaign.BOX`), as the regression records it: where its maps are interpolated."""
    from lvenv.anatomy import load_regression

    return {name: (float(lo), float(hi)) for name, (lo, hi) in load_regression().box.items()}


def simulate(n: int, *, bases: Sequence[str] = BASES, heart_rate: tuple[float, float] = HEART_RATE, seed: int = 0, batch: int = 256) -> Any:
    """``n`` (parameters, noise-free observation) pairs from :func:`optim.identify.posterior`'s
    prior (:func:`optim.identify.prior_sample`) at heart rates uniform in ``heart_rate``
    (1/min), simulated ``batch`` at a time; failed members are left out and counted by status
    (``PriorSample.left_out``). ``bases``: the heart kinds (:data:`KINDS`), each with an equal
    share of the pairs: a pair of the presets is one of them at random, and the :data:`ANATOMY`
    kind draws one anatomy per :data:`PAIRS_PER_ANATOMY` pairs (uniform in the box, seed
    ``[seed, 7]``; its pairs' seed is ``seed +`` :data:`ANATOMY_SEED`). Each pair's ``base`` is
    its kind's index in :data:`KINDS`, its ``geometry`` its heart's."""
    n, kinds = integer("n", n, 1), heart_kinds(bases)
    preset_kinds = [k for k in kinds if k != ANATOMY]
    n_anatomy = n // len(kinds) if ANATOMY in kinds else 0
    parts = []
    if preset_kinds:
        part = prior_sample(n - n_anatomy, training_patients(preset_kinds), heart_rate=heart_rate, seed=seed, batch=batch)
        parts.append(dataclasses.replace(part, base=np.array([KINDS.index(preset_kinds[b]) for b in part.base], int)))
    if n_anatomy:
        box = _anatomy_box()
        rng = np.random.default_rng([seed, 7])
        count = -(-n_anatomy // PAIRS_PER_ANATOMY)
        shapes = rng.uniform([lo for lo, _ in box.values()], [hi for _, hi in box.values()], (count, len(box)))
        patients = [Patient(f"anatomy{j}", anatomy_heart(Geometry(**dict(zip(box, map(float, row))))), _TARGETS) for j, row in enumerate(shapes)]
        part = prior_sample(n_anatomy, patients, heart_rate=heart_rate, seed=seed + ANATOMY_SEED, batch=batch)
        parts.append(dataclasses.replace(part, base=np.full(len(part.base), KINDS.index(ANATOMY))))
    return PriorSample.concatenate(parts)


DRAWS_FORMAT = "lvenv-amortised-draws"


def save_draws(draws: PriorSample, path: str | pathlib.Path, *, seeds: Sequence[int], bases: Sequence[str] = BASES,
               heart_rate: tuple[float, float] = HEART_RATE) -> pathlib.Path:
    """Write simulated pairs (:func:`simulate` over ``bases`` and ``heart_rate``, made with the
    ``seeds`` given) to ``path``, an :mod:`lvenv.archive` ``.npz`` that :func:`load_draws` reads
    back: the training set of a long simulation survives an interruption."""
    arrays = {name: getattr(draws, name) for name in ARRAYS}
    meta = {"format": DRAWS_FORMAT, "names": list(draws.names), "tried": int(draws.tried), "left_out": dict(draws.left_out),
            "seeds": [int(v) for v in seeds], "prior": _prior_meta(bases, heart_rate), "code_version": _code_version()}
    return archive.save(path, arrays, meta)


def load_draws(path: str | pathlib.Path, *, bases: Sequence[str] | None = None,
               heart_rate: tuple[float, float] = HEART_RATE) -> tuple[PriorSample, list[int], str, tuple[str, ...]]:
    """The pairs :func:`save_draws` wrote to ``path``, the seeds they were made with, the code
    version that made them and their heart kinds; :class:`lvenv.archive.ArchiveError` if the file
    is not such pairs of :data:`OBSERVED`, or was drawn under another prior than this code's over
    its kinds (``bases``, if given, must be them) and ``heart_rate``. A file written before pairs
    carried their geometry gets it from its base presets."""
    arrays, meta = archive.load(path, "amortised training pairs")
    what = f"training pairs {str(path)!r}"
    if meta.get("format") != DRAWS_FORMAT or meta.get("names") != list(OBSERVED):
        raise ArchiveError(f"{what} are not {DRAWS_FORMAT!r} pairs of {list(OBSERVED)} (format {meta.get('format')!r}, targets {meta.get('names')})")
    recorded = (meta.get("prior") or {}).get("bases") if isinstance(meta.get("prior"), dict) else None
    try:
        kinds = heart_kinds(recorded if bases is None else bases)
        expected = _prior_meta(kinds, heart_rate)
    except (InputError, TypeError):
        raise ArchiveError(f"{what} were drawn over the heart kinds {recorded}, not kinds of {list(KINDS)}") from None
    if not _json_equal(meta.get("prior"), expected):
        raise ArchiveError(f"{what} were drawn under the prior {meta.get('prior')}, not this code's {expected}; simulate new ones")
    n = len(arrays.get("parameters", ()))
    if "geometry" not in arrays and ANATOMY not in kinds and "base" in arrays:
        shapes = np.array([_base_heart(k).geometry.as_tuple() for k in kinds])
        arrays["geometry"] = shapes[np.clip(arrays["base"].astype(int), 0, len(kinds) - 1)]
    shapes = {"parameters": (n, len(DEFAULT_ACTION_PARAMS)), "observations": (n, len(OBSERVED)), "heart_rate": (n,), "base": (n,),
              "geometry": (n, len(GEOMETRY))}
    if any(arrays.get(k) is None or arrays[k].shape != shape for k, shape in shapes.items()):
        raise ArchiveError(f"{what}: arrays {[(k, getattr(arrays.get(k), 'shape', None)) for k in shapes]} do not have the shapes {list(shapes.values())}")
    base = arrays["base"].astype(int)
    if not set(np.unique(base)) <= {KINDS.index(k) for k in kinds}:
        raise ArchiveError(f"{what}: pairs of heart kinds {sorted({KINDS[b] for b in np.unique(base) if 0 <= b < len(KINDS)})} outside the file's {list(kinds)}")
    draws = PriorSample(arrays["parameters"], arrays["observations"], arrays["heart_rate"], base, arrays["geometry"], tuple(OBSERVED),
                        int(meta["tried"]), {str(k): int(v) for k, v in meta["left_out"].items()})
    return draws, [int(v) for v in meta["seeds"]], str(meta.get("code_version")), kinds


def _noise_sd(noise: Mapping[str, Any]) -> np.ndarray:
    """σ of each :data:`OBSERVED` target (internal units); relative errors are not supported."""

    relative = [k for k in OBSERVED if isinstance(noise.get(k), Relative)]
    if relative:
        raise InputError(f"the amortised estimator takes absolute measurement errors only; {relative} are relative")
    return measurement_sd(dict.fromkeys(OBSERVED, 1.0), noise)


def covered_geometry(heart: Heart, bases: Sequence[str]) -> np.ndarray:
    """The unloaded geometry (:data:`GEOMETRY`, (6,)) of ``heart`` if an estimator over the heart
    kinds ``bases`` covers it, up to the six parameters and the heart rate: one of its base
    presets, or, with :data:`ANATOMY`, the N preset with a geometry inside the anatomy box and the
    maps the anatomy regression predicts for it (:func:`anatomy_heart`). :class:`InputError`
    saying why not otherwise."""
    free = (*DEFAULT_ACTION_PARAMS, "HR")
    same = lambda other: heart.replace(**{k: heart.get(k) for k in free}) == other.replace(**{k: heart.get(k) for k in free})
    row = np.array(heart.geometry.as_tuple())
    for name in bases:
        if name != ANATOMY and same(_base_heart(name)):
            return row
    if ANATOMY in bases:
        box = _anatomy_box()
        outside = [f"{k} = {getattr(heart.geometry, k):g} outside [{lo:g}, {hi:g}]" for k, (lo, hi) in box.items() if not lo <= getattr(heart.geometry, k) <= hi]
        if outside:
            raise InputError(f"the patient's geometry is outside the amortised estimator's anatomy box ({'; '.join(outside)}); use optim.identify.posterior")
        if same(anatomy_heart(heart.geometry)):
            return row
    kinds = [b for b in bases if b != ANATOMY] + (["the N preset with any geometry in the anatomy box and its regression maps"] if ANATOMY in bases else [])
    raise InputError(f"the patient's heart is none of the estimator's hearts ({'; '.join(kinds)}; up to {free}); "
                     "the amortised posterior covers only those: use optim.identify.posterior")


def observations(patient: Patient) -> np.ndarray:
    """The patient's :data:`OBSERVED` targets (internal units), NaN where missing;
    :class:`InputError` if it has a target the estimator does not condition on."""
    extra = [k for k in patient.targets if k not in OBSERVED]
    if extra:
        raise InputError(f"patient {patient.name!r} has target(s) {extra} the amortised estimator does not condition on "
                         f"(it takes any subset of {OBSERVED}); drop them or use optim.identify.posterior")
    return np.array([float(patient.targets.get(k, np.nan)) for k in OBSERVED])


def _mixture_log_density(weights: np.ndarray, means: np.ndarray, covariances: np.ndarray, y: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """log Σ_j w_j N(y_m; μ_j,m, Σ_j,mm) of rows ``y`` (n, 6) over the columns ``mask`` (6,) bool."""
    from scipy.special import logsumexp
    from scipy.stats import multivariate_normal

    m = np.flatnonzero(mask)
    per = np.stack([np.log(w) + multivariate_normal(mu[m], cov[np.ix_(m, m)]).logpdf(y[:, m]).reshape(len(y))
                    for w, mu, cov in zip(weights, means, covariances)], axis=1)
    return logsumexp(per, axis=1)


def _mask_code(mask: np.ndarray) -> np.ndarray:
    """Integer code Σ_k 2^k mask_k of each row's mask (1 … 63)."""
    return (np.asarray(mask, int) * (1 << np.arange(len(OBSERVED)))).sum(axis=-1)


@dataclasses.dataclass(frozen=True)
class Estimator:
    """A trained amortised posterior: the flow, the normalisation, the out-of-distribution
    mixture and its thresholds, and the artefact's metadata (module docstring)."""

    flow: Any
    architecture: Architecture
    arrays: dict[str, np.ndarray]  # normalisation and mixture (names as in the artefact)
    meta: dict[str, Any]

    @property
    def bases(self) -> tuple[str, ...]:
        return tuple(self.meta["prior"]["bases"])

    @property
    def heart_rate(self) -> tuple[float, float]:
        return tuple(self.meta["prior"]["heart_rate"])

    def condition(self, obs: np.ndarray, heart_rate: np.ndarray, geometry: np.ndarray) -> np.ndarray:
        """Condition vectors (n, len(:data:`CONDITION`)) of observations ``obs`` (n, 6; NaN where
        missing, internal units), heart rates (n,) 1/min and unloaded geometries (n, 6;
        :data:`GEOMETRY`, mm and degrees)."""
        mask = np.isfinite(obs)
        y = np.where(mask, (obs - self.arrays["obs_mean"]) / self.arrays["obs_sd"], 0.0)
        rest = np.column_stack([heart_rate, np.asarray(geometry, float).reshape(len(obs), len(GEOMETRY))])
        return np.column_stack([y, mask, (rest - self.arrays["rest_mean"]) / self.arrays["rest_sd"]])

    def out_of_distribution(self, obs: np.ndarray, heart_rate: np.ndarray) -> list[str]:
        """Per row of ``obs`` (n, 6; NaN where missing) and ``heart_rate`` (n,): ``""`` if in
        distribution, else why not (module docstring)."""
        mask = np.isfinite(obs)
        y = (np.where(mask, obs, 0.0) - self.arrays["obs_mean"]) / self.arrays["obs_sd"]
        lo, hi = self.heart_rate
        reasons = [f"heart rate {h:g}/min outside the training range {lo:g}–{hi:g}" if not lo <= h <= hi else "" for h in heart_rate]
        codes = _mask_code(mask)
        for code in np.unique(codes):
            rows = np.flatnonzero(codes == code)
            density = _mixture_log_density(self.arrays["ood_weights"], self.arrays["ood_means"], self.arrays["ood_covariances"], y[rows], mask[rows[0]])
            threshold = self.arrays["ood_threshold"][code]
            for r, d in zip(rows, density):
                if d < threshold:
                    text = f"observation log density {d:.3g} below the training set's {OOD_QUANTILE:g} quantile {threshold:.3g}"
                    reasons[r] = "; ".join(filter(None, [reasons[r], text]))
        return reasons

    @functools.cached_property
    def _sampler(self) -> Any:
        """The jitted draw (key, conditions (n, C), n_samples) → (n, n_samples, 6) standardised
        logit coordinates, float32, :data:`SAMPLE_BLOCK` rows at a time (``lax.map``), compiled
        once per estimator and shape."""
        import jax
        import jax.numpy as jnp
        import paramax

        base = paramax.unwrap(self.flow).base_dist
        loc, scale = (jnp.asarray(a, jnp.float32) for a in (base.loc, base.scale))
        inverse = _coupling_inverse(self.flow, jnp.float32)

        def block(key: jax.Array, cond: jax.Array, n_samples: int) -> jax.Array:
            eps = loc + scale * jax.random.normal(key, (cond.shape[0], n_samples, loc.shape[0]), jnp.float32)
            return inverse(eps, cond)

        def draw(key: jax.Array, cond: jax.Array, n_samples: int) -> jax.Array:
            blocks = cond.reshape(-1, SAMPLE_BLOCK, cond.shape[-1])
            z = jax.lax.map(lambda kc: block(*kc, n_samples), (jax.random.split(key, len(blocks)), blocks))
            return z.reshape(-1, n_samples, loc.shape[0])

        return jax.jit(draw, static_argnums=2)

    def sample(self, obs: np.ndarray, heart_rate: np.ndarray, geometry: np.ndarray, n_samples: int, seed: int = 0) -> np.ndarray:
        """``n_samples`` posterior draws per row: (n, n_samples, 6), physical units, columns
        :data:`DEFAULT_ACTION_PARAMS`. One jitted pass over all rows (:func:`_coupling_inverse`,
        float32); a row's draws depend on ``seed`` and on its block of :data:`SAMPLE_BLOCK` rows."""
        import jax

        cond = self.condition(obs, heart_rate, geometry)
        n = len(cond)
        padded = np.concatenate([cond, np.repeat(cond[-1:], -n % SAMPLE_BLOCK, axis=0)]).astype(np.float32)
        z = np.asarray(self._sampler(jax.random.key(seed), padded, integer("n_samples", n_samples, 1))[:n], np.float64)
        z = z * self.arrays["theta_sd"] + self.arrays["theta_mean"]
        return ParameterSpace.for_names(DEFAULT_ACTION_PARAMS).from_unit(from_logit(z))

    def log_density(self, x: np.ndarray, obs: np.ndarray, heart_rate: np.ndarray, geometry: np.ndarray) -> np.ndarray:
        """log q(u | c) of physical parameters ``x`` (n, 6) given each row's condition: the flow's
        density in the unit-cube coordinates u of the identification bounds (log scale on log
        axes), where :func:`optim.identify.log_density` gives the posterior's, so that their
        difference is an importance weight. log q(u) = log q_z(z) − Σ_k [log sd_k + log u_k +
        log(1 − u_k)], z = (logit u − mean) / sd the flow's standardised coordinates."""
        import paramax

        u = np.clip(ParameterSpace.for_names(DEFAULT_ACTION_PARAMS).to_unit(x), LOGIT_EDGE, 1.0 - LOGIT_EDGE)
        z = (to_logit(u) - self.arrays["theta_mean"]) / self.arrays["theta_sd"]
        log_q = np.asarray(paramax.unwrap(self.flow).log_prob(z, self.condition(obs, heart_rate, geometry)), np.float64)
        return log_q - np.sum(np.log(self.arrays["theta_sd"]) + np.log(u) + np.log1p(-u), axis=1)


#: Rows of conditions per block of the jitted draw (:meth:`Estimator.sample`): a block's
#: intermediates (rows × samples × spline knots) stay in cache, which on a CPU is faster than one
#: pass over every row (measured: 1,000 rows × 1,000 draws, 8 → 5 s CPU, 1,000 → 17 s).
SAMPLE_BLOCK = 8
#: Minimum knot derivative of flowjax's ``RationalQuadraticSpline`` (its default, which
#: :meth:`Architecture.build` keeps); :func:`_coupling_inverse` needs it.
_MIN_DERIVATIVE = 1e-3


def _coupling_inverse(flow: Any, dtype: Any) -> Any:
    """The flow's bijection, base → parameters (flowjax's ``Invert(Scan(Coupling, Permute))``),
    as one batched function ``(eps (n, s, 6), cond (n, C)) → z (n, s, 6)`` in ``dtype``: the same
    arithmetic as ``flow.bijection.transform`` per draw (Durkan et al. 2019, the rational-quadratic
    spline's inverse, their eq. 6–8), laid out for a CPU: each coupling layer's conditioner is three
    matrix products over all draws, the conditions' share of its first layer computed once per row,
    and the spline's knots lie along the leading axis, its bin picked by comparison (no gathers).
    flowjax's own vectorised path evaluates the knots draw by draw and is 3× slower."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import paramax
    from jax.flatten_util import ravel_pytree

    flow = paramax.unwrap(flow)
    coupling, permute = flow.bijection.bijection.bijection.bijections
    inverse = np.asarray(permute.inverse_permutation[0])
    weights = [jnp.asarray(layer.weight, dtype) for layer in coupling.conditioner.layers]
    biases = [jnp.asarray(layer.bias, dtype) for layer in coupling.conditioner.layers]
    kept, dim = coupling.untransformed_dim, coupling.dim
    spline = coupling.transformer_constructor(jnp.zeros(weights[-1].shape[1] // (dim - kept)))
    init = ravel_pytree(eqx.filter(spline, eqx.is_inexact_array))[0].astype(dtype)
    lo, hi = spline.interval
    widths, min_width = spline.x_pos.arr.shape[-1], spline.x_pos.min_width
    cumulative = jnp.tril(jnp.ones((widths - 1, widths - 1), dtype))

    def positions(a: jax.Array) -> jax.Array:
        """Knot positions (widths + 1, m) from unconstrained (widths, m): paramax's RealToIncreasingOnInterval."""
        w = min_width + (hi - lo - min_width * widths) * jax.nn.softmax(a, axis=0)
        edge = jnp.ones((1, a.shape[1]), dtype)
        return jnp.concatenate([lo * edge, lo + cumulative @ w[:-1], hi * edge])

    def transform(eps: jax.Array, cond: jax.Array) -> jax.Array:
        y = eps.astype(dtype)
        c = cond.astype(dtype)
        rows, draws = y.shape[:2]
        for layer in reversed(range(weights[0].shape[0])):
            y = y[..., inverse[layer]]
            fixed, moved = y[..., :kept], y[..., kept:].reshape(-1)
            first = weights[0][layer]
            h = fixed @ first[:, :kept].T + (c @ first[:, kept:].T + biases[0][layer])[:, None, :]
            for w, b in zip(weights[1:], biases[1:]):
                h = jax.nn.relu(h) @ w[layer].T + b[layer]
            p = (h.reshape(rows * draws, dim - kept, -1) + init).transpose(2, 0, 1).reshape(len(init), -1)
            xp, yp = positions(p[:widths]), positions(p[widths:2 * widths])
            deriv = jax.nn.softplus(p[2 * widths:]) + _MIN_DERIVATIVE
            inside = (moved >= lo) & (moved <= hi)
            v = jnp.clip(moved, lo, hi)
            k = jnp.clip(jnp.sum(yp < v, axis=0) - 1, 0, widths - 1)
            onehot = (jnp.arange(widths)[:, None] == k).astype(dtype)
            xk, xk1, yk, yk1, dk, dk1 = (jnp.sum(onehot * a[o:o + widths], axis=0) for a in (xp, yp, deriv) for o in (0, 1))
            sk = (yk1 - yk) / (xk1 - xk)
            shift = (v - yk) * (dk1 + dk - 2 * sk)
            qa, qb, qc = (yk1 - yk) * (sk - dk) + shift, (yk1 - yk) * dk - shift, -sk * (v - yk)
            xi = 2 * qc / (-qb - jnp.sqrt(qb * qb - 4 * qa * qc))
            x = jnp.where(inside, jnp.clip(xi * (xk1 - xk) + xk, lo, hi), moved)
            y = jnp.concatenate([fixed, x.reshape(rows, draws, dim - kept)], axis=-1)
        return y

    return transform


def _noisy_masked(clean: np.ndarray, sigma: np.ndarray, rng: np.random.Generator, common_share: float) -> np.ndarray:
    """Observations with Gaussian noise σ, masked (NaN where missing): a share ``common_share`` of
    the rows with one of :data:`COMMON_MASKS` (uniformly), the others with each target dropped
    with probability :data:`MISSING`."""
    noisy = clean + sigma * rng.standard_normal(clean.shape)
    mask = rng.random(clean.shape) >= MISSING
    common = np.flatnonzero(rng.random(len(clean)) < common_share)
    sets = np.array([[k in targets for k in OBSERVED] for targets in COMMON_MASKS])
    mask[common] = sets[rng.integers(len(sets), size=len(common))]
    empty = ~mask.any(axis=1)
    mask[np.flatnonzero(empty), rng.integers(len(OBSERVED), size=int(empty.sum()))] = True
    return np.where(mask, noisy, np.nan)


def _prior_meta(bases: Sequence[str], heart_rate: tuple[float, float]) -> dict[str, Any]:
    """The prior as the metadata records it; with :data:`ANATOMY`, also the anatomy box and the
    anatomy regression's identity (its dataset's SHA-256 and its count of training anatomies), which set those hearts."""
    meta = {"bounds": {n: [ACTION_BOUNDS[n].lo, ACTION_BOUNDS[n].hi, ACTION_BOUNDS[n].log] for n in DEFAULT_ACTION_PARAMS},
            "plausibility": [b.describe() for b in resolve_bands(True)], "heart_rate": list(heart_rate), "bases": list(bases)}
    if ANATOMY in bases:
        from lvenv.anatomy import load_regression

        regression = load_regression()
        meta["anatomy"] = {"box": {k: list(v) for k, v in _anatomy_box().items()},
                           "regression": {"dataset_sha256": regression.provenance.get("dataset_sha256"), "anatomies": len(regression.ids)}}
    return meta


def train(
    draws: Any,
    *,
    bases: Sequence[str] = BASES,
    heart_rate: tuple[float, float] = HEART_RATE,
    noise: Mapping[str, Any] | None = None,
    architecture: Architecture = Architecture(),
    seed: int = 0,
    copies: int = 1,
    val_prop: float = 0.1,
    batch_size: int = 512,
    learning_rate: float = 1e-3,
    max_epochs: int = 200,
    patience: int = 10,
    plateau: int = 3,
    decay: float = 0.5,
    max_seconds: float = float("inf"),
    common_share: float = COMMON_SHARE,
    code_version: str | None = None,
    progress: Callable[[int, float, float, float], None] | None = None,
) -> Estimator:
    """Train an estimator on ``draws`` (an :class:`optim.identify.PriorSample` of
    :data:`OBSERVED` over ``bases`` and ``heart_rate``, e.g. from :func:`simulate`), each pair
    used ``copies`` times per epoch, each time with fresh noise and masks (a share ``common_share`` of
    them one of :data:`COMMON_MASKS`; module docstring). The
    first ``val_prop`` of the shuffled pairs, each with all its copies, are the validation set
    (:func:`_validation_first`; their noise drawn once); Adam (``learning_rate``, gradients
    clipped to norm 10, the rate times ``decay`` after every ``plateau`` epochs without a better
    validation loss) on minibatches of ``batch_size`` for at most ``max_epochs`` epochs, stopping
    after ``patience`` epochs without a better validation loss or once ``max_seconds`` have
    passed at an epoch's end, and keeping the epoch with the best validation loss. ``code_version``: for
    the metadata (default: lvenv's version and git commit, where known). ``progress(epoch, train
    loss, validation loss, learning rate)`` is called after every epoch."""
    from sklearn.mixture import GaussianMixture


    if tuple(draws.names) != OBSERVED:
        raise InputError(f"the draws observe {draws.names}; the estimator needs {OBSERVED}")
    kinds = heart_kinds(bases)
    if stray := sorted({KINDS[b] for b in np.unique(draws.base)} - set(kinds)):
        raise InputError(f"the draws hold hearts of kinds {stray} that bases = {list(kinds)} leave out")
    seed, copies = integer("seed", seed, 0), integer("copies", copies, 1)
    val_prop = real("val_prop", val_prop, 0.0, 0.5, lo_open=True)
    decay = real("decay", decay, 0.0, 1.0, lo_open=True)
    common_share = real("common_share", common_share, 0.0, 1.0)
    sigma = _noise_sd(NOISE if noise is None else noise)
    rng = np.random.default_rng(seed)
    x, clean = np.tile(draws.parameters, (copies, 1)), np.tile(draws.observations, (copies, 1))
    obs = _noisy_masked(clean, sigma, rng, common_share)
    hr, geometry = np.tile(draws.heart_rate, copies), np.tile(draws.geometry, (copies, 1))
    order, n_val = _validation_first(len(draws.parameters), copies, val_prop, rng)
    x, clean, obs, hr, geometry = x[order], clean[order], obs[order], hr[order], geometry[order]
    z = to_logit(ParameterSpace.for_names(DEFAULT_ACTION_PARAMS).to_unit(x))
    rest = np.column_stack([hr, geometry])
    rest_sd = rest.std(axis=0)
    arrays = {"theta_mean": z.mean(axis=0), "theta_sd": z.std(axis=0), "obs_mean": np.nanmean(obs, axis=0), "obs_sd": np.nanstd(obs, axis=0),
              "rest_mean": rest.mean(axis=0), "rest_sd": np.where(rest_sd > 0, rest_sd, 1.0)}
    meta = {"format": FORMAT, "version": VERSION, "parameters": list(DEFAULT_ACTION_PARAMS), "observed": list(OBSERVED), "condition": list(CONDITION),
            "prior": _prior_meta(kinds, heart_rate), "noise": dict(zip(OBSERVED, map(float, sigma))),
            "architecture": dataclasses.asdict(architecture)}
    estimator = Estimator(architecture.build(seed), architecture, arrays, meta)
    theta, val_cond = (z - arrays["theta_mean"]) / arrays["theta_sd"], estimator.condition(obs[:n_val], hr[:n_val], geometry[:n_val])

    def fresh_condition(generator: np.random.Generator) -> np.ndarray:
        return estimator.condition(_noisy_masked(clean[n_val:], sigma, generator, common_share), hr[n_val:], geometry[n_val:])

    started = time.perf_counter()
    flow, losses = _fit(estimator.flow, (theta[n_val:], fresh_condition), (theta[:n_val], val_cond), seed=seed, batch_size=batch_size,
                        learning_rate=learning_rate, max_epochs=max_epochs, patience=patience, plateau=plateau, decay=decay, max_seconds=max_seconds,
                        progress=progress)
    seconds = time.perf_counter() - started
    # The out-of-distribution mixture: fitted to fresh noisy full observations of the pairs; the
    # thresholds come from the first val_prop of them, left out of the fit.
    full = draws.observations + sigma * rng.standard_normal(draws.observations.shape)
    y = (full - arrays["obs_mean"]) / arrays["obs_sd"]
    n_val = max(1, int(val_prop * len(y)))
    y = y[: n_val + OOD_FIT_ROWS]
    gmm = GaussianMixture(min(OOD_COMPONENTS, max(1, (len(y) - n_val) // 50)), covariance_type="full", reg_covar=1e-4, random_state=seed)
    gmm.fit(y[n_val:])
    threshold = np.zeros(1 << len(OBSERVED))  # code 0, no target, never occurs
    for code in range(1, 1 << len(OBSERVED)):
        mask = (code >> np.arange(len(OBSERVED))) & 1 == 1
        threshold[code] = np.quantile(_mixture_log_density(gmm.weights_, gmm.means_, gmm.covariances_, y[:n_val], mask), OOD_QUANTILE)
    arrays.update(ood_weights=gmm.weights_, ood_means=gmm.means_, ood_covariances=gmm.covariances_, ood_threshold=threshold)
    meta["training"] = {"pairs": int(len(draws.parameters)), "copies": copies, "tried": int(draws.tried), "left_out": dict(draws.left_out),
                        "seed": seed, "val_prop": val_prop, "batch_size": batch_size, "learning_rate": learning_rate, "plateau": plateau, "decay": decay,
                        "masks": {"missing": MISSING, "common": [list(t) for t in COMMON_MASKS], "common_share": common_share},
                        "epochs": len(losses["train"]), "seconds": seconds, "train_loss": losses["train"], "validation_loss": losses["val"],
                        "learning_rates": losses["rate"],
                        "best_validation_loss": float(min(losses["val"]))}
    meta["code_version"] = code_version or _code_version()
    return Estimator(flow, architecture, arrays, meta)


def _validation_first(n_pairs: int, copies: int, val_prop: float, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """(order, n_val): a shuffle of the ``copies * n_pairs`` rows of :func:`train` (row i holds
    pair i mod n_pairs) whose first n_val rows are every copy of the first
    max(1, int(val_prop n_pairs)) pairs met in the shuffle. No pair is in both sets with only its
    noise changed, which would leak training pairs into the early stopping. One copy: the
    shuffle itself, split at n_val."""
    order = rng.permutation(copies * n_pairs)
    pair = order % n_pairs
    met = pair[np.sort(np.unique(pair, return_index=True)[1])]
    held = np.zeros(n_pairs, dtype=bool)
    held[met[: max(1, int(val_prop * n_pairs))]] = True
    validation = held[pair]
    return np.concatenate([order[validation], order[~validation]]), int(np.count_nonzero(validation))


def _fit(flow: Any, train_set: tuple[np.ndarray, Callable[[np.random.Generator], np.ndarray]], val_set: tuple[np.ndarray, np.ndarray], *, seed: int,
         batch_size: int, learning_rate: float, max_epochs: int, patience: int, plateau: int, decay: float,
         max_seconds: float, progress: Callable[[int, float, float, float], None] | None) -> tuple[Any, dict[str, list[float]]]:
    """Maximum likelihood of ``flow`` on ``train_set`` (θ, and a function of a generator that draws
    the rows' conditions c afresh each epoch) with early stopping on (θ, c) ``val_set`` and the
    learning rate times ``decay`` after every ``plateau`` epochs without improvement
    (:func:`train`, also for ``progress``); each epoch is one jitted ``lax.scan`` over its
    minibatches. Returns the best flow and the per-epoch mean losses (−log q, nats) and learning rates."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optax
    import paramax

    batch_size = integer("batch_size", batch_size, 1)
    max_epochs, patience, plateau = integer("max_epochs", max_epochs, 1), integer("patience", patience, 1), integer("plateau", plateau, 1)
    params, static = eqx.partition(flow, eqx.is_inexact_array, is_leaf=lambda leaf: isinstance(leaf, paramax.NonTrainable))
    optimizer = optax.chain(optax.clip_by_global_norm(10.0), optax.scale_by_adam())
    opt_state = optimizer.init(params)

    def loss(p: Any, theta: jax.Array, cond: jax.Array) -> jax.Array:
        return -jnp.mean(paramax.unwrap(eqx.combine(p, static)).log_prob(theta, cond))

    @jax.jit
    def epoch(p: Any, state: Any, rate: jax.Array, theta: jax.Array, cond: jax.Array) -> tuple[Any, Any, jax.Array]:
        def body(carry: Any, batch: tuple[jax.Array, jax.Array]) -> tuple[Any, jax.Array]:
            p, state = carry
            value, grads = jax.value_and_grad(loss)(p, *batch)
            updates, state = optimizer.update(grads, state, p)
            return (optax.apply_updates(p, jax.tree.map(lambda u: -rate * u, updates)), state), value

        (p, state), values = jax.lax.scan(body, (p, state), (theta, cond))
        return p, state, jnp.mean(values)

    @jax.jit
    def validation(p: Any, theta: jax.Array, cond: jax.Array) -> jax.Array:
        return jax.lax.map(lambda batch: loss(p, *batch), (theta, cond)).mean()

    def batched(a: np.ndarray, size: int) -> jax.Array:
        count = max(1, len(a) // size)
        return jnp.asarray(a[: count * size].reshape(count, size, *a.shape[1:]))

    theta, condition = train_set
    size = min(batch_size, len(theta))
    val_size = min(4 * size, len(val_set[0]))
    val = (batched(val_set[0], val_size), batched(val_set[1], val_size))
    rng = np.random.default_rng(seed)
    best, rate, losses = params, learning_rate, {"train": [], "val": [], "rate": []}
    started = time.perf_counter()
    for _ in range(max_epochs):
        cond, order = condition(rng), rng.permutation(len(theta))
        params, opt_state, value = epoch(params, opt_state, jnp.asarray(rate), batched(theta[order], size), batched(cond[order], size))
        losses["train"].append(float(value))
        losses["val"].append(float(validation(params, *val)))
        losses["rate"].append(rate)
        if progress is not None:
            progress(len(losses["val"]), losses["train"][-1], losses["val"][-1], rate)
        stale = len(losses["val"]) - 1 - int(np.argmin(losses["val"]))
        if stale == 0:
            best = params
        elif stale >= patience:
            break
        elif stale % plateau == 0:
            rate *= decay
        if time.perf_counter() - started > max_seconds:
            break
    return eqx.combine(best, static), losses


_ARRAY_NAMES = ("theta_mean", "theta_sd", "obs_mean", "obs_sd", "rest_mean", "rest_sd", "ood_weights", "ood_means", "ood_covariances", "ood_threshold")


def save(estimator: Estimator, path: str | pathlib.Path) -> pathlib.Path:
    """Write ``estimator`` to ``path`` as an :mod:`lvenv.archive` ``.npz`` (module docstring)."""
    flow = {f"flow_{j:03d}": a for j, a in enumerate(_arrays_of(estimator.flow))}
    return archive.save(path, {**flow, **estimator.arrays}, estimator.meta)


def load(path: str | pathlib.Path = DEFAULT_ARTEFACT) -> Estimator:
    """The estimator stored at ``path`` (default: the shipped one), checked against this code
    (module docstring); :class:`lvenv.archive.ArchiveError` saying what is wrong otherwise."""

    path = pathlib.Path(path)
    if not path.exists():
        raise ArchiveError(f"no trained amortised estimator at {str(path)!r}; train one with scripts/train_amortised.py")
    arrays, meta = archive.load(path, "amortised estimator")
    what = f"amortised estimator {str(path)!r}"
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ArchiveError(f"{what} has format {meta.get('format')!r} version {meta.get('version')!r}; this code reads {FORMAT!r} version {VERSION}")
    expected = {"parameters": list(DEFAULT_ACTION_PARAMS), "observed": list(OBSERVED), "condition": list(CONDITION)}
    for key, value in expected.items():
        if meta.get(key) != value:
            raise ArchiveError(f"{what} was trained with {key} {meta.get(key)}, not {value}; retrain it (scripts/train_amortised.py)")
    prior = meta.get("prior")
    if not isinstance(prior, dict) or not isinstance(prior.get("bases"), list) or not isinstance(prior.get("heart_rate"), list):
        raise ArchiveError(f"{what} has no valid prior in its metadata")
    try:
        current = _prior_meta(heart_kinds(prior["bases"]), tuple(prior["heart_rate"]))
    except (InputError, TypeError, ValueError):
        current = None
    if current is None or not _json_equal(prior, current):
        raise ArchiveError(f"{what} was trained under the prior {prior}, but this code's is {current}; retrain it (scripts/train_amortised.py)")
    sigma = dict(zip(OBSERVED, map(float, _noise_sd(NOISE))))
    if meta.get("noise") != sigma:
        raise ArchiveError(f"{what} was trained with the noise σ {meta.get('noise')}, but optim.identify.NOISE gives {sigma}; retrain it")
    try:
        architecture = Architecture(**meta["architecture"])
        flow = architecture.build()
    except (KeyError, TypeError, ValueError, InputError) as err:
        raise ArchiveError(f"{what} has no valid architecture ({type(err).__name__}: {err})") from None
    like = _arrays_of(flow)
    names = [f"flow_{j:03d}" for j in range(len(like))]
    missing = [k for k in (*names, *_ARRAY_NAMES) if k not in arrays]
    unknown = sorted(set(arrays) - set(names) - set(_ARRAY_NAMES))
    if missing or unknown:
        raise ArchiveError(f"{what} lacks the arrays {missing} or has unexpected ones {unknown}: not an artefact of this architecture")
    for name, a in zip(names, like):
        if arrays[name].shape != a.shape:
            raise ArchiveError(f"{what}: array {name} has shape {arrays[name].shape}, the architecture needs {a.shape}")
    bad = [k for k, v in arrays.items() if v.dtype.kind not in "fiub" or not np.all(np.isfinite(v))]
    if bad:
        raise ArchiveError(f"{what}: arrays {bad} are not finite numbers")
    return Estimator(_with_arrays(flow, [arrays[n] for n in names]), architecture, {k: arrays[k] for k in _ARRAY_NAMES}, meta)


def held_out_patients(estimator: Estimator, n: int, seed: int, targets: Sequence[str] = HELD_OUT_TARGETS,
                      bases: Sequence[str] | None = None) -> tuple[list[Patient], np.ndarray, int]:
    """``n`` simulated truths from the prior over ``estimator``'s heart kinds (or the ``bases``
    given among them) and heart-rate range (:func:`simulate`, seed ``seed + 1000``, which
    training did not use), each a patient whose ``targets`` carry the noise of
    :data:`optim.identify.NOISE` (``numpy`` seed ``seed``). Returns the patients, their true
    parameters (m, 6; physical units, columns :data:`DEFAULT_ACTION_PARAMS`) and how many truths
    were skipped because the noise pushed a target outside its metric's range."""
    kinds = estimator.bases if bases is None else heart_kinds(bases)
    if stray := sorted(set(kinds) - set(estimator.bases)):
        raise InputError(f"bases {stray} are not among the estimator's heart kinds {list(estimator.bases)}")
    draws = simulate(n, bases=kinds, heart_rate=estimator.heart_rate, seed=seed + 1000, batch=128)
    sigma = measurement_sd(dict.fromkeys(OBSERVED, 1.0), NOISE)
    noisy = draws.observations + sigma * np.random.default_rng(seed).standard_normal(draws.observations.shape)
    columns = [OBSERVED.index(k) for k in targets]
    patients, truths = [], []
    for j in range(len(noisy)):
        kind = KINDS[draws.base[j]]
        heart = anatomy_heart(Geometry(**dict(zip(GEOMETRY, map(float, draws.geometry[j]))))) if kind == ANATOMY else _base_heart(kind)
        try:
            patients.append(Patient(f"truth{j}", heart.replace(HR=float(draws.heart_rate[j])), {k: float(noisy[j, c]) for k, c in zip(targets, columns)}))
        except InputError:  # noise pushed a target outside its metric's range
            continue
        truths.append(draws.parameters[j])
    return patients, np.array(truths).reshape(-1, len(DEFAULT_ACTION_PARAMS)), len(noisy) - len(patients)


def _json_equal(a: Any, b: Any) -> bool:
    """Whether two JSON-able values are equal after a JSON round trip (tuples as lists)."""
    import json

    return json.loads(json.dumps(a)) == json.loads(json.dumps(b))
