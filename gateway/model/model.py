"""The thermal model: a matrix of paths (axis x factor), each a small parametric transfer function.

The model is data. It is saved as TOML next to the profile and round-trips exactly (floats are written
with ``repr``). Inputs are deviations of the factors from the reference state (the machine at rest,
powered long enough to be in thermal equilibrium): ``reference`` holds those factor levels, e.g. the Z
motor's holding current squared on a vertical machine.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import tomli_w

from gateway.errors import ModelError
from gateway.model import limits
from gateway.model.correlation import GainCorrelation, correlation_to_toml, parse_correlation
from gateway.model.coverage import Coverage, coverage_to_toml, parse_coverage
from gateway.model.discrete import Section
from gateway.model.envelope import Envelope, envelope_to_toml, parse_envelope
from gateway.model.inputs import DerivedInput, check_order, input_to_toml, parse_inputs, recorded_columns
from gateway.model.terms import TERM_KINDS, FirstOrder, SecondOrder, Term
from gateway.tomlcheck import Table, TomlDoc

FORMAT = 1


@dataclass(frozen=True, kw_only=True, slots=True)
class PathTF:
    """G_ij(s): the sum of ``terms``, behind a dead time of ``delay_s``. No terms is a zero path."""

    axis: str
    factor: str
    terms: tuple[Term, ...] = ()
    delay_s: float = 0.0
    #: standard deviations of the identified parameters, keyed "term0.gain", "term0.tau_s", ...
    sd: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))

    def __post_init__(self) -> None:
        if not (math.isfinite(self.delay_s) and self.delay_s >= 0):
            raise ValueError(f"path {self.axis}/{self.factor}: delay_s must be finite and >= 0. "
                             f"Got {self.delay_s!r}")

    @property
    def gain(self) -> float:
        """Static gain in um per factor unit (the sum of the terms' gains)."""
        return float(sum(t.gain for t in self.terms))

    @property
    def K(self) -> float:
        """The paper's K = 1/gain (inf for a zero path)."""
        g = self.gain
        return math.inf if g == 0 else 1.0 / g

    @property
    def kind(self) -> str:
        if not self.terms or all(t.gain == 0 for t in self.terms):
            return "zero"
        kinds = [t.kind for t in self.terms]
        if len(kinds) == 1:
            return kinds[0]
        if all(k == "first_order" for k in kinds):
            return "two_modes" if len(kinds) == 2 else f"{len(kinds)}_modes"
        return "+".join(kinds)

    @property
    def n_params(self) -> int:
        per = {"first_order": 2, "second_order": 3}
        return sum(per[t.kind] for t in self.terms) + (1 if self.delay_s else 0)

    def sections(self, dt_s: float) -> list[tuple[float, Section]]:
        """(gain, unit-gain section) for every term, discretised at ``dt_s``."""
        out = []
        for t in self.terms:
            A, B, C = t.unit_state_space()
            out.append((t.gain, Section.from_state_space(A, B, C, dt_s, self.delay_s)))
        return out

    def impulse_response(self, t_s: np.ndarray) -> np.ndarray:
        """g(t): the path's weighting function (um per factor unit per second), the paper's g_ij."""
        t_s = np.asarray(t_s, dtype=float)
        out = np.zeros_like(t_s)
        shifted = t_s - self.delay_s
        on = shifted >= 0
        for term in self.terms:
            A, B, C = term.unit_state_space()
            w, V = np.linalg.eig(A)
            # C e^{At} B through the eigen-decomposition (distinct poles; critically damped is nudged apart)
            if np.isclose(w[0], w[-1]) and len(w) > 1:
                A = A + np.diag([1e-9 * abs(w[0]), 0.0])
                w, V = np.linalg.eig(A)
            coef = (C @ V) * np.linalg.solve(V, B)
            out[on] += term.gain * np.real(np.exp(np.outer(shifted[on], w)) @ coef)
        return out

    def describe(self) -> str:
        if self.kind == "zero":
            return "0"
        body = " + ".join(t.describe() for t in self.terms)
        return body + (f", delay {self.delay_s / 60:.3g} min" if self.delay_s else "")


@dataclass(frozen=True, kw_only=True)
class ThermalModel:
    """lambda_i = sum_j G_ij(s) (u_j - reference_j), for axes i and inputs j.

    The inputs are the profile's ``factors`` followed by the derived ``inputs`` (see
    :mod:`gateway.model.inputs`) that diagnosis adds; a model without derived inputs is the paper's.
    """

    axes: tuple[str, ...]
    factors: tuple[str, ...]
    units: Mapping[str, str]
    reference: Mapping[str, float]
    paths: Mapping[tuple[str, str], PathTF]
    machine: str = ""
    #: provenance and fit figures written by identification; informational, kept on round trip
    info: Mapping[str, Any] = field(default_factory=dict)
    #: derived inputs (computed from recorded columns), after the factors in :attr:`input_names`
    inputs: tuple[DerivedInput, ...] = ()
    #: what the identification data support (:mod:`gateway.model.envelope`); ``None`` in older files
    envelope: Envelope | None = None
    #: the factor region the identification data covered (:mod:`gateway.model.coverage`); ``None`` in older files
    coverage: Coverage | None = None
    #: per axis, the correlation of the identified path gains' errors (:mod:`gateway.model.correlation`); empty
    #: in older files and from the paper's method (every gain error independent)
    gain_correlation: Mapping[str, GainCorrelation] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(set(self.axes)) != len(self.axes) or len(set(self.factors)) != len(self.factors):
            raise ValueError("axes and factors must be unique")
        problems = check_order(self.inputs, self.factors)
        if problems:
            raise ValueError("; ".join(problems))
        object.__setattr__(self, "inputs", tuple(self.inputs))
        full: dict[tuple[str, str], PathTF] = {}
        for a in self.axes:
            for f in self.input_names:
                p = self.paths.get((a, f))
                full[(a, f)] = p if p is not None else PathTF(axis=a, factor=f)
        extra = set(self.paths) - set(full)
        if extra:
            raise ValueError(f"paths for unknown axis/factor: {sorted(extra)}")
        object.__setattr__(self, "paths", MappingProxyType(full))
        units = {f: self.units.get(f, "") for f in self.factors} | {d.name: d.unit for d in self.inputs}
        object.__setattr__(self, "units", MappingProxyType(units))
        object.__setattr__(self, "reference",
                           MappingProxyType({f: float(self.reference.get(f, 0.0)) for f in self.factors}))
        object.__setattr__(self, "info", MappingProxyType(dict(self.info)))
        # a model made from another by dropping axes or inputs keeps the correlation of what it still has (a
        # part of a correlation matrix is one; a path not named is independent): files are checked at load
        corr = {}
        for a, c in self.gain_correlation.items():
            if a in self.axes:
                c = c.restricted(self.input_names)
                if c is not None:
                    corr[a] = c
        object.__setattr__(self, "gain_correlation", MappingProxyType(corr))

    def gain_correlation_matrix(self, axis: str) -> np.ndarray:
        """The correlation of ``axis``'s path gains over :attr:`input_names` (the identity where none is stored)."""
        c = self.gain_correlation.get(axis)
        return c.full(self.input_names) if c is not None else np.eye(len(self.input_names))

    @property
    def input_names(self) -> tuple[str, ...]:
        """Every model input: the factors, then the derived inputs."""
        return self.factors + tuple(d.name for d in self.inputs)

    def path(self, axis: str, factor: str) -> PathTF:
        return self.paths[(axis, factor)]

    def reference_vector(self) -> np.ndarray:
        return np.array([self.reference[f] for f in self.factors])

    def gain_matrix(self) -> np.ndarray:
        """Static gains (um per input unit), shape (axes, inputs)."""
        return np.array([[self.paths[(a, f)].gain for f in self.input_names] for a in self.axes])

    def with_paths(self, paths: Iterable[PathTF], **changes: Any) -> ThermalModel:
        new = dict(self.paths)
        for p in paths:
            new[(p.axis, p.factor)] = p
        return replace(self, paths=new, **changes)

    def discretize(self, dt_s: float) -> DiscreteModel:
        return DiscreteModel(self, dt_s)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ThermalModel):
            return NotImplemented
        return (self.axes == other.axes and self.factors == other.factors
                and dict(self.units) == dict(other.units) and dict(self.reference) == dict(other.reference)
                and {k: _path_key(v) for k, v in self.paths.items()}
                == {k: _path_key(v) for k, v in other.paths.items()}
                and self.machine == other.machine and _plain(self.info) == _plain(other.info)
                and self.inputs == other.inputs and self.envelope == other.envelope
                and self.coverage == other.coverage
                and dict(self.gain_correlation) == dict(other.gain_correlation))

    __hash__ = None  # type: ignore[assignment]


