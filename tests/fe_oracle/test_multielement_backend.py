"""The ``multielement`` oracle backend: the DOLFINx backend's interface, without DOLFINx."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import brentq

import fe_oracle
from fe_oracle import multielement_backend as be
from fe_oracle.cases import Passive
from fe_oracle.metrics import beat_metrics
from fe_oracle.result import TRACE_NAMES
from lvenv import coupling, multielement, presets
from lvenv.geometry import Geometry, cavity_volume
from lvenv.params import LOParams

#: The paper's Table 3 maps: the multi-element models are defined with them (DESIGN §1.4).
TABLE3 = presets.normal(lo="table3")

BEAT_TRACES = set(TRACE_NAMES) | {"P_c", "P_at"}  # result.py: beats also carry P_c and P_at
#: Metadata the DOLFINx backend's beats carry (fe_oracle.dolfinx_backend.run_beat and fe_oracle.run).
FE_BEAT_METADATA = {
    "cells", "dofs", "V0_analytic_ml", "V0_mesh_ml", "wall_s", "setup_s", "steps", "step_cuts", "fe_solves",
    "newton_iterations", "quadrature_points", "stretch_min", "stretch_max", "stretch_p01", "stretch_p99",
    "activation_time_max_s", "period_s", "volume_tol_ml",
    "backend", "case", "key", "code_version", "mesh_size_mm", "total_s", "dt_s", "beats",
}
FE_PASSIVE_METADATA = {
    "cells", "dofs", "V0_analytic_ml", "V0_mesh_ml", "wall_s", "setup_s", "newton_iterations", "solves",
    "backend", "case", "key", "code_version", "mesh_size_mm", "total_s",
}


def _shared_keys(meta: dict) -> set:
    return set(meta) - set(be.FE_ONLY_METADATA) - set(be.MULTIELEMENT_METADATA)


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("me_cache")


@pytest.mark.parametrize("arrangement", multielement.ARRANGEMENTS)
def test_beat_answers_the_oracle_interface(arrangement, cache_dir):
    """Condition ② at 256 elements: the DOLFINx trace fields and metadata keys, a full valve
    cycle through fe_oracle.metrics.beat_metrics, equal to the model's own metrics."""
    res = fe_oracle.run(presets.N_UNLOADED, 2, backend="multielement", arrangement=arrangement, dt=0.001, cache_dir=cache_dir)
    tr, meta = res.traces, res.metadata
    assert set(tr) == BEAT_TRACES and len({len(v) for v in tr.values()}) == 1
    assert _shared_keys(meta) == FE_BEAT_METADATA - set(be.FE_ONLY_METADATA)
    assert meta["backend"] == "multielement" and meta["arrangement"] == arrangement and meta["n_elements"] == 256
    assert meta["mesh_size_mm"] is None and meta["lo"] == {k: getattr(presets.N_LO, k) for k in meta["lo"]}
    assert tr["t"][0] == 0.0 and tr["t"][-1] == pytest.approx(meta["period_s"]) == 1.0 and meta["steps"] == 1000
    assert tr["P_lv"][0] == pytest.approx(0.66, abs=0.02) and tr["P_ao"][0] == 10.0 and np.all(tr["P_at"] == 0.66)
    m = beat_metrics(res)
    assert m["valid"] == 1.0 and 0.35 < m["EF"] < 0.75
    own = multielement.simulate(presets.training_condition(2, TABLE3), multielement.Arrangement(arrangement, 256)).metrics
    for name in ("EF", "EDV", "ESV", "IVCT", "ET", "IVRT", "P_lv_peak", "P_ao_mean"):
        assert m[name] == pytest.approx(own[name], rel=1e-9, abs=1e-12), name
    again = fe_oracle.run(presets.N_UNLOADED, 2, backend="multielement", arrangement=arrangement, dt=0.001, cache_dir=cache_dir)
    assert again.from_cache and np.array_equal(again.traces["V"], tr["V"]) and again.metadata == meta


@pytest.mark.parametrize("arrangement", multielement.ARRANGEMENTS)
def test_passive_inflation_is_the_lo_pressure_volume_law(arrangement, cache_dir):
    """Ⓟ with Ta = 0: parallel V = Ppass⁻¹(p); series V = mean_ξ V_ξ with w_ξ Ppass(V_ξ) = p,
    each root found here by scipy's brentq."""
    res = fe_oracle.run(presets.N_UNLOADED, "passive", backend="multielement", arrangement=arrangement, n_elements=16, cache_dir=cache_dir)
    tr = res.traces
    assert set(tr) == set(TRACE_NAMES) and np.all(np.isnan(tr["P_ao"]))
    assert _shared_keys(res.metadata) == FE_PASSIVE_METADATA - set(be.FE_ONLY_METADATA)
    p = Passive().pressures()
    np.testing.assert_array_equal(tr["P_lv"], p)
    np.testing.assert_allclose(tr["t"], p / 4.0)
    v0, lo = cavity_volume(presets.N_UNLOADED), presets.N_LO
    w = np.ones(1) if arrangement == "parallel" else multielement.Arrangement("series", 16).element_values()
    expected = [np.mean([brentq(lambda v: wi * float(coupling.passive_pressure(v, v0, lo)) - pi, 0.5 * v0, 5.0 * v0, xtol=1e-13) for wi in w]) for pi in p]
    np.testing.assert_allclose(tr["V"], expected, rtol=1e-10)
    assert tr["V"][0] == pytest.approx(v0, rel=1e-12) and np.all(np.diff(tr["V"]) > 0)


