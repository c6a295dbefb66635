"""Blocked cross-validation of hypotheses, with false-positive control.

One axis at a time. The target is the residual r = measured - model. A hypothesis at nonlinear
parameters theta (time constants, dead times, a path shape) gives regressors X(theta) whose gains enter
linearly, next to the fixed columns F (free offset per recording, accepted hypotheses, measurement
artefacts). Time is cut into K contiguous blocks; for each block, theta is chosen on the grid and the gains
are solved on the OTHER blocks only, and the held-out block is predicted. The search over theta is inside
every fold, so its cost in false positives is paid by the held-out error itself.

Everything comes from per-block Gram matrices (X_b' X_b, X_b' r_b, r_b' r_b), so a grid of hundreds of
settings costs a few small solves per fold.

Evidence is judged on the K held-out blocks: d_b = SSE_before,b - SSE_after,b. Blocks are hours long,
longer than most of the residual's correlation, so the block sums are treated as independent (batch
means, valid for slow coloured residuals where a per-sample 1/sqrt(N) bound is not) and tested with a
signed-rank test; the p-values of all hypotheses tried in a round are corrected together (Holm).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.stats

RIDGE = 1e-9  # relative to unit-norm columns: keeps near-collinear offsets and decays solvable
#: settings of one grid are scored together up to this many regressors at once (memory: K x this x fixed)
BATCH_COLUMNS = 128


BURN_IN = -2  #: block id of a recording's first block: always fitted, never held out


def make_blocks(bounds: Sequence[tuple[int, int]], valid: np.ndarray, k: int) -> np.ndarray:
    """Block id per window: about ``k`` held-out blocks of equal valid length, plus a burn-in per recording.

    The first block of every recording (same length as the others) is :data:`BURN_IN`: the machine's
    state at a recording's start is not known exactly (a recorded room temperature has been acting on it
    long before), so hypotheses fit that initial state there and are judged on the blocks after it.
    Windows that are not valid get -1.
    """
    counts = np.array([int(valid[a:b].sum()) for a, b in bounds])
    total = max(int(counts.sum()), 1)
    per = [max(3, round((k + len(bounds)) * c / total)) if c >= 6 else 0 for c in counts]
    block = np.full(len(valid), -1)
    next_id = 0
    for (a, b), n_b in zip(bounds, per, strict=True):
        idx = np.flatnonzero(valid[a:b]) + a
        if not n_b:
            continue
        cuts = np.array_split(idx, n_b)
        block[cuts[0]] = BURN_IN
        for c in cuts[1:]:
            block[c] = next_id
            next_id += 1
    return block


class Fold:
    """The design of one axis: target ``r`` (n,), block ids (n,), and the fixed columns (n, q) every fit carries.

    The fixed columns' per-block products are computed once here; each setting of a hypothesis then adds
    only its own columns' products.
    """

    def __init__(self, *, r: np.ndarray, block: np.ndarray, fixed: np.ndarray, k: int | None = None) -> None:
        self.r = r
        self.block = block
        #: held-out blocks (``k``: those of every axis, so that per-block figures of axes line up where one is
        #: measured in fewer: a day without its column); burn-in rows sum into slot k
        self.k = max(int(block.max()) + 1, k or 0)
        # contiguous runs of one block, and the slot each run's sums land in
        self.starts = np.concatenate([[0], np.flatnonzero(np.diff(block)) + 1])
        self.stops = np.append(self.starts[1:], len(r))
        self.slot = np.where(block[self.starts] >= 0, block[self.starts], self.k)
        self._slot_of_run = (self.slot[:, None] == np.arange(self.k + 1)[None, :]).astype(float)
        scale = np.sqrt(np.einsum("ij,ij->j", fixed, fixed))
        scale[scale == 0] = 1.0
        self.fixed_scale = scale
        self.F = fixed / scale
        q = self.F.shape[1]
        self.FF = np.zeros((self.k + 1, q, q))
        #: per contiguous run of a block: its rows, its slot, and the fixed columns not all zero in it (an
        #: offset, a recording's nuisance or an input's lag is zero outside its recordings) with their rows,
        #: the target beside them as a last column (a setting's X'F and X'r are one matrix product per run)
        self.runs: list[tuple[int, int, int, np.ndarray | None, np.ndarray]] = []
        for a, b, j in zip(self.starts, self.stops, self.slot, strict=True):
            self.FF[j] += self.F[a:b].T @ self.F[a:b]
            nz = np.flatnonzero(np.any(self.F[a:b] != 0.0, axis=0))
            Fr = np.column_stack([self.F[a:b] if len(nz) == q else self.F[a:b, nz], r[a:b]])
            self.runs.append((int(a), int(b), int(j), None if len(nz) == q else nz, Fr))
        self.Fr = self.sums(self.F * r[:, None])
        self.rr = self.sums(r * r)
        self._solver: _FixedSolve | None = None

    @property
    def solver(self) -> _FixedSolve:
        """The fixed columns' normal equations, factorised once for every setting scored on this fold."""
        if self._solver is None:
            self._solver = _FixedSolve(self)
        return self._solver

    def run_sums(self, cols: np.ndarray) -> np.ndarray:
        """Per-block sums along the last axis of ``cols`` (..., n) into K + 1 slots (the last: burn-in)."""
        seg = np.add.reduceat(cols, self.starts, axis=-1)
        return seg @ self._slot_of_run

    def sums(self, rows: np.ndarray) -> np.ndarray:
        """Per-block sums of ``rows`` (first axis: windows) into K + 1 slots (the last: burn-in)."""
        seg = np.add.reduceat(rows, self.starts, axis=0)
        out = np.zeros((self.k + 1, *rows.shape[1:]))
        np.add.at(out, self.slot, seg)
        return out


