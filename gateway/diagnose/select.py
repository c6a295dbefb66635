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

    def __init__(self, *, r: np.ndarray, block: np.ndarray, fixed: np.ndarray) -> None:
        self.r = r
        self.block = block
        self.k = int(block.max()) + 1  #: held-out blocks; burn-in rows sum into slot k
        # contiguous runs of one block, and the slot each run's sums land in
        self.starts = np.concatenate([[0], np.flatnonzero(np.diff(block)) + 1])
        self.stops = np.append(self.starts[1:], len(r))
        self.slot = np.where(block[self.starts] >= 0, block[self.starts], self.k)
        scale = np.sqrt(np.einsum("ij,ij->j", fixed, fixed))
        scale[scale == 0] = 1.0
        self.fixed_scale = scale
        self.F = fixed / scale
        self.FF = self.sums(self.F[:, :, None] * self.F[:, None, :])
        self.Fr = self.sums(self.F * r[:, None])
        self.rr = self.sums(r * r)

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


def _grams(fold: Fold, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-block (G_b, h_b, s_b) of the scaled design [fixed, X] and the scale (slot K: burn-in rows)."""
    F = fold.F
    q, p = F.shape[1], X.shape[1]
    xs = np.sqrt(np.einsum("ij,ij->j", X, X)) if p else np.zeros(0)
    xs[xs == 0] = 1.0
    scale = np.concatenate([fold.fixed_scale, xs])
    G = np.zeros((fold.k + 1, q + p, q + p))
    h = np.zeros((fold.k + 1, q + p))
    G[:, :q, :q] = fold.FF
    h[:, :q] = fold.Fr
    if p:
        Xs = X / xs
        # one matrix product per contiguous run of a block: wide designs (a decay per recording) stay cheap
        for a, b, j in zip(fold.starts, fold.stops, fold.slot, strict=True):
            Xb = Xs[a:b]
            XF = Xb.T @ F[a:b]
            G[j, q:, :q] += XF
            G[j, :q, q:] += XF.T
            G[j, q:, q:] += Xb.T @ Xb
            h[j, q:] += Xb.T @ fold.r[a:b]
    return G, h, fold.rr.copy(), scale


def _folds(G: np.ndarray, h: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
    """(all-data G, h, s; training G, h, s per held-out block; held-out G, h, s per block)."""
    Gt, ht, st = G.sum(0), h.sum(0), s.sum()
    return Gt, ht, st, Gt - G[:-1], ht - h[:-1], st - s[:-1], G[:-1], h[:-1], s[:-1]


def _solve(G: np.ndarray, h: np.ndarray) -> np.ndarray:
    m = G.shape[-1]
    eye = np.eye(m) * RIDGE
    return np.linalg.solve(G + eye, h[..., None])[..., 0]


def _quad(G: np.ndarray, h: np.ndarray, s: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """s - 2 beta'h + beta' G beta (the SSE of r - X beta from Gram quantities)."""
    return s - 2 * np.einsum("...i,...i->...", beta, h) + np.einsum("...i,...ij,...j->...", beta, G, beta)


def grid_scores(fold: Fold, designs: Sequence[np.ndarray], *, signs: Sequence[np.ndarray] | None = None,
                limits: Sequence[np.ndarray] | None = None) -> GridScores:
    """Score every grid setting (regressors ``designs[g]``, (n, p)) in every fold.

    ``signs[g]`` and ``limits[g]`` (one entry per regressor of setting g; sign 0 and limit inf: free) make a
    setting inadmissible in a fold whose fitted gains break them: plausibility is enforced inside every
    fold, not judged afterwards on all data.
    """
    n_grid = len(designs)
    k = fold.k
    train = np.full((n_grid, k), np.inf)
    held = np.full((n_grid, k), np.inf)
    full = np.full(n_grid, np.inf)
    gains_f: list[np.ndarray] = []
    gains_a: list[np.ndarray] = []
    q = fold.F.shape[1]
    _, _, _, G0tr, h0tr, _, G0, h0, s0 = _folds(*_grams(fold, np.zeros((len(fold.r), 0)))[:3])
    without = _quad(G0, h0, s0, _solve(G0tr, h0tr))
    for g, X in enumerate(designs):
        G4, h4, s4, scale = _grams(fold, X)
        Gt, ht, st, Gtr, htr, s_tr, G, h, s = _folds(G4, h4, s4)
        beta_all = _solve(Gt, ht)
        beta = _solve(Gtr, htr)  # (K, m)
        gf = beta[:, q:] / scale[q:]
        ga = beta_all[q:] / scale[q:]
        sg = signs[g] if signs else None
        lim = limits[g] if limits else None
        ok_f = _admissible(gf, sg, lim)
        ok_a = _admissible(ga[None, :], sg, lim)[0]
        train[g] = np.where(ok_f, _quad(Gtr, htr, s_tr, beta), np.inf)
        held[g] = _quad(G, h, s, beta)
        full[g] = float(_quad(Gt, ht, st, beta_all)) if ok_a else np.inf
        gains_f.append(gf)
        gains_a.append(ga)
    return GridScores(train=train, held=held, full=full, gains_fold=gains_f, gains_all=gains_a, without=without)


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


def _admissible(gains: np.ndarray, signs: np.ndarray | None, limits: np.ndarray | None) -> np.ndarray:
    """Per row of ``gains`` (folds), whether every gain has its required sign and stays within its limit."""
    ok = np.ones(gains.shape[0], dtype=bool)
    p = gains.shape[1]
    if signs is not None and len(signs):
        sg = np.zeros(p)
        sg[: min(p, len(signs))] = np.asarray(signs, float)[:p]
        ok &= np.all(gains * sg >= 0, axis=1)
    if limits is not None and len(limits):
        lim = np.full(p, np.inf)
        lim[: min(p, len(limits))] = np.asarray(limits, float)[:p]
        ok &= np.all(np.abs(gains) <= lim, axis=1)
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
    return float(scipy.stats.wilcoxon(d, alternative="greater").pvalue)


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
