"""Gains the experiments do not determine: a prior toward zero, its strength chosen by leaving experiments out.

With the time constants of a fit held, an axis is linear in its term gains. The prior is on each path's
static gain (the sum of its terms' gains; a two-mode path's shape stays free):

    gain_j ~ N(0, (kappa * D / u_j)^2)

``D``: the largest span of the axis's measured displacement in one recording; ``u_j``: the largest
deviation of factor j the recordings covered. With kappa = 1 a path may move its axis about as much as the
largest displacement the data showed, at the factor's covered maximum: "physically plausible size", no
sign assumed. The data term weighs each window by the residual variance inflated for autocorrelation
(n / n_eff), so a path the data fix keeps its fitted gain and one they do not (co-varying factors, a factor
barely excited) is pulled toward zero instead of keeping a wide estimate.

kappa is chosen from ``KAPPAS`` (infinity: no prior) by leave-one-experiment-out prediction: every recording
is predicted from gains fitted on the others (its own offset free), the squared errors summed. That is the
user's question, "does it predict a run it has not seen"; on the paper's nine experiments every factor is
excited by only two or three of them, so leaving one out often leaves a split of co-varying factors to the
prior alone, and the criterion chooses how much to trust it.

Per path the report says whether it is poorly determined (the static gain's standard deviation exceeds
``POOR_RELATIVE`` of the gain, and times the factor's covered maximum ``POOR_SHARE`` of ``D``) and why: it
co-varies with other paths (with the time constants held, its standard deviation is over ``COVARY_RATIO``
times what its own excitation alone would give) or its factor is barely excited.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gateway.identify.common import ExperimentSet
from gateway.identify.joint import AxisFit, AxisProblem

#: prior scales tried (infinity: no prior), from strong to none
KAPPAS = (0.03, 0.1, 0.3, 1.0, 3.0, 10.0, math.inf)
#: a path is poorly determined when its gain's sd exceeds this share of the gain and the sd x its factor's
#: covered maximum exceeds POOR_SHARE of D (a path that barely matters is not worth a line)
POOR_RELATIVE = 0.3
POOR_SHARE = 0.02
#: ... and it co-varies with others when its sd is this many times what its own excitation alone gives
COVARY_RATIO = 3.0


@dataclass(frozen=True, kw_only=True)
class PathDetermination:
    """How well the data fix one path's static gain (um per factor unit)."""

    factor: str
    gain: float  # with the prior
    unshrunk: float  # without it
    sd: float  # of the gain without the prior, time constants held
    prior_sd: float  # the prior's (inf: none)
    poorly: bool
    why: str = ""

    def line(self, unit: str = "") -> str:
        per = f" um/{unit}" if unit else ""
        shrunk = abs(self.gain - self.unshrunk) > 0.05 * abs(self.unshrunk)
        moved = f" (shrunk from {self.unshrunk:.3g})" if shrunk else ""
        return f"{self.factor}: gain {self.gain:.3g} +- {self.sd:.2g}{per}{moved}: {self.why}"


@dataclass(kw_only=True)
class AxisShrinkage:
    """The prior chosen for one axis, what leaving each experiment out gave, and the paths' determination."""

    axis: str
    kappa: float
    fit: AxisFit  # the fit with the prior's gains (time constants as given), offsets and RSS recomputed
    loeo_sse: dict[float, float]  # per kappa: held-out squared error summed over experiments
    held_out_rms: dict[str, float]  # per experiment at the chosen kappa (um)
    paths: list[PathDetermination] = field(default_factory=list)
    d_um: float = 0.0
    experiments: int = 0  # with measured windows on this axis: below 2 there is nothing to leave out

    @property
    def left_out(self) -> bool:
        """Whether the prior was chosen by leaving experiments out (two or more): else it is none."""
        return self.experiments >= 2

    @property
    def loeo_rms(self) -> float:
        """Held-out RMS pooled over experiments at the chosen kappa."""
        return self._rms(self.kappa)

    @property
    def loeo_rms_without_prior(self) -> float:
        return self._rms(math.inf)

    def _rms(self, kappa: float) -> float:
        n = self.fit.n
        return math.sqrt(max(self.loeo_sse[kappa], 0.0) / max(n, 1))

    @property
    def poorly_determined(self) -> list[PathDetermination]:
        return [p for p in self.paths if p.poorly]


