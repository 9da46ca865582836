"""What a patient's measurements pin down: the measurement model, the sensitivity at a fit,
profile likelihoods and the posterior (DESIGN §6).

One module per job; every public name is re-exported here, so ``from optim import identify``
then ``identify.posterior(patient)`` is the usual entry point:

* :mod:`optim.identify.noise`: the measurement model, each target's error σ_k (:data:`NOISE`,
  :class:`Relative`, with their published sources) and the misfit χ² (:func:`chi2`,
  :func:`chi2_weighted`);
* :mod:`optim.identify.sensitivities`: the noise-scaled sensitivity at a parameter set, its
  singular values and null directions (:func:`sensitivity`);
* :mod:`optim.identify.profiles`: profile likelihoods through constrained cohort fits, and each
  parameter's class (:func:`profile`);
* :mod:`optim.identify.density`: the posterior's prior and density through the vector env, and
  exact prior draws for calibration (:func:`log_density`, :func:`prior_sample`, :func:`prior_draws`);
* :mod:`optim.identify.sampler`: the posterior's samples, by ensemble pilot and independent
  chains or NUTS (:func:`posterior`), or by the amortised flow of :mod:`optim.amortised`
  (:func:`amortised`; for a list of patients, MCMC where flagged: :func:`identify_patients`),
  and their comparison (:func:`probability_lower`);
* :mod:`optim.identify.report`: all of it at a fit, as a per-patient report (:func:`write_report`).

The scripts' sampler options live with the scripts (``scripts/posterior_options.py``).
"""

from optim.identify import density, noise, profiles, sampler
from optim.identify.density import PriorSample, log_density, prior_draws, prior_sample
from optim.identify.noise import Relative, chi2, chi2_weighted, measurement_sd
from optim.identify.profiles import Profiles, profile
from optim.identify.report import write_report
from optim.identify.sampler import Identified, Posterior, amortised, identify_patients, posterior, probability_lower
from optim.identify.sensitivities import Sensitivity, sensitivity

# The constants are bound by assignment, so that the API reference documents them here too.
#: Each target's measurement error σ_k (:data:`optim.identify.noise.NOISE`).
NOISE = noise.NOISE
#: The volume metrics, whose errors are relative (:data:`optim.identify.noise.VOLUME_NAMES`).
VOLUME_NAMES = noise.VOLUME_NAMES
#: σ (kPa) of the posterior's plausibility factor (:data:`optim.identify.density.PLAUSIBILITY_SD`).
PLAUSIBILITY_SD = density.PLAUSIBILITY_SD
#: The profile-likelihood threshold, Δχ² (:data:`optim.identify.profiles.DELTA_95`).
DELTA_95 = profiles.DELTA_95
#: A flat profile's largest range, χ² units (:data:`optim.identify.profiles.FLAT`).
FLAT = profiles.FLAT
#: What samples after the pilot (:data:`optim.identify.sampler.SAMPLERS`).
SAMPLERS = sampler.SAMPLERS

__all__ = [
    "NOISE", "Relative", "VOLUME_NAMES", "measurement_sd", "chi2_weighted", "chi2", "PLAUSIBILITY_SD", "DELTA_95", "FLAT",
    "Sensitivity", "Profiles", "Posterior", "sensitivity", "profile", "posterior", "probability_lower", "prior_draws",
    "prior_sample", "PriorSample", "amortised", "identify_patients", "Identified", "log_density", "write_report", "SAMPLERS",
]
