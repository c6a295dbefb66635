"""How the identified path gains of one axis co-vary: the correlation of their estimation errors.

Identification fits all paths of an axis at once. Where factors change together (spindle speed and its
motor currents squared; a feed and its motor current squared) the experiments fix a combination of their
gains far better than each gain: the errors of the two gains are strongly (usually negatively) correlated.
Each path's own standard deviation (``[path.sd] gain``) says how uncertain a gain is alone; this table says
how the errors of an axis's gains go together, so that a prediction along a combination the experiments
determined is tight and one along a combination they did not is wide (:mod:`gateway.adaptive.filter` uses
it as the gains' prior covariance: ``cov = diag(sd) R diag(sd)``).

In the model file, one table per axis, a key per pair of paths whose gain errors correlate (``"a/b"``, the
inputs in the model's order)::

    [gain_correlation.z]
    "spindle_speed/spindle_i1_sq" = -0.97
    "spindle_speed/z_feed" = 0.1

A pair not named correlates 0; a path in no pair (a zero path, a derived input added later by diagnosis) is
uncorrelated with the others. A file without the table (written before cncgw stored it, or by the paper's
method, which fits the groups of factors separately) reads as before: every path's gain error independent
(the identity). The pairs of an axis together must form a correlation matrix (positive semidefinite).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gateway.tomlcheck import Table

#: what a stored matrix may miss being a correlation matrix by: floating-point sums, a file written by hand
#: with rounded entries (symmetry and the unit diagonal to 1e-9; eigenvalues down to -TOLERANCE)
TOLERANCE = 1e-6
#: decimals identification writes, and below what a correlation is written as 0 (it changes no band)
DECIMALS = 10
NEGLIGIBLE = 1e-6
EXPECTED = "a correlation matrix: symmetric, 1 on the diagonal, entries in [-1, 1], positive semidefinite"


@dataclass(frozen=True, kw_only=True, slots=True)
class GainCorrelation:
    """One axis: the correlation matrix of the static gains of ``inputs`` (in that order)."""

    inputs: tuple[str, ...]
    matrix: tuple[tuple[float, ...], ...]

    def __post_init__(self) -> None:
        problem = matrix_problem(self.matrix, len(self.inputs))
        if problem:
            raise ValueError(f"gain correlation of {', '.join(self.inputs)}: {problem}")

    def array(self) -> np.ndarray:
        return np.array(self.matrix, dtype=float)

    def restricted(self, names: Sequence[str]) -> GainCorrelation | None:
        """Only the inputs among ``names`` (itself when all are; None when fewer than two are left)."""
        keep = [i for i, n in enumerate(self.inputs) if n in names]
        if len(keep) == len(self.inputs):
            return self
        if len(keep) < 2:
            return None
        return GainCorrelation(inputs=tuple(self.inputs[i] for i in keep),
                               matrix=tuple(tuple(self.matrix[i][j] for j in keep) for i in keep))

    def full(self, names: Sequence[str]) -> np.ndarray:
        """The correlation over every input in ``names`` (the identity where an input is not named)."""
        out = np.eye(len(names))
        idx = [list(names).index(n) if n in names else -1 for n in self.inputs]
        m = self.array()
        for a, i in enumerate(idx):
            for b, j in enumerate(idx):
                if i >= 0 and j >= 0:
                    out[i, j] = m[a, b]
        return out


def from_covariance(names: Sequence[str], cov: np.ndarray) -> GainCorrelation | None:
    """The correlation of the inputs whose variance in ``cov`` (inputs x inputs) is positive; None if none."""
    cov = np.asarray(cov, dtype=float)
    keep = [i for i in range(len(names)) if cov[i, i] > 0 and math.isfinite(cov[i, i])]
    if not keep:
        return None
    sub = cov[np.ix_(keep, keep)]
    sub = (sub + sub.T) / 2.0
    sd = np.sqrt(np.diag(sub))
    # 10 decimals: what separates two near-collinear paths (1 - |r| down to 1e-6 and less) is kept; the float
    # noise of paths no experiment moved together (1e-15..1e-10) reads as the 0 it is
    r = np.round(np.clip(sub / np.outer(sd, sd), -1.0, 1.0), DECIMALS) + 0.0
    r[np.abs(r) < NEGLIGIBLE] = 0.0
    np.fill_diagonal(r, 1.0)
    # a path in no pair is independent of the others, as a path not named: only the paired ones are kept
    paired = [a for a in range(len(keep)) if np.any(r[a, np.arange(len(keep)) != a] != 0.0)]
    if not paired:
        return None
    r = r[np.ix_(paired, paired)]
    return GainCorrelation(inputs=tuple(names[keep[a]] for a in paired),
                           matrix=tuple(tuple(float(v) for v in row) for row in r))


def matrix_problem(matrix: Any, n: int) -> str:
    """What keeps ``matrix`` from being an n x n correlation matrix ('' when nothing does)."""
    if not isinstance(matrix, list | tuple) or len(matrix) != n or not all(
            isinstance(row, list | tuple) and len(row) == n for row in matrix):
        return f"expected {n} rows of {n} numbers (one per input named), got {_shape(matrix)}"
    try:
        m = np.array(matrix, dtype=float)
    except (TypeError, ValueError):
        return "expected numbers only"
    if m.dtype != float or not np.all(np.isfinite(m)):
        return "expected finite numbers only"
    for i in range(n):
        if abs(m[i, i] - 1.0) > 1e-9:
            return f"row {i + 1}, column {i + 1}: {float(m[i, i])!r}: expected 1 on the diagonal ({EXPECTED})"
    bad = np.argwhere(np.abs(m) > 1.0 + 1e-12)
    if bad.size:
        i, j = bad[0]
        return f"row {i + 1}, column {j + 1}: {float(m[i, j])!r}: expected a correlation in [-1, 1]"
    asym = np.argwhere(np.abs(m - m.T) > 1e-9)
    if asym.size:
        i, j = asym[0]
        return (f"row {i + 1}, column {j + 1} is {float(m[i, j])!r} but row {j + 1}, column {i + 1} is "
                f"{float(m[j, i])!r}: expected {EXPECTED}")
    low = float(np.linalg.eigvalsh((m + m.T) / 2.0).min())
    if low < -TOLERANCE:
        return f"its smallest eigenvalue is {low:.3g}: expected {EXPECTED}"
    return ""


def _shape(v: Any) -> str:
    if not isinstance(v, list | tuple):
        return type(v).__name__
    lengths = [len(r) if isinstance(r, list | tuple) else "?" for r in v]
    return f"{len(v)} rows of {', '.join(map(str, lengths))} entries" if v else "no rows"


def correlation_to_toml(corr: dict[str, GainCorrelation]) -> dict[str, Any]:
    """``[gain_correlation.<axis>]`` tables: every pair whose correlation is not 0 (floats written exactly)."""
    out: dict[str, Any] = {}
    for a, c in corr.items():
        pairs = {f"{c.inputs[i]}/{c.inputs[j]}": float(c.matrix[i][j]) for i in range(len(c.inputs))
                 for j in range(i + 1, len(c.inputs)) if c.matrix[i][j] != 0.0}
        if pairs:
            out[a] = pairs
    return out


def parse_correlation(t: Table, axes: Sequence[str], names: Sequence[str]) -> dict[str, GainCorrelation]:
    """Read ``[gain_correlation]``: per axis of the model, ``"a/b" = r`` for pairs of its inputs."""
    out: dict[str, GainCorrelation] = {}
    for axis in t:
        sub = t.table(axis, expected=f'a table [gain_correlation.{axis}] of "input/input" = correlation')
        if sub is None:
            continue
        if axis not in axes:
            t.problem(axis, f"not an axis of this model (axes: {', '.join(axes)})")
            continue
        pairs: dict[tuple[str, str], float] = {}
        for key in sub:
            parts = key.split("/")
            if len(parts) != 2 or parts[0] not in names or parts[1] not in names or parts[0] == parts[1]:
                sub.problem(key, f'expected a key "a/b" naming two different inputs of this model (inputs: '
                                 f'{", ".join(names)})')
                sub.raw(key)
                continue
            r = sub.float(key, min=-1.0, max=1.0, expected="a correlation in [-1, 1]")
            pair = tuple(sorted(parts, key=list(names).index))
            if pair in pairs:
                sub.problem(key, f"the pair {pair[0]}/{pair[1]} is named twice")
            elif r is not None:
                pairs[pair] = r  # type: ignore[index]
        sub.done()
        used = [n for n in names if any(n in p for p in pairs)]
        if not used:
            continue
        m = np.eye(len(used))
        for (x, y), r in pairs.items():
            m[used.index(x), used.index(y)] = m[used.index(y), used.index(x)] = r
        problem = matrix_problem(m.tolist(), len(used))
        if problem:
            t.problem(axis, f"the pairs together are not a correlation: {problem}")
            continue
        out[axis] = GainCorrelation(inputs=tuple(used), matrix=tuple(tuple(float(v) for v in row) for row in m))
    t.done()
    return out


def describe_correlation(corr: dict[str, GainCorrelation], threshold: float = 0.5) -> list[str]:
    """Lines for ``cncgw model show``: per axis the pairs whose gain errors correlate beyond ``threshold``."""
    if not corr:
        return ["gain correlation: none stored (a model written before cncgw stored it, or by the paper's method): "
                "every path's gain error is taken as independent"]
    lines = ["gain correlation (how the identified gains' errors go together; pairs beyond +-0.5):"]
    for a, c in corr.items():
        m = c.array()
        pairs = [(m[i, j], c.inputs[i], c.inputs[j]) for i in range(len(c.inputs)) for j in range(i)
                 if abs(m[i, j]) >= threshold]
        pairs.sort(key=lambda p: -abs(p[0]))
        body = ", ".join(f"{y}/{x} {r:+.3f}" for r, x, y in pairs) or "none"
        lines.append(f"  {a} ({len(c.inputs)} paths): {body}")
    return lines


__all__ = ["GainCorrelation", "correlation_to_toml", "describe_correlation", "from_covariance", "matrix_problem",
           "parse_correlation"]