def _path_key(p: PathTF) -> tuple[Any, ...]:
    return (p.axis, p.factor, p.terms, p.delay_s, dict(p.sd))


def _plain(x: Any) -> Any:
    if isinstance(x, Mapping):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    return x


class DiscreteModel:
    """A model discretised at one window length: batch replay and live estimators come from here."""

    def __init__(self, model: ThermalModel, dt_s: float) -> None:
        self.model = model
        self.dt_s = float(dt_s)
        # per axis: (factor index, gain, section)
        self.sections: list[list[tuple[int, float, Section]]] = []
        for a in model.axes:
            row = []
            for j, f in enumerate(model.input_names):
                for gain, sec in model.path(a, f).sections(self.dt_s):
                    if gain != 0.0:
                        row.append((j, gain, sec))
            self.sections.append(row)
        self.max_delay = max((s.m + 1 for row in self.sections for _, _, s in row), default=1)

    def simulate(self, du: np.ndarray, lead: np.ndarray | None = None) -> np.ndarray:
        """Displacements (axes, N) for input deviations ``du`` (inputs, N), from the reference state.

        ``lead`` (inputs, L): deviations over the L windows before the first, run first and not returned
        (:attr:`gateway.prepare.Prepared.lead`: the days before a recording of a column that cycles daily).
        """
        du = self._checked(du, lead)
        y = np.zeros((len(self.model.axes), du.shape[1]))
        for i, _, part in self._parts(du, lead):
            y[i] += part
        return y

    def contributions(self, du: np.ndarray, lead: np.ndarray | None = None) -> np.ndarray:
        """Per-path displacements, shape (axes, inputs, N): what each input adds to each axis.

        ``lead``: see :meth:`simulate`.
        """
        du = self._checked(du, lead)
        out = np.zeros((len(self.model.axes), len(self.model.input_names), du.shape[1]))
        for i, j, part in self._parts(du, lead):
            out[i, j] += part
        return out

    def _checked(self, du: np.ndarray, lead: np.ndarray | None) -> np.ndarray:
        du = np.asarray(du, dtype=float)
        if du.ndim != 2 or du.shape[0] != len(self.model.input_names):
            raise ValueError(f"du: wrong shape {du.shape}, expected ({len(self.model.input_names)}, N)")
        if not np.all(np.isfinite(du)):
            raise ValueError("du: inputs must be finite (fill gaps by a stated policy first)")
        if lead is not None and lead.shape[1] and (lead.shape[0] != du.shape[0] or not np.all(np.isfinite(lead))):
            raise ValueError(f"lead: expected {du.shape[0]} finite rows, got shape {lead.shape}")
        return du

    def _parts(self, du: np.ndarray, lead: np.ndarray | None) -> Iterator[tuple[int, int, np.ndarray]]:
        """(axis, input, displacement) of every section (inputs checked by :meth:`_checked`)."""
        for i, row in enumerate(self.sections):
            for j, gain, sec in row:
                yield i, j, gain * sec.filter(du[j], None if lead is None else lead[j])

    def stepper(self) -> ModelStepper:
        return ModelStepper(self)