def test_lo_defaults_and_cache_keys(cache_dir):
    """lo=None is the paper's N / HF values for those geometries, LOParams() otherwise; the
    cache key tells backend, arrangement, n_elements and lo apart."""
    run = lambda geometry=presets.N_UNLOADED, **kw: fe_oracle.run(geometry, Passive(n_points=3), backend="multielement", cache_dir=cache_dir, **kw)  # noqa: E731
    lo_of = lambda res: LOParams(**res.metadata["lo"])  # noqa: E731
    base = run()
    assert lo_of(base) == presets.N_LO and base.metadata["arrangement"] == "parallel" and base.metadata["n_elements"] == 256
    assert lo_of(run(presets.HF_UNLOADED)) == presets.HF_LO
    other = Geometry(Rb=36.0, L=9.0, Z=52.0, H=11.0, e=0.7, C0=-55.0)
    assert lo_of(run(other)) == LOParams()
    assert run(lo=presets.N_LO).metadata["key"] == base.metadata["key"]
    variants = [run(arrangement="series"), run(n_elements=8), run(lo=presets.HF_LO)]
    keys = {base.metadata["key"]} | {r.metadata["key"] for r in variants}
    assert len(keys) == 4 and not any(r.from_cache for r in variants)
    assert run().from_cache


def test_bad_arguments_name_field_value_and_allowed():
    with pytest.raises(ValueError, match=r"arrangement = 'diagonal' is not one of 'parallel', 'series'"):
        fe_oracle.run(presets.N_UNLOADED, backend="multielement", arrangement="diagonal", use_cache=False)
    with pytest.raises(ValueError, match=r"n_elements = 0 must be an integer in \[1, 4096\]"):
        fe_oracle.run(presets.N_UNLOADED, backend="multielement", n_elements=0, use_cache=False)
    with pytest.raises(ValueError, match=r"n_elements = 'many'"):
        fe_oracle.run(presets.N_UNLOADED, backend="multielement", n_elements="many", use_cache=False)
    with pytest.raises(ValueError, match="lo = "):
        fe_oracle.run(presets.N_UNLOADED, backend="multielement", lo={"mu1": 0.2}, use_cache=False)
    with pytest.raises(ValueError, match="apply to backend 'multielement' only"):
        fe_oracle.run(presets.N_UNLOADED, backend="dolfinx", arrangement="series", use_cache=False)


_BLOCK_DOLFINX = """
import sys
for name in ("dolfinx_solver", "dolfinx", "petsc4py", "mpi4py", "gmsh", "ufl"):
    sys.modules[name] = None
import fe_oracle
res = fe_oracle.run(fe_oracle.N_UNLOADED, "passive", backend="multielement", arrangement="series", use_cache=False)
print(round(float(res.traces["V"][-1]), 3))
"""


def test_needs_no_dolfinx():
    out = subprocess.run([sys.executable, "-c", _BLOCK_DOLFINX], capture_output=True, text=True, check=True)
    assert float(out.stdout) > 50.0


@pytest.mark.fe
def test_same_fields_units_and_metadata_as_a_real_dolfinx_run(tmp_path):
    """A tiny real DOLFINx run (10 mm mesh, one 10 ms step of condition ②, two passive loads)
    next to the multielement backend on the same case: same trace fields, same metadata keys
    up to the documented FE-only / multielement-only ones, same units (s, ml, kPa)."""
    fe = fe_oracle.run(presets.N_UNLOADED, 2, mesh_size=10.0, dt=0.01, duration=0.01, cache_dir=tmp_path)
    me = fe_oracle.run(presets.N_UNLOADED, 2, backend="multielement", dt=0.001, duration=0.01, cache_dir=tmp_path)
    assert set(fe.traces) == set(me.traces) == BEAT_TRACES
    assert set(fe.metadata) == FE_BEAT_METADATA
    assert _shared_keys(me.metadata) == set(fe.metadata) - set(be.FE_ONLY_METADATA)
    for res in (fe, me):
        tr = res.traces
        assert tr["t"][0] == 0.0 and tr["t"][-1] == pytest.approx(0.01)  # s
        assert tr["P_lv"][0] == pytest.approx(0.66, abs=0.02) and tr["P_ao"][0] == pytest.approx(10.0)  # kPa
        assert res.metadata["period_s"] == 1.0 and res.metadata["dt_s"] in (0.01, 0.001)
    assert 0.75 < me.traces["V"][0] / fe.traces["V"][0] < 1.33  # both ml, same cavity
    assert me.metadata["V0_analytic_ml"] == fe.metadata["V0_analytic_ml"]
    case = Passive(p_max=0.5, n_points=2)
    fe_p = fe_oracle.run(presets.N_UNLOADED, case, mesh_size=10.0, cache_dir=tmp_path)
    me_p = fe_oracle.run(presets.N_UNLOADED, case, backend="multielement", cache_dir=tmp_path)
    assert set(fe_p.traces) == set(me_p.traces) == set(TRACE_NAMES) and set(fe_p.metadata) == FE_PASSIVE_METADATA
    assert _shared_keys(me_p.metadata) == set(fe_p.metadata) - set(be.FE_ONLY_METADATA)
    np.testing.assert_array_equal(fe_p.traces["t"], me_p.traces["t"])
    np.testing.assert_array_equal(fe_p.traces["P_lv"], me_p.traces["P_lv"])
    assert me_p.traces["V"][0] == pytest.approx(fe_p.traces["V"][0], rel=0.02)  # V(0) = V0 (ml) in both
