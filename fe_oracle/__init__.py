"""FE oracle: a 3-D nonlinear finite-element left ventricle (DESIGN §4).

``import fe_oracle`` needs no DOLFINx; :func:`run` loads the DOLFINx backend lazily and tells
you how to install it if it is missing. See :func:`fe_oracle.api.run` for the interface and
:func:`fe_oracle.metrics.beat_metrics` for a beat's EF, volumes and phase durations.
"""

from fe_oracle.api import ACTIVATIONS, BACKENDS, DEFAULT_DT, DEFAULT_MESH_SIZE, run
from fe_oracle.cases import HF_UNLOADED, N_UNLOADED, Passive, training_condition
from fe_oracle.material import Guccione
from fe_oracle.metrics import beat_metrics
from fe_oracle.result import OracleDidNotConverge, OracleResult

__all__ = [
    "ACTIVATIONS",
    "BACKENDS",
    "DEFAULT_DT",
    "DEFAULT_MESH_SIZE",
    "HF_UNLOADED",
    "N_UNLOADED",
    "Guccione",
    "OracleDidNotConverge",
    "OracleResult",
    "Passive",
    "beat_metrics",
    "run",
    "training_condition",
]
