"""Recordings made by a known model: for tests, benchmarks and for checking a pipeline end to end.

A plant that IS a :class:`ThermalModel` is the easiest case for identification; it is how the tests
check that known parameters come back. The bundled simulated machine (``simulators``) is the hard case.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from gateway.model.model import ThermalModel
from gateway.recording import Recording


@dataclass(frozen=True, kw_only=True)
class Segment:
    """Factor levels held for ``minutes`` (factors not named stay at their idle level)."""

    minutes: int
    levels: Mapping[str, float]


def schedule_inputs(segments: Sequence[Segment], factors: Sequence[str], idle: Mapping[str, float]) -> np.ndarray:
    """Per-window factor values (factors, N) for a schedule of segments."""
    cols = []
    for seg in segments:
        col = np.array([seg.levels.get(f, idle.get(f, 0.0)) for f in factors], dtype=float)
        cols.append(np.repeat(col[:, None], seg.minutes, axis=1))
    return np.hstack(cols) if cols else np.zeros((len(factors), 0))


def make_recording(
    model: ThermalModel,
    u: np.ndarray,
    *,
    name: str,
    dt_s: float = 60.0,
    noise_um: float = 0.0,
    factor_noise: Mapping[str, float] | None = None,
    seed: int = 0,
    zero_um: Mapping[str, float] | None = None,
) -> Recording:
    """A recording of ``model`` driven by raw factor values ``u`` (factors, N).

    The plant starts in equilibrium with the first window's factors; measured displacement gets white
    noise of ``noise_um`` and an arbitrary sensor zero ``zero_um`` per axis; factor columns get relative
    noise ``factor_noise[f]`` (share of the value).
    """
    rng = np.random.default_rng(seed)
    u = np.asarray(u, dtype=float)
    du = u - u[:, :1]
    y = model.discretize(dt_s).simulate(du)
    n = u.shape[1]
    disp = {}
    for i, a in enumerate(model.axes):
        disp[a] = y[i] + (zero_um or {}).get(a, 0.0) + noise_um * rng.standard_normal(n)
    factors = {}
    for j, f in enumerate(model.factors):
        rel = (factor_noise or {}).get(f, 0.0)
        factors[f] = u[j] * (1.0 + rel * rng.standard_normal(n)) if rel else u[j].copy()
    return Recording(source=f"{name}.csv", period_s=dt_s, time_s=dt_s * np.arange(1, n + 1),
                     present=np.ones(n, dtype=bool), factors=factors, displacement=disp)
