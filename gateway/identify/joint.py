"""The default identification: all paths of an axis fitted jointly over all experiments at once.

For one axis, every experiment e contributes y_e(k) = o_e + sum_j G_j(s) du_je(k) + noise: a free offset
per experiment (sensors are zeroed anywhere), every path at once, so co-varying factors need not change in
exact proportion as the paper's V^-1 separation requires.

- Variable projection: for given time constants the model is linear in the gains and offsets, which are
  solved by linear least squares inside the residual function; ``scipy.optimize.least_squares`` then only
  searches the log time constants (one or two per path), which are well scaled and bounded.
- Starting values from a linear fit over a bank of first-order modes (log-spaced time constants).
- Structure per axis (first order / second order / two modes, the same for every path of the axis) chosen
  by an information criterion whose sample size is the effective one of autocorrelated residuals; paths
  whose gain is not significant are then tried as zero paths and dropped when the criterion allows.
- Parameter standard deviations from the full Jacobian at the optimum, inflated for residual
  autocorrelation.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize

from gateway.errors import IdentificationError
from gateway.identify.common import (
    Bounds,
    ExperimentSet,
    effective_n,
    fast_time_constant,
    n_linear,
    n_nonlinear,
    terms_with_gains,
    theta_from_time_constants,
    unit_responses,
)
from gateway.model.correlation import GainCorrelation, from_covariance
from gateway.model.model import PathTF

CANDIDATES = ("first_order", "second_order", "two_modes")
#: the order candidates are fitted in: each is seeded from the bank and from every fit before it, and
#: two modes of opposite sign are the best start for a second order
FIT_ORDER = ("first_order", "two_modes", "second_order")


@dataclass(kw_only=True)
class AxisFit:
    """One axis fitted with given path structures."""

    axis: str
    structures: tuple[str, ...]
    thetas: list[np.ndarray]
    gains: list[np.ndarray]
    offsets: np.ndarray
    rss: float
    extra_gains: np.ndarray = field(default_factory=lambda: np.zeros(0))  # of the set's extra columns
    n: int
    nfev: int = 0
    converged: bool = True  # False when the optimizer stopped at its evaluation budget
    residuals: list[np.ndarray] = field(default_factory=list)  # per experiment, NaN where not fitted
    sd: list[dict[str, float]] = field(default_factory=list)
    #: covariance of the paths' static gains (inputs x inputs, 0 for a zero path), from the same Jacobian as sd
    gain_cov: np.ndarray | None = None
    bic: float = math.nan

    @property
    def k(self) -> int:
        """Number of fitted parameters, offsets included."""
        return (sum(n_nonlinear(s) + n_linear(s) for s in self.structures)) + len(self.offsets) + len(self.extra_gains)

    @property
    def rms(self) -> float:
        return math.sqrt(self.rss / max(self.n, 1))

    def gain_correlation(self, factors: Sequence[str]) -> GainCorrelation | None:
        """The correlation of the estimated (non-zero) paths' gains, for the model file; None without sds."""
        if self.gain_cov is None:
            return None
        cov = self.gain_cov.copy()
        for j, s in enumerate(self.structures):
            if s == "zero":
                cov[j, :] = cov[:, j] = 0.0
        return from_covariance(list(factors), cov)

    def paths(self, factors: Sequence[str]) -> list[PathTF]:
        out = []
        for j, f in enumerate(factors):
            s = self.structures[j]
            terms = terms_with_gains(s, self.thetas[j], self.gains[j]) if s != "zero" else ()
            sd = self.sd[j] if self.sd else {}
            out.append(PathTF(axis=self.axis, factor=f, terms=terms, sd=sd))
        return out


def _length_groups(rows: np.ndarray, lengths: np.ndarray) -> list[np.ndarray]:
    """``rows`` in groups whose lengths are within a factor 2: each group is filtered over its longest."""
    groups: list[list[int]] = []
    for r in sorted(rows.tolist(), key=lambda r: lengths[r]):
        if groups and lengths[r] <= 2 * lengths[groups[-1][0]]:
            groups[-1].append(r)
        else:
            groups.append([r])
    return [np.array(g) for g in groups]