def _blocks(problem: AxisProblem) -> list[tuple[int, int, int]]:
    """(experiment, first row, end row) of every experiment with measured windows on this axis."""
    out, start = [], 0
    for e, c in enumerate(problem._counts):
        if c:
            out.append((e, start, start + int(c)))
            start += int(c)
    return out


def shrink_axis(problem: AxisProblem, fit: AxisFit, *, n_eff: float, kappas: Sequence[float] = KAPPAS
                ) -> AxisShrinkage:
    """Apply the prior to ``fit``'s gains with kappa chosen by leave-one-experiment-out (module docstring)."""
    es = problem.es
    factors = es.factors
    raw, owner = [], []
    for j, s in enumerate(fit.structures):
        if s == "zero":
            continue
        for c in problem.path_columns(j, s, fit.thetas[j]):
            raw.append(c)
            owner.append(j)
    blocks = _blocks(problem)
    y = problem.y_demeaned
    d_um = max((float(np.ptp(problem.y[a:b])) for _, a, b in blocks if b > a), default=0.0)
    u_max = np.abs(np.nan_to_num(es.du)).reshape(len(factors), -1).max(axis=1)
    if not raw or d_um <= 0:
        return AxisShrinkage(axis=fit.axis, kappa=math.inf, fit=fit, loeo_sse=dict.fromkeys(kappas, 0.0),
                             held_out_rms={}, d_um=d_um, experiments=len(blocks))
    owner_arr = np.array(owner)
    extra = problem.extra
    X = problem.demean(np.column_stack([*raw, extra]) if extra.shape[1] else np.column_stack(raw))
    p_paths = len(raw)
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    Xs = X / scale
    grams = [(Xs[a:b].T @ Xs[a:b], Xs[a:b].T @ y[a:b], float(y[a:b] @ y[a:b])) for _, a, b in blocks]
    G = sum(g for g, _, _ in grams)
    bvec = sum(b for _, b, _ in grams)
    # the residual variance per window, inflated for autocorrelation: the data's weight against the prior
    sigma2 = fit.rss / max(fit.n, 1) * (fit.n / max(n_eff, 1.0))
    paths = sorted(set(owner))
    P = np.zeros((len(paths), X.shape[1]))
    for r, j in enumerate(paths):
        # a path may move its axis by about D at its factor's covered maximum
        P[r, : p_paths][owner_arr == j] = u_max[j] / d_um if u_max[j] > 0 else 1.0 / d_um
    Ps = P / scale
    PP = Ps.T @ Ps

    def solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.linalg.lstsq(A, b, rcond=1e-12)[0]

    sse: dict[float, float] = {}
    held: dict[float, list[float]] = {}
    for k in kappas:
        R = sigma2 * PP / k**2 if math.isfinite(k) else np.zeros_like(PP)
        total, per = 0.0, []
        for g, b, c in grams:
            beta = solve(G - g + R, bvec - b)
            e = max(c - 2.0 * float(beta @ b) + float(beta @ g @ beta), 0.0)
            total += e
            per.append(e)
        sse[k] = total
        held[k] = per
    # the strongest prior is only taken when it predicts left-out experiments better: ties go to less prior.
    # One experiment leaves nothing to predict it from (its "held-out" error would be its own variance): none
    kappa = min(reversed(kappas), key=lambda k: sse[k]) if len(blocks) >= 2 else math.inf
    R = sigma2 * PP / kappa**2 if math.isfinite(kappa) else np.zeros_like(PP)
    coef = solve(G + R, bvec) / scale
    unshrunk = solve(G, bvec) / scale
    gains, extra_gains = coef[:p_paths], coef[p_paths:]
    new_gains = []
    k = 0
    for s, g0 in zip(fit.structures, fit.gains, strict=True):
        n = len(g0) if s != "zero" else 0
        new_gains.append(np.asarray(gains[k: k + n], dtype=float))
        k += n
    full = np.column_stack([*raw, extra]) if extra.shape[1] else np.column_stack(raw)
    means = problem._group_means(full)
    offsets = np.zeros(es.n_exp)
    offsets[problem._counts > 0] = problem._y_means - means @ coef
    r = y - X @ coef
    shrunk = AxisFit(axis=fit.axis, structures=fit.structures, thetas=fit.thetas, gains=new_gains,
                     offsets=offsets, rss=float(r @ r), extra_gains=extra_gains if extra.shape[1] else fit.extra_gains,
                     n=fit.n, nfev=fit.nfev, converged=fit.converged, residuals=problem._per_experiment(r),
                     sd=fit.sd, gain_cov=fit.gain_cov, bic=fit.bic)
    held_rms = ({es.names[e]: math.sqrt(v / max(b - a, 1)) for (e, a, b), v in zip(blocks, held[kappa], strict=True)}
                if len(blocks) >= 2 else {})
    cov = np.linalg.pinv(G, rcond=1e-12) / np.outer(scale, scale) * sigma2
    determinations = []
    for j in paths:
        cols = owner_arr == j
        sel = np.concatenate([cols, np.zeros(X.shape[1] - p_paths, dtype=bool)])
        sd_linear = math.sqrt(max(float(cov[np.ix_(sel, sel)].sum()), 0.0))
        own = X[:, sel]
        alone = np.linalg.pinv(own.T @ own, rcond=1e-12) * sigma2
        sd_alone = math.sqrt(max(float(alone.sum()), 0.0))
        # the full Jacobian's sd (time constants free) where the fit has one: a slow mode seen for an hour
        # fixes its start, not its static gain
        sd = max(sd_linear, float(fit.sd[j].get("gain", 0.0)) if fit.sd else 0.0)
        prior = kappa * d_um / u_max[j] if math.isfinite(kappa) and u_max[j] > 0 else math.inf
        gain_j = float(gains[cols].sum())
        poorly = sd > POOR_RELATIVE * abs(gain_j) and sd * u_max[j] > POOR_SHARE * d_um
        why = ""
        if poorly:
            along = _moves_with(es, j)
            if along:
                why = f"co-varies with {along}"
            elif sd_linear > COVARY_RATIO * sd_alone:
                why = (f"its response looks like that of {', '.join(_partners(X[:, :p_paths], owner_arr, j, factors))}"
                       f" (sd {sd_linear / max(sd_alone, 1e-300):.1f}x what its own excitation alone gives)")
            else:
                du = np.nan_to_num(es.du[j])
                on = du >= 0.1 * u_max[j]
                on_h = float(np.count_nonzero(on)) * es.dt_s / 3600.0
                moved = int(np.count_nonzero(np.any(on, axis=1)))  # recordings where it was on at all
                where = f"{factors[j]} at >= 10 % of its highest for {on_h:.3g} h, in {moved} of {es.n_exp} recordings"
                # hours on in most recordings are not what is missing: a gain is seen in the factor's changes
                why = (f"too little excitation ({where})" if moved < max(2, es.n_exp / 2) else
                       f"too little change in it for its gain to show ({where}: on long enough, but its rises and "
                       "falls move this axis too little against the noise and the other paths)")
        determinations.append(PathDetermination(
            factor=factors[j], gain=gain_j, unshrunk=float(unshrunk[:p_paths][cols].sum()), sd=sd,
            prior_sd=prior, poorly=poorly, why=why))
    return AxisShrinkage(axis=fit.axis, kappa=kappa, fit=shrunk, loeo_sse=sse, held_out_rms=held_rms,
                         paths=determinations, d_um=d_um, experiments=len(blocks))


