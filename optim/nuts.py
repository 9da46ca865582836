"""No-U-Turn sampling of a patient's posterior with gradients through the LO heart.

The log-posterior of :mod:`optim.identify` (Gaussian measurement errors :data:`~optim.identify.NOISE`,
the bands' prior factor, uniform in the unit cube u of the identification bounds) is written in
whitened logit coordinates w, z = logit(u) = m + L w, with m and L L^T the mean and covariance of
pilot draws (the ensemble pilot of :func:`optim.identify.posterior`):

    log p(w) = −½ Σ_k ((o_k − t_k) / σ_k)² − ½ Σ_b (d_b / s)² + Σ_i log(u_i (1 − u_i)) + const,

the last sum being the Jacobian of the logit. Its gradient comes from :func:`lvenv.jacobian`
(forward mode through one beat at the periodic steady state, the implicit-function theorem for
the rest) and the chain rule through the unit-cube map. The value and the gradient are computed
together on the host, for all chains at once, and enter JAX through ``jax.pure_callback`` with a
custom VJP, so BlackJAX's NUTS (Hoffman & Gelman, JMLR 15:1593, 2014) runs ``vmap``-ped over
the chains and each leapfrog step of all chains is one batched steady-state and tangent
computation. A member without a usable steady state has log p = −∞ (the trajectory counts as
divergent and is not taken).

Adaptation: the whitening takes the place of the mass matrix (identity in w). Each chain tunes
its own step size by dual averaging (Hoffman & Gelman §3.2.1, target acceptance 0.8) during
``warmup`` iterations whose draws are dropped; the step size is then frozen at the averaged
value. The fixed-step log-density is continuous but not smooth at the integrator's grid scale:
the gradient has kinks where a valve event passes a step (:mod:`lvenv.sensitivity`), and the
value wobbles about a smooth trend by at most 0.011 between neighbouring points 0.02 % apart at
500 steps per beat on N (:mod:`optim.identify.sampler`). Energy errors from them lower the acceptance and
the adapted step size, and cost longer trees, but do not bias the chains: NUTS weighs the
trajectory's states by the exact log-density. Cost and measurements: README, "Posterior".
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

import lvenv
from lvenv.identification import ParameterSpace, from_logit
from lvenv.patients import Patient
from lvenv.plausibility import Band, distance, distance_slope

__all__ = ["LogDensity", "as_jax", "run_nuts", "TARGET_ACCEPTANCE"]

#: Dual averaging's target mean acceptance (Stan's default).
TARGET_ACCEPTANCE = 0.8


class LogDensity:
    """log p(w) and its gradient at whitened points ``w`` (n, d), all members in one
    :func:`lvenv.jacobian` call (module docstring). Counts its evaluations."""

    def __init__(self, patient: Patient, space: ParameterSpace, sigma: np.ndarray, bands: Sequence[Band], band_sd: float,
                 mean: np.ndarray, chol: np.ndarray, steps_per_beat: int, max_beats: int) -> None:
        self.patient, self.space, self.bands, self.band_sd = patient, space, tuple(bands), band_sd
        self.targets = tuple(patient.targets)
        self.t = np.array(list(patient.targets.values()))
        self.sigma = np.asarray(sigma, float)
        self.metrics = tuple(dict.fromkeys([*self.targets, *(b.metric for b in self.bands)]))
        self.mean, self.chol = np.asarray(mean, float), np.asarray(chol, float)
        self.settings = {"steps_per_beat": steps_per_beat, "max_beats": max_beats}
        self.evaluations = self.failed = self.calls = 0

    def unit(self, w: np.ndarray) -> np.ndarray:
        """Unit-cube points of whitened points ``w`` (n, d)."""
        return from_logit(self.mean + np.asarray(w, float) @ self.chol.T)

    def __call__(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = np.asarray(w, float)
        shape, d = w.shape[:-1], w.shape[-1]
        w = w.reshape(-1, d)
        u = self.unit(w)
        x = self.space.from_unit(u)
        hearts = [self.patient.heart.replace(**dict(zip(self.space.names, map(float, row)))) for row in x]
        jac = lvenv.jacobian(hearts, wrt=self.space.names, metrics=self.metrics, **self.settings)
        status = np.atleast_1d(jac.status)
        at = {k: np.atleast_1d(np.asarray(v, float)) for k, v in jac.metrics_at.items()}
        values = jac.values.reshape(len(w), len(self.metrics), d) * self.space.rate(x)[:, None, :]  # d metric / du
        o = np.stack([at[k] for k in self.targets], axis=1)
        r = (o - self.t) / self.sigma
        logp = -0.5 * np.sum(r**2, axis=1)
        grad_u = -np.einsum("nk,nkj->nj", r / self.sigma, values[:, : len(self.targets)])
        for band in self.bands:
            value = at[band.metric]
            dist, side = (np.asarray(f(band, value), float) for f in (distance, distance_slope))
            logp -= 0.5 * (dist / self.band_sd) ** 2
            grad_u -= (dist * side / self.band_sd**2)[:, None] * values[:, self.metrics.index(band.metric)]
        logp += np.sum(np.log(u * (1.0 - u)), axis=1)
        grad_z = grad_u * u * (1.0 - u) + (1.0 - 2.0 * u)
        grad_w = grad_z @ self.chol
        ok = (status == "ok") & np.isfinite(logp) & np.all(np.isfinite(grad_w), axis=1)
        logp, grad_w = np.where(ok, logp, -np.inf), np.where(ok[:, None], grad_w, 0.0)
        self.evaluations += len(w)
        self.failed += int(np.sum(~ok))
        self.calls += 1
        return logp.reshape(shape), grad_w.reshape(*shape, d)


def as_jax(host: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> Callable[[jax.Array], jax.Array]:
    """A JAX function of one point (d,) from ``host``, which maps points (n, d) to their log
    densities (n,) and gradients (n, d) on the host: differentiable (its gradient is the host's)
    and ``vmap``-able, a batched ``vmap`` making one host call for the whole batch."""

    def both(w):
        shapes = (jax.ShapeDtypeStruct(w.shape[:-1], jnp.float64), jax.ShapeDtypeStruct(w.shape, jnp.float64))
        return jax.pure_callback(lambda x: tuple(np.asarray(a, np.float64) for a in host(np.asarray(x))), shapes, w, vmap_method="broadcast_all")

    @jax.custom_vjp
    def log_density(w):
        return both(w)[0]

    def backward(grad, cotangent):
        return (cotangent[..., None] * grad,)

    log_density.defvjp(both, backward)
    return log_density


def run_nuts(host: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], start: np.ndarray, *, warmup: int, draws: int, seed: int, step_size: float = 0.5,
             max_doublings: int = 6, progress: Callable[[str], None] | None = None) -> dict[str, np.ndarray | float]:
    """Run ``len(start)`` NUTS chains of the density ``host`` (:func:`as_jax`; a :class:`LogDensity`)
    from points ``start`` (chains, d), with an identity mass matrix: ``warmup``
    iterations of dual-averaging step-size adaptation (dropped), then ``draws`` kept. Returns the
    kept positions (draws, chains, d), the step sizes, the acceptance and integration steps per
    iteration, the divergences and the wall time of each stage (s)."""
    import blackjax
    from blackjax.adaptation.step_size import dual_averaging_adaptation

    log_density = as_jax(host)
    kernel = blackjax.mcmc.nuts.build_kernel()
    da_init, da_update, da_final = dual_averaging_adaptation(TARGET_ACCEPTANCE)
    chains, d = start.shape
    eye = jnp.eye(d)

    @jax.jit
    def init(position):
        return jax.vmap(lambda p: blackjax.nuts.init(p, log_density))(position)

    @jax.jit
    def transition(keys, state, size):
        def one(key, state, size):
            state, info = kernel(key, state, log_density, size, eye, max_num_doublings=max_doublings)
            return state, info.acceptance_rate, info.num_integration_steps, info.is_divergent
        return jax.vmap(one)(keys, state, size)

    adapt = jax.jit(jax.vmap(da_update))

    key = jax.random.key(seed)
    clock = time.perf_counter()
    state = init(jnp.asarray(start, jnp.float64))
    da = jax.vmap(da_init)(jnp.full(chains, step_size))
    accept, leapfrogs, divergent, positions = [], [], [], []
    for i in range(warmup):
        key, sub = jax.random.split(key)
        state, a, n, _ = transition(jax.random.split(sub, chains), state, jnp.exp(da.log_step_size))
        da = adapt(da, a)
        accept.append(np.asarray(a))
        leapfrogs.append(np.asarray(n))
        if progress and (i + 1) % 10 == 0:
            progress(f"NUTS warmup {i + 1}/{warmup}: acceptance {np.mean(accept[-10:]):.2f}, step {np.median(np.exp(np.asarray(da.log_step_size))):.3g}")
    warmup_s = time.perf_counter() - clock
    size = jax.vmap(da_final)(da) if warmup else jnp.full(chains, step_size)
    for i in range(draws):
        key, sub = jax.random.split(key)
        state, a, n, div = transition(jax.random.split(sub, chains), state, size)
        accept.append(np.asarray(a))
        leapfrogs.append(np.asarray(n))
        divergent.append(np.asarray(div))
        positions.append(np.asarray(state.position))
        if progress and (i + 1) % 10 == 0:
            progress(f"NUTS draw {i + 1}/{draws}: acceptance {np.mean(accept[-10:]):.2f}, {np.mean(leapfrogs[-10:]):.1f} leapfrog steps")
    return {"positions": np.stack(positions), "step_size": np.asarray(size), "acceptance": np.stack(accept), "leapfrogs": np.stack(leapfrogs),
            "divergent": np.stack(divergent) if divergent else np.zeros((0, chains), bool),
            "warmup_s": warmup_s, "sampling_s": time.perf_counter() - clock - warmup_s}