def _column_norms(X: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(X, axis=0)`` of a real matrix, the same numbers without its copy (``X.conj()``)."""
    return np.sqrt(np.add.reduce(X * X, axis=0))


def _term_keys(structure: str, theta: Sequence[float]) -> list[tuple[float, ...]]:
    """Per term of :func:`unit_responses`, what its response depends on (two modes: each mode's time constant)."""
    if structure == "two_modes":
        return [(fast_time_constant(theta),), (math.exp(theta[0]),)]
    return [tuple(float(t) for t in theta)] * n_linear(structure)


def _split(v: np.ndarray, sizes: Sequence[int]) -> list[np.ndarray]:
    """Cut a flat parameter vector into consecutive pieces of the given sizes."""
    out, k = [], 0
    for n in sizes:
        out.append(v[k: k + n])
        k += n
    return out


class _ExtraBasis:
    """An orthonormal basis of a problem's (demeaned, scaled) extra columns that keeps their sparsity.

    Most extra columns of a diagnosis are one recording's own (its initial state, its drift): zero outside its
    rows. Their basis is built recording by recording (a QR of that recording's rows), the other columns' after
    projecting those out, so ``Q'M`` and ``Q C`` cost a recording's rows per local column instead of every row:
    the projection of :class:`AxisProblem` with ``project_extra`` (the span, and so the least squares, is the
    same as one QR of all the columns gives). Columns are reordered (:attr:`order`): each recording's local
    ones, then the rest; :attr:`r` is the triangular factor in that order.
    """

    def __init__(self, blocks: list[tuple[int, int, np.ndarray]], q_rest: np.ndarray, r: np.ndarray,
                 order: np.ndarray) -> None:
        self.blocks = blocks  # (first row, stop row, Q of the recording's local columns on its rows)
        self.q_rest = q_rest  # (n, m_rest)
        self.r = r
        self.order = order
        self.m = r.shape[0]
        self.n_local = self.m - q_rest.shape[1]

    @classmethod
    def of(cls, E: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> _ExtraBasis | None:
        """The basis of ``E`` (columns demeaned and scaled; rows experiment by experiment), None if rank-deficient."""
        m = E.shape[1]
        owner = np.full(m, -1)
        for c in range(m):
            nz = np.flatnonzero(E[:, c])
            if nz.size:
                g = int(np.searchsorted(stops, nz[0], side="right"))
                if g < len(stops) and nz[-1] < stops[g]:
                    owner[c] = g
        rest = np.flatnonzero(owner < 0)
        G = E[:, rest].copy()
        blocks, order, r_blocks, c_blocks = [], [], [], []
        for g in np.unique(owner[owner >= 0]):
            a, b = int(starts[g]), int(stops[g])
            cols = np.flatnonzero(owner == g)
            if len(cols) > b - a:
                return None
            Qg, Rg = scipy.linalg.qr(E[a:b, cols], mode="economic", check_finite=False)
            Cg = Qg.T @ G[a:b]
            G[a:b] -= Qg @ Cg
            blocks.append((a, b, Qg))
            order += cols.tolist()
            r_blocks.append(Rg)
            c_blocks.append(Cg)
        if len(rest) > G.shape[0]:
            return None
        Qr, Rr = (scipy.linalg.qr(G, mode="economic", check_finite=False) if len(rest)
                  else (np.zeros((G.shape[0], 0)), np.zeros((0, 0))))
        r = np.zeros((m, m))
        k = 0
        for Rg, Cg in zip(r_blocks, c_blocks, strict=True):
            kg = Rg.shape[0]
            r[k: k + kg, k: k + kg] = Rg
            r[k: k + kg, m - len(rest):] = Cg
            k += kg
        r[k:, k:] = Rr
        diag = np.abs(np.diag(r))
        if not (diag.size and np.all(diag > 1e-10 * max(diag.max(), 1e-300))):
            return None
        return cls(blocks, Qr, r, np.array(order + rest.tolist(), dtype=int))

    def qt(self, M: np.ndarray) -> np.ndarray:
        """Q' M: the coordinates of ``M`` (n, ...) in the basis, in :attr:`order`."""
        out = np.empty((self.m, *M.shape[1:]))
        k = 0
        for a, b, Qg in self.blocks:
            out[k: k + Qg.shape[1]] = Qg.T @ M[a:b]
            k += Qg.shape[1]
        out[k:] = self.q_rest.T @ M
        return out

    def q(self, C: np.ndarray) -> np.ndarray:
        """Q C: the combination ``C`` of the basis (rows in :attr:`order`) as columns over every row."""
        out = self.q_rest @ C[self.n_local:]
        k = 0
        for a, b, Qg in self.blocks:
            out[a:b] += Qg @ C[k: k + Qg.shape[1]]
            k += Qg.shape[1]
        return out


class AxisProblem:
    """The variable-projection problem of one axis.

    For time constants theta the design matrix Phi(theta) holds the unit-gain response of every term
    plus one offset column per experiment; gains and offsets are its least-squares solution and the
    residual is r = (I - Q Q^T) y with Phi = Q R. The Jacobian uses Kaufman's approximation
    dr/dtheta_q = -(I - Q Q^T) (dPhi/dtheta_q) g, and dPhi/dtheta_q touches only the columns of the path
    that owns theta_q, so a Jacobian costs one extra filter per parameter instead of a whole design matrix.
    """

    def __init__(self, es: ExperimentSet, axis_index: int, *,
                 input_bounds: Sequence[Bounds | None] | None = None, project_extra: bool = False) -> None:
        self.es = es
        self.i = axis_index
        self.valid = es.valid(axis_index)
        self.y = es.y[axis_index][self.valid]
        self.n = int(self.y.size)
        if self.n == 0:
            raise ValueError("no measured displacement on this axis")
        # the set's extra regressors ride along with the path columns in every solve
        self.extra = (np.column_stack([c[self.valid] for c in es.extra]) if es.n_extra
                      else np.zeros((self.n, 0)))
        exp_idx = np.broadcast_to(np.arange(es.n_exp)[:, None], self.valid.shape)[self.valid]
        self.offset_cols = (exp_idx[:, None] == np.arange(es.n_exp)[None, :]).astype(float)
        # rows run experiment by experiment: the offsets are projected out by removing each experiment's
        # mean (Frisch-Waugh), so the QR and the Jacobian carry the path columns only
        self._counts = self.valid.sum(axis=1)
        self._starts = np.concatenate([[0], np.cumsum(self._counts)[:-1]])[self._counts > 0]
        self._stops = self._starts + self._counts[self._counts > 0]
        # weighted least squares: every row scaled by the square root of its weight (probe points by their
        # stated uncertainty, gateway.identify.api); with all weights 1 the arithmetic is the unweighted one
        w2 = es.weights(axis_index)
        self.w = np.sqrt(w2)
        self._w2 = w2[:, None]
        self._unweighted = bool(np.all(w2 == 1.0))
        self._w2_sums = np.add.reduceat(w2, self._starts)[:, None] if self._starts.size else np.zeros((0, 1))
        self._y_means = self._group_means(self.y[:, None])[:, 0]
        self.y_demeaned = self.demean(self.y[:, None])[:, 0]
        self.bounds = Bounds.for_data(es.dt_s, es.longest_s)
        #: per input, where its time constants may go (default: the data's bounds)
        self.input_bounds = [b or self.bounds for b in (input_bounds or [None] * len(es.factors))]
        self.evaluations = 0
        # the extra columns are the same in every solve: with ``project_extra`` they are projected out once
        # (Frisch-Waugh again), so each evaluation factorises the path columns only (a diagnosis carries dozens
        # of nuisance columns). Off by default (``cncgw identify`` keeps its numbers); diagnosis's re-identification
        # and its per-fold refits use it. The same least squares, but its rounding differs, and a fit from several
        # starts over many paths can then settle in another local minimum, better or worse by about 1 % of the
        # training error (measured on the diagnosis bench, 49 cases: the same decisions in all, the fresh-day
        # RMS of the written model different in 4, two better and two worse, at 0.1-0.3 um)
        self._extra_q: _ExtraBasis | None = None
        self._extra_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        if self.extra.shape[1] and project_extra:
            E = self.demean(self.extra)
            escale = np.linalg.norm(E, axis=0)
            # columns that are zero where measured (a held-out recording's own nuisance, a constant absorbed by
            # its offset) are left out: their gains are 0, as the unprojected solve leaves them
            live = np.flatnonzero(escale > 0)
            basis = _ExtraBasis.of(E[:, live] / escale[live], self._starts, self._stops)
            if basis is not None:  # else (rank-deficient) solved with the paths
                self._extra_q, self._extra_r = basis, basis.r
                self._extra_live = live[basis.order]
                self._extra_scale = escale[self._extra_live]
                self._extra_means = self._group_means(self.extra[:, self._extra_live])
                self._qty_extra = basis.qt(self.y_demeaned)
                self._y_projected = self.y_demeaned - basis.q(self._qty_extra)
        # the racing restarts an optimizer where the last one stopped: its first residual and Jacobian
        # were computed at the end of the round before (a few entries, each a design matrix's worth)
        self._memo: OrderedDict[tuple, object] = OrderedDict()
        # where each fit ended (residual and Jacobian): the racing of :meth:`best_of` continues a start from its
        # end point a round later, after the other starts' evaluations pushed it out of the memo above; the
        # same numbers are taken again, not recomputed
        self._ends: OrderedDict[tuple, object] = OrderedDict()
        # per factor: the experiments in which it moves, in groups of similar length (a 12 h experiment is not
        # filtered over the padding up to a 4-day production recording), and where their valid samples go
        position = np.full(self.valid.shape, -1)
        position[self.valid] = np.arange(self.n)
        #: per factor and group: its inputs (experiments, samples), where the valid samples are and go, and the
        #: group's last first-order responses (:func:`unit_responses`)
        self._moving: list[list[tuple[np.ndarray, np.ndarray, np.ndarray, OrderedDict]]] = []
        for j in range(len(es.factors)):
            rows = np.flatnonzero(np.any(es.du[j] != 0.0, axis=1))
            groups = []
            for g in _length_groups(rows, es.lengths):
                length = int(es.lengths[g].max())
                valid = self.valid[g, :length]
                groups.append((es.du[j][g, :length], np.flatnonzero(valid), position[g, :length][valid],
                               OrderedDict()))
            self._moving.append(groups)

    # -- the design matrix and the projected residual --------------------------------------------------
    def _responses(self, j: int, structure: str, theta: Sequence[float]
                   ) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(term, rows, values) of path ``j``'s columns on the experiments in which its factor moves.

        A factor moves in a few experiments only; its response is exactly zero in the others (inputs are
        deviations from rest), so only those are filtered.
        """
        for du, src, dest, memo in self._moving[j]:
            for t, resp in enumerate(unit_responses(structure, theta, du, self.es.dt_s, memo=memo)):
                yield t, dest, resp.ravel().take(src)

    def path_columns(self, j: int, structure: str, theta: Sequence[float]) -> list[np.ndarray]:
        out = [np.zeros(self.n) for _ in range(n_linear(structure))]
        for t, dest, values in self._responses(j, structure, theta):
            out[t][dest] = values
        return out

    def path_design(self, structures: Sequence[str], thetas: Sequence[Sequence[float]]
                    ) -> tuple[np.ndarray, list[list[np.ndarray]]]:
        """(every path's :meth:`path_columns` side by side, (n, terms); per path its columns, views of it).

        Written straight into place: the numbers of ``np.column_stack`` of the columns, without them.
        """
        widths = [n_linear(s) if s != "zero" else 0 for s in structures]
        design = np.zeros((self.n, sum(widths)))
        per_path: list[list[np.ndarray]] = []
        k = 0
        for j, s in enumerate(structures):
            if widths[j]:
                for t, dest, values in self._responses(j, s, thetas[j]):
                    design[dest, k + t] = values
            per_path.append([design[:, k + t] for t in range(widths[j])])
            k += widths[j]
        return design, per_path

    def path_difference(self, j: int, structure: str, theta: Sequence[float], moved: Sequence[float],
                        base: Sequence[np.ndarray], gains: Sequence[float], h: float, out: np.ndarray) -> None:
        """``out`` (zeros) := sum over the path's terms of (column at ``moved`` - ``base`` column) * gain / ``h``.

        The numbers of ``sum((m - c) * g for ...) / h`` over whole :meth:`path_columns`, computed only on the
        rows of the experiments in which the factor moves (elsewhere both columns are zeros and so is the
        difference) and without the terms ``moved`` leaves as they were (a two-mode path's slow mode when
        only its fast one moves: a difference of exact zeros adds nothing).
        """
        changed = [a != b for a, b in zip(_term_keys(structure, theta), _term_keys(structure, moved), strict=True)]
        for du, src, dest, memo in self._moving[j]:
            acc: float | np.ndarray = 0
            for resp, c, g, on in zip(unit_responses(structure, moved, du, self.es.dt_s, memo=memo), base, gains,
                                      changed, strict=True):
                if on:
                    acc = acc + (resp.ravel().take(src) - c[dest]) * g
            if isinstance(acc, np.ndarray):
                out[dest] = acc / h

    def columns(self, structures: Sequence[str], thetas: Sequence[Sequence[float]]) -> np.ndarray:
        """The whole design: path columns, the extra columns, one offset column per experiment."""
        cols = [c for j, s in enumerate(structures) if s != "zero" for c in self.path_columns(j, s, thetas[j])]
        return np.column_stack([*cols, self.extra, self.offset_cols])

    def _group_means(self, m: np.ndarray) -> np.ndarray:
        """Per-experiment weighted column means of ``m`` (rows of the experiments that have any)."""
        if self._unweighted:  # multiplying by ones changes nothing but the time
            return np.add.reduceat(m, self._starts, axis=0) / self._w2_sums
        return np.add.reduceat(m * self._w2, self._starts, axis=0) / self._w2_sums

    def demean(self, m: np.ndarray) -> np.ndarray:
        """``m`` less each experiment's weighted column means, rows scaled by their root weights.

        The residual maker of the (weighted) offset columns: every fitted quantity lives in these rows.
        """
        return self._demeaned(m)[0]

    def _demeaned(self, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(:meth:`demean` of ``m``, its per-experiment means): a solve needs both, computed once."""
        means = self._group_means(m)
        # each experiment's rows less its means, in place: the numbers of ``m - repeat(means)`` without the copy
        centred = np.empty(m.shape)
        for g, (a, b) in enumerate(zip(self._starts, self._stops, strict=True)):
            np.subtract(m[a:b], means[g], out=centred[a:b])
        if not self._unweighted:
            centred *= self.w[:, None]
        return centred, means

    def project_extra(self, m: np.ndarray) -> np.ndarray:
        """Demeaned columns ``m`` less their projection on the (demeaned) extra columns."""
        if self._extra_q is None:
            return m
        # twice: one pass of classical Gram-Schmidt leaves a column that lies nearly in the extra columns'
        # span with a rounding error large against what remains of it; a second pass is enough ("twice is
        # enough", Kahan and Parlett). Once only, diagnosis's re-identification landed in a worse minimum in
        # 6 of the 6 bench cases where it landed elsewhere (fresh-day RMS up 0.06-0.34 um); twice, in 2 of 4
        # (and better in the other 2)
        once = m - self._extra_q.q(self._extra_q.qt(m))
        return once - self._extra_q.q(self._extra_q.qt(once))

    def solve(self, paths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(path gains, extra gains, then per-experiment offsets; residual; Q of the demeaned columns).

        Columns are scaled for conditioning; the offsets come from the experiments' means after the gains.
        With the extra columns projected out once (:meth:`project_extra`), Q spans the projected path
        columns only: the residual maker is then (I - Q Q^T) applied after :meth:`project_extra`.
        """
        self.evaluations += 1
        if self._extra_q is not None:
            return self._solve_projected(paths)
        offsets = np.zeros(self.es.n_exp)
        p, m = paths.shape[1], self.extra.shape[1]
        if p + m == 0:
            offsets[self._counts > 0] = self._y_means
            return offsets, self.y_demeaned.copy(), np.zeros((self.n, 0))
        if p >= 2 and m >= 2:
            # the extra columns are the same in every solve: demeaned and scaled once. Column by column these
            # are the numbers the whole matrix gives (sums down each column of a matrix of two columns or more
            # run the same way however many columns there are); the QR below is the same factorisation
            Xp, means_p = self._demeaned(paths)
            scale_p = _column_norms(Xp)
            scale_p[scale_p == 0] = 1.0
            es, scale_e, means_e = self._extra_scaled()
            Xs = np.empty((self.n, p + m), order="F")
            np.divide(Xp, scale_p, out=Xs[:, :p])
            Xs[:, p:] = es
            scale = np.concatenate([scale_p, scale_e])
            means = np.concatenate([means_p, means_e], axis=1)
        else:
            X, means = self._demeaned(np.column_stack([paths, self.extra]) if m else paths)
            scale = _column_norms(X)
            scale[scale == 0] = 1.0
            # scaled straight into LAPACK's column order, factorised in place (no copies; the same numbers)
            Xs = np.divide(X, scale, out=np.empty(X.shape, order="F"))
        Q, R = scipy.linalg.qr(Xs, mode="economic", check_finite=False, overwrite_a=True)
        qty = Q.T @ self.y_demeaned
        # a (near-)rank-deficient design happens when a path's response is nearly another's; keep going
        diag = np.abs(np.diag(R))
        keep = diag > 1e-10 * max(diag.max(), 1e-300)
        coef = np.zeros(p + m)
        if keep.all():
            coef = scipy.linalg.solve_triangular(R, qty, check_finite=False)
        else:
            coef[keep] = np.linalg.lstsq(R[np.ix_(keep, keep)], qty[keep], rcond=None)[0]
        coef = coef / scale
        offsets[self._counts > 0] = self._y_means - means @ coef
        resid = self.y_demeaned - Q @ qty
        return np.concatenate([coef, offsets]), resid, Q

    def _extra_scaled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the extra columns demeaned and scaled to unit norm, in column order; their scales; their means)."""
        if self._extra_cache is None:
            E, means = self._demeaned(self.extra)
            scale = np.linalg.norm(E, axis=0)
            scale[scale == 0] = 1.0
            self._extra_cache = (np.divide(E, scale, out=np.empty(E.shape, order="F")), scale, means)
        return self._extra_cache

    def _solve_projected(self, paths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`solve` with the extra columns already factorised: only the path columns' QR is new."""
        assert self._extra_q is not None
        offsets = np.zeros(self.es.n_exp)
        p = paths.shape[1]
        y = self._y_projected
        coef = np.zeros(p)
        Q = np.zeros((self.n, 0))
        means = None
        if p:
            X, means = self._demeaned(paths)
            scale = _column_norms(X)
            scale[scale == 0] = 1.0
            Xs = X / scale
            Q, R = scipy.linalg.qr(self.project_extra(Xs), mode="economic", check_finite=False)
            qty = Q.T @ y
            diag = np.abs(np.diag(R))
            keep = diag > 1e-10 * max(diag.max(), 1e-300)
            if keep.all():
                coef = scipy.linalg.solve_triangular(R, qty, check_finite=False)
            else:
                coef[keep] = np.linalg.lstsq(R[np.ix_(keep, keep)], qty[keep], rcond=None)[0]
            resid = y - Q @ qty
            extra_rhs = self._qty_extra - self._extra_q.qt(Xs @ coef)
            coef = coef / scale
        else:
            resid = y.copy()
            extra_rhs = self._qty_extra
        live = scipy.linalg.solve_triangular(self._extra_r, extra_rhs, check_finite=False) / self._extra_scale
        shift = means @ coef if means is not None else 0.0
        offsets[self._counts > 0] = self._y_means - shift - self._extra_means @ live
        extra = np.zeros(self.extra.shape[1])
        extra[self._extra_live] = live
        return np.concatenate([coef, extra, offsets]), resid, Q

    def fit(self, structures: Sequence[str], theta0: Sequence[Sequence[float]], *,
            max_nfev: int = 100) -> AxisFit:
        structures = tuple(structures)
        sizes = [n_nonlinear(s) for s in structures]
        owner = [j for j, n in enumerate(sizes) for _ in range(n)]
        lo, hi = [], []
        for s, bounds in zip(structures, self.input_bounds, strict=True):
            a, b = bounds.of(s)
            lo += a
            hi += b
        x0 = np.array([v for th in theta0 for v in th], dtype=float)
        if x0.size:
            x0 = np.clip(x0, np.array(lo) + 1e-6, np.array(hi) - 1e-6)

        def split(x: np.ndarray) -> list[np.ndarray]:
            return _split(x, sizes)

        def evaluate(x: np.ndarray) -> tuple[list[np.ndarray], list[list[np.ndarray]], np.ndarray, np.ndarray,
                                             np.ndarray]:
            return self._remember(("r", structures, x.tobytes()), lambda: compute(x))  # type: ignore[return-value]

        def compute(x: np.ndarray) -> tuple[list[np.ndarray], list[list[np.ndarray]], np.ndarray, np.ndarray,
                                            np.ndarray]:
            thetas = split(x)
            design, per_path = self.path_design(structures, thetas)
            coef, r, Q = self.solve(design)
            return thetas, per_path, coef, r, Q

        def residual(x: np.ndarray) -> np.ndarray:
            return evaluate(x)[3]

        def jacobian(x: np.ndarray) -> np.ndarray:
            return self._remember(("J", structures, x.tobytes()), lambda: kaufman(x))  # type: ignore[return-value]

        def kaufman(x: np.ndarray) -> np.ndarray:
            thetas, per_path, coef, _, Q = evaluate(x)
            gains = _split(coef, [len(cols) for cols in per_path])
            V = np.zeros((self.n, x.size))  # rows where the path's factor rests stay 0
            for q, j in enumerate(owner):
                local = q - sum(sizes[:j])
                h = 1e-6 * max(1.0, abs(thetas[j][local]))
                th = thetas[j].copy()
                th[local] += h
                self.path_difference(j, structures[j], thetas[j], th, per_path[j], gains[j], h, V[:, q])
            V = self.project_extra(self.demean(V))
            return -(V - Q @ (Q.T @ V))

        nfev = 1
        converged = True
        x = x0
        if x0.size:
            try:
                sol = scipy.optimize.least_squares(residual, x0, jac=jacobian, bounds=(lo, hi), method="trf",
                                                   x_scale=1.0, max_nfev=max_nfev, xtol=1e-7, ftol=1e-6, gtol=1e-8)
            except ValueError as exc:  # "Residuals are not finite": data far beyond what the filters can carry
                raise IdentificationError(
                    f"axis {self.es.axes[self.i]}: the fit cannot go on ({exc}): factor or displacement values "
                    "too large to filter; check the recordings' units and outliers") from None
            x, nfev, converged = sol.x, sol.nfev, sol.status > 0
        thetas, per_path, coef, r, _ = evaluate(x)
        self._keep_end(structures, x)
        sizes_lin = [len(cols) for cols in per_path]
        gains = _split(coef, sizes_lin)
        k = sum(sizes_lin)
        m = self.extra.shape[1]
        fit = AxisFit(axis=self.es.axes[self.i], structures=structures, thetas=[t.copy() for t in thetas],
                      gains=gains, offsets=coef[k + m:], extra_gains=coef[k: k + m], rss=float(r @ r), n=self.n,
                      nfev=nfev, converged=converged)
        fit.residuals = self._per_experiment(r)
        return fit

    def _remember(self, key: tuple, compute: Callable[[], object], size: int = 6) -> object:
        if key in self._memo:
            self._memo.move_to_end(key)
            return self._memo[key]
        value = self._memo[key] = self._ends[key] if key in self._ends else compute()
        if len(self._memo) > size:
            self._memo.popitem(last=False)
        return value

    def _keep_end(self, structures: tuple[str, ...], x: np.ndarray, size: int = 16) -> None:
        """Keep the residual and Jacobian at a fit's end point (those computed) for a fit continuing from it."""
        for kind in ("r", "J"):
            key = (kind, structures, x.tobytes())
            if key in self._memo:
                self._ends[key] = self._memo[key]
                self._ends.move_to_end(key)
        while len(self._ends) > size:
            self._ends.popitem(last=False)

    def best_of(self, structures: Sequence[str], starts: Sequence[Sequence[Sequence[float]]], *,
                round_nfev: int = 5, max_rounds: int = 8) -> AxisFit:
        """Fit from several starting points, racing them in rounds.

        Every start gets ``round_nfev`` evaluations a round. A start is dropped when it is clearly behind
        (residual over 1.5x the best) and has stalled (less than 2 % better than a round ago); a start still
        improving fast keeps running even while behind: on the simulated machine's z axis the right start
        is 6x worse than the wrong one after 6 evaluations and 4x better after 10. A start whose optimizer
        has converged runs no further rounds. The best one left goes on to convergence.
        """
        if len(starts) == 1:
            return self.fit(structures, starts[0])
        live = [(math.inf, self.fit(structures, th0, max_nfev=round_nfev)) for th0 in starts]
        spent = sum(f.nfev for _, f in live)
        for _ in range(max_rounds):
            best = min(f.rss for _, f in live)
            live = [(prev, f) for prev, f in live
                    if not (f.rss > 1.5 * best and (prev - f.rss) < 0.02 * prev)]
            if len(live) == 1 or all(f.converged for _, f in live):
                break
            nxt = []
            for prev, f in live:
                if f.converged:
                    nxt.append((prev, f))
                    continue
                g = self.fit(structures, f.thetas, max_nfev=round_nfev)
                spent += g.nfev
                nxt.append((f.rss, g))
            live = nxt
        lead = min((f for _, f in live), key=lambda f: f.rss)
        if lead.converged:
            lead.nfev = spent
            return lead
        final = self.fit(structures, lead.thetas)
        final.nfev += spent
        return final

    def _per_experiment(self, r: np.ndarray) -> list[np.ndarray]:
        full = np.full(self.valid.shape, np.nan)
        full[self.valid] = r
        return [full[e, : self.es.lengths[e]] for e in range(self.es.n_exp)]

    # -- uncertainty -------------------------------------------------------------------------------------
    def uncertainties(self, fit: AxisFit, inflation: float) -> list[dict[str, float]]:
        """Standard deviations of gains and time constants from the full Jacobian at the optimum."""
        return self.covariances(fit, inflation)[0]

    def attach_uncertainties(self, fit: AxisFit, inflation: float) -> None:
        """Set ``fit.sd`` and ``fit.gain_cov`` (:meth:`covariances`)."""
        fit.sd, fit.gain_cov = self.covariances(fit, inflation)

    def covariances(self, fit: AxisFit, inflation: float) -> tuple[list[dict[str, float]], np.ndarray]:
        """Per path the standard deviations (:meth:`uncertainties`), and the covariance of the paths' static gains.

        The static gain of a path is the sum of its terms' gains, so the covariance of two paths' gains is the
        sum of their terms' block of the full covariance (time constants free: their uncertainty is in it).
        Co-varying factors show here: the experiments fix a combination of their gains better than each one.
        """
        structures = fit.structures
        sizes = [n_nonlinear(s) for s in structures]
        x = np.concatenate([np.asarray(t, float) for t in fit.thetas]) if fit.thetas else np.zeros(0)
        lin = np.concatenate([*fit.gains, fit.extra_gains, fit.offsets])

        def split(v: np.ndarray) -> list[np.ndarray]:
            return _split(v, sizes)

        base = self.columns(structures, fit.thetas)
        out0 = base @ lin
        jac_nl = np.empty((self.n, x.size))
        for q in range(x.size):
            h = 1e-6 * max(1.0, abs(x[q]))
            xp = x.copy()
            xp[q] += h
            jac_nl[:, q] = (self.columns(structures, split(xp)) @ lin - out0) / h
        J = np.column_stack([jac_nl, base]) * self.w[:, None]
        s2 = fit.rss / max(self.n - J.shape[1], 1)
        # columns differ by orders of magnitude (rpm-sized responses, unit offsets): scale before inverting
        norm = np.linalg.norm(J, axis=0)
        norm[norm == 0] = 1.0
        Js = J / norm
        cov = np.linalg.pinv(Js.T @ Js, rcond=1e-12) / np.outer(norm, norm) * s2 * inflation
        var = np.clip(np.diag(cov), 0, None)
        out: list[dict[str, float]] = []
        qn, ql = 0, x.size
        blocks: list[slice | None] = []
        for j, s in enumerate(structures):
            d: dict[str, float] = {}
            th = fit.thetas[j]
            if s == "first_order":
                d["tau_s"] = math.exp(th[0]) * math.sqrt(var[qn])
            elif s in ("second_order", "two_modes"):
                d["tau_slow_s"] = math.exp(th[0]) * math.sqrt(var[qn])
                v_fast = var[qn] + var[qn + 1] - 2 * cov[qn, qn + 1]
                d["tau_fast_s"] = math.exp(th[0] - th[1]) * math.sqrt(max(v_fast, 0.0))
            m = n_linear(s)
            for t in range(m):
                d[f"term{t + 1}.gain"] = math.sqrt(var[ql + t])
            if m:
                d["gain"] = math.sqrt(max(float(np.sum(cov[ql: ql + m, ql: ql + m])), 0.0))
            blocks.append(slice(ql, ql + m) if m else None)
            qn += n_nonlinear(s)
            ql += m
            out.append(d)
        gain_cov = np.zeros((len(structures), len(structures)))
        for j, bj in enumerate(blocks):
            for k, bk in enumerate(blocks):
                if bj is not None and bk is not None:
                    gain_cov[j, k] = float(np.sum(cov[bj, bk]))
        return out, (gain_cov + gain_cov.T) / 2.0


# ---------------------------------------------------------------------------------------- starting values --
def bank_start(problem: AxisProblem, active: Sequence[bool], n_modes: int = 12) -> list[list[float]]:
    """Per factor, the one or two dominant time constants of a ridge fit over a bank of first-order modes."""
    b = problem.bounds
    taus = np.geomspace(max(math.exp(b.log_tau_min), problem.es.dt_s), math.exp(b.log_tau_max) * 2, n_modes)
    cols, owner = [], []
    for j, on in enumerate(active):
        if not on:
            continue
        for tau in taus:
            cols.append(unit_responses("first_order", [math.log(tau)], problem.es.du[j], problem.es.dt_s)[0]
                        [problem.valid])
            owner.append(j)
    starts: list[list[float]] = [[] for _ in active]
    if not cols:
        return starts
    phi = np.column_stack([*cols, problem.extra, problem.offset_cols])
    scale = np.linalg.norm(phi, axis=0)
    scale[scale == 0] = 1.0
    A = phi * problem.w[:, None] / scale
    ridge = 1e-3 * np.trace(A.T @ A) / A.shape[1]
    coef = np.linalg.solve(A.T @ A + ridge * np.eye(A.shape[1]), A.T @ (problem.w * problem.y)) / scale
    owner_arr = np.array(owner)
    for j, on in enumerate(active):
        if not on:
            continue
        # weight each bank mode by the displacement it carries (gain x its input's size)
        g = np.abs(coef[: len(owner)][owner_arr == j]) * np.abs(problem.es.du[j]).max()
        if not np.any(g > 0):
            starts[j] = [3600.0]
            continue
        order = np.argsort(g)[::-1]
        first = taus[order[0]]
        second = next((taus[k] for k in order[1:] if max(taus[k], first) / min(taus[k], first) > 2.5
                       and g[k] > 0.2 * g[order[0]]), None)
        starts[j] = [first] if second is None else sorted([first, second])
    return starts


# ----------------------------------------------------------------------------------------- selection --
@dataclass(kw_only=True)
class AxisSelection:
    """The fits tried on one axis and the one chosen."""

    axis: str
    chosen: AxisFit
    tried: dict[str, AxisFit]
    rho: float
    n_eff: float
    pruned: tuple[str, ...] = ()
    wall_s: float = 0.0
    #: paths the information criterion pruned but leaving experiments out kept (gateway.identify.api)
    unpruned: tuple[str, ...] = ()


def bic(fit: AxisFit, n_eff: float) -> float:
    """Bayesian information criterion with the effective sample size of autocorrelated residuals."""
    return n_eff * math.log(max(fit.rss, 1e-300) / fit.n) + fit.k * math.log(n_eff)


def select_axis(es: ExperimentSet, axis_index: int, *, active: Sequence[bool],
                candidates: Sequence[str] = CANDIDATES, prune: bool = True,
                progress: Callable[[str], None] | None = None, seeds: Sequence[Sequence[Sequence[float]]] = (),
                input_bounds: Sequence[Bounds | None] | None = None, project_extra: bool = False) -> AxisSelection:
    """Fit every candidate structure on one axis, choose by :func:`bic`, then prune weak paths.

    ``seeds``: more starting time constants (per input) beside the bank's, e.g. an earlier model's;
    ``input_bounds``: per input, where its time constants may go (default: the data's bounds);
    ``project_extra``: :class:`AxisProblem`'s (the extra columns factorised once).
    """
    t0 = time.perf_counter()
    problem = AxisProblem(es, axis_index, input_bounds=input_bounds, project_extra=project_extra)
    # a structure with as many parameters as windows fits anything (and its least squares is underdetermined)
    offsets = int(np.count_nonzero(problem._counts)) + problem.extra.shape[1]
    need = {c: sum(n_nonlinear(c) + n_linear(c) for on in active if on) + offsets + 1 for c in candidates}
    candidates = [c for c in candidates if need[c] <= problem.n]
    if not candidates:
        simplest = min(need, key=need.get)
        raise IdentificationError(
            f"axis {es.axes[axis_index]}: {problem.n} windows with measured displacement cannot fix the "
            f"{need[simplest] - 1} parameters of the simplest structure ({simplest}, {sum(active)} paths, "
            f"{offsets} experiment offsets): expected at least {need[simplest]}; record longer experiments")
    starts = bank_start(problem, active)
    tried: dict[str, AxisFit] = {}
    for cand in sorted(candidates, key=FIT_ORDER.index):
        if progress:
            progress(f"axis {es.axes[axis_index]}: {cand}")
        structures = [cand if on else "zero" for on in active]
        # start from the bank's time constants and from every fit already made: a structure that contains
        # another must not end up fitting worse than it because of a local minimum
        earlier = [[_time_constants(f, j) for j in range(len(active))] for f in tried.values()]
        # the bank's start never beat the first-order or two-mode solutions as a start for a second order
        tried_seeds = earlier if cand == "second_order" and earlier else [starts, *earlier]
        tried[cand] = problem.best_of(structures, _theta_starts(structures, [*tried_seeds, *seeds], problem))
    tried = {c: tried[c] for c in candidates}
    return _choose(problem, tried, prune=prune, progress=progress, t0=t0)


def _choose(problem: AxisProblem, tried: dict[str, AxisFit], *, prune: bool,
            progress: Callable[[str], None] | None, t0: float) -> AxisSelection:
    """The fit of ``tried`` with the least :func:`bic`, its weak paths pruned where the criterion allows."""
    es, axis_index = problem.es, problem.i
    richest = max(tried.values(), key=lambda f: f.k)
    n_eff, rho = effective_n(richest.residuals)
    for fit in tried.values():
        fit.bic = bic(fit, n_eff)
    chosen = min(tried.values(), key=lambda f: f.bic)
    inflation = richest.n / n_eff
    problem.attach_uncertainties(chosen, inflation)
    pruned: tuple[str, ...] = ()
    if prune:
        weak = [j for j, s in enumerate(chosen.structures)
                if s != "zero" and abs(float(np.sum(chosen.gains[j]))) < 2.0 * chosen.sd[j].get("gain", 0.0)]
        if weak:
            if progress:
                progress(f"axis {es.axes[axis_index]}: pruning {len(weak)} weak path(s)")
            structures = [("zero" if j in weak else s) for j, s in enumerate(chosen.structures)]
            theta0 = [[] if j in weak else list(th) for j, th in enumerate(chosen.thetas)]
            smaller = problem.fit(structures, theta0)
            smaller.nfev += 0
            smaller.bic = bic(smaller, n_eff)
            if smaller.bic <= chosen.bic:
                problem.attach_uncertainties(smaller, inflation)
                pruned = tuple(es.factors[j] for j in weak)
                chosen = smaller
    return AxisSelection(axis=es.axes[axis_index], chosen=chosen, tried=tried, rho=rho, n_eff=n_eff,
                         pruned=pruned, wall_s=time.perf_counter() - t0)


def refine_axis(es: ExperimentSet, axis_index: int, previous: AxisSelection, *, prune: bool = True,
                input_bounds: Sequence[Bounds | None] | None = None, project_extra: bool = False) -> AxisSelection:
    """:func:`select_axis` on a slightly different set, every structure refined from ``previous`` instead of searched.

    Each structure ``previous`` tried is fitted again from where it ended there (one start, not the bank's and
    every earlier fit's raced), then chosen and pruned as :func:`select_axis` does. For a set that differs
    from the one ``previous`` was selected on in a few rows (diagnosis's history passes: the same recordings,
    other work before the warm ones), where a search costs tens of fits.
    """
    t0 = time.perf_counter()
    problem = AxisProblem(es, axis_index, input_bounds=input_bounds, project_extra=project_extra)
    tried = {c: problem.fit(f.structures, f.thetas) for c, f in previous.tried.items()}
    return _choose(problem, tried, prune=prune, progress=None, t0=t0)


def _theta_starts(structures: Sequence[str], seeds: Sequence[Sequence[Sequence[float]]],
                  problem: AxisProblem) -> list[list[list[float]]]:
    return [[theta_from_time_constants(s, seed[j], problem.input_bounds[j]) if s != "zero" else []
             for j, s in enumerate(structures)] for seed in seeds]


def refit_axis(es: ExperimentSet, axis_index: int, *, structures: Sequence[str],
               seeds: Sequence[Sequence[Sequence[float]]] = (), input_bounds: Sequence[Bounds | None] | None = None,
               with_sd: bool = True) -> AxisFit:
    """Fit one axis with given path structures (and the set's extra columns), from several starts.

    The starts are the bank's (a linear fit over first-order modes, the extra columns beside them) and
    every seed given (time constants per input, e.g. an earlier model's): a model identified while some
    disturbance acted sits in a local minimum that its own time constants do not leave.
    """
    problem = AxisProblem(es, axis_index, input_bounds=input_bounds)
    active = [s != "zero" for s in structures]
    starts = [bank_start(problem, active), *([list(map(list, s)) for s in seeds])]
    fit = problem.best_of(structures, _theta_starts(structures, starts, problem))
    if with_sd:
        n_eff, _ = effective_n(fit.residuals)
        problem.attach_uncertainties(fit, fit.n / n_eff)
    return fit


def _time_constants(fit: AxisFit, j: int) -> list[float]:
    s, th = fit.structures[j], fit.thetas[j]
    if s == "zero":
        return [3600.0]
    return [float(t) for term in terms_with_gains(s, th, [1.0] * n_linear(s)) for t in term.time_constants_s]
