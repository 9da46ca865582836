"""FE oracle front end without DOLFINx: import, case resolution, cache (pure Python)."""

import os
import subprocess
import sys

import numpy as np
import pytest

import fe_oracle
from fe_oracle import cache
from fe_oracle.analytic import sphere_pressure, sphere_volume
from fe_oracle.cases import Passive, resolve_case, training_condition
from fe_oracle.result import OracleResult
from lvenv.params import Circulation

_BLOCK_DOLFINX = """
import sys
for name in ("dolfinx_solver", "dolfinx", "petsc4py", "mpi4py", "gmsh"):
    sys.modules[name] = None
import fe_oracle
try:
    fe_oracle.run(fe_oracle.N_UNLOADED, "passive", use_cache=False)
except ImportError as err:
    print(str(err))
"""


def test_import_without_dolfinx_then_install_hint():
    out = subprocess.run([sys.executable, "-c", _BLOCK_DOLFINX], capture_output=True, text=True, check=True)
    assert "pip install -e '.[fe]'" in out.stdout


def test_training_conditions_are_table_2():
    for k, (pat, r3) in {1: (0.33, 0.20), 2: (0.66, 0.05), 3: (1.5, 0.20)}.items():
        c = resolve_case(k)
        assert (c.Pat, c.R3, c.C, c.R1, c.R2, c.Pc0, c.closed_loop) == (pat, r3, 8.0, 0.0015, 0.0, 10.0, 0.0)
    assert resolve_case("passive") == Passive()
    assert resolve_case(Circulation()) == Circulation()
    with pytest.raises(ValueError, match="training condition"):
        training_condition(4)
    with pytest.raises(ValueError, match="case must be"):
        resolve_case("active")


def test_cache_key_depends_on_every_input():
    base = {"geometry": fe_oracle.N_UNLOADED, "case": training_condition(2), "mesh_size": 6.0}
    k = cache.key(base)
    assert k == cache.key(dict(base))
    assert k != cache.key(dict(base, mesh_size=5.0))
    assert k != cache.key(dict(base, case=training_condition(2).__class__(**{**training_condition(2).__dict__, "R3": 0.06})))


def test_cache_store_is_atomic(tmp_path, monkeypatch):
    result = OracleResult({"t": np.arange(3.0), "V": np.ones(3)}, {"a": 1.5}, [{"iterations": 2}])
    cache.store(tmp_path, "k1", result)
    back = cache.load(tmp_path, "k1")
    assert back.from_cache and back.metadata == {"a": 1.5} and np.array_equal(back.traces["t"], np.arange(3.0))

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", killed)
    with pytest.raises(KeyboardInterrupt):
        cache.store(tmp_path, "k2", result)
    assert cache.load(tmp_path, "k2") is None
    assert sorted(os.listdir(tmp_path)) == ["k1.npz"]


def test_sphere_analytic_small_strain_limit():
    """Linear elasticity limit of the exact solution: p = 4 μ (δ/A) (1 − A³/B³), μ = C b / 2."""
    A, B, C, b = 20.0, 30.0, 10.0, 1.0
    assert sphere_pressure(A, A, B, C, b) == pytest.approx(0.0, abs=1e-12)
    da = 1e-4
    mu = C * b / 2.0  # W ≈ C b tr(E²) / 2 ⇒ S = C b E = 2 μ E
    assert sphere_pressure(A + da, A, B, C, b) == pytest.approx(4 * mu * (da / A) * (1 - A**3 / B**3), rel=1e-3)
    v = [sphere_volume(p, A, B, C, b) for p in (0.0, 1.0, 2.0)]
    assert v[0] < v[1] < v[2]


def test_run_rejects_bad_arguments():
    with pytest.raises(ValueError, match="backend"):
        fe_oracle.run(fe_oracle.N_UNLOADED, backend="abaqus")
    with pytest.raises(ValueError, match="mesh_size"):
        fe_oracle.run(fe_oracle.N_UNLOADED, mesh_size=0.0)
    with pytest.raises(ValueError, match=r"activation = 'purkinje'.*'eikonal', 'synchronous'"):
        fe_oracle.run(fe_oracle.N_UNLOADED, 2, activation="purkinje")
    with pytest.raises(ValueError, match="activation = 'synchronous' applies to backend 'dolfinx' only"):
        fe_oracle.run(fe_oracle.N_UNLOADED, 2, backend="multielement", activation="synchronous")
    # unbounded work is refused before any computation, on either backend
    for backend in fe_oracle.BACKENDS:
        with pytest.raises(ValueError, match=r"beats = 1000000000 must be an integer in \[1, 100\]"):
            fe_oracle.run(fe_oracle.N_UNLOADED, 2, backend=backend, beats=10**9)
        with pytest.raises(ValueError, match=r"duration = 1000000.0 must be a finite real number in \(0, 300\]"):
            fe_oracle.run(fe_oracle.N_UNLOADED, 2, backend=backend, duration=1e6)


