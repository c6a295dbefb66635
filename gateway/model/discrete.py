"""The one discretisation: exact zero-order hold for piecewise-constant window means.

A recording row stamped t_k holds the factor means over (t_{k-1}, t_k] and the displacement sampled at
t_k. For a term dx/dt = A x + B u, y = C x, with u constant = u_k on that window, the exact solution is

    x_k = Ad x_{k-1} + Gamma(dt) u_k,   y_k = C x_k,   Ad = e^{A dt},  Gamma(t) = int_0^t e^{A s} ds B,

so u_k acts on y_k in the same row: no one-window lag. A dead time d = m dt + f (0 <= f < dt) is exact
too: the delayed input is u_{k-m} for the last dt - f of the window and u_{k-m-1} before, so

    x_k = Ad x_{k-1} + B0 u_{k-m} + B1 u_{k-m-1},  B0 = Gamma(dt - f),  B1 = Gamma(dt) - Gamma(dt - f).

Batch replay (``lfilter`` on the same matrices), the live step-by-step estimator (constant work per step)
and identification all use :class:`Section`, so they cannot disagree. States are deviations from the
reference (equilibrium) state, so every section starts at zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# scipy is imported where it is used: importing scipy.signal takes 2-3 s on a busy edge PC, and `cncgw run`
# must reach the CNC's heartbeat watchdog before that matters (see gateway.live.runtime)


def split_delay(delay_s: float, dt_s: float) -> tuple[int, float]:
    """A dead time as (whole windows m, fraction f of a window in seconds), 0 <= f < dt."""
    m = math.floor(delay_s / dt_s + 1e-12)
    f = delay_s - m * dt_s
    return m, (0.0 if f < 1e-9 * dt_s else f)


def first_order_coefficients(tau_s: float, dt_s: float, delay_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) in z^-1 of 1/(tau s + 1) under the exact ZOH with dead time.

    The same numbers :meth:`Section.from_state_space` computes for a first-order term, without matrices.
    """
    m, f = split_delay(delay_s, dt_s)
    a = math.exp(-dt_s / tau_s)
    b0 = 1.0 - math.exp(-(dt_s - f) / tau_s) if f else 1.0 - a
    b1 = (1.0 - a) - b0
    num = np.zeros(m + 2)
    num[m], num[m + 1] = b0, b1
    return num, np.array([1.0, -a])


def _gamma(A: np.ndarray, B: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(e^{A t}, int_0^t e^{A s} ds B) from one matrix exponential of the augmented system."""
    n = A.shape[0]
    if t == 0.0:
        return np.eye(n), np.zeros(n)
    if n == 1:
        a = math.exp(A[0, 0] * t)
        return np.array([[a]]), np.array([(a - 1.0) / A[0, 0] * B[0]])
    M = np.zeros((n + 1, n + 1))
    M[:n, :n] = A * t
    M[:n, n] = B * t
    from scipy.linalg import expm

    E = expm(M)
    return E[:n, :n], E[:n, n]


@dataclass(frozen=True, slots=True)
class Section:
    """One term's unit-gain dynamics discretised at ``dt_s`` with a dead time of ``delay_s``."""

    Ad: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    C: np.ndarray
    m: int  # whole windows of delay
    num: np.ndarray  # transfer function in z^-1 (including the delay), for batch replay
    den: np.ndarray

    @classmethod
    def from_state_space(cls, A: np.ndarray, B: np.ndarray, C: np.ndarray, dt_s: float,
                         delay_s: float = 0.0) -> Section:
        if not dt_s > 0:
            raise ValueError(f"dt_s must be > 0. Got {dt_s!r}")
        if not delay_s >= 0:
            raise ValueError(f"delay_s must be >= 0. Got {delay_s!r}")
        m, f = split_delay(delay_s, dt_s)
        Ad, g_full = _gamma(A, B, dt_s)
        B0 = _gamma(A, B, dt_s - f)[1] if f else g_full
        B1 = g_full - B0
        n = A.shape[0]
        if n == 1:
            den = np.array([1.0, -Ad[0, 0]])
            num = np.array([C[0] * B0[0], C[0] * B1[0]])
        elif n == 2:
            adj = np.array([[Ad[1, 1], -Ad[0, 1]], [-Ad[1, 0], Ad[0, 0]]])
            den = np.array([1.0, -np.trace(Ad), np.linalg.det(Ad)])
            num = np.array([C @ B0, C @ B1 - C @ adj @ B0, -(C @ adj @ B1)])
        else:  # pragma: no cover - no term has more than two states
            raise ValueError(f"sections of order {n} are not supported")
        num = np.concatenate([np.zeros(m), num])
        return cls(Ad=Ad, B0=B0, B1=B1, C=C, m=m, num=num, den=den)

    @property
    def order(self) -> int:
        return self.Ad.shape[0]

    def filter(self, u: np.ndarray, before: np.ndarray | None = None) -> np.ndarray:
        """Unit-gain response to ``u`` (last axis is time), starting from rest.

        ``before`` (1-D): the input over the windows before ``u``, run first from rest and not returned (a
        daily-start column's days before a recording, :func:`gateway.model.inputs.daily_start`).
        """
        from scipy.signal import lfilter

        if before is None or not before.size or not np.any(before):
            return lfilter(self.num, self.den, u, axis=-1)
        return lfilter(self.num, self.den, np.concatenate([before, u]))[before.size:]

    def final_state(self, u: np.ndarray) -> np.ndarray:
        """State x_N after the input history ``u`` (1-D), from rest: same recursion, vectorised."""
        from scipy.signal import lfilter

        n = self.order
        adj = np.eye(1) if n == 1 else np.array([[self.Ad[1, 1], -self.Ad[0, 1]],
                                                  [-self.Ad[1, 0], self.Ad[0, 0]]])
        x = np.empty(n)
        for i in range(n):
            e = np.zeros(n)
            e[i] = 1.0
            if n == 1:
                num = np.array([self.B0[0], self.B1[0]])
            else:
                num = np.array([e @ self.B0, e @ self.B1 - e @ adj @ self.B0, -(e @ adj @ self.B1)])
            num = np.concatenate([np.zeros(self.m), num])
            x[i] = lfilter(num, self.den, u)[-1] if len(u) else 0.0
        return x

    def steady_gain(self) -> float:
        """Static gain of the discrete section (1 for a stable unit-gain term)."""
        return float(np.sum(self.num) / np.sum(self.den))
