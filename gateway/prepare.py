"""From a recording to model inputs.

Factor deviations from a reference state, with gaps handled by a stated policy.

The paper's convention: experiments start after the machine has been powered long enough to be in
thermal equilibrium, and displacement is measured relative to the start. Heat present at rest (the Z
motor's holding current, the drives' idle losses) is then already in equilibrium, so the model works on
DEVIATIONS of the factors from that initial steady state. Feeding raw factors into the transfer
functions would predict a drift that is not there.

- ``initial="first"``: the machine was in equilibrium with the factors of the first recorded window.
- ``initial="reference"``: it was in equilibrium with the model's reference levels (the idle levels seen
  during identification); use this when a recording starts in the middle of work.

Derived inputs (``inputs``, see :mod:`gateway.model.inputs`) are computed from the gap-filled factors, the
time stamps and the recording's other columns, and enter ``du`` after the factors as deviations from
their value in the same initial equilibrium.

Probe points (``probe_points=True``, for identification and diagnosis): a recording whose displacement is
measured only at a CNC's probe cycles carries it either in sparse displacement columns (empty except at the
probe instants) or, as ``cncgw record --export-only`` writes it from a gateway with ``[probes]``, in
``probe_<axis>_um`` columns with ``probe_sd_um`` beside them (each probe on the row of the window it was
applied after: the displacement at that window's end). Without any measured displacement column, those
probe columns are the measured displacement, and ``y_sd`` the probes' stated uncertainty.

Gaps (missing windows) are never interpolated silently: ``gap_policy="hold"`` assumes the factors of the
last window before the gap went on, ``"reference"`` assumes the machine stood idle at the reference
state; either way the rows stay marked missing and carry no measured displacement.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from gateway.errors import RecordingError
from gateway.model.inputs import Column, DerivedInput, evaluate_inputs, initial_values, start_leads
from gateway.recording import Recording, number_or_blank

INITIAL_CHOICES = ("first", "reference")
#: a recording whose displacement is measured on fewer than this share of its windows is sampled (probes)
SPARSE_SHARE = 0.5
#: a recording sampled by probes informs an axis with at least this many points: its own zero takes one
MIN_PROBE_POINTS = 3
#: the probe columns ``cncgw record --export-only`` writes (gateway.record_store.export_recording)
PROBE_AXIS_COLUMN = "probe_{axis}_um"
PROBE_SD_COLUMN = "probe_sd_um"
GAP_POLICIES = ("hold", "reference")


@dataclass(frozen=True, kw_only=True)
class Prepared:
    """A recording ready for the model: deviations ``du`` (inputs, N), measured ``y`` (axes, N).

    ``u0`` holds the factors' initial levels; rows of ``du`` beyond the factors are derived inputs.
    """

    name: str
    dt_s: float
    time_s: np.ndarray
    du: np.ndarray
    u0: np.ndarray
    y: np.ndarray  # NaN where not measured (gaps, empty cells, axis not recorded)
    present: np.ndarray
    notes: tuple[str, ...] = ()
    #: the stated standard uncertainty (um) of each measured value, NaN where none is stated (sensor rows)
    y_sd: np.ndarray | None = None
    #: where ``y`` comes from: "displacement" (the displacement columns) or "probes" (probe_* columns)
    y_source: str = "displacement"
    #: (inputs, L) deviations over the windows run before the first (a daily-start column's days before it, see
    #: :func:`gateway.model.inputs.daily_start`; zero for every other input); None: the model starts settled
    lead: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.du.shape[1]

    @property
    def sparse(self) -> bool:
        """Measured at a few instants only (probe cycles): on no axis at :data:`SPARSE_SHARE` of the windows."""
        counts = np.isfinite(self.y).sum(axis=1)
        return bool(counts.any()) and bool(np.all(counts < SPARSE_SHARE * max(int(self.present.sum()), 1)))


def prepare(
    rec: Recording,
    *,
    factors: Sequence[str],
    axes: Sequence[str],
    initial: str = "first",
    reference: Mapping[str, float] | None = None,
    gap_policy: str = "hold",
    inputs: Sequence[DerivedInput] = (),
    probe_points: bool = False,
) -> Prepared:
    """Turn ``rec`` into deviations from its initial equilibrium; see the module docstring."""
    if initial not in INITIAL_CHOICES:
        raise ValueError(f"initial must be one of {INITIAL_CHOICES}. Got {initial!r}")
    if gap_policy not in GAP_POLICIES:
        raise ValueError(f"gap_policy must be one of {GAP_POLICIES}. Got {gap_policy!r}")
    missing = [f for f in factors if f not in rec.factors]
    if missing:
        raise RecordingError(f"{rec.source}: no column for factor(s) {', '.join(missing)}")
    u = rec.factor_matrix(factors).copy()
    n = u.shape[1]
    notes: list[str] = []
    if n == 0:
        raise RecordingError(f"{rec.source}: no data rows")

    finite = np.isfinite(u)
    rows_ok = finite.all(axis=0)
    if initial == "reference":
        if reference is None:
            raise ValueError("initial='reference' needs the model's reference levels")
        u0 = np.array([reference[f] for f in factors], dtype=float)
    else:
        if not rows_ok.any():
            raise RecordingError(f"{rec.source}: no row has every factor ({', '.join(factors)})")
        first = int(np.flatnonzero(rows_ok)[0])
        u0 = u[:, first].copy()
        if first > 0:
            notes.append(f"initial state taken from row {first + 1}, the first with every factor present")

    # cells missing inside a present row count as missing windows for that factor
    bad = ~finite
    if bad.any():
        n_bad = int((~rows_ok).sum())
        missing_rows = int((~rec.present).sum())
        what = "hold: last window's factors assumed to go on" if gap_policy == "hold" else \
            "reference: machine assumed idle at the reference state"
        extra = n_bad - missing_rows
        # where: the longest stretches without every factor, in hours from the start (the file's rows and the
        # windows of a gap are not numbered alike); the estimate over and after them rests on the policy
        edges = np.flatnonzero(np.diff(np.r_[0, (~rows_ok).astype(np.int8), 0]))
        stretches = sorted(zip(edges[::2], edges[1::2], strict=True), key=lambda r: r[0] - r[1])
        where = ", ".join(f"{b - a} windows from {(rec.time_s[a] - rec.time_s[0]) / 3600:.3g} h"
                          for a, b in stretches[:3])
        parts = ([f"{missing_rows} missing window(s) in {len(rec.gaps)} gap(s)"] if missing_rows else []) + (
            [f"{extra} row(s) with empty factor cells"] if extra > 0 else [])
        notes.append(f"{' and '.join(parts)} (the longest: {where}{', ...' if len(stretches) > 3 else ''}); gap "
                     f"policy {what}; the estimate over them and for hours after rests on that assumption")
        for j in range(u.shape[0]):
            row = u[j]
            if gap_policy == "reference":
                row[~np.isfinite(row)] = u0[j] if initial == "reference" else (
                    reference[factors[j]] if reference is not None else u0[j])
            else:
                last = u0[j]
                for k in range(n):
                    if np.isfinite(row[k]):
                        last = row[k]
                    else:
                        row[k] = last

    du = u - u0[:, None]
    lead = None
    if inputs:
        derived, leads, said = _derived(rec, inputs, factors, u, u0)
        du = np.vstack([du, derived])
        notes += said
        if leads:
            n_lead = max(len(v) for v in leads.values())
            lead = np.zeros((du.shape[0], n_lead))
            for k, inp in enumerate(inputs):
                if inp.name in leads:
                    lead[len(factors) + k, n_lead - len(leads[inp.name]):] = leads[inp.name]

    y = np.full((len(axes), n), np.nan)
    for i, a in enumerate(axes):
        if a in rec.displacement:
            y[i] = rec.displacement[a]
    y_sd = None
    source = "displacement"
    if probe_points:
        y, y_sd, source = _probe_points(rec, axes, y)
    y[:, ~rec.present] = np.nan
    return Prepared(name=rec.name, dt_s=rec.period_s, time_s=np.asarray(rec.time_s), du=du,
                    u0=u0, y=y, present=np.asarray(rec.present), notes=tuple(notes), y_sd=y_sd, y_source=source,
                    lead=lead)


def _probe_points(rec: Recording, axes: Sequence[str], y: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """(y, its stated sd, source): the displacement columns, else the probe_* columns (module docstring)."""
    sd_col = rec.extras.get(PROBE_SD_COLUMN)
    sd = np.full(y.shape, np.nan)
    if np.isfinite(y).any():
        if sd_col is not None:  # sparse displacement columns with the probes' uncertainty beside them
            sd[:] = np.where(np.isfinite(y), sd_col[None, :], np.nan)
        return y, sd, "displacement"
    cols = {i: rec.extras.get(PROBE_AXIS_COLUMN.format(axis=a)) for i, a in enumerate(axes)}
    if not any(c is not None and np.isfinite(c).any() for c in cols.values()):
        return y, sd, "displacement"
    y = np.full(y.shape, np.nan)
    for i, c in cols.items():
        if c is not None:
            y[i] = c
            if sd_col is not None:
                sd[i] = np.where(np.isfinite(c), sd_col, np.nan)
    return y, sd, "probes"


def _derived(rec: Recording, inputs: Sequence[DerivedInput], factors: Sequence[str], u: np.ndarray,
             u0: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray], list[str]]:
    """Deviations of the derived inputs (rows in declaration order) from the initial equilibrium.

    With the deviations over the windows before the first of each daily-start column input (by input name:
    :func:`gateway.model.inputs.start_leads`) and what was done there, in words.
    """
    columns = {}
    for inp in inputs:
        if isinstance(inp, Column):
            col = rec.extras.get(inp.column)
            if col is None or not np.isfinite(col).any():
                head = f'{rec.source}: the model\'s input {inp.name} reads column "{inp.column}", '
                cells = rec.text.get(inp.column)
                odd = next(((k, c) for k, c in enumerate(cells or ()) if not number_or_blank(c)), None)
                if odd is not None:  # read as text for one cell that is not a number: say which
                    raise RecordingError(head + f'which holds text: "{odd[1][:40]}" in its data row {odd[0] + 1} '
                                         "(expected numbers; leave a cell empty to make it a gap)")
                if col is not None or cells is not None:
                    raise RecordingError(head + "which has no value in any row of this recording (expected numbers)")
                have = ", ".join(sorted(rec.extras)) or "none"
                raise RecordingError(head + f"which this recording does not have (numeric extra columns: {have})")
            columns[inp.column] = col
    initial = {f: float(v) for f, v in zip(factors, u0, strict=True)}
    initial |= {c: float(v[np.isfinite(v)][0]) for c, v in columns.items()}
    time_s = np.asarray(rec.time_s, float)
    columns, leads, said = start_leads(inputs, time_s, columns, rec.period_s)
    values = evaluate_inputs(inputs, {f: u[j] for j, f in enumerate(factors)}, time_s=time_s, dt_s=rec.period_s,
                             columns=columns, initial=initial)
    start = initial_values(inputs, initial, time0_s=float(time_s[0]))
    by_input = {d.name: leads[d.column] - start[d.name] for d in inputs if isinstance(d, Column) and d.column in leads}
    return np.array([values[d.name] - start[d.name] for d in inputs]), by_input, said