#: two factors co-vary when their deviations correlate at least this much over the recordings
COVARY_R = 0.9


def _moves_with(es: ExperimentSet, j: int) -> str:
    """The factors whose deviations correlate with factor ``j``'s over every window (|r| >= COVARY_R)."""
    x = np.nan_to_num(es.du[j]).ravel()
    named = []
    for k, f in enumerate(es.factors):
        if k == j:
            continue
        other = np.nan_to_num(es.du[k]).ravel()
        den = float(np.linalg.norm(x - x.mean()) * np.linalg.norm(other - other.mean()))
        r = float((x - x.mean()) @ (other - other.mean())) / den if den > 0 else 0.0
        if abs(r) >= COVARY_R:
            named.append(f"{f} (r {r:.2f} over the recordings' windows)")
    return ", ".join(named)


def _partners(X: np.ndarray, owner: np.ndarray, j: int, factors: Sequence[str], top: int = 3) -> list[str]:
    """The paths whose summed columns correlate most with path ``j``'s (at least 0.5 in magnitude)."""
    mine = X[:, owner == j].sum(axis=1)
    scores = []
    for k in sorted(set(owner.tolist()) - {j}):
        other = X[:, owner == k].sum(axis=1)
        den = float(np.linalg.norm(mine) * np.linalg.norm(other))
        if den > 0:
            scores.append((abs(float(mine @ other)) / den, factors[k]))
    scores.sort(reverse=True)
    named = [f"{name} (|r| {r:.2f})" for r, name in scores[:top] if r >= 0.5]
    return named or ["a combination of the other paths"]
