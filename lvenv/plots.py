"""Figures of a beat (matplotlib, Agg backend): PV loop and traces, a fit against its targets
(the paper's Fig. 10), LO against FE traces, profile likelihoods and posterior pairs, and the
anatomy regression's trained maps over geometry (the paper's Fig. 9) with its parity plot. Each writes PNG or PDF by the file's suffix.

Axes are in display units (mmHg, ms, ml) through :mod:`lvenv.units`; the functions take internal
units (s, ml, kPa) like the rest of :mod:`lvenv`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from lvenv.simulation import Traces
from lvenv.units import MS_PER_S, kpa_to_mmhg
from lvenv.validation import InputError

__all__ = ["SUFFIXES", "beat_figure", "fit_figure", "lo_fe_figure", "convergence_figure", "histogram_figure", "generalisation_figure",
           "pairs_figure", "profile_figure", "ANATOMY_OUTPUTS", "anatomy_scatter_figure", "anatomy_contour_figure", "parity_figure"]

SUFFIXES = (".png", ".pdf")


def _figure(path: str | os.PathLike[str], ncols: int, width: float = 11.0, nrows: int = 1, height: float = 4.0):
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise InputError(f"plot file {str(path)!r} must end in one of {SUFFIXES}")
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    return path, fig, fig.subplots(nrows, ncols, squeeze=nrows == 1)


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def _log_axis(axis) -> None:
    """A log axis with ticks at 1, 2 and 5 × 10^k, labelled plainly (no minor labels)."""
    from matplotlib import ticker

    axis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(ticker.FormatStrFormatter("%g"))
    axis.set_minor_formatter(ticker.NullFormatter())


def _traces(ax, tr: Traces, style: str = "-", label: str = "") -> None:
    t_ms = np.asarray(tr.t) * MS_PER_S
    ax.plot(t_ms, kpa_to_mmhg(np.asarray(tr.P_lv)), style, color="C3", label=f"P_lv {label}".strip())
    if tr.P_ao is not None and np.any(np.isfinite(tr.P_ao)):
        ax.plot(t_ms, kpa_to_mmhg(np.asarray(tr.P_ao)), style, color="C0", label=f"P_ao {label}".strip())
    ax.set(xlabel="t (ms)", ylabel="P (mmHg)")


def beat_figure(traces: Traces, path: str | os.PathLike[str], title: str = "") -> Path:
    """PV loop (left) and P_lv, P_ao and V against time (right) of one beat."""
    path, fig, (ax_pv, ax_t) = _figure(path, 2)
    ax_pv.plot(traces.V, kpa_to_mmhg(np.asarray(traces.P_lv)), color="C3")
    ax_pv.set(xlabel="V (ml)", ylabel="P_lv (mmHg)", title=title)
    _traces(ax_t, traces)
    ax_v = ax_t.twinx()
    ax_v.plot(np.asarray(traces.t) * MS_PER_S, traces.V, "--", color="C2", label="V")
    ax_v.set_ylabel("V (ml)")
    ax_t.legend(loc="upper right", fontsize=8)
    return _save(fig, path)


def fit_figure(traces: Traces, metrics: Mapping[str, float], targets: Mapping[str, float], path: str | os.PathLike[str],
               title: str = "") -> Path:
    """A fitted beat against its targets (after the paper's Fig. 10): pressures and volume over
    the beat, the targeted pressures as dotted lines, the target ET as a bar from the fitted
    aortic opening and the target IVRT from the fitted aortic closing, and the target
    ESV = EDV·(1 − EF) as a line."""
    path, fig, (ax_p, ax_v) = _figure(path, 2)
    _traces(ax_p, traces)
    for key, color in (("P_ao_sys", "C0"), ("P_ao_dia", "C0"), ("P_ao_mean", "C9")):
        if key in targets:
            ax_p.axhline(kpa_to_mmhg(targets[key]), ls=":", color=color, label=f"target {key}")
    t_open, t_close = _ejection(traces)
    top = ax_p.get_ylim()[1]
    for i, (key, start) in enumerate((("ET", t_open), ("IVRT", t_close))):
        if key in targets and np.isfinite(start):
            ax_p.plot([start, start + float(targets[key]) * MS_PER_S], [top * (0.95 - 0.05 * i)] * 2, lw=4, color=f"C{i + 1}", label=f"target {key}")
    ax_p.legend(loc="upper right", fontsize=7)
    ax_p.set_title(title)
    t_ms = np.asarray(traces.t) * MS_PER_S
    ax_v.plot(t_ms, traces.V, color="C2", label="V")
    if "EF" in targets:
        esv = float(metrics["EDV"]) * (1.0 - float(targets["EF"]))
        ax_v.axhline(esv, ls=":", color="k", label="target ESV = EDV (1 − EF)")
    for key in ("EDV", "ESV"):
        if key in targets:
            ax_v.axhline(float(targets[key]), ls="--", color="k", label=f"target {key}")
    ax_v.set(xlabel="t (ms)", ylabel="V (ml)")
    ax_v.legend(loc="upper right", fontsize=7)
    return _save(fig, path)


def _ejection(traces: Traces) -> tuple[float, float]:
    """Times (ms) of the fitted aortic opening and closing: the first run of P_lv > P_ao."""
    open_ = np.asarray(traces.P_lv) > np.asarray(traces.P_ao)
    if not open_.any():
        return np.nan, np.nan
    first = int(np.argmax(open_))
    last = first + int(np.argmin(open_[first:])) if not open_[first:].all() else len(open_) - 1
    t_ms = np.asarray(traces.t) * MS_PER_S
    return float(t_ms[first]), float(t_ms[last])


def lo_fe_figure(lo: Traces, fe: Traces, path: str | os.PathLike[str], title: str = "") -> Path:
    """P and V against time of the FE oracle (solid) and the LO heart (dashed), and both PV loops."""
    path, fig, (ax_p, ax_v, ax_pv) = _figure(path, 3, width=14.0)
    _traces(ax_p, fe, "-", "FE")
    _traces(ax_p, lo, "--", "LO")
    ax_p.legend(fontsize=7)
    ax_p.set_title(title)
    for tr, style, label in ((fe, "-", "FE"), (lo, "--", "LO")):
        ax_v.plot(np.asarray(tr.t) * MS_PER_S, tr.V, style, color="C2", label=label)
        ax_pv.plot(tr.V, kpa_to_mmhg(np.asarray(tr.P_lv)), style, color="C3", label=label)
    ax_v.set(xlabel="t (ms)", ylabel="V (ml)")
    ax_pv.set(xlabel="V (ml)", ylabel="P_lv (mmHg)")
    ax_pv.legend(fontsize=7)
    return _save(fig, path)


def convergence_figure(best: Mapping[str, np.ndarray], path: str | os.PathLike[str], title: str = "") -> Path:
    """Optimiser convergence: best mismatch so far (%, log scale) against evaluations, one line
    per run (``best[label]`` is the running minimum per evaluation, inf before a success)."""
    path, fig, ax = _figure(path, 1, width=6.0)
    for label, values in best.items():
        values = np.asarray(values, float)
        ax.plot(np.arange(1, len(values) + 1), np.where(np.isfinite(values), 100.0 * values, np.nan), label=label)
    ax.set(xlabel="evaluations", ylabel="best mismatch (%)", yscale="log", title=title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def histogram_figure(values: np.ndarray, path: str | os.PathLike[str], xlabel: str, title: str = "") -> Path:
    """A histogram of ``values`` (already in display units), e.g. a cohort's mismatch."""
    path, fig, ax = _figure(path, 1, width=6.0)
    ax.hist(np.asarray(values, float), bins=40, color="C0")
    ax.set(xlabel=xlabel, ylabel="count", title=title)
    return _save(fig, path)


def generalisation_figure(rows: list[Mapping], path: str | os.PathLike[str], columns: int) -> Path:
    """The paper's Fig. 7 panel: per scenario (``columns`` per heart) V and P_lv of the oracle
    (solid; ``row["oracle"]`` with ``t``, ``V``, ``P_lv``) and the LO heart (dashed; ``row["lo"]``,
    the same keys), titled with the scenario and its C. A row's ``candidates`` (optional, a
    label → traces mapping, the same for every row) adds one coloured line per candidate LO
    heart, with a legend."""
    hearts = -(-len(rows) // columns)
    path, fig, axes = _figure(path, columns, width=2.6 * columns, nrows=2 * hearts, height=4.4 * hearts)
    for i, r in enumerate(rows):
        h, j = divmod(i, columns)
        for k, (key, unit) in enumerate((("V", "ml"), ("P_lv", "mmHg"))):
            ax = axes[2 * h + k, j]
            show = (lambda v: kpa_to_mmhg(np.asarray(v))) if key == "P_lv" else np.asarray
            ax.plot(r["oracle"]["t"], show(r["oracle"][key]), "k-", lw=1.2, label="FE")
            ax.plot(r["lo"]["t"], show(r["lo"][key]), "C3--", lw=1.2, label="LO")
            for c, (label, tr) in enumerate(r.get("candidates", {}).items()):
                ax.plot(tr["t"], show(tr[key]), color=f"C{c if c < 3 else c + 1}", ls=":", lw=1.2, label=label)  # C3: the LO line
            if i == 0 and k == 0 and r.get("candidates"):
                ax.legend(fontsize=6)
            ax.set_title(f"{r['heart']} {r['scenario']}\nC {100 * r['C']:.1f} %" if k == 0 else "", fontsize=8)
            ax.set_ylabel(f"{key} ({unit})" if j == 0 else "", fontsize=8)
            ax.tick_params(labelsize=7)
    return _save(fig, path)


def pairs_figure(samples: Mapping[str, Mapping[str, np.ndarray]], path: str | os.PathLike[str], log: Mapping[str, bool] | None = None,
                 max_points: int = 2000) -> Path:
    """Posterior pairs plot: for each label (e.g. a patient) of ``samples[label][name]``, the
    marginal histograms on the diagonal and ``max_points`` draws of each pair below it, one
    colour per label. ``log[name]``: a log axis for that parameter (as its identification bound)."""
    labels = list(samples)
    names = list(samples[labels[0]])
    log = dict(log or {})
    k = len(names)
    path, fig, axes = _figure(path, k, width=1.9 * k, nrows=k, height=1.9 * k)
    rng = np.random.default_rng(0)
    for c, label in enumerate(labels):
        draws = {n: np.asarray(samples[label][n], float) for n in names}
        pick = rng.choice(len(draws[names[0]]), size=min(max_points, len(draws[names[0]])), replace=False)
        for i, ni in enumerate(names):
            for j, nj in enumerate(names):
                ax = axes[i, j]
                if j > i:
                    ax.set_visible(False)
                elif i == j:
                    bins = np.geomspace(*np.percentile(draws[ni], [0, 100]), 40) if log.get(ni) else 40
                    ax.hist(draws[ni], bins=bins, color=f"C{c}", alpha=0.5, density=True, label=label)
                else:
                    ax.plot(draws[nj][pick], draws[ni][pick], ".", color=f"C{c}", ms=1.5, alpha=0.3)
    for i, ni in enumerate(names):
        for j, nj in enumerate(names[: i + 1]):
            ax = axes[i, j]
            if log.get(nj):
                ax.set_xscale("log")
                _log_axis(ax.xaxis)
            if log.get(ni) and i != j:
                ax.set_yscale("log")
                _log_axis(ax.yaxis)
            ax.tick_params(labelsize=6)
            ax.set_xlabel(nj if i == k - 1 else "", fontsize=8)
            ax.set_ylabel(ni if j == 0 and i > 0 else "", fontsize=8)
    axes[0, 0].legend(fontsize=7)
    return _save(fig, path)


def profile_figure(grid: Mapping[str, np.ndarray], chi2: Mapping[str, np.ndarray], chi2_min: float, path: str | os.PathLike[str],
                   threshold: float, log: Mapping[str, bool] | None = None, best: Mapping[str, float] | None = None) -> Path:
    """Profile likelihoods: per parameter, χ² of its constrained fits minus the overall minimum
    against the parameter (NaN points left out), the threshold Δχ² (dashed) and the best fit's
    value (dotted, ``best``). ``log[name]``: a log axis for that parameter."""
    names = list(grid)
    log, best = dict(log or {}), dict(best or {})
    cols = min(3, len(names))
    rows = -(-len(names) // cols)
    path, fig, axes = _figure(path, cols, width=3.6 * cols, nrows=rows, height=2.9 * rows)
    axes = np.atleast_2d(axes)
    for i, name in enumerate(names):
        ax = axes[i // cols, i % cols]
        x, y = np.asarray(grid[name], float), np.asarray(chi2[name], float) - chi2_min
        ax.plot(x[np.isfinite(y)], y[np.isfinite(y)], "o-", color="C0", ms=4)
        ax.axhline(threshold, ls="--", color="C3", lw=1)
        if name in best:
            ax.axvline(best[name], ls=":", color="k", lw=1)
        if log.get(name):
            ax.set_xscale("log")
            _log_axis(ax.xaxis)
        ax.set(xlabel=name, ylabel="Δχ²" if i % cols == 0 else "")
        ax.tick_params(labelsize=7)
    for j in range(len(names), rows * cols):
        axes[j // cols, j % cols].set_visible(False)
    return _save(fig, path)


#: The trained parameters the anatomy figures show (the paper's Fig. 9 and our delay).
ANATOMY_OUTPUTS = ("mu1", "mu2", "gamma", "delay")


def _anatomy_grid(regression, name: str, n: int = 60) -> np.ndarray:
    lo, hi = regression.box[name]
    return np.linspace(lo, hi, n)


def _slice_geometries(regression, values: Mapping[str, np.ndarray]) -> list:
    """Geometries along ``values`` (by `Geometry` field) with every other parameter at the
    training anatomies' median."""
    from lvenv.anatomy import INPUTS
    from lvenv.geometry import Geometry

    median = np.median(regression.x * regression.x_scale + regression.x_mean, axis=0)
    n = len(next(iter(values.values())))
    columns = [np.asarray(values[k]) if k in values else np.full(n, median[j]) for j, k in enumerate(INPUTS)]
    return [Geometry(*row) for row in np.stack(columns, axis=1)]


def anatomy_scatter_figure(regression, path: str | os.PathLike[str], inputs: tuple[str, ...] = ("Rb", "L"),
                           outputs: tuple[str, ...] = ANATOMY_OUTPUTS) -> Path:
    """Trained values of the training anatomies against each of ``inputs`` (mm), with the GP's
    mean ± 1 sd along that input (the others at their median): the paper's Fig. 9 scatter."""
    from lvenv.anatomy import INPUTS

    path, fig, axes = _figure(path, len(outputs), width=3.2 * len(outputs), nrows=len(inputs), height=3.0 * len(inputs))
    x = regression.x * regression.x_scale + regression.x_mean
    for i, inp in enumerate(inputs):
        grid = _anatomy_grid(regression, inp)
        mean, sd = regression.predict(_slice_geometries(regression, {inp: grid}), outputs)
        for j, out in enumerate(outputs):
            ax = axes[i][j]
            spec = regression.outputs[out]
            ax.plot(x[:, INPUTS.index(inp)], regression.y[out] * spec["scale"] + spec["mean"], "o", ms=3, color="tab:blue")
            ax.plot(grid, mean[out], "-", color="tab:red")
            ax.fill_between(grid, mean[out] - sd[out], mean[out] + sd[out], color="tab:red", alpha=0.2, lw=0)
            ax.set_xlabel(f"{inp} (mm)" if inp in ("Rb", "L", "Z", "H") else inp)
            ax.set_ylabel(f"{out} (s)" if out == "delay" else out)
    return _save(fig, path)


def anatomy_contour_figure(regression, path: str | os.PathLike[str], outputs: tuple[str, ...] = ANATOMY_OUTPUTS) -> Path:
    """GP mean of each output over (Rb, L) in mm, the other parameters at their median."""
    path, fig, axes = _figure(path, len(outputs), width=3.4 * len(outputs), height=3.2)
    rb, thickness = np.meshgrid(_anatomy_grid(regression, "Rb", 40), _anatomy_grid(regression, "L", 40))
    mean, _ = regression.predict(_slice_geometries(regression, {"Rb": rb.ravel(), "L": thickness.ravel()}), outputs)
    for ax, out in zip(axes, outputs):
        filled = ax.contourf(rb, thickness, mean[out].reshape(rb.shape), levels=12, cmap="viridis")
        fig.colorbar(filled, ax=ax)
        ax.set(xlabel="Rb (mm)", ylabel="L (mm)", title=f"{out} (s)" if out == "delay" else out)
    return _save(fig, path)


def parity_figure(truth: Mapping[str, np.ndarray], predicted: Mapping[str, np.ndarray], sd: Mapping[str, np.ndarray],
                  path: str | os.PathLike[str]) -> Path:
    """Cross-validated predictions (± 2 sd) against the trained values, one panel per output."""
    names = list(truth)
    cols = min(5, len(names))
    rows = -(-len(names) // cols)
    path, fig, axes = _figure(path, cols, width=3.0 * cols, nrows=rows, height=3.0 * rows)
    flat = np.ravel(axes)
    for ax, name in zip(flat, names):
        t, p, s = (np.asarray(d[name], float) for d in (truth, predicted, sd))
        ax.errorbar(t, p, yerr=2 * s, fmt="o", ms=3, lw=0.8, alpha=0.8)
        lo, hi = float(min(t.min(), p.min())), float(max(t.max(), p.max()))
        ax.plot([lo, hi], [lo, hi], "k--", lw=0.8)
        ax.set(xlabel=f"trained {name}", ylabel=f"predicted {name}")
    for ax in flat[len(names):]:
        ax.set_visible(False)
    return _save(fig, path)