class ModelStepper:
    """The model stepped one window at a time: one window's inputs in, one displacement per axis out; constant work.

    Its state is a pure function of the input history (:meth:`from_history` rebuilds it), so after a
    restart it is recomputed from the durable records instead of being persisted.
    """

    def __init__(self, dm: DiscreteModel) -> None:
        self.dm = dm
        self._flat = [(i, j, gain, sec) for i, row in enumerate(dm.sections) for j, gain, sec in row]
        self._x = [np.zeros(sec.order) for _, _, _, sec in self._flat]
        n_f = len(dm.model.input_names)
        self._hist = np.zeros((dm.max_delay + 1, n_f))  # row 0 = current input, row d = d steps ago
        self.steps = 0

    def step(self, du: Sequence[float] | np.ndarray) -> np.ndarray:
        """Advance one window with input deviations ``du``; return the displacement per axis (um).

        A model with derived inputs needs their deviations too (factors first): compute them with
        :class:`gateway.model.inputs.InputStepper` from the window's factor values.
        """
        du, xs, y = self._next(du)
        self._hist = np.roll(self._hist, 1, axis=0)
        self._hist[0] = du
        self._x = xs
        self.steps += 1
        return y

    def peek(self, du: Sequence[float] | np.ndarray) -> np.ndarray:
        """The displacement :meth:`step` would return for ``du``, without advancing (the state is untouched)."""
        return self._next(du)[2]

    def _next(self, du: Sequence[float] | np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """The checked input, the states and the output one window on.

        Row d of the shifted history is row d - 1 of the current one; its row 0 is ``du``.
        """
        du = np.asarray(du, dtype=float)
        if du.shape != (self._hist.shape[1],) or not np.all(np.isfinite(du)):
            raise ValueError(f"du: expected {self._hist.shape[1]} finite input deviations, got {du!r}")
        xs = []
        y = np.zeros(len(self.dm.model.axes))
        for k, (i, j, gain, sec) in enumerate(self._flat):
            now = du[j] if sec.m == 0 else self._hist[sec.m - 1, j]
            x = sec.Ad @ self._x[k] + sec.B0 * now + sec.B1 * self._hist[sec.m, j]
            xs.append(x)
            y[i] += gain * float(sec.C @ x)
        return du, xs, y

    @classmethod
    def from_history(cls, dm: DiscreteModel, du: np.ndarray) -> ModelStepper:
        """The estimator as it would be after stepping through ``du`` (factors, N), computed in batch."""
        est = cls(dm)
        du = np.asarray(du, dtype=float)
        for k, (_, j, _, sec) in enumerate(est._flat):
            est._x[k] = sec.final_state(du[j])
        n = du.shape[1]
        for d in range(min(n, est._hist.shape[0])):
            est._hist[d] = du[:, n - 1 - d]
        est.steps = n
        return est

    def output(self) -> np.ndarray:
        """Current displacement per axis without advancing."""
        y = np.zeros(len(self.dm.model.axes))
        for k, (i, _, gain, sec) in enumerate(self._flat):
            y[i] += gain * float(sec.C @ self._x[k])
        return y

    def contributions(self) -> np.ndarray:
        """Current displacement per path, shape (axes, inputs): :meth:`output` before summing over inputs.

        The same numbers as :meth:`DiscreteModel.contributions` at this step (the probe update in
        :mod:`gateway.adaptive` scales each path by its own gain factor).
        """
        out = np.zeros((len(self.dm.model.axes), self._hist.shape[1]))
        for k, (i, j, gain, sec) in enumerate(self._flat):
            out[i, j] += gain * float(sec.C @ self._x[k])
        return out


def paper_convolution(model: ThermalModel, du: np.ndarray, dt_s: float, n_terms: int) -> np.ndarray:
    """The paper's estimator, eq. 5-6: lambda_i(k dt) = sum_j sum_{l=0..n} g_ij(l dt) u_j((k-l) dt) dt.

    A reference for tests: it is a rectangle rule on the convolution integral, so it differs from the
    exact zero-order-hold result by its own discretisation error, and its work grows with ``n_terms``.
    """
    du = np.asarray(du, dtype=float)
    t = dt_s * np.arange(n_terms + 1)
    y = np.zeros((len(model.axes), du.shape[1]))
    for i, a in enumerate(model.axes):
        for j, f in enumerate(model.input_names):
            p = model.path(a, f)
            if p.kind != "zero":
                y[i] += np.convolve(du[j], p.impulse_response(t) * dt_s)[: du.shape[1]]
    return y


# ---------------------------------------------------------------------------------------------- TOML ---
def model_to_toml(model: ThermalModel) -> str:
    """The model file text; every (axis, factor) pair is written, zero paths included."""
    doc: dict[str, Any] = {
        "format": FORMAT,
        "model": {"machine": model.machine, "axes": list(model.axes), "factors": list(model.factors)},
        "units": {f: model.units[f] for f in model.factors},  # derived inputs carry theirs
        "reference": {f: float(v) for f, v in model.reference.items()},
    }
    if model.info:
        doc["info"] = _plain(model.info)
    if model.inputs:
        doc["inputs"] = {d.name: input_to_toml(d) for d in model.inputs}
    if model.envelope is not None:
        doc["envelope"] = envelope_to_toml(model.envelope)
    if model.coverage is not None:
        doc["coverage"] = coverage_to_toml(model.coverage)
    if model.gain_correlation:
        doc["gain_correlation"] = correlation_to_toml(dict(model.gain_correlation))
    paths = []
    for a in model.axes:
        for f in model.input_names:
            p = model.path(a, f)
            entry: dict[str, Any] = {"axis": a, "factor": f, "kind": p.kind, "gain": p.gain, "K": p.K}
            if p.delay_s:
                entry["delay_s"] = float(p.delay_s)
            terms = []
            for t in p.terms:  # floats always, so a loaded model writes the same text again
                if isinstance(t, FirstOrder):
                    terms.append({"kind": t.kind, "gain": float(t.gain), "tau_s": float(t.tau_s)})
                else:
                    terms.append({"kind": t.kind, "gain": float(t.gain), "K": t.K, "zeta": float(t.zeta),
                                  "omega_rad_s": float(t.omega_rad_s)})
            if terms:
                entry["term"] = terms
            if p.sd:
                entry["sd"] = dict(p.sd)
            paths.append(entry)
    doc["path"] = paths
    header = ("# cncgw thermal model: lambda_i = sum_j G_ij(s) (u_j - reference_j)\n"
              "# gain: static gain in um per factor unit; K = 1/gain is the paper's K (eq. 12).\n"
              "# kind, gain and K of a path are written for people; the terms are what counts.\n")
    return header + tomli_w.dumps(doc)


def save_model(model: ThermalModel, path: str | Path) -> Path:
    """Write the model file atomically; a model :func:`load_model` would refuse is not written (ModelError)."""
    path = Path(path)
    problems = model_problems(model)
    if problems:
        raise ModelError("\n".join(f"{path}: not written: {p}" for p in problems))
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(model_to_toml(model), encoding="utf-8")
    tmp.replace(path)
    return path


def model_problems(model: ThermalModel) -> list[str]:
    """What loading this model's file would refuse (nothing: it loads), with paths named ``axis/factor``.

    Every writer checks this, so a model file on disk always loads again: identification on experiments that
    barely move a factor can find a gain beyond the physical range (:mod:`gateway.model.limits`).
    """
    try:
        load_model("model", text=model_to_toml(model))
    except ModelError as exc:
        order = [f"{a}/{f}" for a in model.axes for f in model.input_names]
        out = []
        for line in str(exc).splitlines():
            body = re.sub(r"^model(:\d+)?: ", "", line)
            out.append(re.sub(r"^path\.(\d+)", lambda m: f"path {order[int(m.group(1)) - 1]}", body))
        return out
    return []


def load_model(path: str | Path, *, text: str | None = None) -> ThermalModel:
    """Read and check a model file; raise :class:`ModelError` listing every problem."""
    doc = TomlDoc(path, error=ModelError, text=text)
    root = doc.root
    if "machine" in root and "format" not in root and "path" not in root:
        # a machine profile given for the model: one line, not a dozen missing keys
        raise ModelError(f"{doc.path}: a machine profile (it has [machine]), not a model file: expected a model "
                         "written by cncgw identify; pass the profile with --profile (its [model] file is the "
                         "default model)")
    fmt = root.int("format", expected=f"the model format number {FORMAT}")
    if fmt is not None and fmt != FORMAT:
        root.problem("format", f"expected {FORMAT}, got {fmt}: this model was written by another version")
    head = root.table("model", required=True)
    axes: tuple[str, ...] = ()
    factors: tuple[str, ...] = ()
    machine = ""
    if head is not None:
        machine = head.str("machine", default="")
        axes = head.str_list("axes", choices=("x", "y", "z"), min_len=1) or ()
        factors = head.str_list("factors", min_len=1) or ()
        head.done()
    inputs = parse_inputs(root) if "inputs" in root else []  # files without derived inputs read as before
    for problem in check_order(inputs, factors):
        root.problem("inputs", problem)
    names = factors + tuple(d.name for d in inputs)
    units = _name_table(root.table("units"), factors, lambda t, f: t.str(f))
    reference = _name_table(root.table("reference"), factors, lambda t, f: t.float(
        f, min=-limits.REFERENCE_MAX, max=limits.REFERENCE_MAX, expected=limits.REFERENCE_EXPECTED))
    env_t = root.table("envelope")
    envelope = parse_envelope(env_t, axes) if env_t is not None else None
    cov_t = root.table("coverage")
    coverage = parse_coverage(cov_t, factors, recorded_columns(inputs)) if cov_t is not None else None
    info_t = root.table("info")
    info = _parse_info(info_t, factors) if info_t is not None else {}
    corr_t = root.table("gain_correlation", expected="a table of [gain_correlation.<axis>] tables")
    gain_correlation = parse_correlation(corr_t, axes, names) if corr_t is not None else {}

    paths: dict[tuple[str, str], PathTF] = {}
    raw = root.raw("path", default=[], expected="an array of [[path]] tables")
    if not isinstance(raw, list):
        root.problem("path", "expected an array of [[path]] tables")
        raw = []
    for n, entry in enumerate(raw):
        if not isinstance(entry, dict):
            root.problem("path", f"entry {n + 1}: expected a [[path]] table")
            continue
        t = Table(doc, entry, ("path", str(n + 1)))
        p = _parse_path(t, axes, names)
        if p is not None:
            if (p.axis, p.factor) in paths:
                t.problem(None, f"a second path for axis {p.axis}, factor {p.factor}: expected one per pair")
            paths[(p.axis, p.factor)] = p
    root.done()
    doc.raise_problems()
    return ThermalModel(axes=axes, factors=factors, units=units, reference=reference, paths=paths,
                        machine=machine, info=info, inputs=tuple(inputs), envelope=envelope,
                        coverage=coverage, gain_correlation=gain_correlation)


def _name_table(t: Table | None, factors: Sequence[str], get: Callable[[Table, str], Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if t is None:
        return out
    for f in factors:
        if f in t:
            value = get(t, f)
            if value is not None:
                out[f] = value
    t.done()
    return out


def _parse_info(t: Table, factors: Sequence[str]) -> dict[str, Any]:
    """``[info]`` is provenance kept as written; the keys that commands read are checked for their type."""
    for k in t:
        t.raw(k)
    if "method" in t:
        t.str("method")
    if "experiments" in t:
        t.str_list("experiments", unique=False)
    if "experiment_fingerprints" in t:
        t.str_list("experiment_fingerprints", unique=False)
    if "longest_experiment_s" in t:
        t.float("longest_experiment_s", min=0.0, min_exclusive=True)
    ranges = t.table("deviation_range", expected="a table of factor -> [lowest, highest] deviation")
    if ranges is not None:
        for f in ranges:
            pair = ranges.float_list(f, expected="[lowest, highest] deviation of the factor in the experiments")
            if pair is not None and (len(pair) != 2 or pair[0] > pair[1]):
                ranges.problem(f, f"expected [lowest, highest] deviation of the factor in the experiments, "
                                  f"got {list(pair)!r}")
    return dict(t.data)


def _parse_path(t: Table, axes: Sequence[str], factors: Sequence[str]) -> PathTF | None:
    axis = t.str("axis", choices=axes)
    factor = t.str("factor", choices=factors)
    t.str("kind", default="")  # written for people; recomputed from the terms
    gain = t.float("gain", default=None)
    K = t.float("K", default=None, allow_inf=True)
    delay = t.float("delay_s", default=0.0, min=0.0, max=limits.DELAY_MAX_S, expected=limits.DELAY_EXPECTED)
    sd_t = t.table("sd")
    sd = {}
    if sd_t is not None:
        for k in sd_t:
            v = sd_t.float(k, min=0.0, allow_inf=True)
            if v is not None:
                sd[k] = v
        sd_t.done()
    terms: list[Term] = []
    failed_term = False
    raw_terms = t.raw("term", default=[], expected="an array of [[path.term]] tables")
    for n, rt in enumerate(raw_terms if isinstance(raw_terms, list) else []):
        tt = Table(t.doc, rt, (*t.path, "term", str(n + 1))) if isinstance(rt, dict) else None
        if tt is None:
            t.problem("term", f"entry {n + 1}: expected a [[path.term]] table")
            continue
        term = _parse_term(tt)
        if term is None:
            failed_term = True
        else:
            terms.append(term)
    t.done()
    if axis is None or factor is None or delay is None or failed_term:
        return None  # the problems are recorded; a summary check on the remaining terms would only add noise
    p = PathTF(axis=axis, factor=factor, terms=tuple(terms), delay_s=delay, sd=MappingProxyType(sd))
    # the summary keys must agree with the terms, so a hand edit of one without the other is caught
    if gain is not None and not math.isclose(gain, p.gain, rel_tol=1e-9, abs_tol=1e-15):
        t.problem("gain", f"{gain!r} does not match the sum of the terms' gains {p.gain!r}: edit the terms")
    if K is not None and not (math.isinf(K) and math.isinf(p.K)) and not math.isclose(K, p.K, rel_tol=1e-9):
        t.problem("K", f"{K!r} does not match 1/gain = {p.K!r}")
    return p


def _parse_term(t: Table) -> Term | None:
    kind = t.str("kind", choices=list(TERM_KINDS))
    gain_bounds = {"min": -limits.GAIN_MAX, "max": limits.GAIN_MAX, "expected": limits.GAIN_EXPECTED}
    if kind == FirstOrder.kind:
        gain = t.float("gain", **gain_bounds)
        tau = t.float("tau_s", min=limits.TAU_MIN_S, max=limits.TAU_MAX_S, expected=limits.TAU_EXPECTED)
        t.done()
        return FirstOrder(gain=gain, tau_s=tau) if None not in (gain, tau) else None
    if kind == SecondOrder.kind:
        gain = t.float("gain", default=None, **gain_bounds)
        K = t.float("K", default=None, allow_inf=True)
        zeta = t.float("zeta", min=0.0, min_exclusive=True, max=limits.ZETA_MAX, expected=limits.ZETA_EXPECTED)
        omega = t.float("omega_rad_s", min=1 / limits.TAU_MAX_S, max=1 / limits.TAU_MIN_S,
                        expected=limits.OMEGA_EXPECTED)
        t.done()
        if K is not None and abs(K) < 1 / limits.GAIN_MAX:
            t.problem("K", f"expected {limits.K_EXPECTED}, got {K!r}")
            return None
        if gain is None and K is None:
            if "gain" not in t and "K" not in t:
                t.problem(None, 'missing "gain" (um per factor unit) or the paper\'s "K" (= 1/gain)')
            return None
        if gain is None:
            gain = 0.0 if math.isinf(K) else 1.0 / K
        elif K is not None and not (math.isinf(K) and gain == 0) and not math.isclose(
                K * gain, 1.0, rel_tol=1e-9):
            t.problem("K", f"{K!r} does not match 1/gain = {1 / gain if gain else math.inf!r}")
        if zeta is None or omega is None:
            return None
        fast, slow = limits.second_order_time_constants(zeta, omega)
        if not (limits.time_constant_ok(fast) and limits.time_constant_ok(slow)):
            t.problem("zeta", f"zeta = {zeta!r} with omega_rad_s = {omega!r} gives time constants {fast:.4g} s "
                              f"and {slow:.4g} s: expected both to be {limits.TAU_EXPECTED}")
            return None
        return SecondOrder(gain=gain, zeta=zeta, omega_rad_s=omega)
    t.done()
    return None
