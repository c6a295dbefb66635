"""The paper's identification procedure (Shamoto et al. 2003, section 3), kept as the reference baseline.

1. Factors that change together in an experiment form a group (e.g. spindle speed, I1^2, I2^2). With h
   co-varying factors p..q, h experiments are needed in which (1) the number of experiments equals the
   number of factors, (2) each factor follows the same time shape u'_j in every experiment, only scaled:
   u_jr = v_jr u'_j, and (3) the h vectors [v_pr .. v_qr] are linearly independent (eqs. 8-9).
2. Then [lambda'] = [lambda][V^-1] separates the displacement each factor alone would cause (eq. 10).
3. Each separated response is fitted with the second-order form of eq. 12 by steepest descent on the
   summed squared error E (eq. 13) with a numerical gradient (eq. 13 and the text after it).

Two details differ from the paper, both stated: the descent works on gain = 1/K rather than K (the same
model; a path with no effect then sits at gain 0 instead of K = infinity), and responses are computed
with the project's exact zero-order-hold discretisation rather than eq. 5's rectangle rule, so the model
this produces is evaluated exactly as the live estimator will evaluate it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from gateway.errors import IdentificationError
from gateway.identify.common import ExperimentSet
from gateway.model.discrete import Section
from gateway.model.model import PathTF
from gateway.model.terms import SecondOrder

#: a factor counts as changing in an experiment when it moves by more than this share of its largest move
ACTIVE_SHARE = 0.01
#: condition (2): largest non-proportional part allowed, relative to the factor's size
PROPORTIONAL_TOL = 0.05
#: condition (3): largest condition number of V accepted
COND_MAX = 1e6


@dataclass(frozen=True, kw_only=True)
class Group:
    """Co-varying factors and the experiments that excite them (the paper's p..q and r = 1..h)."""

    factors: tuple[int, ...]
    experiments: tuple[int, ...]
    shapes: np.ndarray  # (h, N): u'_j
    V: np.ndarray  # (h factors, h experiments): v_jr
    nonproportional: tuple[float, ...]  # per factor: |u - v u'| / |u|


def active_factors(es: ExperimentSet, share: float = ACTIVE_SHARE) -> np.ndarray:
    """(E, F) boolean: which factors change in which experiment."""
    size = np.abs(es.du).max(axis=2)  # (F, E)
    top = size.max(axis=1, keepdims=True)
    return ((size > share * top) & (top > 0)).T


def find_groups(es: ExperimentSet, *, tol: float = PROPORTIONAL_TOL, cond_max: float = COND_MAX) -> list[Group]:
    """Group experiments by the factors they change and check the paper's three conditions.

    Raises :class:`IdentificationError` naming the group and the condition that fails.
    """
    act = active_factors(es)
    sets: dict[tuple[int, ...], list[int]] = {}
    for r in range(es.n_exp):
        key = tuple(int(j) for j in np.flatnonzero(act[r]))
        if key:
            sets.setdefault(key, []).append(r)
    covered = {j for key in sets for j in key}
    groups = []
    for key, exps in sets.items():
        names = ", ".join(es.factors[j] for j in key)
        enames = ", ".join(es.names[r] for r in exps)
        h = len(key)
        if len(exps) != h:
            raise IdentificationError(
                f"paper method, condition (1) fails for the factors {{{names}}}: they change together in "
                f"{len(exps)} experiment(s) ({enames}) but {h} are needed, one per co-varying factor")
        n = int(min(es.lengths[r] for r in exps))
        shapes = np.zeros((h, n))
        V = np.zeros((h, h))
        nonprop = []
        for a, j in enumerate(key):
            U = np.vstack([es.du[j, r, :n] for r in exps])  # (h experiments, N)
            _, _, vt = np.linalg.svd(U, full_matrices=False)
            shape = vt[0] * (1.0 if vt[0][np.argmax(np.abs(vt[0]))] > 0 else -1.0)
            shape = shape / np.abs(shape).max()
            coef = U @ shape / (shape @ shape)
            rest = np.linalg.norm(U - np.outer(coef, shape)) / max(np.linalg.norm(U), 1e-300)
            nonprop.append(float(rest))
            if rest > tol:
                raise IdentificationError(
                    f"paper method, condition (2) fails for factor {es.factors[j]} in experiments {enames}: "
                    f"its time shapes are not one shape scaled ({rest:.0%} of it is not proportional, "
                    f"tolerance {tol:.0%}); the joint method does not need this")
            shapes[a] = shape
            V[a] = coef
        cond = np.linalg.cond(V)
        if not np.isfinite(cond) or cond > cond_max:
            raise IdentificationError(
                f"paper method, condition (3) fails for the factors {{{names}}}: the experiments {enames} change "
                f"them in nearly the same ratios (condition number of V {cond:.3g} > {cond_max:g}); "
                "run experiments with clearly different ratios")
        groups.append(Group(factors=key, experiments=tuple(exps), shapes=shapes, V=V,
                            nonproportional=tuple(nonprop)))
    missing = [es.factors[j] for j in range(len(es.factors)) if j not in covered]
    if missing:
        raise IdentificationError(
            f"paper method: factor(s) {', '.join(missing)} change in no experiment, so their paths cannot be "
            "identified; add experiments that move them")
    return groups


def separate(es: ExperimentSet, group: Group, axis: int) -> np.ndarray:
    """lambda' = lambda V^-1 (eq. 10): the response to each factor's shape alone, (h, N), from zero."""
    n = group.shapes.shape[1]
    lam = np.vstack([es.y[axis, r, :n] for r in group.experiments])  # (h experiments, N)
    if not np.all(np.isfinite(lam)):
        raise IdentificationError(
            f"paper method: experiment(s) {', '.join(es.names[r] for r in group.experiments)} have missing "
            f"displacement on axis {es.axes[axis]}; the separation needs every sample (use the joint method)")
    lam = lam - lam[:, :1]  # relative to the start, as measured in the paper
    # row vector form: [lambda_1..lambda_h] = [lambda'_1..lambda'_h] V  ->  lambda' = lambda V^-1
    return np.linalg.solve(group.V.T, lam)


@dataclass(frozen=True, kw_only=True)
class DescentResult:
    """One steepest-descent fit: the second-order term, E at the end, and what it cost."""

    term: SecondOrder
    E: float
    iterations: int
    evaluations: int


def steepest_descent(u: np.ndarray, target: np.ndarray, dt_s: float, *, max_iter: int = 3000,
                     rtol: float = 1e-10) -> DescentResult:
    """Fit gain * w^2/(s^2 + 2 zeta w s + w^2) to ``target`` = response to ``u``, the paper's way.

    Parameters are scaled by their starting values so the gradient step is dimensionless; the step
    length is found by backtracking (halving) along -grad E; stops when E improves by less than ``rtol``
    relative or after ``max_iter`` iterations.
    """
    evals = 0

    def response(p: np.ndarray) -> np.ndarray:
        term = SecondOrder(gain=1.0, zeta=p[1], omega_rad_s=p[2])
        A, B, C = term.unit_state_space()
        return p[0] * Section.from_state_space(A, B, C, dt_s).filter(u)

    def E(p: np.ndarray) -> float:
        nonlocal evals
        evals += 1
        if p[1] <= 0 or p[2] <= 0:
            return math.inf
        r = target - response(p)
        return float(r @ r) * dt_s

    # "suitable initial values": 30 min natural period, critically damped, gain by least squares
    w0, z0 = 1.0 / 1800.0, 1.0
    unit = response(np.array([1.0, z0, w0]))
    g0 = float(unit @ target / (unit @ unit)) if unit @ unit > 0 else 0.0
    scale = np.array([abs(g0) if g0 else 1.0, z0, w0])
    q = np.array([g0, z0, w0]) / scale
    e = E(q * scale)
    step = 1e-2
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        grad = np.empty(3)
        for k in range(3):
            h = 1e-6 * max(1.0, abs(q[k]))
            qp = q.copy()
            qp[k] += h
            grad[k] = (E(qp * scale) - e) / h
        norm = np.linalg.norm(grad)
        if not np.isfinite(norm) or norm == 0:
            break
        direction = -grad / norm
        step *= 2.0
        while step > 1e-12:
            qn = q + step * direction
            en = E(qn * scale)
            if en < e:
                break
            step *= 0.5
        else:
            break
        improvement = (e - en) / max(e, 1e-300)
        q, e = qn, en
        if improvement < rtol:
            break
    p = q * scale
    return DescentResult(term=SecondOrder(gain=float(p[0]), zeta=float(p[1]), omega_rad_s=float(p[2])),
                         E=e, iterations=it, evaluations=evals)


@dataclass(frozen=True, kw_only=True)
class PaperFit:
    """The paper method's paths and groups."""

    paths: list[PathTF]
    groups: list[Group]
    wall_s: float
    evaluations: int


def identify_paper(es: ExperimentSet, *, progress: Callable[[str], None] | None = None,
                   max_iter: int = 3000) -> PaperFit:
    """Groups, separation and one steepest-descent fit per (axis, factor) path."""
    t0 = time.perf_counter()
    groups = find_groups(es)
    paths: list[PathTF] = []
    evals = 0
    for i, axis in enumerate(es.axes):
        for g in groups:
            sep = separate(es, g, i)
            for a, j in enumerate(g.factors):
                if progress:
                    progress(f"paper: axis {axis}, factor {es.factors[j]}")
                res = steepest_descent(g.shapes[a], sep[a], es.dt_s, max_iter=max_iter)
                evals += res.evaluations
                paths.append(PathTF(axis=axis, factor=es.factors[j], terms=(res.term,)))
    return PaperFit(paths=paths, groups=groups, wall_s=time.perf_counter() - t0, evaluations=evals)


def describe_groups(es: ExperimentSet, groups: Sequence[Group]) -> list[str]:
    """One line per group: factors, experiments, V and how proportional the shapes are."""
    lines = []
    for g in groups:
        factors = ", ".join(es.factors[j] for j in g.factors)
        lines.append(
            f"group {{{factors}}} from {', '.join(es.names[r] for r in g.experiments)}:"
            f" cond(V) = {np.linalg.cond(g.V):.3g}, non-proportional part max {max(g.nonproportional):.1%}")
    return lines
