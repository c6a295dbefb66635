"""What every identification method shares.

Experiments stacked for fast filtering, and the path structures with their nonlinear parameters (log time
constants) and linear ones (gains).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.signal

from gateway.errors import IdentificationError
from gateway.model import limits
from gateway.model.discrete import Section, first_order_coefficients
from gateway.model.terms import FirstOrder, SecondOrder, Term
from gateway.prepare import Prepared

#: path structures identification can choose from, simplest first
STRUCTURES = ("zero", "first_order", "second_order", "two_modes")


@dataclass(frozen=True, kw_only=True)
class ExperimentSet:
    """Experiments padded to one length so one ``lfilter`` call filters all of them.

    ``du[j]`` is (E, N) for factor j (zero after an experiment's end: causal filters are unaffected);
    ``y`` is (axes, E, N), NaN where not measured; ``valid[i]`` marks the rows fitted on axis i.
    """

    names: tuple[str, ...]
    factors: tuple[str, ...]
    axes: tuple[str, ...]
    dt_s: float
    du: np.ndarray  # (F, E, N)
    y: np.ndarray  # (A, E, N)
    lengths: np.ndarray  # (E,)
    u0: np.ndarray  # (E, F) initial factor levels
    #: regressors that enter every axis linearly beside the paths, (C, E, N): a disturbance's known shape
    #: (a daily harmonic, a per-experiment drift) or a term whose time constants are fixed
    extra: np.ndarray | None = None
    extra_names: tuple[str, ...] = ()
    #: per measured row, its weight in the least squares (A, E, N); None: every row weighs 1. A probe point
    #: with a stated uncertainty weighs by it (gateway.identify.api); dense sensor rows weigh 1
    weight: np.ndarray | None = None

    @classmethod
    def from_prepared(cls, exps: Sequence[Prepared], *, factors: Sequence[str], axes: Sequence[str]) -> ExperimentSet:
        if not exps:
            raise IdentificationError("no experiments given")
        dts = {round(e.dt_s, 9) for e in exps}
        if len(dts) != 1:
            raise IdentificationError(
                "experiments have different window lengths: "
                + ", ".join(f"{e.name} {e.dt_s:g} s" for e in exps) + "; expected one window length for all")
        n = max(e.n for e in exps)
        du = np.zeros((len(factors), len(exps), n))
        y = np.full((len(axes), len(exps), n), np.nan)
        for r, e in enumerate(exps):
            du[:, r, : e.n] = e.du
            y[:, r, : e.n] = e.y
        return cls(names=tuple(e.name for e in exps), factors=tuple(factors), axes=tuple(axes),
                   dt_s=exps[0].dt_s, du=du, y=y, lengths=np.array([e.n for e in exps]),
                   u0=np.array([e.u0 for e in exps]))

    @property
    def n_exp(self) -> int:
        return self.du.shape[1]

    @property
    def n_extra(self) -> int:
        return 0 if self.extra is None else self.extra.shape[0]

    def valid(self, axis: int) -> np.ndarray:
        return np.isfinite(self.y[axis])

    def weights(self, axis: int) -> np.ndarray:
        """The weights of the measured rows of ``axis`` (in :meth:`valid`'s order): ones unless given."""
        valid = self.valid(axis)
        if self.weight is None:
            return np.ones(int(valid.sum()))
        return np.asarray(self.weight[axis][valid], dtype=float)

    @property
    def longest_s(self) -> float:
        return float(self.lengths.max() * self.dt_s)


# ------------------------------------------------------------------------------------------ structures --
def n_nonlinear(structure: str) -> int:
    """Number of time-constant parameters of a structure."""
    return {"zero": 0, "first_order": 1, "second_order": 2, "two_modes": 2}[structure]


def n_linear(structure: str) -> int:
    """Number of gains of a structure."""
    return {"zero": 0, "first_order": 1, "second_order": 1, "two_modes": 2}[structure]


@dataclass(frozen=True, kw_only=True)
class Bounds:
    """Bounds on the nonlinear parameters, from the window length and the experiments' length.

    Second order and two modes are both parametrised by (log tau_slow, log tau_slow/tau_fast), so the bound
    on the slowest time constant applies directly: a mode much slower than the data would only fit a
    drift and extrapolate its static gain from nothing. Second order is the paper's form restricted to
    real poles (zeta >= 1): heat conduction has real poles; an overshoot is two modes of opposite sign.
    """

    log_tau_min: float
    log_tau_max: float
    log_ratio_second: float = 0.0  # second order: tau_slow/tau_fast >= 1 (critically damped at 1)
    log_ratio_modes: float = math.log(2.0)  # two modes: at least a factor 2 apart, else they are one

    @classmethod
    def for_data(cls, dt_s: float, longest_s: float) -> Bounds:
        # within the range a model file may hold (gateway.model.limits), so every fit can be loaded again
        lo = min(max(0.25 * dt_s, limits.TAU_MIN_S), limits.TAU_MAX_S)
        hi = min(max(longest_s, dt_s, lo), limits.TAU_MAX_S)
        return cls(log_tau_min=math.log(lo), log_tau_max=math.log(hi))

    def of(self, structure: str) -> tuple[list[float], list[float]]:
        span = self.log_tau_max - self.log_tau_min
        if structure == "first_order":
            return [self.log_tau_min], [self.log_tau_max]
        if structure == "second_order":
            return [self.log_tau_min, self.log_ratio_second], [self.log_tau_max, span]
        if structure == "two_modes":
            return [self.log_tau_min + self.log_ratio_modes, self.log_ratio_modes], [self.log_tau_max, span]
        return [], []


def fast_time_constant(theta: Sequence[float]) -> float:
    """The faster time constant of a two-parameter structure: tau_slow / ratio.

    Never below what a model file may hold: a mode that fast is static at any window length anyway, and a
    fit must be a model that loads again.
    """
    # a hair above the floor: a second order is stored as (zeta, omega), and the time constants computed back
    # from them may land an ulp below 1 s, which the loader refuses
    return max(math.exp(theta[0] - theta[1]), limits.TAU_MIN_S * (1.0 + 1e-9))


def unit_terms(structure: str, theta: Sequence[float]) -> list[Term]:
    """Unit-gain terms of a structure for nonlinear parameters ``theta`` (log time constants)."""
    if structure == "zero":
        return []
    if structure == "first_order":
        return [FirstOrder(gain=1.0, tau_s=math.exp(theta[0]))]
    slow = math.exp(theta[0])
    fast = fast_time_constant(theta)
    if structure == "second_order":
        return [SecondOrder.from_time_constants(gain=1.0, tau1_s=fast, tau2_s=slow)]
    if structure == "two_modes":
        return [FirstOrder(gain=1.0, tau_s=fast), FirstOrder(gain=1.0, tau_s=slow)]
    raise ValueError(f"unknown structure {structure!r}")


def theta_from_time_constants(structure: str, taus: Sequence[float], bounds: Bounds) -> list[float]:
    """Starting nonlinear parameters from one or two time constants (clipped into the bounds)."""
    lo, hi = bounds.of(structure)
    taus = sorted(taus)
    if structure == "first_order":
        th = [float(np.mean(np.log(taus)))]
    elif structure in ("second_order", "two_modes"):
        if len(taus) > 1 and taus[-1] > 2.5 * taus[0]:
            fast, slow = taus[0], taus[-1]
        else:  # one time constant: start at the first-order limit (a negligible fast mode)
            fast, slow = taus[0] / 20.0, taus[0]
        th = [math.log(slow), math.log(slow / fast)]
    else:
        return []
    return [float(np.clip(v, a + 1e-6, b - 1e-6)) for v, a, b in zip(th, lo, hi, strict=True)]


#: first-order responses a :func:`unit_responses` memo keeps (a two-mode path's Jacobian: five time constants)
MEMO_RESPONSES = 8


def unit_responses(structure: str, theta: Sequence[float], du: np.ndarray, dt_s: float,
                   delay_s: float = 0.0, memo: OrderedDict[tuple[float, float], np.ndarray] | None = None
                   ) -> list[np.ndarray]:
    """Responses of each unit-gain term of the structure to ``du`` (E, N): the regressors of its gains.

    Fast paths, same numbers as :class:`~gateway.model.discrete.Section`: a first-order term is filtered
    with its closed-form coefficients, and a second order with distinct real poles is split into partial
    fractions, 1/((t1 s+1)(t2 s+1)) = (t2/(t2 s+1) - t1/(t1 s+1)) / (t2 - t1), exact because the ZOH
    discretisation is linear in the transfer function.

    ``memo``: first-order responses to this same ``du`` by (time constant, delay), the last few kept: a
    Jacobian moves one time constant of a two-mode path at a time, and the other one's response is the same
    array again (not to be written to).
    """
    def first(tau: float) -> np.ndarray:
        key = (tau, delay_s)
        if memo is not None and key in memo:
            memo.move_to_end(key)
            return memo[key]
        num, den = first_order_coefficients(tau, dt_s, delay_s)
        out = scipy.signal.lfilter(num, den, du, axis=-1)
        if memo is not None:
            memo[key] = out
            if len(memo) > MEMO_RESPONSES:
                memo.popitem(last=False)
        return out

    if structure == "first_order":
        return [first(math.exp(theta[0]))]
    if structure == "two_modes":
        return [first(fast_time_constant(theta)), first(math.exp(theta[0]))]
    if structure == "second_order" and theta[1] > 0.01:
        slow = math.exp(theta[0])
        fast = fast_time_constant(theta)
        return [(slow * first(slow) - fast * first(fast)) / (slow - fast)]
    out = []
    for term in unit_terms(structure, theta):
        A, B, C = term.unit_state_space()
        out.append(Section.from_state_space(A, B, C, dt_s, delay_s).filter(du))
    return out


def terms_with_gains(structure: str, theta: Sequence[float], gains: Sequence[float]) -> tuple[Term, ...]:
    """The structure's terms with fitted gains."""
    return tuple(t.with_gain(float(g)) for t, g in zip(unit_terms(structure, theta), gains, strict=True))


def effective_n(residuals: Sequence[np.ndarray]) -> tuple[float, float]:
    """(n_eff, rho): samples worth of independent information in autocorrelated residuals.

    n_eff = N (1 - rho) / (1 + rho) with rho the lag-1 autocorrelation pooled over experiments: thermal
    residuals are slow, and treating every minute as independent would make any extra parameter look
    significant.
    """
    num = den = 0.0
    n = 0
    for r in residuals:
        r = r[np.isfinite(r)]
        n += len(r)
        if len(r) > 2:
            r = r - r.mean()
            num += float(np.dot(r[1:], r[:-1]))
            den += float(np.dot(r, r))
    rho = min(max(num / den, 0.0), 0.999) if den > 0 else 0.0
    return max(n * (1 - rho) / (1 + rho), 2.0), rho
