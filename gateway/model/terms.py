"""Transfer-function terms, the building blocks of a path.

A path G_ij(s) from factor j to displacement axis i is a sum of terms, optionally behind a dead time:

- :class:`FirstOrder`:  gain / (tau s + 1)
- :class:`SecondOrder`: gain * omega^2 / (s^2 + 2 zeta omega s + omega^2), the paper's eq. 12 with
  gain = 1/K (the paper's K is kept as a derived property; ``gain = 0`` is a zero path, K = inf).

Every term has unit-gain dynamics (``unit_state_space``) scaled by ``gain`` (um per factor unit), so
identification can solve gains linearly for given time constants.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np


@dataclass(frozen=True, kw_only=True, slots=True)
class FirstOrder:
    """gain / (tau_s * s + 1)."""

    kind: ClassVar[str] = "first_order"
    gain: float
    tau_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gain) and math.isfinite(self.tau_s) and self.tau_s > 0):
            raise ValueError(f"FirstOrder needs a finite gain and tau_s > 0. Got gain={self.gain!r}, "
                             f"tau_s={self.tau_s!r}")

    def unit_state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.array([[-1.0 / self.tau_s]]), np.array([1.0 / self.tau_s]), np.array([1.0]))

    @property
    def time_constants_s(self) -> tuple[float, ...]:
        return (self.tau_s,)

    def with_gain(self, gain: float) -> FirstOrder:
        return FirstOrder(gain=gain, tau_s=self.tau_s)

    def describe(self) -> str:
        return f"{self.gain:+.4g} / ({self.tau_s / 60:.4g} min s + 1)"


@dataclass(frozen=True, kw_only=True, slots=True)
class SecondOrder:
    """gain * omega^2 / (s^2 + 2 zeta omega s + omega^2): the paper's form, gain = 1/K."""

    kind: ClassVar[str] = "second_order"
    gain: float
    zeta: float
    omega_rad_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gain) and math.isfinite(self.zeta) and self.zeta > 0
                and math.isfinite(self.omega_rad_s) and self.omega_rad_s > 0):
            raise ValueError(f"SecondOrder needs a finite gain, zeta > 0 and omega_rad_s > 0. Got gain="
                             f"{self.gain!r}, zeta={self.zeta!r}, omega_rad_s={self.omega_rad_s!r}")

    @property
    def K(self) -> float:
        """The paper's K (eq. 12): 1/gain, infinite for a zero path."""
        return math.inf if self.gain == 0 else 1.0 / self.gain

    @classmethod
    def from_time_constants(cls, *, gain: float, tau1_s: float, tau2_s: float) -> SecondOrder:
        """The overdamped (or critically damped) form gain / ((tau1 s + 1)(tau2 s + 1))."""
        omega = 1.0 / math.sqrt(tau1_s * tau2_s)
        zeta = (tau1_s + tau2_s) * omega / 2.0
        return cls(gain=gain, zeta=zeta, omega_rad_s=omega)

    def unit_state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        w, z = self.omega_rad_s, self.zeta
        # states: normalised output and its derivative / omega; well scaled when omega ~ 1e-4 rad/s
        return (np.array([[0.0, w], [-w, -2.0 * z * w]]), np.array([0.0, w]), np.array([1.0, 0.0]))

    @property
    def time_constants_s(self) -> tuple[float, ...]:
        """The two real time constants when overdamped; otherwise (1/(zeta omega),) twice."""
        w, z = self.omega_rad_s, self.zeta
        if z >= 1.0:
            r = math.sqrt(z * z - 1.0)
            return (1.0 / (w * (z + r)), 1.0 / (w * (z - r)) if z > 1.0 else 1.0 / w)
        return (1.0 / (z * w), 1.0 / (z * w))

    def with_gain(self, gain: float) -> SecondOrder:
        return SecondOrder(gain=gain, zeta=self.zeta, omega_rad_s=self.omega_rad_s)

    def describe(self) -> str:
        return (f"{self.gain:+.4g} w^2/(s^2+2*{self.zeta:.3g}*w*s+w^2), w = 1/({1 / self.omega_rad_s / 60:.4g} min)")


Term = FirstOrder | SecondOrder
TERM_KINDS: dict[str, type[FirstOrder] | type[SecondOrder]] = {
    FirstOrder.kind: FirstOrder, SecondOrder.kind: SecondOrder,
}
