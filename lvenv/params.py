"""Frozen, typed parameter containers of the LO heart, with documented ranges.

Every numeric field is a PyTree leaf, so a *stacked* parameter set (leaves of shape ``(batch,)``)
vmaps for free. Ranges live in the field metadata and are checked at the Python boundary by
:func:`validate`, which names the field, the offending value and the allowed range.

Units (DESIGN): kPa, ml, s, µM, mm.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterator, Sequence

import jax
import numpy as np

from lvenv.geometry import Geometry, GeometryError, cavity_volume
from lvenv.validation import InputError, choice, integer, real, real_array

__all__ = ["LOParams", "CellParams", "Circulation", "Heart", "Arrangement", "ARRANGEMENTS", "DEFAULT_SPREAD", "MAX_ELEMENTS", "MAX_ONSET_S", "validate", "stack", "as_batch", "ranges", "field_names", "locate"]


def _param(default: float, lo: float, hi: float, units: str, doc: str, values: tuple[float, ...] | None = None) -> Any:
    """A parameter field: default, allowed range [lo, hi], units, doc and, for a switch, its ``values``."""
    return dataclasses.field(default=default, metadata={"range": (lo, hi), "units": units, "doc": doc, "values": values})


def _pytree(cls):
    cls = dataclasses.dataclass(frozen=True)(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    return jax.tree_util.register_dataclass(cls, data_fields=names, meta_fields=[])


@_pytree
class LOParams:
    """The trained LO parameters (DESIGN §1, table; defaults: N geometry), plus the activation
    delay of DESIGN §3 (ours, :func:`lvenv.coupling.calcium`; 0 in the paper's Table 3)."""

    mu1: float = _param(0.191, 1e-3, 1.0, "1", "stretch map: λ = μ1 (V/V0 − 1) + 1")
    mu2: float = _param(0.183, 1e-3, 2.0, "1", "pressure map: P = μ2 Ta + Ppass")
    gamma: float = _param(4.97, 0.0, 50.0, "1", "compression stiffening factor of Ppass (x ≤ 0)")
    alpha: float = _param(0.640, 0.0, 20.0, "kPa", "Ppass compression amplitude")
    beta: float = _param(1.39, 0.0, 20.0, "1", "Ppass compression exponent")
    a: float = _param(1.70, 0.0, 50.0, "kPa", "Ppass cubic coefficient")
    b: float = _param(-1.41, -50.0, 50.0, "kPa", "Ppass quadratic coefficient")
    c: float = _param(1.64, 1e-3, 50.0, "kPa", "Ppass linear coefficient")
    delay: float = _param(0.0, 0.0, 0.3, "s", "activation delay: the LO cell's Ca transient starts this long after the beat's onset (ours; 0 in the paper)")


@_pytree
class CellParams:
    """Land et al. 2017 human myofilament model with the paper's named parameters (DESIGN §1.1).

    Calcium-transient defaults are ours (README, "Cell defaults"): τ1 = 0.033 s, τ2 = 0.12 s,
    Cmax = 2.3 µM with Land's cross-bridge rates (Vmax factor 1) keep the training beats
    physiological and make human ejection and relaxation timing reachable.
    """

    Sa: float = _param(1.0, 0.05, 10.0, "1", "contraction efficiency (multiplies Tref)")
    vmax_factor: float = _param(1.0, 0.1, 10.0, "1", "cross-bridge cycling speed (multiplies kuw, kws)")
    n0: float = _param(0.7174, 0.3, 0.95, "1", "stretch below which no active force: h(n0) = 0")
    nA: float = _param(5.0, 1.0, 10.0, "1", "Hill coefficient of cooperativity (nTm)")
    tau1: float = _param(0.033, 1e-3, 0.3, "s", "Ca transient rise time constant")
    tau2: float = _param(0.12, 0.01, 2.0, "s", "Ca transient decay time constant")
    Cdia: float = _param(0.1, 0.0, 2.0, "µM", "diastolic [Ca]")
    Cmax: float = _param(2.3, 0.05, 10.0, "µM", "peak systolic [Ca]")
    Tref: float = _param(120.0, 1.0, 1000.0, "kPa", "reference tension")
    Ca50ref: float = _param(0.805, 0.05, 10.0, "µM", "Ca50 at λ = 1")
    beta1: float = _param(-2.4, -20.0, 20.0, "µM", "length dependence of Ca50")
    nTRPN: float = _param(2.0, 0.5, 10.0, "1", "troponin Hill coefficient")
    kTRPN: float = _param(100.0, 1.0, 1e4, "1/s", "troponin Ca binding rate")
    TRPN50: float = _param(0.35, 0.01, 0.99, "1", "CaTRPN at half tropomyosin activation")
    ku: float = _param(1000.0, 1.0, 1e5, "1/s", "tropomyosin unblocking rate")
    rw: float = _param(0.5, 0.01, 0.99, "1", "steady-state fraction of weak cross-bridges")
    rs: float = _param(0.25, 0.01, 0.99, "1", "steady-state fraction of strong cross-bridges")
    gamma_s: float = _param(8.5, 0.0, 1e4, "1/s", "strong-bridge distortion detachment")
    gamma_w: float = _param(615.0, 0.0, 1e5, "1/s", "weak-bridge distortion detachment")
    phi: float = _param(2.23, 0.0, 100.0, "1", "distortion relaxation scaling")
    Aeff: float = _param(25.0, 0.0, 1000.0, "1", "distortion per unit stretch rate")
    kuw: float = _param(182.0, 1.0, 1e5, "1/s", "unbound → weak rate (before Vmax factor)")
    kws: float = _param(12.0, 0.1, 1e5, "1/s", "weak → strong rate (before Vmax factor)")


@_pytree
class Circulation:
    """Valves, Windkessel and atrium (DESIGN §1.2). ``closed_loop`` is 0 (constant Pat) or 1 (Cat).

    Defaults (ours, README "Circulation defaults"): closed loop at 60 bpm; R2, R3, C and Cat
    from the reachability search with C fixed in the human range (15 ml/kPa ≈ 2 ml/mmHg).
    In the closed loop the conserved volume is V(0) + C Pc0 + Cat Pat (initial state).
    """

    R1: float = _param(0.0015, 1e-5, 1.0, "kPa·s/ml", "aortic valve resistance")
    R2: float = _param(0.025, 0.0, 1.0, "kPa·s/ml", "proximal (characteristic) resistance")
    R3: float = _param(0.22, 1e-3, 10.0, "kPa·s/ml", "peripheral resistance")
    C: float = _param(15.0, 0.01, 200.0, "ml/kPa", "arterial compliance")
    Rmv: float = _param(0.002, 1e-5, 1.0, "kPa·s/ml", "mitral valve resistance")
    Pat: float = _param(1.0, 0.0, 10.0, "kPa", "atrial pressure (open loop) or its initial value (closed loop)")
    Cat: float = _param(2.0, 0.1, 1000.0, "ml/kPa", "atrial compliance (closed loop)")
    Pc0: float = _param(10.0, 0.0, 40.0, "kPa", "initial Windkessel capacitor pressure")
    HR: float = _param(60.0, 20.0, 240.0, "1/min", "heart rate")
    closed_loop: float = _param(1.0, 0.0, 1.0, "1", "0: open loop (constant Pat, venous side at 0 kPa); 1: closed loop", values=(0.0, 1.0))


ARRANGEMENTS = ("parallel", "series")
#: Default range of the per-element value: μ1_ξ (parallel) or the weight w_ξ (series).
DEFAULT_SPREAD = {"parallel": (0.01, 0.179), "series": (0.6, 1.0)}
#: Largest number of elements accepted at the Python boundary.
MAX_ELEMENTS = 4096
#: Largest magnitude of an element's onset relative to the LO delay (s).
MAX_ONSET_S = 0.3
_W_RANGE = (1e-3, 10.0)  # allowed series weights w_ξ (1)


@dataclasses.dataclass(frozen=True)
class Arrangement:
    """A multi-element LO heart (:mod:`lvenv.multielement`, DESIGN §1.4): how its cells are
    arranged: ``kind`` ∈ {"parallel", "series"}, ``n_elements``, the ``spread`` of μ1_ξ
    (parallel) or w_ξ (series), linear over [spread[0], spread[1]], and the elements' calcium
    ``onsets`` (s, relative to the LO delay; ``None``: all 0), one per element or, in a stacked
    Heart, one row of them per member (:func:`stack` builds those rows: walls differ in their
    onsets, and still batch together).

    ``spread=None`` takes :data:`DEFAULT_SPREAD`. Validated on construction (``ValueError``
    naming the field, the value and what is allowed). Hashable: a :class:`Heart` carries it as
    static data (``Heart.elements``); the members of a batch share its :meth:`model_key`.
    """

    kind: str
    n_elements: int = 256
    spread: tuple[float, float] | None = None
    onsets: tuple[float, ...] | tuple[tuple[float, ...], ...] | None = None

    def __post_init__(self):
        choice("arrangement", self.kind, ARRANGEMENTS)
        object.__setattr__(self, "n_elements", integer("n_elements", self.n_elements, 1, MAX_ELEMENTS))
        spread = DEFAULT_SPREAD[self.kind] if self.spread is None else self.spread
        if np.ndim(spread) != 1 or len(spread) != 2:
            raise InputError(f"spread = {spread!r} must be a pair (low, high)")
        lo, hi = (ranges()["mu1"][:2] if self.kind == "parallel" else _W_RANGE)
        name = "spread (μ1_ξ)" if self.kind == "parallel" else "spread (w_ξ)"
        low = real(f"{name}[0]", spread[0], lo, hi)
        high = real(f"{name}[1]", spread[1], low, hi)
        object.__setattr__(self, "spread", (low, high))
        if self.onsets is not None:
            try:
                shape = np.shape(self.onsets)
            except ValueError:  # ragged rows
                shape = None
            n = self.n_elements
            if shape != (n,) and not (shape is not None and len(shape) == 2 and shape[0] >= 1 and shape[1] == n):
                raise InputError(f"onsets = {self.onsets!r} must give one onset (s) per element, {n} in all (in a stacked Heart: one such row per member)")
            onset = lambda where, x: real(where, x, -MAX_ONSET_S, MAX_ONSET_S)
            rows = (tuple(onset(f"onsets[{i}]", x) for i, x in enumerate(self.onsets)) if len(shape) == 1 else
                    tuple(tuple(onset(f"onsets[{m}][{i}]", x) for i, x in enumerate(row)) for m, row in enumerate(self.onsets)))
            object.__setattr__(self, "onsets", rows)

    def model_key(self) -> tuple[str, int, tuple[float, float]]:
        """(kind, n_elements, spread): what the members of a batch share (their onsets may differ)."""
        return self.kind, self.n_elements, self.spread

    def element_onsets(self) -> np.ndarray:
        """Onset of each element relative to the LO delay (s), shape ``(n_elements,)``, or
        ``(members, n_elements)`` for per-member onsets."""
        return np.zeros(self.n_elements) if self.onsets is None else np.array(self.onsets, float)

    def member_onsets(self, n_members: int) -> np.ndarray:
        """Each member's element onsets (s), ``(n_elements, n_members)``: the one row for every
        member, or one row each; :class:`~lvenv.validation.InputError` if the rows are not one per member."""
        onsets = self.element_onsets()
        if onsets.ndim == 1:
            return onsets[:, None] * np.ones(n_members)
        if len(onsets) != n_members:
            raise InputError(f"elements.onsets has {len(onsets)} rows (one per member) for a batch of {n_members} members")
        return onsets.T.copy()

    def element_values(self) -> np.ndarray:
        """μ1_ξ (parallel) or w_ξ (series), shape ``(n_elements,)``."""
        lo, hi = self.spread
        frac = np.linspace(0.0, 1.0, self.n_elements) if self.n_elements > 1 else np.array([0.5])
        return lo + (hi - lo) * frac

    def to_dict(self) -> dict[str, Any]:
        """The arrangement as a JSON-ready object (:meth:`from_dict` reads it back)."""
        return {"kind": self.kind, "n_elements": self.n_elements, "spread": list(self.spread),
                "onsets": None if self.onsets is None else np.asarray(self.onsets).tolist()}

    @classmethod
    def from_dict(cls, record: Any, where: str = "elements") -> "Arrangement":
        """An arrangement from :meth:`to_dict`'s object (``where`` names it in errors): ``kind``
        required, ``n_elements``, ``spread`` and ``onsets`` optional; an unknown field, or a value
        of the wrong type or out of range, raises :class:`~lvenv.validation.InputError`."""
        if not isinstance(record, dict):
            raise InputError(f"{where} = {record!r} must be null (the single-cell heart) or an object with the fields {_ARRANGEMENT_FIELDS}")
        if "kind" not in record:
            raise InputError(f"{where} lacks the field 'kind' (one of {ARRANGEMENTS})")
        if unknown := sorted(str(k) for k in record if k not in _ARRANGEMENT_FIELDS):
            raise InputError(f"{where} has the unknown field(s) {unknown}; known: {list(_ARRANGEMENT_FIELDS)}")
        for name in ("spread", "onsets"):
            if record.get(name) is not None and not isinstance(record[name], list):
                raise InputError(f"{where}.{name} = {record[name]!r} must be a list of numbers")
        try:
            onsets = record.get("onsets")
            return cls(kind=record["kind"], n_elements=record.get("n_elements", 256),
                       spread=None if record.get("spread") is None else tuple(record["spread"]),
                       onsets=None if onsets is None else tuple(tuple(r) if isinstance(r, list) else r for r in onsets))
        except ValueError as err:
            raise InputError(f"{where}: {err}") from None


_ARRANGEMENT_FIELDS = ("kind", "n_elements", "spread", "onsets")


@dataclasses.dataclass(frozen=True)
class Heart:
    """One LO heart: unloaded geometry, trained LO maps, cell unit and circulation.

    A *stacked* Heart (every leaf an array of shape ``(batch,)``) is a batch; build one with
    :func:`stack`. ``V0`` is derived from ``geometry`` (:func:`lvenv.geometry.cavity_volume`).
    ``elements``: ``None`` (default) for the paper's single-cell LO heart, or an
    :class:`Arrangement` for a multi-element one (:mod:`lvenv.multielement`); every function
    that takes a Heart simulates whichever it carries, and a batch shares one.
    """

    geometry: Geometry
    lo: LOParams = dataclasses.field(default_factory=LOParams)
    cell: CellParams = dataclasses.field(default_factory=CellParams)
    circulation: Circulation = dataclasses.field(default_factory=Circulation)
    elements: Arrangement | None = None

    def replace(self, **changes: Any) -> "Heart":
        """Return a copy with fields changed by name, e.g. ``heart.replace(tau2=0.2, R3=0.1)``.

        Names are looked up in ``lo``, ``cell`` and ``circulation``; ``geometry``, ``lo``,
        ``cell``, ``circulation`` and ``elements`` replace the whole part.
        """
        top = {k: changes.pop(k) for k in ("geometry", "lo", "cell", "circulation", "elements") if k in changes}
        if unknown := sorted(k for k in changes if k not in _LOCATION):
            raise TypeError(f"unknown Heart parameter(s): {unknown}; known: {field_names()}")
        heart = dataclasses.replace(self, **top)
        parts: dict[str, dict[str, Any]] = {}
        for name, value in changes.items():
            parts.setdefault(locate(name), {})[name] = value
        return dataclasses.replace(heart, **{part: dataclasses.replace(getattr(heart, part), **mine) for part, mine in parts.items()})

    def get(self, name: str) -> Any:
        """The value of the LO, cell or circulation parameter ``name`` (scalar or per member)."""
        return getattr(getattr(self, locate(name)), name)


def _flatten_geometry(g: Geometry):
    return [getattr(g, f.name) for f in dataclasses.fields(Geometry)], None


def _unflatten_geometry(_, leaves):
    g = object.__new__(Geometry)
    for f, v in zip(dataclasses.fields(Geometry), leaves):
        object.__setattr__(g, f.name, v)
    return g


jax.tree_util.register_pytree_node(Geometry, _flatten_geometry, _unflatten_geometry)
jax.tree_util.register_dataclass(Heart, data_fields=["geometry", "lo", "cell", "circulation"], meta_fields=["elements"])

_PARTS = (("lo", LOParams), ("cell", CellParams), ("circulation", Circulation))
_LOCATION = {f.name: part for part, cls in _PARTS for f in dataclasses.fields(cls)}


def locate(name: str) -> str:
    """The part of :class:`Heart` (``"lo"``, ``"cell"`` or ``"circulation"``) holding parameter ``name``."""
    if name not in _LOCATION:
        raise TypeError(f"unknown Heart parameter {name!r}; known: {field_names()}")
    return _LOCATION[name]


def field_names() -> list[str]:
    """All settable parameter names of :class:`Heart` (LO, cell and circulation)."""
    return [f.name for _, cls in _PARTS for f in dataclasses.fields(cls)]


def ranges() -> dict[str, tuple[float, float, str, str]]:
    """``{name: (lo, hi, units, doc)}`` for every parameter with a documented range."""
    out = {}
    for _, cls in _PARTS:
        for f in dataclasses.fields(cls):
            lo, hi = f.metadata["range"]
            out[f.name] = (lo, hi, f.metadata["units"], f.metadata["doc"])
    return out


def _member(arr: np.ndarray, where: np.ndarray) -> str:
    if arr.ndim == 0:
        return ""
    return f" (batch member {int(np.flatnonzero(where.ravel())[0])})"


def validate(heart: Heart) -> None:
    """Raise ``ValueError`` naming the field, value and allowed range of the first bad parameter.

    Works on a single Heart or a stacked batch. Also checks the cross-field conditions
    τ1 < τ2, Cdia < Cmax and that Ppass is monotone for x > 0 (b² < 3ac or b ≥ 0).
    """
    _check(_as_arrays(heart))


def _check(heart: Heart) -> int | None:
    """:func:`validate` of a Heart whose parameters are arrays already; returns its batch size."""
    size = batch_size(heart)
    for part, cls in _PARTS:
        for f in dataclasses.fields(cls):
            arr, name = getattr(getattr(heart, part), f.name), f.name
            (lo, hi), units, values = f.metadata["range"], f.metadata["units"], f.metadata["values"]
            bad = ~np.isfinite(arr) | (arr < lo) | (arr > hi)
            if np.any(bad):
                value = float(arr.ravel()[np.flatnonzero(bad.ravel())[0]])
                shown = f"{value:g}" if units == "1" else f"{value:g} {units}"  # "1": dimensionless
                raise InputError(f"{part}.{name} = {shown} is outside the allowed range [{lo:g}, {hi:g}]{_member(arr, bad)}")
            if values is not None and np.any(bad := ~np.isin(arr, values)):
                value = float(arr.ravel()[np.flatnonzero(bad.ravel())[0]])
                raise InputError(f"{part}.{name} = {value:g} must be one of {', '.join(f'{v:g}' for v in values)}{_member(arr, bad)}")
    cell, lo = heart.cell, heart.lo
    tau1, tau2 = np.asarray(cell.tau1, float), np.asarray(cell.tau2, float)
    if np.any(bad := tau1 >= tau2):
        raise InputError(f"cell.tau1 = {float(np.ravel(tau1)[np.flatnonzero(bad.ravel())[0]]):g} s must be below cell.tau2 (rise faster than decay){_member(tau1, bad)}")
    cdia, cmax = np.asarray(cell.Cdia, float), np.asarray(cell.Cmax, float)
    if np.any(bad := cdia >= cmax):
        raise InputError(f"cell.Cdia = {float(np.ravel(cdia)[np.flatnonzero(bad.ravel())[0]]):g} µM must be below cell.Cmax{_member(cdia, bad)}")
    a, b, c = (np.asarray(v, float) for v in (lo.a, lo.b, lo.c))
    if np.any(bad := (b < 0) & (b * b >= 3 * a * c)):
        raise InputError(f"lo.b = {float(np.ravel(b)[np.flatnonzero(bad.ravel())[0]]):g} kPa makes Ppass non-monotone for V > V0 (need b² < 3ac){_member(b, bad)}")
    if heart.elements is not None:
        heart.elements.member_onsets(size or 1)
    cavity_volumes(heart)
    return size


def cavity_volumes(heart: Heart) -> np.ndarray:
    """V0 (ml) of each member's geometry; validates every distinct geometry once."""
    g = heart.geometry
    rows = np.stack(np.broadcast_arrays(*(real_array(f"geometry.{f.name}", getattr(g, f.name)) for f in dataclasses.fields(Geometry))), axis=-1)
    flat = np.ascontiguousarray(rows.reshape(-1, rows.shape[-1]))
    keys = flat.view(np.dtype((np.void, flat.dtype.itemsize * flat.shape[1]))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    unique = flat[first]
    v0 = np.empty(len(unique))
    for i, row in enumerate(unique):
        try:
            v0[i] = cavity_volume(Geometry(*row))
        except GeometryError as err:
            where = np.flatnonzero(inverse.ravel() == i)
            suffix = f" (batch member {int(where[0])})" if rows.ndim > 1 else ""
            raise GeometryError(f"{err}{suffix}") from None
    return v0[inverse.ravel()].reshape(rows.shape[:-1])


def stack(hearts: Sequence[Heart]) -> Heart:
    """Stack a sequence of Hearts into one batched Heart (leaves of shape ``(len(hearts),)``)."""
    if isinstance(hearts, (str, bytes)) or not isinstance(hearts, Sequence):
        raise InputError(f"expected a sequence of lvenv.Heart, got {type(hearts).__name__}")
    if len(hearts) == 0:
        raise InputError("cannot stack an empty sequence of Hearts")
    arrays = []
    for i, heart in enumerate(hearts):
        if not isinstance(heart, Heart):
            raise InputError(f"member {i} is a {type(heart).__name__}, not an lvenv.Heart")
        try:
            arrays.append(dataclasses.replace(_as_arrays(heart), elements=None))
        except InputError as err:
            raise InputError(f"{err} (batch member {i})") from None
        if batch_size(arrays[-1]) is not None or (heart.elements is not None and np.ndim(heart.elements.element_onsets()) > 1):
            raise InputError(f"member {i} is itself a stacked batch; pass single Hearts")
    return dataclasses.replace(jax.tree.map(lambda *xs: np.stack(xs), *arrays), elements=_stacked_elements([h.elements for h in hearts]))


def _stacked_elements(elements: Sequence[Arrangement | None]) -> Arrangement | None:
    """The members' one LO heart model; per-member onsets where their walls' differ."""
    first = elements[0]
    key = lambda e: None if e is None else e.model_key()
    for i, e in enumerate(elements):
        if key(e) != key(first):
            raise InputError(f"member {i} has elements = {e!r} but member 0 has {first!r}: a batch shares one LO heart model "
                             "(kind, n_elements, spread; simulate different ones in separate batches)")
    if first is None or all(e == first for e in elements):
        return first
    return dataclasses.replace(first, onsets=tuple(tuple(e.element_onsets()) for e in elements))


def _as_arrays(heart: Heart) -> Heart:
    """The same Heart with every parameter a float64 array (a list becomes one array, not a
    subtree); wrong types raise :class:`InputError` naming the field."""
    if not isinstance(heart, Heart):
        raise InputError(f"expected an lvenv.Heart, got {type(heart).__name__}")
    if not isinstance(heart.geometry, Geometry):
        raise InputError(f"heart.geometry must be an lvenv.Geometry, got {type(heart.geometry).__name__}")
    parts = {}
    for part, cls in _PARTS:
        obj = getattr(heart, part)
        if not isinstance(obj, cls):
            raise InputError(f"heart.{part} must be an lvenv.{cls.__name__}, got {type(obj).__name__}")
        parts[part] = dataclasses.replace(obj, **{f.name: real_array(f"{part}.{f.name}", getattr(obj, f.name)) for f in dataclasses.fields(cls)})
    if heart.elements is not None and not isinstance(heart.elements, Arrangement):
        raise InputError(f"heart.elements must be None (the single-cell heart) or an lvenv.params.Arrangement, got {type(heart.elements).__name__}")
    g = heart.geometry
    leaves = [real_array(f"geometry.{f.name}", getattr(g, f.name)) for f in dataclasses.fields(Geometry)]
    return Heart(geometry=jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(g), leaves), elements=heart.elements, **parts)


def as_batch(params: Heart | Sequence[Heart]) -> tuple[Heart, bool]:
    """Validated batch (every leaf a float array of shape ``(B,)``) and whether ``params`` was one Heart.

    Accepts a single Heart, a sequence of Hearts, or a stacked Heart whose leaves are numbers or
    arrays of shape ``(B,)`` (numbers are broadcast to every member).
    """
    if isinstance(params, Heart):
        heart = _as_arrays(params)
        size = _check(heart)
        return jax.tree.map(lambda x: np.broadcast_to(x, (size or 1,)).copy(), heart), size is None
    heart = stack(params)
    _check(heart)
    return heart, False


def _named_leaves(heart: Heart) -> Iterator[tuple[str, Any]]:
    for f in dataclasses.fields(Geometry):
        yield f"geometry.{f.name}", getattr(heart.geometry, f.name)
    for part, cls in _PARTS:
        for f in dataclasses.fields(cls):
            yield f"{part}.{f.name}", getattr(getattr(heart, part), f.name)


def batch_size(heart: Heart) -> int | None:
    """``None`` for a single Heart, else the common leading dimension of a stacked one."""
    size, first = None, None
    for name, value in _named_leaves(heart):
        shape = np.shape(value)
        if len(shape) > 1 or shape == (0,):
            raise InputError(f"{name} has shape {shape}; a parameter is a number or, in a batch, one number per member (shape (B,), B ≥ 1)")
        if shape and size is None:
            size, first = shape[0], name
        elif shape and shape[0] != size:
            raise InputError(f"{name} has {shape[0]} members but {first} has {size}: every batched parameter needs one value per member")
    return size
