"""Independent NumPy/SciPy reference of the LO heart, written from DESIGN §1 equations only.

It shares no code with ``lvenv`` beyond reading parameter values: the right-hand side is
re-derived here in plain NumPy and integrated with ``solve_ivp(method="Radau")``. Valve events
are located by root-finding on the dense output.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import integrate, optimize


def _pars(heart, v0):
    lo, c, w = heart.lo, heart.cell, heart.circulation
    return dict(
        v0=v0, mu1=lo.mu1, mu2=lo.mu2, gam=lo.gamma, alpha=lo.alpha, beta=lo.beta, a=lo.a, b=lo.b, c=lo.c, delay=lo.delay,
        Sa=c.Sa, fv=c.vmax_factor, n0=c.n0, nTm=c.nA, tau1=c.tau1, tau2=c.tau2, cdia=c.Cdia, cmax=c.Cmax,
        Tref=c.Tref, ca50ref=c.Ca50ref, beta1=c.beta1, ntrpn=c.nTRPN, ktrpn=c.kTRPN, trpn50=c.TRPN50, ku=c.ku,
        rw=c.rw, rs=c.rs, gs=c.gamma_s, gw=c.gamma_w, phi=c.phi, aeff=c.Aeff, kuw=c.kuw * c.vmax_factor, kws=c.kws * c.vmax_factor,
        R1=w.R1, R2=w.R2, R3=w.R3, C=w.C, Rmv=w.Rmv, Pat=w.Pat, Cat=w.Cat, Pc0=w.Pc0, T=60.0 / w.HR, closed=w.closed_loop > 0.5,
    )


def calcium(t, q):
    t = t - q["delay"]  # the LO activation delay: the transient starts d after the beat's onset
    if t < 0.0:
        return q["cdia"]
    tp = q["tau1"] * q["tau2"] / (q["tau2"] - q["tau1"]) * math.log(q["tau2"] / q["tau1"])
    norm = math.exp(-tp / q["tau2"]) - math.exp(-tp / q["tau1"])
    return q["cdia"] + (q["cmax"] - q["cdia"]) * (math.exp(-t / q["tau2"]) - math.exp(-t / q["tau1"])) / norm


def ppass(v, q):
    x = v / q["v0"] - 1.0
    if x <= 0:
        return q["alpha"] * (1.0 - math.exp(-q["beta"] * q["gam"] * x))
    return q["a"] * x**3 + q["b"] * x**2 + q["c"] * x


def tension(y, v, q):
    lam = q["mu1"] * (v / q["v0"] - 1.0) + 1.0
    lc = min(lam, 1.2)
    b0 = 1.0 / (1.87 - 2 * q["n0"]) if q["n0"] <= 0.87 else 1.0 / (1.0 - q["n0"])
    h = max(0.0, 1.0 + b0 * (lc + min(lc, 0.87) - 1.87))
    _, _, s, w, zs, zw = y[:6]
    return q["Sa"] * h * q["Tref"] / q["rs"] * (s * (zs + 1.0) + w * zw), lam


def pressures(y, q):
    v, pc, pat_state = y[6], y[7], y[8]
    ta, lam = tension(y, v, q)
    plv = q["mu2"] * ta + ppass(v, q)
    pat = pat_state if q["closed"] else q["Pat"]
    qmv = max(pat - plv, 0.0) / q["Rmv"]
    qao = max(plv - pc, 0.0) / (q["R1"] + q["R2"])
    return plv, pat, qmv, qao, lam


def rhs(t, y, q):
    catrpn, bb, s, w, zs, zw, v, pc, pat_state = y
    plv, pat, qmv, qao, lam = pressures(y, q)
    pven = pat_state if q["closed"] else 0.0
    qper = (pc - pven) / q["R3"]
    dv = qmv - qao
    dlam = q["mu1"] / q["v0"] * dv
    lc = min(lam, 1.2)
    ca50 = q["ca50ref"] + q["beta1"] * (lc - 1.0)
    ca = calcium(t % q["T"], q)
    kb = q["ku"] * q["trpn50"] ** q["nTm"] / (1 - q["rs"] - (1 - q["rs"]) * q["rw"])
    kwu = q["kuw"] * (1 / q["rw"] - 1) - q["kws"]
    ksu = q["kws"] * q["rw"] * (1 / q["rs"] - 1)
    u = 1 - bb - s - w
    cp = max(catrpn, 1e-12)
    gwu = q["gw"] * abs(zw)
    gsu = q["gs"] * (zs if zs > 0 else (-zs - 1 if zs < -1 else 0.0))
    aw = q["aeff"] * q["rs"] / ((1 - q["rs"]) * q["rw"] + q["rs"])
    cw = q["phi"] * q["kuw"] * (1 - q["rw"]) / q["rw"]
    cs = q["phi"] * q["kws"] * (1 - q["rs"]) * q["rw"] / q["rs"]
    return np.array([
        q["ktrpn"] * ((ca / ca50) ** q["ntrpn"] * (1 - catrpn) - catrpn),
        kb * min(cp ** (-q["nTm"] / 2), 100.0) * u - q["ku"] * cp ** (q["nTm"] / 2) * bb,
        q["kws"] * w - (ksu + gsu) * s,
        q["kuw"] * u - (kwu + q["kws"] + gwu) * w,
        aw * dlam - cs * zs,
        aw * dlam - cw * zw,
        dv,
        (qao - qper) / q["C"],
        (qper - qmv) / q["Cat"] if q["closed"] else 0.0,
    ])


def initial_state(q):
    v = optimize.brentq(lambda vv: ppass(vv, q) - q["Pat"], 1e-3 * q["v0"], 10 * q["v0"], xtol=1e-13)
    lam = q["mu1"] * (v / q["v0"] - 1.0) + 1.0
    ca50 = q["ca50ref"] + q["beta1"] * (min(lam, 1.2) - 1.0)
    x = (q["cdia"] / ca50) ** q["ntrpn"]
    catrpn = x / (1 + x)
    kb = q["ku"] * q["trpn50"] ** q["nTm"] / (1 - q["rs"] - (1 - q["rs"]) * q["rw"])
    b_u = kb * min(catrpn ** (-q["nTm"] / 2), 100.0) / (q["ku"] * catrpn ** (q["nTm"] / 2))
    kwu = q["kuw"] * (1 / q["rw"] - 1) - q["kws"]
    ksu = q["kws"] * q["rw"] * (1 / q["rs"] - 1)
    w_u = q["kuw"] / (kwu + q["kws"])
    s_u = q["kws"] / ksu * w_u
    u = 1 / (1 + b_u + w_u + s_u)
    return np.array([catrpn, b_u * u, s_u * u, w_u * u, 0.0, 0.0, v, q["Pc0"], q["Pat"]])


def _root(fun, t0, t1):
    return optimize.brentq(fun, t0, t1, xtol=1e-12)


def beat_metrics(sol, q, y_start):
    """Metrics of one beat from a dense solution on [0, T]."""
    T = q["T"]
    tt = np.linspace(0.0, T, 20001)
    ys = sol.sol(tt)
    pr = np.array([pressures(ys[:, i], q) for i in range(len(tt))])
    plv, pat = pr[:, 0], pr[:, 1]
    gmv = pat - plv
    gao = plv - ys[7]
    g_mv_fun = lambda t: (lambda p: p[1] - p[0])(pressures(sol.sol(t), q))
    g_ao_fun = lambda t: (lambda y: pressures(y, q)[0] - y[7])(sol.sol(t))

    def first(g, start, closing):
        for i in range(start, len(tt) - 1):
            hit = (g[i] >= 0 > g[i + 1]) if closing else (g[i] <= 0 < g[i + 1])
            if hit:
                return i
        raise RuntimeError("event not found")

    if gmv[0] < 0:
        t_mvc, i_mvc = 0.0, 0
    else:
        i_mvc = first(gmv, 0, True)
        t_mvc = _root(g_mv_fun, tt[i_mvc], tt[i_mvc + 1]) if gmv[i_mvc] > 0 else tt[i_mvc]
    i_avo = first(gao, i_mvc, False)
    t_avo = _root(g_ao_fun, tt[i_avo], tt[i_avo + 1])
    i_avc = first(gao, i_avo + 1, True)
    t_avc = _root(g_ao_fun, tt[i_avc], tt[i_avc + 1])
    i_mvo = first(gmv, i_avc + 1, False)
    t_mvo = _root(g_mv_fun, tt[i_mvo], tt[i_mvo + 1])
    edv = sol.sol(t_mvc)[6]
    esv = sol.sol(t_avc)[6]
    qao = np.maximum(plv - ys[7], 0) / (q["R1"] + q["R2"])
    pao = ys[7] + q["R2"] * qao
    return {
        "EDV": edv, "ESV": esv, "SV": edv - esv, "EF": (edv - esv) / edv,
        "IVCT": t_avo - t_mvc, "ET": t_avc - t_avo, "IVRT": t_mvo - t_avc,
        "filling_time": T - (t_mvo - t_mvc),
        "P_lv_peak": plv.max(), "P_ao_sys": pao.max(), "P_ao_dia": pao.min(),
        "P_ao_pulse": pao.max() - pao.min(), "P_ao_mean": integrate.trapezoid(pao, tt) / T,
        "EDP": pressures(sol.sol(t_mvc), q)[0], "P_at_mean": integrate.trapezoid(pat, tt) / T,
        **{f"V_frame_{j:02d}": sol.sol(j * T / 20)[6] for j in range(20)},
    }


def simulate_reference(heart, v0, beats=1, rtol=1e-8, atol=1e-10):
    """Integrate ``beats`` beats from the training-protocol initial state; metrics of the last."""
    q = _pars(heart, v0)
    y = initial_state(q)
    for _ in range(beats):
        sol = integrate.solve_ivp(lambda t, yy: rhs(t, yy, q), (0.0, q["T"]), y, method="Radau", rtol=rtol, atol=atol, dense_output=True)
        assert sol.success, sol.message
        metrics = beat_metrics(sol, q, y)
        y = sol.y[:, -1]
    return metrics, y
