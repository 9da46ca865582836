"""The DOLFINx backend on real (tiny) meshes: passive inflation, sphere, fibres, activation, beats."""

import time

import numpy as np
import pytest

import dolfinx_solver  # noqa: E402,F401  (make test installs the fe extra: missing DOLFINx must fail, not skip)

import fe_oracle  # noqa: E402
from fe_oracle.cases import N_UNLOADED, Passive  # noqa: E402
from lvenv.geometry import cavity_volume  # noqa: E402

pytestmark = pytest.mark.fe

DEFAULT_H = 6.0  # mm: the default mesh of fe_oracle.run
TINY_H = 10.0  # mm: ~500 tetrahedra, for the coupled steps


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fe_cache")


def test_passive_inflation_default_mesh(cache_dir):
    """Acceptance: V(0) = analytic V0 within 2 %, V(p) increasing over 0 → 4 kPa."""
    res = fe_oracle.run(N_UNLOADED, "passive", mesh_size=DEFAULT_H, cache_dir=cache_dir)
    v, p = res.traces["V"], res.traces["P_lv"]
    assert p[0] == 0.0 and p[-1] == 4.0
    assert v[0] == pytest.approx(cavity_volume(N_UNLOADED), rel=0.02)
    assert np.all(np.diff(v) > 0)
    assert 1.3 < v[-1] / v[0] < 3.0  # the paper's trained LO law gives ≈ 2.4 at 4 kPa
    assert res.log and all(r["converged"] for r in res.log)


def test_cache_hit_and_resume(cache_dir):
    case = Passive(p_max=0.5, n_points=2)
    first = fe_oracle.run(N_UNLOADED, case, mesh_size=TINY_H, cache_dir=cache_dir)
    t0 = time.perf_counter()
    again = fe_oracle.run(N_UNLOADED, case, mesh_size=TINY_H, cache_dir=cache_dir)
    assert not first.from_cache and again.from_cache
    assert time.perf_counter() - t0 < 1.0
    assert np.array_equal(first.traces["V"], again.traces["V"])
    assert again.metadata["key"] == first.metadata["key"]
    assert again.log == first.log


def test_non_convergence_raises_with_time_and_residual(cache_dir):
    with pytest.raises(fe_oracle.OracleDidNotConverge) as info:
        fe_oracle.run(N_UNLOADED, Passive(p_max=4.0, n_points=2), mesh_size=TINY_H, newton_max_it=1, max_cuts=1, cache_dir=cache_dir)
    err = info.value
    assert err.time == 0.0 and np.isfinite(err.residual) and err.residual > 0
    assert len(err.log) == 2 and not any(r["converged"] for r in err.log)
    assert not list(cache_dir.glob("*.tmp"))


def test_thick_walled_sphere_matches_analytic():
    """Isotropic Guccione (Land 2015 problem 2), octant of a 20/30 mm shell, 0 → 3 kPa: < 1 %."""
    from fe_oracle.analytic import sphere_volumes
    from fe_oracle.mechanics import Solid, symmetry_dirichlet
    from fe_oracle.mesh import INNER, SYM_X, SYM_Y, SYM_Z, sphere_shell_mesh
    from fe_oracle.passive import inflate

    A, B = 20.0, 30.0
    material = fe_oracle.Guccione.isotropic(C=10.0, b=1.0)
    tm = sphere_shell_mesh(A, B, 5.0)
    solid = Solid(tm, material, lambda V, m: symmetry_dirichlet(V, m, (SYM_X, SYM_Y, SYM_Z)), pressure_tag=INNER, volume_form="sphere_octant", prefix="sphere")
    p = np.array([0.0, 1.0, 2.0, 3.0])
    v_fe = inflate(solid, p, first_step=1.0)
    v_exact = sphere_volumes(p, A, B, material.C, material.bf)
    assert v_exact[-1] / v_exact[0] > 2.5  # a large deformation, not the linear regime
    np.testing.assert_allclose(v_fe, v_exact, rtol=0.01)


def test_newton_stops_at_a_pressure_scaled_residual(monkeypatch):
    """Newton stops below the nodal force of PRESSURE_TOLERANCE on the endocardium: that moves the
    volume by far less than a beat's volume tolerance (1e-4 V0), in fewer iterations than a stop
    100 times tighter."""
    from fe_oracle import mechanics
    from fe_oracle.dolfinx_backend import LVModel
    from fe_oracle.passive import inflate

    def inflated(tolerance):
        monkeypatch.setattr(mechanics, "PRESSURE_TOLERANCE", tolerance)
        model = LVModel(N_UNLOADED, TINY_H, fe_oracle.Guccione(), None)
        reference_force = tolerance * model.solid._load_norm()  # on the unloaded wall
        log = []
        volumes = inflate(model.solid, [0.0, 1.0], log=log)
        atol = model.solid.snes.getTolerances()[1]
        return volumes[-1], log, atol, reference_force

    v, log, atol, expected = inflated(mechanics.PRESSURE_TOLERANCE)
    v_tight, log_tight, _, _ = inflated(mechanics.PRESSURE_TOLERANCE / 100)
    assert atol == pytest.approx(expected, rel=1e-12) and atol > 0
    assert all(r["residual"] < atol for r in log if r["converged"])
    assert abs(v - v_tight) < 1e-3 * 1e-4 * cavity_volume(N_UNLOADED)
    assert sum(r["iterations"] for r in log) < sum(r["iterations"] for r in log_tight)