@dataclass
class GridFit:
    """Cross-validated fit of one hypothesis over its grid on one axis."""

    held: np.ndarray  # (K,) held-out SSE per block with the setting chosen in each fold
    theta_fold: np.ndarray  # (K,) grid index chosen in each fold (-1: none admissible)
    gains_fold: np.ndarray  # (K, p) the hypothesis's gains in each fold
    best: int  # grid index chosen on all data
    gains: np.ndarray  # (p,) gains on all data
    sse: float  # all-data SSE at best
    admissible: bool = True  # some setting is plausible on all data
    without: np.ndarray | None = None  # (K,) held-out SSE without the hypothesis


@dataclass
class GridScores:
    """Training, held-out and all-data SSE of every setting of a grid on one axis, per fold."""

    train: np.ndarray  # (G, K), inf where the fold's gains are not admissible
    held: np.ndarray  # (G, K)
    full: np.ndarray  # (G,), inf where not admissible on all data
    gains_fold: list[np.ndarray]  # per setting (K, p_g)
    gains_all: list[np.ndarray]  # per setting (p_g,)
    without: np.ndarray  # (K,) held-out SSE without the hypothesis


def _run_sums(fold: Fold, XT: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-slot sums X'F, X'X, X'r of G settings' scaled regressors, and X's scale (G, p).

    ``XT`` (G p, n): setting g's regressors are rows g p .. g p + p - 1 (windows along a row, so each row
    is one contiguous column of the stack; scaled in place). Returned slots first: (K + 1, G, p, q),
    (K + 1, G, p, p), (K + 1, G, p) (slot K: burn-in rows). X'F and X'r are one matrix product per contiguous
    run of a block for the whole batch (the fixed columns and the target are read once, not once per
    setting); X'X is sums per run of elementwise products.
    """
    n_set = XT.shape[0] // p
    q = fold.F.shape[1]
    xs = np.sqrt(np.einsum("in,in->i", XT, XT))
    xs[xs == 0] = 1.0
    Xs = np.divide(XT, xs[:, None], out=XT)  # in place: the batch's own copy (grid_scores)
    # per regressor and contiguous run of a block: its sum of squares (X'X's diagonal, run by run), and so
    # whether it is non-zero there (a square underflows only below 1e-154 of the regressor's norm)
    squares = np.add.reduceat(Xs * Xs, fold.starts, axis=-1)
    live = squares > 0.0
    XF = np.zeros((fold.k + 1, n_set * p, q))
    Xr_run = np.zeros((n_set * p, len(fold.runs)))
    for i, (a, b, j, nz, Fr) in enumerate(fold.runs):  # columns (fixed or the settings') zero in a run add nothing
        Xb = Xs[:, a:b]
        moving = np.flatnonzero(live[:, i])
        if len(moving) < 0.8 * len(Xb):
            if not len(moving):
                continue
            part = Xb[moving] @ Fr
            if nz is None:
                XF[j][moving] += part[:, :-1]
            else:
                XF[j][np.ix_(moving, nz)] += part[:, :-1]
            Xr_run[moving, i] = part[:, -1]
        else:
            part = Xb @ Fr
            if nz is None:
                XF[j] += part[:, :-1]
            else:
                XF[j][:, nz] += part[:, :-1]
            Xr_run[:, i] = part[:, -1]
    Xr = Xr_run @ fold._slot_of_run  # (G p, K + 1)
    X3 = Xs.reshape(n_set, p, -1)
    # the runs in which regressor u of any setting is not zero: a recording's nuisance (its initial state, its
    # drift) is zero in every other recording, and two regressors that are never non-zero in the same run have
    # a product of exact zeros, whose sums are zero (computed, they would be zero too, up to the sign of zero)
    support = live.reshape(n_set, p, -1).any(axis=0)
    XX = np.zeros((fold.k + 1, n_set, p, p))
    diagonal = squares.reshape(n_set, p, -1)
    for u in range(p):
        XX[:, :, u, u] = (diagonal[:, u] @ fold._slot_of_run).T
        for v in range(u + 1, p):
            common = support[u] & support[v]
            if common.all():
                XX[:, :, u, v] = XX[:, :, v, u] = fold.run_sums(X3[:, u] * X3[:, v]).T
            elif common.any():
                # only the runs where both can be non-zero: each run's sum is its own reduction, the same
                # numbers as over the whole stack; the other runs' sums are zeros
                seg = np.zeros((n_set, len(fold.starts)))
                idx = np.flatnonzero(common)
                for grp in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                    a, b = fold.starts[grp[0]], fold.stops[grp[-1]]
                    seg[:, grp] = np.add.reduceat(X3[:, u, a:b] * X3[:, v, a:b], fold.starts[grp] - a, axis=-1)
                XX[:, :, u, v] = XX[:, :, v, u] = (seg @ fold._slot_of_run).T
    return (XF.reshape(fold.k + 1, n_set, p, q), XX, Xr.reshape(n_set, p, fold.k + 1).transpose(2, 0, 1),
            xs.reshape(n_set, p))


class _FixedSolve:
    """The fixed columns' normal equations, per fold and on all data, factorised once.

    A setting's regressors X are then solved by the Schur complement of the fixed block,
    S = X'X - X'F (F'F)^-1 F'X: a solve of the size of X per fold, however many fixed columns every fit
    carries (offsets, artefacts, the paths' corrections).
    """

    def __init__(self, fold: Fold) -> None:
        q = fold.F.shape[1]
        eye = np.eye(q) * RIDGE
        self.FF_all, self.Fr_all, self.rr_all = fold.FF.sum(0), fold.Fr.sum(0), float(fold.rr.sum())
        self.FF_tr = self.FF_all - fold.FF[:-1]
        self.Fr_tr = self.Fr_all - fold.Fr[:-1]
        self.rr_tr = self.rr_all - fold.rr[:-1]
        self.inv_all = np.linalg.inv(self.FF_all + eye)
        self.inv_tr = np.linalg.inv(self.FF_tr + eye)
        self.b_all = self.inv_all @ self.Fr_all
        self.b_tr = np.einsum("kij,kj->ki", self.inv_tr, self.Fr_tr)
        self.fold = fold
        #: held-out SSE per block with the fixed columns alone
        self.without = _quad(fold.FF[:-1], fold.Fr[:-1], fold.rr[:-1], self.b_tr)

    def solve(self, XF: np.ndarray, XX: np.ndarray, Xr: np.ndarray) -> tuple[np.ndarray, ...]:
        """(beta_F, beta_X per fold; beta_F, beta_X on all data) for per-slot sums of G settings.

        Slots first: ``XF`` (K + 1, G, p, q), ``XX`` (K + 1, G, p, p), ``Xr`` (K + 1, G, p); returns bF (K, G, q),
        bX (K, G, p), bF1 (G, q), bX1 (G, p). The products with the fixed columns' (q, q) inverses are one
        matrix product per fold for the whole batch.
        """
        k1, g, p, q = XF.shape
        k = k1 - 1
        eye = np.eye(p) * RIDGE
        XF_all, XX_all, Xr_all = XF.sum(0), XX.sum(0), Xr.sum(0)
        XF_tr, XX_tr, Xr_tr = XF_all - XF[:-1], XX_all - XX[:-1], Xr_all - Xr[:-1]
        A = (XF_tr.reshape(k, g * p, q) @ self.inv_tr).reshape(k, g, p, q)
        S = XX_tr - np.einsum("kgpq,kgrq->kgpr", A, XF_tr)
        rhs = Xr_tr - (A.reshape(k, g * p, q) @ self.Fr_tr[:, :, None]).reshape(k, g, p)
        bX = np.linalg.solve(S + eye, rhs[..., None])[..., 0]
        bF = self.b_tr[:, None, :] - np.einsum("kgpq,kgp->kgq", A, bX)
        A1 = (XF_all.reshape(g * p, q) @ self.inv_all).reshape(g, p, q)
        bX1 = np.linalg.solve(XX_all - np.einsum("gpq,grq->gpr", A1, XF_all) + eye,
                              (Xr_all - (A1.reshape(g * p, q) @ self.Fr_all).reshape(g, p))[..., None])[..., 0]
        bF1 = self.b_all - np.einsum("gpq,gp->gq", A1, bX1)
        return bF, bX, bF1, bX1


def _sse(FF: np.ndarray, Fr: np.ndarray, rr: np.ndarray, XF: np.ndarray, XX: np.ndarray, Xr: np.ndarray,
         bF: np.ndarray, bX: np.ndarray) -> np.ndarray:
    """SSE of r - F bF - X bX from Gram quantities, per fold and setting: (K, G).

    ``FF`` (K, q, q), ``Fr`` (K, q), ``rr`` (K,) of the fixed columns; ``XF`` (K, G, p, q), ``XX`` (K, G, p, p),
    ``Xr`` (K, G, p), ``bF`` (K, G, q), ``bX`` (K, G, p) of the settings (one fold: K = 1).
    """
    FFb = FF @ np.swapaxes(bF, 1, 2)  # (K, q, G): one matrix product per fold, not one per setting
    quad_f = np.einsum("kgq,kqg->kg", bF, FFb)
    XFb = np.einsum("kgpq,kgq->kgp", XF, bF)
    XXb = np.einsum("kgpr,kgr->kgp", XX, bX)
    return (rr[:, None] - 2 * (np.einsum("kgq,kq->kg", bF, Fr) + np.sum(bX * Xr, axis=-1))
            + quad_f + 2 * np.sum(bX * XFb, axis=-1) + np.sum(bX * XXb, axis=-1))


def _quad(G: np.ndarray, h: np.ndarray, s: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """s - 2 beta'h + beta' G beta (the SSE of r - X beta from Gram quantities)."""
    return s - 2 * np.einsum("...i,...i->...", beta, h) + np.einsum("...i,...ij,...j->...", beta, G, beta)


def grid_scores(fold: Fold, designs: Sequence[np.ndarray] | Sequence[Sequence[np.ndarray]], *,
                signs: Sequence[np.ndarray] | None = None, limits: Sequence[np.ndarray] | None = None,
                rows: np.ndarray | None = None) -> GridScores:
    """Score every grid setting (regressors ``designs[g]``, (n, p)) in every fold.

    ``signs[g]`` and ``limits[g]`` (one entry per regressor of setting g; sign 0 and limit inf: free) make a
    setting inadmissible in a fold whose fitted gains break them: plausibility is enforced inside every
    fold, not judged afterwards on all data.

    ``rows`` (increasing): ``designs[g]`` is then setting g's regressors as longer columns (a sequence of 1-d
    arrays) of which the fold's windows are ``rows``: each is copied once, straight into the batch scored.
    """
    n_grid = len(designs)
    k = fold.k
    train = np.full((n_grid, k), np.inf)
    held = np.full((n_grid, k), np.inf)
    full = np.full(n_grid, np.inf)
    fs = fold.solver
    gains_f: list[np.ndarray] = [np.zeros((k, 0))] * n_grid
    gains_a: list[np.ndarray] = [np.zeros(0)] * n_grid
    by_width: dict[int, list[int]] = {}
    for g, X in enumerate(designs):
        by_width.setdefault(len(X) if rows is not None else X.shape[1], []).append(g)
    for p, members in by_width.items():
        if p == 0:  # nothing but nuisance: the fixed fit itself
            train[members] = _quad(fs.FF_tr, fs.Fr_tr, fs.rr_tr, fs.b_tr)
            held[members] = fs.without
            full[members] = float(_quad(fs.FF_all, fs.Fr_all, fs.rr_all, fs.b_all))
            continue
        # settings of the same width scored together, in batches that keep the per-slot sums small
        per = max(1, BATCH_COLUMNS // p)
        for start in range(0, len(members), per):
            idx = members[start: start + per]
            # a regressor to a row, each row contiguous whatever the designs' layout (concatenating the
            # transposes of C-ordered (n, p) designs gives column-major rows: strided sums, 1.2x the time)
            XT = np.empty((len(idx) * p, len(fold.r)))
            for i, g in enumerate(idx):
                if rows is None:
                    XT[i * p: (i + 1) * p] = designs[g].T
                    continue
                for u, c in enumerate(designs[g]):
                    if len(c) == len(rows):  # every window (``rows`` increasing): the column as it is
                        XT[i * p + u] = c
                    else:
                        np.take(c, rows, out=XT[i * p + u])
            XF, XX, Xr, xs = _run_sums(fold, XT, p)
            bF, bX, bF1, bX1 = fs.solve(XF, XX, Xr)
            gf = np.swapaxes(bX, 0, 1) / xs[:, None, :]  # (G, K, p)
            ga = bX1 / xs
            sg = _per_regressor([signs[g] for g in idx] if signs else None, p, 0.0)
            lim = _per_regressor([limits[g] for g in idx] if limits else None, p, np.inf)
            ok_f = _admissible_batch(gf, sg, lim)
            ok_a = _admissible_batch(ga[:, None, :], sg, lim)[:, 0]
            XF_all, XX_all, Xr_all = XF.sum(0), XX.sum(0), Xr.sum(0)
            tr = _sse(fs.FF_tr, fs.Fr_tr, fs.rr_tr, XF_all - XF[:-1], XX_all - XX[:-1], Xr_all - Xr[:-1], bF, bX)
            train[idx] = np.where(ok_f, tr.T, np.inf)
            held[idx] = _sse(fold.FF[:-1], fold.Fr[:-1], fold.rr[:-1], XF[:-1], XX[:-1], Xr[:-1], bF, bX).T
            one = _sse(fs.FF_all[None], fs.Fr_all[None], np.array([fs.rr_all]), XF_all[None], XX_all[None],
                       Xr_all[None], bF1[None], bX1[None])[0]
            full[idx] = np.where(ok_a, one, np.inf)
            for i, g in enumerate(idx):
                gains_f[g] = gf[i]
                gains_a[g] = ga[i]
    return GridScores(train=train, held=held, full=full, gains_fold=gains_f, gains_all=gains_a, without=fs.without)


def choose(scores: dict[str, GridScores], keys: dict[str, Sequence[object]] | None = None) -> dict[str, GridFit]:
    """Pick each fold's setting on its training blocks (and one on all data), per axis.

    ``keys[axis][g]`` names the machine-wide parameters of setting g (a transport delay, the bearing's
    time constant): settings of all axes with the same key are chosen together, by the training SSE summed
    over the axes, because one machine has one such value. Without keys every axis chooses alone. A fold
    with no admissible setting predicts without the hypothesis.
    """
    axes = list(scores)
    if not axes:
        return {}
    k = next(iter(scores.values())).train.shape[1]
    choice: dict[str, np.ndarray] = {}
    best: dict[str, int] = {}
    if keys is None:
        for a in axes:
            choice[a] = np.argmin(scores[a].train, axis=0)
            best[a] = int(np.argmin(scores[a].full))
    else:
        values = list(dict.fromkeys(v for a in axes for v in keys[a]))
        tot_f = np.zeros((len(values), k))
        tot_a = np.zeros(len(values))
        for a in axes:
            kv = np.array([values.index(v) for v in keys[a]])
            for i in range(len(values)):
                sel = kv == i
                tot_f[i] += scores[a].train[sel].min(axis=0) if sel.any() else np.inf
                tot_a[i] += scores[a].full[sel].min() if sel.any() else np.inf
        v_f = np.argmin(tot_f, axis=0)
        v_a = int(np.argmin(tot_a))
        for a in axes:
            kv = np.array([values.index(v) for v in keys[a]])
            tr = np.where(kv[:, None] == v_f[None, :], scores[a].train, np.inf)
            choice[a] = np.argmin(tr, axis=0)
            best[a] = int(np.argmin(np.where(kv == v_a, scores[a].full, np.inf)))
    out = {}
    for a in axes:
        sc = scores[a]
        c = choice[a]
        none_ok = ~np.isfinite(sc.train[c, np.arange(k)])
        out[a] = GridFit(held=np.where(none_ok, sc.without, sc.held[c, np.arange(k)]),
                         theta_fold=np.where(none_ok, -1, c),
                         gains_fold=_padded([sc.gains_fold[g][f] for f, g in enumerate(c)]), best=best[a],
                         gains=sc.gains_all[best[a]], sse=float(sc.full[best[a]]),
                         admissible=bool(np.isfinite(sc.full[best[a]])), without=sc.without)
    return out


def _padded(rows: Sequence[np.ndarray]) -> np.ndarray:
    """Rows of different lengths (settings of one grid may have different regressors) padded with NaN."""
    width = max((len(r) for r in rows), default=0)
    out = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out


def _per_regressor(values: Sequence[np.ndarray | None] | None, p: int, free: float) -> np.ndarray | None:
    """Signs or limits of a batch of settings as a (G, p) array (``free`` where a setting gives none).

    NaN rows: the setting gives no constraint at all (:func:`_admissible_batch` skips the check).
    """
    if values is None:
        return None
    out = np.full((len(values), p), free)
    for i, v in enumerate(values):
        if v is None or not len(v):
            out[i] = np.nan
        else:
            m = min(p, len(v))
            out[i, :m] = np.asarray(v, float)[:m]
    return out


def _admissible_batch(gains: np.ndarray, signs: np.ndarray | None, limits: np.ndarray | None) -> np.ndarray:
    """Per setting and fold, whether every gain has its required sign and stays within its limit.

    ``gains`` (G, K, p), ``signs`` and ``limits`` (G, p; a NaN row: that setting gives none) -> (G, K).
    """
    ok = np.ones(gains.shape[:2], dtype=bool)
    if signs is not None:
        given = ~np.isnan(signs[:, 0])
        ok &= ~given[:, None] | np.all(gains * signs[:, None, :] >= 0, axis=-1)
    if limits is not None:
        given = ~np.isnan(limits[:, 0])
        ok &= ~given[:, None] | np.all(np.abs(gains) <= limits[:, None, :], axis=-1)
    return ok


def one_sided_p(d: np.ndarray) -> float:
    """P-value of "the blocks improve" from the blocks' improvements ``d`` (Wilcoxon signed rank, one-sided).

    Ranks, not values: thermal errors are large in working hours and small at night, so a t-test on
    the raw block improvements is swamped by their spread; the signed-rank test asks whether blocks
    improve consistently, with blocks hours long treated as independent (batch means).
    """
    d = np.asarray(d, float)
    d = d[d != 0]
    if len(d) < 3:
        return 1.0
    size = np.abs(d)
    order = np.argsort(size)
    if len(d) > EXACT_WILCOXON_MAX or np.any(size[order[1:]] == size[order[:-1]]):
        return float(scipy.stats.wilcoxon(d, alternative="greater").pvalue)  # ties or large: as scipy decides
    # no ties, no zeros, few blocks: scipy's exact null distribution, whose p depends on the count and the
    # positive rank sum only (a search asks it thousands of times for a few dozen distinct sums)
    ranks = np.empty(len(d), dtype=int)
    ranks[order] = np.arange(1, len(d) + 1)
    key = (len(d), int(ranks[d > 0].sum()))
    if key not in _EXACT_P:
        _EXACT_P[key] = float(scipy.stats.wilcoxon(d, alternative="greater").pvalue)
    return _EXACT_P[key]


def blocks_to_decide(d: np.ndarray, *, multiplicity: float, alpha: float, power: float = 0.8, draws: int = 400,
                     most: int = 2000, seed: int = 0) -> int | None:
    """How many more held-out blocks like ``d`` a test of "the blocks improve" would need to pass.

    ``d``: the blocks' improvements so far (held-out SSE without minus with). Blocks drawn from ``d`` with
    replacement stand for recordings like these; the answer is the smallest count m for which, with m such
    blocks added, ``multiplicity`` x the one-sided signed-rank p (its normal approximation, which is what
    scipy uses beyond a few dozen blocks) falls below ``alpha`` in ``power`` of the draws. 0: it passes
    already; None: not within ``most`` blocks, or no block improves. A projection, not a promise: it assumes
    the recordings to come vary as these did.
    """
    d = np.asarray(d, float)
    d = d[np.isfinite(d) & (d != 0)]
    if not (d > 0).any():
        return None
    rng = np.random.default_rng(seed)
    extra = rng.integers(0, len(d), size=(draws, most))  # common draws: one sequence of blocks per draw
    cut = alpha / multiplicity

    def passes(m: int) -> bool:
        v = np.concatenate([np.broadcast_to(d, (draws, len(d))), d[extra[:, :m]]], axis=1)
        n = v.shape[1]
        ranks = np.argsort(np.argsort(np.abs(v), axis=1), axis=1) + 1.0
        t = np.where(v > 0, ranks, 0.0).sum(axis=1)
        z = (t - n * (n + 1) / 4.0) / math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
        p = scipy.stats.norm.sf(z)
        return float(np.mean(p < cut)) >= power

    if passes(0):
        return 0
    lo, hi = 0, 1
    while not passes(hi):
        lo, hi = hi, 2 * hi
        if hi > most:
            if not passes(most):
                return None
            hi = most
            break
    while hi - lo > 1:  # lo fails, hi passes
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if passes(mid) else (mid, hi)
    return hi


#: scipy's signed-rank test is exact up to this many non-zero differences without ties
EXACT_WILCOXON_MAX = 50
_EXACT_P: dict[tuple[int, int], float] = {}


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm-adjusted p-values (family-wise error over all the hypotheses of one round)."""
    p = np.asarray(pvalues, float)
    order = np.argsort(p)
    m = len(p)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adj[i] = running
    return adj.tolist()


def jackknife_sd(values: np.ndarray) -> np.ndarray:
    """Delete-a-block jackknife standard deviation of per-fold estimates (rows: folds)."""
    v = np.asarray(values, float)
    k = v.shape[0]
    if k < 2:
        return np.full(v.shape[1:], math.nan)
    return np.sqrt((k - 1) / k * np.sum((v - v.mean(axis=0)) ** 2, axis=0))


def held_out(target: np.ndarray, block: np.ndarray, columns: Sequence[np.ndarray], *,
             zeros: Sequence[tuple[int, np.ndarray]] = ()) -> np.ndarray:
    """Predictions of ``target`` on each held-out block from a fit on the other blocks (NaN elsewhere).

    ``columns`` are the regressors whose gains every fold refits; burn-in rows always train and get NaN.
    ``zeros``: per recording, (index in ``columns`` of its offset column, the windows its zero is taken from:
    its first block). Each fold fits that offset like any gain, but predicts the recording on the zero its
    first block gives with the fold's gains, as a gateway that has run for a while is zeroed: an offset found
    later in the recording (or none, for a recording held out whole) does not rescue a model.
    """
    cols = list(columns)
    fold = Fold(r=target, block=block, fixed=np.column_stack(cols))
    fs = fold.solver
    pred = np.full(len(target), np.nan)
    for f in range(fold.k):
        beta = fs.b_tr[f]
        full = fold.F @ beta
        for j, first in zeros:
            member = cols[j] != 0
            shape = full - fold.F[:, j] * beta[j]  # everything but this recording's own offset
            if first.any():
                full[member] = shape[member] + float(np.mean(target[first] - shape[first]))
        rows = block == f
        pred[rows] = full[rows]
    return pred
