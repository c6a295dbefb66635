"""The model updated by probes over a recording: ``cncgw estimate --probes FILE`` (probes from a CSV)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gateway.adaptive.filter import DriftSettings, Replay, replay
from gateway.adaptive.probes import Probe
from gateway.model.coverage import beyond_coverage
from gateway.model.model import ThermalModel
from gateway.prepare import prepare
from gateway.recording import Recording, continued, format_recording


@dataclass(frozen=True, kw_only=True)
class ProbedRun:
    """One recording with the probes taken during it: the updated estimate, its band, the decisions."""

    recording: str
    replay: Replay
    outside: int  # probes of the file outside the recording's time span (not used)

    def refused(self) -> list[str]:
        return [d.describe() for d in self.replay.decisions if not d.accepted]

    def applied(self) -> int:
        return sum(1 for d in self.replay.decisions if d.accepted)

    def figures(self, measured: np.ndarray) -> dict[str, dict[str, float]]:
        """Per axis against ``measured`` (axes, N; NaN where none): RMS, max |error|, band coverage."""
        lo, hi = self.replay.band_um()
        out = {}
        for i, a in enumerate(self.replay.axes):
            ok = np.isfinite(measured[i])
            if not ok.any():
                continue
            err = measured[i, ok] - self.replay.estimate_um[i, ok]
            inside = (measured[i, ok] >= lo[i, ok]) & (measured[i, ok] <= hi[i, ok])
            out[a] = {"windows": int(ok.sum()), "rms_um": float(np.sqrt(np.mean(err ** 2))),
                      "max_abs_error_um": float(np.max(np.abs(err))), "band_coverage": float(inside.mean())}
        return out

    def to_csv(self, meta: dict[str, str], time_column: str = "time_s") -> str:
        """Time, then per axis the updated estimate, its standard uncertainty and the model alone (um)."""
        rp = self.replay
        cols: dict[str, np.ndarray] = {}
        for i, a in enumerate(rp.axes):
            cols[f"{a}_um"] = rp.estimate_um[i]
            cols[f"{a}_sd_um"] = rp.sd_um[i]
            cols[f"{a}_model_um"] = rp.model_um[i]
        return format_recording(time_s=rp.time_s, columns=cols, meta=meta, time_column=time_column)


def estimate_with_probes(model: ThermalModel, rec: Recording, probes: Sequence[Probe], *, initial: str = "first",
                         gap_policy: str = "hold", history: Recording | None = None,
                         settings: DriftSettings | None = None) -> ProbedRun:
    """The model over ``rec`` (after ``history``, as :func:`gateway.replay.estimate`), updated by ``probes``.

    A probe counts from the window it was taken in; probes outside the run's time span are left out.
    """
    run = continued(history, rec) if history is not None else rec
    skip = len(run) - len(rec)
    prep = prepare(run, factors=model.factors, axes=model.axes, initial=initial, reference=model.reference,
                   gap_policy=gap_policy, inputs=model.inputs)
    contributions = model.discretize(rec.period_s).contributions(prep.du, prep.lead)
    t = np.asarray(prep.time_s, dtype=float)
    inside = [p for p in probes if t[0] - rec.period_s < p.time_s <= t[-1] + 1e-9]
    rp = replay(model, contributions, t, inside, window_s=rec.period_s, settings=settings,
                beyond=model_beyond(model, prep.du))
    cut = Replay(axes=rp.axes, time_s=rp.time_s[skip:], estimate_um=rp.estimate_um[:, skip:],
                 sd_um=rp.sd_um[:, skip:], model_um=rp.model_um[:, skip:], decisions=rp.decisions)
    t_rec = float(t[skip]) if skip < len(t) else math.inf
    outside = sum(1 for p in probes if not (t_rec - rec.period_s < p.time_s <= t[-1] + 1e-9))
    return ProbedRun(recording=rec.source, replay=cut, outside=outside)


def model_beyond(model: ThermalModel, du: np.ndarray) -> np.ndarray | None:
    """How far each of the model's inputs lies beyond its coverage per window (inputs, N); None without one.

    Derived inputs (after the factors) have no coverage of their own: 0.
    """
    if model.coverage is None:
        return None
    du = np.asarray(du, dtype=float)
    out = np.zeros((len(model.input_names), du.shape[1]))
    out[: len(model.factors)] = beyond_coverage(model.coverage, du[: len(model.factors)], model.factors)
    return out
