"""Physical ranges a model file's numbers must lie in, and the checks :func:`~gateway.model.load_model` runs.

A model file is written by identification or diagnosis, but people edit it, copy it and keep it for years.
A value outside these ranges is not a thermal model of a machine tool, and some (a dead time of 1e12 s, a
time constant of 5e-324 s, K = 0) would otherwise end in a memory error or in NaN estimates; each is
refused at load with the file, line, key, value and the range below.

- Time constants (``tau_s``, the two of a second-order term, a derived input's lag): 1 s to 90 days.
  Machine-tool thermal time constants run from minutes (a spindle nose) to days (a bed in a slab); a
  window is normally a minute, and identification never searches below a quarter of it.
- Dead time ``delay_s``: 0 to 1 day (a coolant loop is minutes; the live estimator keeps that much
  history per input).
- Static gain: at most 1e6 um per factor unit in magnitude (the paper's K = 1/gain: |K| >= 1e-6, or inf
  for a zero path). Units differ per factor, so this bound only rules out the absurd.
- Damping ratio ``zeta``: (0, 1e4]; ``omega_rad_s``: 1/(90 days) to 1 rad/s, both also bounded by the
  time constants they give.
- Reference (equilibrium) factor levels: within +-1e9 factor units.
- A periodic input's period: 1 s to 366 days.
"""

from __future__ import annotations

import math

TAU_MIN_S = 1.0
TAU_MAX_S = 90 * 86400.0
DELAY_MAX_S = 86400.0
GAIN_MAX = 1e6
ZETA_MAX = 1e4
REFERENCE_MAX = 1e9
PERIOD_MIN_S = 1.0
PERIOD_MAX_S = 366 * 86400.0

TAU_EXPECTED = f"a time constant from {TAU_MIN_S:g} s to {TAU_MAX_S:g} s (90 days)"
DELAY_EXPECTED = f"a dead time from 0 to {DELAY_MAX_S:g} s (1 day)"
GAIN_EXPECTED = f"a static gain within +-{GAIN_MAX:g} um per factor unit"
K_EXPECTED = (f"the paper's K = 1/gain with |K| >= {1 / GAIN_MAX:g} (a gain within +-{GAIN_MAX:g} um per factor "
              "unit), or inf for a zero path")
ZETA_EXPECTED = f"a damping ratio > 0 and <= {ZETA_MAX:g}"
OMEGA_EXPECTED = f"a natural frequency from {1 / TAU_MAX_S:.4g} to {1 / TAU_MIN_S:g} rad/s (1/(90 days) to 1/(1 s))"
REFERENCE_EXPECTED = f"a factor level within +-{REFERENCE_MAX:g} (in the factor's unit)"
LAG_EXPECTED = f"an array of two lags in s, each 0 (none) or from {TAU_MIN_S:g} s to {TAU_MAX_S:g} s (90 days)"
PERIOD_EXPECTED = f"a period from {PERIOD_MIN_S:g} s to {PERIOD_MAX_S:g} s (366 days)"


def second_order_time_constants(zeta: float, omega_rad_s: float) -> tuple[float, float]:
    """The (fast, slow) time constants of a second-order term; 1/(zeta omega) twice when underdamped.

    Written without the cancellation of ``zeta - sqrt(zeta^2 - 1)`` for a large ``zeta``.
    """
    if zeta >= 1.0:
        r = math.sqrt((zeta - 1.0) * (zeta + 1.0))
        return 1.0 / (omega_rad_s * (zeta + r)), (zeta + r) / omega_rad_s
    return 1.0 / (zeta * omega_rad_s), 1.0 / (zeta * omega_rad_s)


def time_constant_ok(tau_s: float) -> bool:
    """Whether ``tau_s`` is a time constant a model file may hold."""
    return TAU_MIN_S <= tau_s <= TAU_MAX_S


def lag_ok(lag_s: float) -> bool:
    """Whether ``lag_s`` is a derived input's lag: 0 (none) or a time constant."""
    return lag_s == 0.0 or time_constant_ok(lag_s)