def _synthetic_beat(onset: float = 0.0):
    """A beat sampled every 10 ms whose valve events are known exactly (all pressures linear
    between samples, so the detector's linear interpolation is exact)."""
    t = np.round(np.arange(0.0, 1.0 + 1e-9, 0.01), 12)
    knots = ([0.0, 0.05, 0.1, 0.3, 0.4, 1.0], [0.5, 1.5, 12.0, 12.0, 0.0, 0.5])
    p_lv = np.interp(t, *knots)
    p_c = 10.0 - 5.0 * t
    v = 100.0 - 100.0 * t
    g = lambda a, b, ga, gb: a + (b - a) * ga / (ga - gb)  # noqa: E731  zero of a line through (a, ga), (b, gb)
    events = {
        "mvc": g(0.02, 0.03, 1 - np.interp(0.02, *knots), 1 - np.interp(0.03, *knots)),
        "avo": g(0.09, 0.1, np.interp(0.09, *knots) - (10 - 5 * 0.09), 12.0 - 9.5),
        "avc": g(0.33, 0.34, np.interp(0.33, *knots) - (10 - 5 * 0.33), np.interp(0.34, *knots) - (10 - 5 * 0.34)),
        "mvo": g(0.39, 0.4, 1 - np.interp(0.39, *knots), 1.0),
    }
    traces = {"t": t + onset, "V": v, "P_lv": p_lv, "P_ao": p_c, "P_c": p_c, "P_at": np.ones_like(t)}
    return traces, events


def test_beat_metrics_locate_valve_events_between_samples():
    from fe_oracle.metrics import beat_metrics

    traces, ev = _synthetic_beat()
    m = beat_metrics(OracleResult(traces, {"case": "beat", "period_s": 1.0}, []))
    assert m["valid"] == 1.0
    edv, esv = 100.0 - 100.0 * ev["mvc"], 100.0 - 100.0 * ev["avc"]
    expected = {"IVCT": ev["avo"] - ev["mvc"], "ET": ev["avc"] - ev["avo"], "IVRT": ev["mvo"] - ev["avc"], "EDV": edv, "ESV": esv, "EF": (edv - esv) / edv, "P_lv_peak": 12.0}
    for name, value in expected.items():
        assert m[name] == pytest.approx(value, rel=1e-9), name
    two = {k: np.concatenate([v[:-1], w]) for (k, v), w in zip(traces.items(), _synthetic_beat(1.0)[0].values())}
    two["P_lv"] = np.concatenate([traces["P_lv"][:-1] * 0.5, traces["P_lv"]])  # a weaker first beat
    last = beat_metrics(OracleResult(two, {"case": "beat", "period_s": 1.0}, []))
    assert last["IVCT"] == pytest.approx(m["IVCT"], rel=1e-9) and last["P_lv_peak"] == 12.0
    first = beat_metrics(OracleResult(two, {"case": "beat", "period_s": 1.0}, []), beat=0)
    assert first["status"] == "no_valve_cycle" and np.isnan(first["P_lv_peak"]), "6 kPa never opens the aortic valve at 10 kPa"
    with pytest.raises(ValueError, match="passive"):
        beat_metrics(OracleResult(traces, {"case": "passive"}, []))


def test_code_version_covers_every_module_a_backend_runs():
    """Every fe_oracle module the DOLFINx backend imports, directly or not, is hashed into its key."""
    import ast
    import pathlib

    root = pathlib.Path(cache.__file__).resolve().parent.parent
    for backend, files in cache.CODE.items():
        assert all((root / f).is_file() for f in files), backend
        todo, seen = [f"fe_oracle/{backend}_backend.py"], set()
        while todo:
            path = todo.pop()
            if path in seen:
                continue
            seen.add(path)
            for node in ast.walk(ast.parse((root / path).read_text())):
                if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("fe_oracle"):
                    names = [node.module] if node.module != "fe_oracle" else [f"fe_oracle.{a.name}" for a in node.names]
                    todo += [n.replace(".", "/") + ".py" for n in names if (root / (n.replace(".", "/") + ".py")).is_file()]
        assert seen <= set(files), sorted(seen - set(files))
    assert "fe_oracle/api.py" not in cache.CODE["dolfinx"] and cache.code_version("dolfinx") != cache.code_version("multielement")


def test_beat_metrics_hand_out_no_numbers_for_an_invalid_or_non_physical_beat():
    from fe_oracle.metrics import beat_metrics

    traces, _ = _synthetic_beat()
    meta = {"case": "beat", "period_s": 1.0}
    assert beat_metrics(OracleResult(traces, meta, []))["status"] == "ok"
    # every pressure 2 kPa lower: the same valve events, but the LV fills by suction (EDP, P_at < 0)
    sucking = {k: v - 2.0 if k.startswith("P_") else v for k, v in traces.items()}
    flat = dict(traces, P_lv=np.full_like(traces["t"], 0.5))  # never opens the aortic valve
    for bad, status in ((sucking, "non_physical"), (flat, "no_valve_cycle")):
        m = beat_metrics(OracleResult(bad, meta, []))
        assert m.pop("status") == status and m.pop("valid") == 0.0
        assert all(np.isnan(v) for v in m.values()), {k: v for k, v in m.items() if not np.isnan(v)}


def test_run_checks_cell_parameters_as_lvenv_simulate_does_on_either_backend():
    import lvenv
    from lvenv import presets
    from lvenv.params import CellParams
    from lvenv.validation import InputError

    with pytest.raises(InputError) as lo:
        lvenv.simulate(presets.normal().replace(Sa=-5.0), beats=1)
    for backend in ("dolfinx", "multielement"):
        with pytest.raises(InputError) as fe:
            fe_oracle.run(fe_oracle.N_UNLOADED, 2, backend, cell=CellParams(Sa=-5.0), use_cache=False)
        assert str(fe.value) == str(lo.value) == "cell.Sa = -5 is outside the allowed range [0.05, 10]"
    with pytest.raises(InputError, match="circulation.R3 = 50"):
        fe_oracle.run(fe_oracle.N_UNLOADED, Circulation(R3=50.0), use_cache=False)
    with pytest.raises(InputError, match="cell must be an lvenv.params.CellParams"):
        fe_oracle.run(fe_oracle.N_UNLOADED, 2, cell={"Sa": 1.0}, use_cache=False)
