"""The LO heart as one ODE system: cell unit + LO coupling + circulation (DESIGN §1).

State vector (9 entries, on the *first* axis; batches and cells broadcast along the rest)::

    y = [CaTRPN, B, S, W, ζs, ζw,  V (ml),  P_c (kPa),  P_at (kPa)]

``P_at`` is the atrial capacitor pressure in the closed loop; in the open loop it stays constant
(its derivative is zero) and the atrium is held at ``Pat``. The right-hand side is explicit:
P_lv depends on the state only (Ta needs S, W, ζs, ζw and λ(V)), and dλ/dt follows from the
valve flows.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from lvenv import cell, circulation, coupling
from lvenv.integrator import is_zero
from lvenv.params import CellParams, Circulation, Heart, LOParams, cavity_volumes, locate

__all__ = ["ModelParams", "Observables", "N_STATES", "IDX_V", "IDX_PC", "IDX_PAT", "rhs", "rhs_at_calcium", "jacobian", "observe", "initial_state", "model_params"]

N_STATES = cell.N_STATES + 3
IDX_V, IDX_PC, IDX_PAT = cell.N_STATES, cell.N_STATES + 1, cell.N_STATES + 2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ModelParams:
    """What the jitted core needs of a Heart: V0 (ml, derived from the geometry) and the three parts."""

    v0: jax.Array
    lo: LOParams
    cell: CellParams
    circ: Circulation

    def get(self, name: str):
        """The value of the LO, cell or circulation parameter ``name``."""
        return getattr(getattr(self, _FIELD[locate(name)]), name)

    def replace(self, **values) -> "ModelParams":
        """A copy with parameters changed by name (traceable; V0 is not recomputed)."""
        parts: dict[str, dict] = {}
        for name, value in values.items():
            parts.setdefault(_FIELD[locate(name)], {})[name] = value
        return dataclasses.replace(self, **{part: dataclasses.replace(getattr(self, part), **mine) for part, mine in parts.items()})


_FIELD = {"lo": "lo", "cell": "cell", "circulation": "circ"}  # Heart part → ModelParams field


def model_params(heart: Heart) -> ModelParams:
    """Host-side conversion Heart → ModelParams (computes V0 from each member's geometry)."""
    as_array = lambda tree: jax.tree.map(lambda x: np.asarray(x, dtype=float), tree)
    return ModelParams(
        v0=np.asarray(cavity_volumes(heart), dtype=float),
        lo=as_array(heart.lo),
        cell=as_array(heart.cell),
        circ=as_array(heart.circulation),
    )


@dataclasses.dataclass(frozen=True)
class Observables:
    """Algebraic outputs of a state: stretch, tension (kPa), pressures (kPa) and flows (ml/s)."""

    lam: jax.Array
    ta: jax.Array
    p_lv: jax.Array
    p_at: jax.Array
    p_ao: jax.Array
    flows: circulation.Flows


def observe(y, p: ModelParams) -> Observables:
    """Pressures and flows of state ``y`` (first axis: the 9 states)."""
    v, p_c, p_at_state = y[IDX_V], y[IDX_PC], y[IDX_PAT]
    lam = coupling.stretch(v, p.v0, p.lo)
    ta = cell.active_tension(y[: cell.N_STATES], lam, p.cell)
    p_lv = coupling.lv_pressure(ta, v, p.v0, p.lo)
    q = circulation.flows(p_lv, p_c, p_at_state, p.circ)
    return Observables(
        lam=lam,
        ta=ta,
        p_lv=p_lv,
        p_at=circulation.atrial_pressure(p_at_state, p.circ),
        p_ao=circulation.aortic_pressure(p_c, q, p.circ),
        flows=q,
    )


def rhs(t, y, p: ModelParams):
    """dy/dt of the LO heart; ``t`` is the time since the beat's onset (s)."""
    return rhs_at_calcium(coupling.calcium(t, p.lo, p.cell), y, p, cell.rates(p.cell))


def rhs_at_calcium(ca, y, p: ModelParams, k: cell.Rates):
    """dy/dt given the calcium input ``ca`` (µM) and precomputed cell rates ``k``."""
    obs = observe(y, p)
    d_v, d_pc, d_pat = circulation.windkessel_derivatives(obs.flows, p.circ)
    d_lam = coupling.stretch_rate(d_v, p.v0, p.lo)
    d_cell = cell.derivatives(y[: cell.N_STATES], ca, obs.lam, d_lam, p.cell, k)
    return jnp.concatenate([d_cell, jnp.stack([d_v, d_pc, d_pat])])


def initial_state(p: ModelParams) -> np.ndarray:
    """Training-protocol initial state (DESIGN §1.2), host-side, shape ``(9, ...)``.

    LV at passive equilibrium with the atrial pressure Pat, Windkessel capacitor at Pc0, atrial
    capacitor at Pat, cell at diastolic rest (isometric steady state at Cdia and λ(V)).
    """
    v = coupling.passive_volume(p.circ.Pat, p.v0, p.lo)
    lam = np.asarray(coupling.stretch(v, p.v0, p.lo))
    y_cell = np.asarray(cell.rest_state(lam, p.cell))
    shape = np.shape(v)
    return np.concatenate([y_cell, np.stack([v, np.broadcast_to(p.circ.Pc0, shape), np.broadcast_to(p.circ.Pat, shape)])])


def _mul(a, b):
    """a·b, keeping the Python float 0.0 as a structural zero."""
    return 0.0 if is_zero(a) or is_zero(b) else a * b


def _add(a, b):
    """a + b, keeping the Python float 0.0 as a structural zero."""
    return b if is_zero(a) else a if is_zero(b) else a + b


def jacobian(ca, y, p: ModelParams, k: cell.Rates, lookahead=None) -> list[list]:
    """Analytic ∂f/∂y of :func:`rhs_at_calcium` as a 9×9 list of lists (row i = ∂f_i/∂y).

    Composed by the chain rule from the parts' own partials: the cell's
    (:func:`lvenv.cell.jacobian`, :func:`lvenv.cell.active_tension_partials`), the LO maps'
    (∂λ/∂V = μ1/V0, dPpass/dV) and the circulation's (:func:`lvenv.circulation.jacobian`)::

        ∂P_lv/∂y   = μ2 ∂Ta/∂y + (μ2 ∂Ta/∂λ μ1/V0 + dPpass/dV) e_V
        circulation rows = D[:, P_lv] ∂P_lv/∂y + D[:, P_c] e_Pc + D[:, P_at] e_Pat
        cell rows  = J_cell + ∂f/∂λ (μ1/V0) e_V + ∂f/∂(dλ/dt) (μ1/V0) (row of dV/dt)

    Structural zeros are the Python float ``0.0`` so that the unrolled LU can skip them. At the
    kinks (clamps, abs(ζw)) the one-sided derivative of the branch selected by the state is used,
    matching ``jax.jacfwd``; with ``lookahead=None`` so are the valves. Checked against
    forward-mode AD in the tests.

    ``lookahead`` (a state increment, the step's explicit predictor h·f): each valve's
    conductance enters weighted by the fraction of the step it is open on the line from y to
    y + lookahead (pressures extrapolated linearly; :func:`lvenv.circulation.open_fractions`).
    This is the W-method freedom of ROS2 (order 2 for any matrix): a step that opens a valve
    treats the stiff valve flow implicitly instead of chattering across the switch, and the
    matrix, hence the step, is continuous in the state, so a fixed-step beat's metrics are
    continuous in the parameters. A yes/no weight (open at y or at y + lookahead) made each valve
    event jump by up to a step wherever the switch moved from one step to the next (IVRT by
    1.9 ms at 500 steps per beat along a line through the N preset, against 0.03 ms now). The
    matrix keeps wᵀJ = 0, so the closed-loop volume stays conserved.
    """
    lo, circ = p.lo, p.circ
    y_cell, v, p_c, p_at_state = y[: cell.N_STATES], y[IDX_V], y[IDX_PC], y[IDX_PAT]
    dlam_dv = lo.mu1 / p.v0
    lam = coupling.stretch(v, p.v0, lo)
    dta_dy, dta_dlam = cell.active_tension_partials(y_cell, lam, p.cell)
    dp_dv = lo.mu2 * dta_dlam * dlam_dv + coupling.passive_pressure_slope(v, p.v0, lo)
    dp_lv = [_mul(lo.mu2, d) for d in dta_dy] + [dp_dv, 0.0, 0.0]
    p_lv = coupling.lv_pressure(cell.active_tension(y_cell, lam, p.cell), v, p.v0, lo)
    if lookahead is None:
        mitral, aortic = circulation.valves_open(p_lv, p_c, p_at_state, circ)
    else:
        ahead = sum(d * lookahead[j] for j, d in enumerate(dp_lv) if not is_zero(d))
        mitral, aortic = circulation.open_fractions((p_lv, p_c, p_at_state), (p_lv + ahead, p_c + lookahead[IDX_PC], p_at_state + lookahead[IDX_PAT]), circ)
    rows_circ = []
    for d_lv, d_pc, d_pat in circulation.jacobian(mitral, aortic, circ):
        row = [_mul(d_lv, d) for d in dp_lv]
        row[IDX_PC], row[IDX_PAT] = d_pc, d_pat
        rows_circ.append(row)
    j_cell, d_lam, d_lam_rate = cell.jacobian(y_cell, ca, lam, p.cell, k)
    rows_cell = []
    for i in range(cell.N_STATES):
        row = j_cell[i] + [0.0] * (N_STATES - cell.N_STATES)
        row[IDX_V] = _add(row[IDX_V], _mul(d_lam[i], dlam_dv))
        if not is_zero(d_lam_rate[i]):  # dλ/dt = μ1/V0 dV/dt
            gain = d_lam_rate[i] * dlam_dv
            row = [_add(r, _mul(gain, e)) for r, e in zip(row, rows_circ[0])]
        rows_cell.append(row)
    return rows_cell + rows_circ