def test_fibres_and_activation():
    from fe_oracle.activation import activation_times
    from fe_oracle.fibres import fibre_field
    from fe_oracle.mesh import lv_mesh

    tm = lv_mesh(N_UNLOADED, TINY_H)
    fib = fibre_field(tm)
    f, s, n = (v.x.array.reshape(-1, 3) for v in fib.vectors())
    for a in (f, s, n):
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    assert np.abs(np.sum(f * s, 1)).max() < 1e-12 and np.abs(np.sum(f * n, 1)).max() < 1e-12
    # helix angle: asin(f · e_l), e_l the long axis projected ⊥ to the sheet (transmural) vector
    e_l = np.array([0.0, 0.0, 1.0]) - s[:, 2:3] * s
    e_l /= np.linalg.norm(e_l, axis=1, keepdims=True)
    helix = np.degrees(np.arcsin(np.clip(np.sum(f * e_l, 1), -1, 1)))
    phi = fib.phi.x.array
    np.testing.assert_allclose(helix, 60.0 - 120.0 * np.clip(phi, 0, 1), atol=1e-6)
    t_act, t_fn, foci = activation_times(tm, N_UNLOADED, fib)
    assert t_fn.x.array.min() == 0.0
    assert 0.04 < t_act.max() < 0.3  # s: whole-LV activation of a human ventricle
    assert np.all(t_act >= 0)


def test_a_few_coupled_active_steps(cache_dir):
    """Real coupled steps on a tiny mesh: isovolumic contraction from passive equilibrium with Pat."""
    res = fe_oracle.run(N_UNLOADED, 2, mesh_size=TINY_H, dt=0.01, duration=0.05, cache_dir=cache_dir)
    t, v, p, p_ao = (res.traces[k] for k in ("t", "V", "P_lv", "P_ao"))
    meta = res.metadata
    assert len(t) == 6 and t[-1] == pytest.approx(0.05)
    assert p[0] == pytest.approx(0.66)  # initial state: passive equilibrium with Pat of condition 2
    assert p_ao[0] == pytest.approx(10.0, abs=0.05)
    assert p[-1] > p[0] + 0.05  # contraction raises LV pressure
    assert np.all(p[1:] > 0.66) and np.ptp(v[1:]) < 1e-9  # both valves shut: isovolumic, V_0D exactly held
    assert meta["stretch_min"] < 0.99 < 1.05 < meta["stretch_max"]  # heterogeneous fibre stretch
    assert all(r["converged"] for r in res.log if "volume_mismatch" in r)


def test_synchronous_activation_contracts_every_point_from_the_onset(cache_dir):
    """The diagnostic ``activation="synchronous"``: every activation time 0, its own cache entry,
    and with the whole wall contracting at once the isovolumic pressure rises faster."""
    eikonal = fe_oracle.run(N_UNLOADED, 2, mesh_size=TINY_H, dt=0.01, duration=0.05, cache_dir=cache_dir)
    synchronous = fe_oracle.run(N_UNLOADED, 2, mesh_size=TINY_H, dt=0.01, duration=0.05, cache_dir=cache_dir, activation="synchronous")
    assert synchronous.metadata["activation_time_max_s"] == 0.0 < eikonal.metadata["activation_time_max_s"]
    assert synchronous.metadata["key"] != eikonal.metadata["key"] and not synchronous.from_cache
    assert synchronous.traces["P_lv"][0] == pytest.approx(eikonal.traces["P_lv"][0])  # same passive start
    assert np.all(synchronous.traces["P_lv"][1:] > eikonal.traces["P_lv"][1:])


def test_closed_loop_steps_conserve_blood_volume(cache_dir):
    """Closed loop (atrial capacitor): V + C P_c + Cat P_at is conserved by the coupled steps."""
    from lvenv.params import Circulation

    circ = Circulation(Pat=1.0, Cat=20.0, C=6.0, R2=0.005, Pc0=10.0, closed_loop=1.0)
    res = fe_oracle.run(N_UNLOADED, circ, mesh_size=TINY_H, dt=0.01, duration=0.03, cache_dir=cache_dir)
    tr = res.traces
    total = tr["V"] + circ.C * tr["P_c"] + circ.Cat * tr["P_at"]
    assert np.ptp(total) < 1e-9 * total[0]
    assert np.ptp(tr["P_at"]) > 0  # the atrium is a state, not a constant


def test_the_wall_record_is_the_distribution_the_beat_computes_with():
    """``wall_quantiles``: one record per trace sample; at the start every point rests (rate 0,
    Ta from the diastolic calcium), the quantiles are ordered, the run's traces are those of a run without the record, and the activation-time
    quantiles are those of `activation_quantiles` on the same mesh and stay below the latest time."""
    from fe_oracle.activation import activation_quantiles
    from fe_oracle.coupled_beat import WALL_FIELDS
    from fe_oracle.dolfinx_backend import run_beat
    from fe_oracle.material import Guccione
    from lvenv import presets
    from lvenv.params import CellParams

    q = (0.05, 0.5, 0.95)
    args = (N_UNLOADED, presets.training_circulation(2), CellParams(), Guccione(), TINY_H, 0.01, 1)
    traces, meta, _ = run_beat(*args, duration=0.05, wall_quantiles=q)
    plain, _, _ = run_beat(*args, duration=0.05)
    wall = traces["wall"]
    assert wall.shape == (len(traces["t"]), len(WALL_FIELDS), len(q) + 1)
    np.testing.assert_array_equal(traces["P_lv"], plain["P_lv"])
    assert np.all(np.diff(wall[..., :-1], axis=-1) >= 0)
    assert np.all(wall[0, 1] == 0.0)
    ta = wall[:, WALL_FIELDS.index("Ta"), -1]
    assert ta[-1] > 10 * ta[0]  # by 50 ms most of the wall is active
    times = meta["activation_quantiles_s"]
    np.testing.assert_allclose(times, activation_quantiles(N_UNLOADED, TINY_H, q), rtol=1e-12)
    assert 0.0 <= times[0] < times[1] < times[2] < meta["activation_time_max_s"]
