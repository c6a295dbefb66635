"""The model updated by probes: a Kalman filter bank on top of the identified model.

State space, per axis (the axes are filtered independently: a probe's axes are measured independently)::

    estimate(t) = sum_p (1 + g_p) c_p(t) + d(t)

- ``c_p(t)``: the displacement the identified model gives through path p (one per model input), from its
  own states: the model's one ZOH discretisation (:meth:`gateway.model.ModelStepper.contributions`, or
  :meth:`gateway.model.DiscreteModel.contributions` in batch). These states are driven by known inputs
  and carry no noise, so they stay outside the filter's covariance and enter through the measurement row.
- ``g_p``: the path's relative gain error, a slowly varying parameter. Its prior is the identification's
  own covariance: each path's standard deviation (``PathTF.sd["gain"] / |gain|``) and, where the model file
  stores it (``[gain_correlation.<axis>]``, :mod:`gateway.model.correlation`), the correlation of the paths'
  errors, so a combination of co-varying paths the experiments fixed is tight and one they did not is wide
  (without it: independent, the diagonal). It relaxes back to 0 with ``gain_memory_h`` (a first-order
  Gauss-Markov process whose stationary covariance is that prior), so without probes the estimate returns to
  the identified model and its band to the identification's.
- ``d``: the disturbance the model does not know (the room, a slow part, coolant): an offset whose rate
  ``r`` is itself a Gauss-Markov process (``rate_sd_um_per_h``, ``rate_tau_h``: an integrated random walk
  whose slope fades), plus a white random walk of the offset (``walk_um_per_sqrt_h``); the offset relaxes
  toward 0 with ``offset_tau_h`` so the band stays bounded without probes.

How strong the disturbance is differs from machine to machine and week to week, so the filter is a bank
of ``len(scales)`` filters whose disturbance variances are the base times each scale; each probe weighs
them by the likelihood of its innovation, and the weights forget with ``weight_memory_h`` (old conditions
fade) toward their prior: even over the scales, or (``residual_prior_weight``) with the scales the probes
cannot resolve weighed by the identification's own residual (:func:`identification_scale_likelihood`).
The estimate is the weighted mean, its variance the weighted variances plus the spread of the members' means.
That variance is the band: parameter uncertainty from identification propagated through the model
(``c_p^2 var(g_p)``) plus the disturbance's.

Bounded: a probe is applied only when it passes :func:`gateway.adaptive.probes.probe_problems`, the
sequence check and the innovation test (``|value - estimate| <= gate_sigma x sd``, the probe's own
uncertainty included); a reading that is the estimate's negative within the gate is named as a wrong sign.
Every refusal is a :class:`~gateway.adaptive.probes.ProbeDecision` with its reason; the state is untouched.

The filter's state is a pure function of the window history and the probes: replaying both rebuilds it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from gateway.adaptive.probes import Probe, ProbeDecision, SequenceCheck, probe_problems
from gateway.model.model import ThermalModel

Z95 = 1.959963984540054


@dataclass(frozen=True, kw_only=True, slots=True)
class DriftSettings:
    """The disturbance model, the forgetting, and the probe gate (see the module docstring)."""

    rate_sd_um_per_h: float = 1.0
    rate_tau_h: float = 6.0
    walk_um_per_sqrt_h: float = 0.3
    offset_tau_h: float = 72.0
    #: variance scales of the filter bank (the disturbance's variances times each)
    scales: tuple[float, ...] = tuple(8.0 ** k for k in range(-6, 3))
    #: variance scales of the gains' prior (production differs from the identification runs); the bank
    #: holds every pair (scale, gain scale)
    gain_scales: tuple[float, ...] = (0.01, 0.1, 1.0, 10.0, 100.0)
    #: after this many probes in a row beyond the gate on the same side, conditions changed: re-anchor
    reanchor_after: int = 2
    weight_memory_h: float = 24.0
    #: estimate each path's gain as a slowly varying parameter (False: the offset only)
    gains: bool = True
    gain_memory_h: float = 48.0
    #: relative gain sd for a path whose model file has none (a hand-written or the paper's model)
    gain_sd_default: float = 0.1
    #: the gains' prior covariance from the model's [gain_correlation] (False, or a file without it: every
    #: path's gain error independent, the diagonal)
    gain_correlation: bool = True
    gate_sigma: float = 3.0
    #: the model's motion (sum over paths of |change|, um/h) at which the disturbance's noise doubles
    activity_ref_um_per_h: float = 3.0
    #: the smallest weight a member keeps (so a change of conditions is found again)
    weight_floor: float = 1e-3
    #: beyond the model's coverage a path's relative gain sd is at least k times how far its factor lies beyond
    #: (gateway.model.coverage.beyond_coverage: log(1 + covered spans)), k one of these per member: the bank
    #: holds every (scale, gain scale, k), so each probe's innovation weighs how much widening beyond coverage
    #: the data support (as it weighs the disturbance's scale). (0.0,), the default: coverage does not widen
    #: the band. Off because on bench/adaptive.py --quick it did not help the calibration: (0, 0.1) with prior
    #: weight 0.02 put 12 of 54 case-axes in 90-98 % beyond coverage (10 off) but the whole run 27 (28 off);
    #: larger priors or more k widened bands that were already too wide (README, Beyond the model's coverage)
    extrapolation_gain_sds: tuple[float, ...] = (0.0,)
    #: the bank's prior weight on the members that widen beyond coverage (split evenly among them; the rest on
    #: those that do not): the weights start there, forget toward it and return to it at a re-anchor, so a
    #: little weight on a wide member, which widens the mixture's band little, is kept until probes beyond
    #: coverage say how much it is needed
    extrapolation_prior: float = 0.1
    #: the bank's prior over the gain-prior scales: None, even over ``gain_scales``; a value sigma, log-normal
    #: about 1 (identification's own covariance), log10 of the scale factor on the gains' sd ~ N(0, sigma^2)
    #: (sigma = 0.5: a tenfold sd is a 2 sigma event). Where the probes cannot resolve the gains (an axis the
    #: model already gets within the probes' noise) the bank's weights stay near this prior and the band is its
    gain_scale_prior_decades: float | None = None
    #: the prior over the disturbance scales the probes cannot resolve, per axis: this weight on those the
    #: identification's own residual supports (:func:`identification_scale_likelihood`), the rest even; the
    #: scales the probes resolve keep their even share. Why: identification fitted the model in the hall with
    #: every effect it knows, and its residual there is white at the sensor's noise on an axis whose model leaves
    #: no drift: a disturbance that would have made it autocorrelated did not act. Production may bring what the
    #: hall did not (a room cycle, a slow part), so that evidence weighs only what the probes cannot tell apart
    #: (a member whose drift since the axis's last probe, at rest, is below the probe's sd: such members predict
    #: the same innovations, and without other evidence the band would be the even prior's, wide where the
    #: model is already within the probes' noise); what the probes resolve keeps its even prior, so a new effect
    #: is followed as fast as without it. 0.5, the default: as likely that production adds nothing the probes
    #: cannot see on this axis as that it adds a drift of any such scale (not fitted to a bench). 0 (or a model
    #: file without the residual's figures, e.g. written by hand): the even prior. Measured (bench/adaptive.py,
    #: 18 cases of 4 days, against 0): pooled coverage x 97.3 % (98.8), y 94.3 (94.8), z 96.5 (96.5); 90 of 162
    #: case-axes in 90-98 % (87); RMS errors within 1 % (median per axis and interval). On a truth drawn from
    #: the even prior (bench/adaptive_ceiling.py, where this evidence misleads whenever the truth's scale lies
    #: above the hall's) pooled 94.6 % (README, Learning in production)
    residual_prior_weight: float = 0.5

    def __post_init__(self) -> None:
        for name in ("rate_sd_um_per_h", "rate_tau_h", "offset_tau_h", "weight_memory_h", "gain_memory_h",
                     "gate_sigma", "activity_ref_um_per_h"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"DriftSettings.{name} must be finite and > 0. Got {v!r}")
        k = self.extrapolation_gain_sds
        if not k or not all(math.isfinite(x) and x >= 0 for x in k):
            raise ValueError(f"DriftSettings.extrapolation_gain_sds must be one or more values >= 0. Got {k!r}")
        if not (0.0 < self.extrapolation_prior < 1.0):
            raise ValueError(f"DriftSettings.extrapolation_prior must be in (0, 1). Got {self.extrapolation_prior!r}")
        if not (math.isfinite(self.walk_um_per_sqrt_h) and self.walk_um_per_sqrt_h >= 0):
            raise ValueError(f"DriftSettings.walk_um_per_sqrt_h must be >= 0. Got {self.walk_um_per_sqrt_h!r}")
        for name in ("scales", "gain_scales"):
            v = getattr(self, name)
            if not v or not all(math.isfinite(x) and x > 0 for x in v):
                raise ValueError(f"DriftSettings.{name} must be positive. Got {v!r}")
        g = self.gain_scale_prior_decades
        if g is not None and not (math.isfinite(g) and g > 0):
            raise ValueError(f"DriftSettings.gain_scale_prior_decades must be None or finite and > 0. Got {g!r}")
        if not (0.0 <= self.residual_prior_weight < 1.0):
            raise ValueError(
                f"DriftSettings.residual_prior_weight must be in [0, 1). Got {self.residual_prior_weight!r}")
        if self.reanchor_after < 2:
            raise ValueError(f"DriftSettings.reanchor_after must be >= 2. Got {self.reanchor_after!r}")


def gain_sd(model: ThermalModel, default: float) -> np.ndarray:
    """Relative standard deviation of each path's static gain, shape (axes, inputs); 0 for a zero path."""
    out = np.zeros((len(model.axes), len(model.input_names)))
    for i, a in enumerate(model.axes):
        for j, f in enumerate(model.input_names):
            p = model.path(a, f)
            if p.gain == 0.0:
                continue
            sd = p.sd.get("gain")
            out[i, j] = default if sd is None or not math.isfinite(sd) else min(sd / abs(p.gain), 1.0)
    return out


def gain_correlation(model: ThermalModel) -> np.ndarray:
    """Per axis the correlation of the paths' gain errors (axes, inputs, inputs); the identity where none is stored.

    Made positive semidefinite (negative eigenvalues, from rounding in a file edited by hand, set to 0) with a
    unit diagonal, so every member's prior stays a covariance.
    """
    out = []
    for a in model.axes:
        c = model.gain_correlation_matrix(a)
        w, v = np.linalg.eigh((c + c.T) / 2.0)
        c = (v * np.clip(w, 0.0, None)) @ v.T
        d = np.sqrt(np.clip(np.diag(c), 1e-300, None))
        c = c / np.outer(d, d)
        out.append((c + c.T) / 2.0)
    return np.array(out)


def _tails(mean: np.ndarray, sd: np.ndarray, w: np.ndarray, mu: np.ndarray, h: np.ndarray) -> np.ndarray:
    """P(|Y - mu| > h) for the Gaussian mixture (weights w, members mean/sd; all (A, M)) at h (A, K)."""
    from scipy.special import ndtr

    a = (mu[:, None, None] + h[:, None, :] - mean[:, :, None]) / sd[:, :, None]
    b = (mu[:, None, None] - h[:, None, :] - mean[:, :, None]) / sd[:, :, None]
    return np.einsum("am,amk->ak", w, ndtr(-a) + ndtr(b))


_GRID = np.linspace(0.0, 1.0, 24)


def half_width(mean: np.ndarray, var: np.ndarray, w: np.ndarray, mu: np.ndarray, p: float) -> np.ndarray:
    """Per axis the h with P(|Y - mu| <= h) = p under the mixture: the band is symmetric about the estimate.

    Not 1.96 x the mixture's standard deviation: a bank with a little weight on a wide member has heavy
    tails, and its moment band would be several times too wide where most of the weight is narrow.
    """
    sd = np.sqrt(var + 1e-18)
    # bracket: at lo every member's tail is above 1 - p, at hi below it (p <= 0.9973)
    lo = 0.06 * sd.min(axis=1)
    hi = (np.abs(mean - mu[:, None]) + 3.0 * sd).max(axis=1)
    grid = lo[:, None] * (hi / lo)[:, None] ** _GRID[None, :]
    tail = _tails(mean, sd, w, mu, grid) - (1.0 - p)  # falls through 0 from above
    k = np.clip((tail > 0).sum(axis=1), 1, grid.shape[1] - 1)
    rows = np.arange(grid.shape[0])
    t0, t1 = tail[rows, k - 1], tail[rows, k]
    h0, h1 = grid[rows, k - 1], grid[rows, k]
    h = h0 + (h1 - h0) * np.clip(t0 / np.where(t0 - t1 > 0, t0 - t1, 1.0), 0.0, 1.0)
    for _ in range(2):  # Newton on the tail probability, from the bracket
        za = (mu[:, None] + h[:, None] - mean) / sd
        zb = (mu[:, None] - h[:, None] - mean) / sd
        dens = (w * (np.exp(-0.5 * za * za) + np.exp(-0.5 * zb * zb)) / (sd * math.sqrt(2 * math.pi))).sum(axis=1)
        f = _tails(mean, sd, w, mu, h[:, None])[:, 0] - (1.0 - p)
        h = np.clip(h + f / np.maximum(dens, 1e-300), h0, h1)
    return h


def equivalent_sigma(mean: np.ndarray, var: np.ndarray, w: np.ndarray, mu: np.ndarray, dev: np.ndarray) -> np.ndarray:
    """How many sigma of a normal distribution have the same two-sided tail as ``dev`` under the mixture."""
    from scipy.special import ndtri

    tail = _tails(mean, np.sqrt(var + 1e-18), w, mu, np.abs(dev)[:, None])[:, 0]
    return np.where(tail > 0, -ndtri(np.clip(tail, 1e-300, 1.0) / 2.0), np.inf) * np.sign(dev)


def _drift_model(s: DriftSettings, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Phi, Q, P_stationary) of the disturbance [d, r] (um, um/s) over one window, at scale 1.

    Continuous: d' = -d / offset_tau + r + w_d, r' = -r / rate_tau + w_r; discretised exactly (Van Loan).
    """
    from scipy.linalg import expm, solve_continuous_lyapunov

    tau_d, tau_r = s.offset_tau_h * 3600.0, s.rate_tau_h * 3600.0
    A = np.array([[-1.0 / tau_d, 1.0], [0.0, -1.0 / tau_r]])
    q_r = 2.0 * (s.rate_sd_um_per_h / 3600.0) ** 2 / tau_r  # stationary var of r = q_r tau_r / 2
    q_d = s.walk_um_per_sqrt_h ** 2 / 3600.0
    Qc = np.diag([q_d, q_r])
    M = np.zeros((4, 4))
    M[:2, :2] = -A * dt_s
    M[:2, 2:] = Qc * dt_s
    M[2:, 2:] = A.T * dt_s
    E = expm(M)
    Phi = E[2:, 2:].T
    Q = Phi @ E[:2, 2:]
    P_inf = solve_continuous_lyapunov(A, -Qc)
    return Phi, (Q + Q.T) / 2.0, (P_inf + P_inf.T) / 2.0


def detrended_drift_variance(s: DriftSettings, duration_s: float, dt_s: float) -> float:
    """The disturbance's variance at scale 1 about its own mean over one run of ``duration_s``, from 0 at rest.

    What a drift of the bank's kind leaves in an identification residual: each experiment's offset is fitted
    (its mean is absorbed), the rest would stay (the model's modes may absorb some of it too: this is the most
    it could leave, so the evidence it gives is on the strict side of that absorption). Averaged over the run's
    windows; the model's activity, which raises the disturbance's noise, is left out (a smaller variance: the
    evidence weaker, not stronger).
    """
    phi, q, _ = _drift_model(s, dt_s)
    n = max(round(duration_s / dt_s), 2)
    P = np.empty((n, 2, 2))
    p = np.zeros((2, 2))
    for i in range(n):
        p = phi @ p @ phi.T + q
        P[i] = p
    pw = np.empty((n, 2))  # first row of Phi^k
    m = np.eye(2)
    for k in range(n):
        pw[k] = m[0]
        m = phi @ m
    # Cov(d_{i+k}, d_i) = pw[k] . P[i, :, 0]; summed over i < n - k that is pw[k] . C[n - k - 1], C the running
    # sum of P[:, :, 0]: 1' Cov 1 in O(n) (the (n, n) matrix would be gigabytes for a day of 10 s windows)
    C = np.cumsum(P[:, :, 0], axis=0)
    diagonal = float(pw[0] @ C[-1])
    total = diagonal + 2.0 * float(np.einsum("kj,kj->", pw[1:], C[-2::-1]))
    return float((diagonal - total / n) / n)


def identification_scale_likelihood(model: ThermalModel, s: DriftSettings, scales: np.ndarray) -> np.ndarray | None:
    """Per axis, how well each disturbance scale agrees with the identification's residual (axes, scales).

    The model file's ``[info.axis_<a>]`` holds the residual's RMS, its lag-1 autocorrelation (one window) and
    its effective sample count; ``[info]`` the longest experiment. A disturbance at scale ``k`` acting there
    would have added a slow part of variance ``v = k x`` :func:`detrended_drift_variance` to a white residual
    of the sensor's variance ``sigma^2``, and so a lag-1 autocorrelation ``v / (v + sigma^2)``; the measured
    one estimates that with a standard error ``1 / sqrt(n)``. The likelihood is that normal density,
    normalised over ``scales`` per axis. None where the file lacks these figures (a hand-written model), per
    axis a row of NaN where its figures are missing or out of range.
    """
    info = model.info
    duration = info.get("longest_experiment_s")
    if not isinstance(duration, int | float) or not (math.isfinite(duration) and duration > 0):
        return None
    dt = info.get("window_s", 60.0)
    if not isinstance(dt, int | float) or not (math.isfinite(dt) and 0 < dt <= duration):
        return None
    v1 = detrended_drift_variance(s, float(duration), float(dt))
    out = np.full((len(model.axes), len(scales)), np.nan)
    for i, a in enumerate(model.axes):
        ax = info.get(f"axis_{a}")
        if not isinstance(ax, Mapping):
            continue
        rms, rho, n = (ax.get(k) for k in ("rms_um", "residual_lag1_autocorrelation", "effective_samples"))
        if not all(isinstance(x, int | float) and math.isfinite(x) for x in (rms, rho, n)) or rms <= 0 or n < 2:
            continue
        rho = min(max(float(rho), 0.0), 0.99)
        sigma2 = rms * rms * (1.0 - rho)  # the white part
        v = scales * v1
        loglik = -0.5 * float(n) * (rho - v / (v + sigma2)) ** 2
        lik = np.exp(loglik - loglik.max())
        out[i] = lik / lik.sum()
    return out


@dataclass(frozen=True, kw_only=True, slots=True)
class AxisEstimate:
    """One axis after a window: the updated estimate and its standard uncertainty (um)."""

    estimate_um: float
    sd_um: float
    model_um: float  # the identified model alone
    disturbance_um: float  # the offset the probes taught (weighted over the bank)

    @property
    def band_um(self) -> tuple[float, float]:
        """The 95 % band of the true displacement."""
        return (self.estimate_um - Z95 * self.sd_um, self.estimate_um + Z95 * self.sd_um)


@dataclass(kw_only=True)
class _AxisMemory:
    last_probe_s: float | None = None
    applied: int = 0
    rejected: int = 0
    #: (sigma, um) of the probes refused as outliers since the last one applied
    beyond: list[tuple[float, float]] = field(default_factory=list)
    reanchored: int = 0


class AdaptiveEstimator:
    """The identified model updated by probes (see the module docstring).

    Call :meth:`step` once per window with the model's per-path contributions at the window's end, and
    :meth:`probe` for each probe taken inside the last stepped window (or the one before).
    """

    def __init__(self, model: ThermalModel, *, window_s: float, settings: DriftSettings | None = None) -> None:
        self.settings = settings or DriftSettings()
        s = self.settings
        self.axes = tuple(model.axes)
        self.window_s = float(window_s)
        n_a, n_in = len(model.axes), len(model.input_names)
        self.n_in = n_in
        n = n_in + 2
        self.gain_sd = gain_sd(model, s.gain_sd_default) if s.gains else np.zeros((n_a, n_in))
        self.gain_corr = gain_correlation(model) if s.gain_correlation else np.broadcast_to(np.eye(n_in),
                                                                                            (n_a, n_in, n_in))
        members = [(a, b, k) for a in s.scales for b in (s.gain_scales if s.gains else (1.0,))
                   for k in (s.extrapolation_gain_sds if s.gains else (0.0,))]
        scales = np.array([a for a, _, _ in members])
        g_scales = np.array([b for _, b, _ in members])
        self.scales, self.gain_scales = scales, g_scales
        #: per member, the relative gain sd per unit of distance beyond coverage
        self.extrapolation = np.array([k for _, _, k in members])
        n_m = len(members)
        phi_dr, q_dr, p_dr = _drift_model(s, self.window_s)
        a_g = math.exp(-self.window_s / (s.gain_memory_h * 3600.0))
        F = np.zeros((n, n))
        F[:n_in, :n_in] = a_g * np.eye(n_in)
        F[n_in:, n_in:] = phi_dr
        self.F = F
        self.Qg = np.zeros((n_a, n_m, n, n))
        self.Qd = np.zeros((n_a, n_m, n, n))
        P0 = np.zeros((n_a, n_m, n, n))
        prior = np.zeros((n_a, n_m, n, n))
        for i in range(n_a):
            # the gains' prior: each path's relative sd (at most 1) and, where identification stored it, how
            # their errors go together, so a combination the experiments fixed (co-varying factors) is tight
            sd_g = np.minimum(self.gain_sd[i][None, :] * np.sqrt(g_scales)[:, None], 1.0)  # (members, inputs)
            P0[i, :, :n_in, :n_in] = sd_g[:, :, None] * self.gain_corr[i][None] * sd_g[:, None, :]
            self.Qg[i, :, :n_in, :n_in] = P0[i, :, :n_in, :n_in] * (1.0 - a_g * a_g)
            self.Qd[i, :, n_in:, n_in:] = scales[:, None, None] * q_dr
            prior[i, :, n_in:, n_in:] = scales[:, None, None] * p_dr
        self.x = np.zeros((n_a, n_m, n))
        # at the start the disturbance is 0: the gateway's reference is the machine at rest in equilibrium (as
        # the datum was probed); it grows from there. A re-anchor widens by the stationary spread instead.
        self.P = P0
        self.P_reanchor = prior + P0
        # the weights' prior: even over the disturbance and gain scales; over the widening beyond coverage,
        # extrapolation_prior on the members that widen (where some do and some do not)
        wide = self.extrapolation > 0
        if wide.any() and not wide.all():
            p = np.where(wide, s.extrapolation_prior / wide.sum(), (1.0 - s.extrapolation_prior) / (~wide).sum())
        else:
            p = np.full(n_m, 1.0 / n_m)
        if s.gain_scale_prior_decades is not None:
            # log10 of the factor on the gains' sd (gain_scales are variance factors), normal about 0
            x = 0.5 * np.log10(g_scales) / s.gain_scale_prior_decades
            p = p * np.exp(-0.5 * x * x)
            p = p / p.sum()
        p = np.tile(p, (n_a, 1))
        self.levels = np.array(sorted(set(s.scales)))
        self.level_of = np.searchsorted(self.levels, scales)
        self.base_prior = p.copy()
        #: per axis, the identification's residual's likelihood of each disturbance scale (None: not used)
        self.residual_lik = (identification_scale_likelihood(model, s, self.levels)
                             if s.residual_prior_weight > 0 else None)
        #: per axis and member
        self.log_prior = np.log(p)
        self.logw = self.log_prior.copy()
        self.c = np.zeros((n_a, n_in))
        self.c_prev = np.zeros((n_a, n_in))
        self.time_s: float | None = None
        self.prev_time_s: float | None = None
        self.steps = 0
        self.start_s: float | None = None  # the start of the first window
        self.seq = SequenceCheck()
        self.memory = [_AxisMemory() for _ in self.axes]
        self.decisions: list[ProbeDecision] = []

    # -- the window ---------------------------------------------------------------------------------------
    def step(self, contributions: np.ndarray, end_s: float, beyond: np.ndarray | None = None) -> None:
        """Advance one window: ``contributions`` (axes, inputs) are the model's per-path outputs at ``end_s``.

        ``beyond`` (inputs,): how far each input lies beyond the model's coverage in this window
        (:func:`gateway.model.coverage.beyond_coverage`, 0 inside). There the estimate extrapolates: the paths'
        relative gain error is taken as the member's ``extrapolation_gain_sds`` value x beyond (at most 1) each,
        one shared error along their common direction (:meth:`_extrapolating`); a probe then weighs the members
        (how much widening the data support) and teaches the gains there, and without probes they relax over
        ``gain_memory_h`` as any gain does.
        """
        c = np.asarray(contributions, dtype=float)
        if c.shape != self.c.shape or not np.all(np.isfinite(c)):
            raise ValueError(f"contributions: expected finite values of shape {self.c.shape}, got {c.shape}")
        if self.time_s is not None:
            self.x = self.x @ self.F.T
            # the disturbance moves faster while the machine works: the model's own motion (every path's,
            # cancelling or not) scales its noise
            act = np.abs(c - self.c).sum(axis=1) * (3600.0 / self.window_s) / self.settings.activity_ref_um_per_h
            self.P = self.F @ self.P @ self.F.T + self.Qg + self.Qd * (1.0 + act)[:, None, None, None]
        if beyond is not None and self.extrapolation.max() > 0:
            b = np.clip(np.nan_to_num(np.asarray(beyond, float)[: self.n_in], nan=0.0), 0.0, None)
            if np.any(b > 0):
                self._extrapolating(c, np.minimum(self.extrapolation[:, None] * b[None, :], 1.0))
        self.c_prev, self.c = self.c, c
        if self.time_s is None:
            self.start_s = float(end_s) - self.window_s
        self.prev_time_s, self.time_s = self.time_s, float(end_s)
        self.steps += 1

    def _extrapolating(self, c: np.ndarray, v: np.ndarray) -> None:
        """Beyond coverage: the paths' gains share a relative error of ``v`` (members, inputs) of unknown sign.

        Co-varying paths (spindle speed and its currents) carry large contributions that cancel, so their
        errors beyond coverage are taken as one: the variance of ``sum_p v_p c_p g_p`` direction, raised in each
        member to at least (sum_p v_p c_p)^2 by adding a multiple of v v^T (a covariance stays one; nothing is
        added where the gains are that uncertain already, so it does not pile up window after window).
        """
        n = self.n_in
        vv = np.where(self.gain_sd[:, None, :] > 0, v[None, :, :], 0.0)  # (axes, members, inputs)
        cv = np.einsum("ai,ami->am", c, vv)
        target = cv * cv
        cur = np.einsum("ai,amij,aj->am", c, self.P[:, :, :n, :n], c)
        alpha = np.where(target > 0, np.clip(1.0 - cur / np.where(target > 0, target, 1.0), 0.0, None), 0.0)
        self.P[:, :, :n, :n] += alpha[:, :, None, None] * (vv[:, :, :, None] * vv[:, :, None, :])

    def _row(self, c: np.ndarray) -> np.ndarray:
        """Measurement rows (axes, n) for contributions ``c`` (axes, inputs)."""
        return np.concatenate([c, np.ones((c.shape[0], 1)), np.zeros((c.shape[0], 1))], axis=1)

    def _members(self, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per axis and member: estimate and variance at contributions ``c``; and the weights."""
        H = self._row(c)
        mean = c.sum(axis=1)[:, None] + np.einsum("an,amn->am", H, self.x)
        var = np.einsum("an,amnk,ak->am", H, self.P, H)
        w = np.exp(self.logw - self.logw.max(axis=1, keepdims=True))
        return mean, np.clip(var, 0.0, None), w / w.sum(axis=1, keepdims=True)

    def estimate(self) -> list[AxisEstimate]:
        """Every axis now: the weighted estimate and its standard uncertainty."""
        mean, var, w = self._members(self.c)
        mu = (w * mean).sum(axis=1)
        sd = half_width(mean, var, w, mu, 0.95) / Z95
        dist = (w * self.x[:, :, self.n_in]).sum(axis=1)
        model = self.c.sum(axis=1)
        return [AxisEstimate(estimate_um=float(mu[i]), sd_um=float(sd[i]), model_um=float(model[i]),
                             disturbance_um=float(dist[i])) for i in range(len(self.axes))]

    def weights(self) -> np.ndarray:
        """The bank's weights per axis (axes, members)."""
        return self._members(self.c)[2]

    # -- probes -------------------------------------------------------------------------------------------
    def probe(self, probe: Probe) -> list[ProbeDecision]:
        """Apply ``probe`` (taken after the window before the last one ended); every axis decided and kept."""
        out = self._probe(probe)
        self.decisions.extend(out)
        return out

    def _refuse(self, probe: Probe, reason: str, axis: str = "") -> ProbeDecision:
        return ProbeDecision(seq=probe.seq, time_s=probe.time_s, axis=axis, accepted=False, reason=reason)

    def _probe(self, probe: Probe) -> list[ProbeDecision]:
        seq = self.seq.check(probe)
        if seq == "":
            return []  # the same probe read again
        if seq is not None:
            return [self._refuse(probe, seq)]
        problems = probe_problems(probe, self.axes)
        if problems:
            self.seq.note(probe)
            return [self._refuse(probe, "; ".join(problems))]
        if self.time_s is None:
            return [self._refuse(probe, "no window estimated yet: nothing to compare the probe with")]
        lo = self.prev_time_s if self.prev_time_s is not None else self.time_s - self.window_s
        if probe.time_s > self.time_s + 1e-6:
            return [self._refuse(probe, f"taken at {probe.time_s:.0f} s, after the last estimated window "
                                        f"({self.time_s:.0f} s): apply it after that window's step")]
        if probe.time_s < lo - self.window_s - 1e-6:
            self.seq.note(probe)
            return [self._refuse(probe, f"taken at {probe.time_s:.0f} s, more than two windows before the last "
                                        f"estimate ({self.time_s:.0f} s): too old to compare")]
        self.seq.note(probe)
        # the model at the probe's instant, between the last two window ends (the disturbance barely moves); a
        # probe handed over a window late is compared with the earlier end
        f = 1.0 if self.prev_time_s is None else (probe.time_s - lo) / max(self.time_s - lo, 1e-9)
        f = min(max(f, 0.0), 1.0)
        c = self.c_prev + f * (self.c - self.c_prev)
        mean, var, w = self._members(c)
        R = probe.sd_um ** 2
        out = []
        for a, z in probe.values_um.items():
            i = self.axes.index(a)
            mu = float(w[i] @ mean[i])
            args = (mean[i: i + 1], var[i: i + 1] + R, w[i: i + 1], np.array([mu]))
            sd = float(half_width(*args, 0.95)[0]) / Z95
            nu = float(equivalent_sigma(*args, np.array([z - mu]))[0])
            gate = self.settings.gate_sigma
            base = dict(seq=probe.seq, time_s=probe.time_s, axis=a, value_um=float(z), predicted_um=mu,
                        predicted_sd_um=sd, innovation_sigma=nu)
            mem = self.memory[i]
            if abs(nu) > gate:
                # the reading's negative is where the estimate is (or far nearer than the reading itself)
                if abs(mu) > gate * sd / 2 and (abs(z + mu) <= gate * sd or abs(z + mu) <= 0.2 * abs(z - mu)):
                    mem.rejected += 1
                    out.append(ProbeDecision(accepted=False, reason=(
                        f"wrong sign: {z:+.2f} um is the negative of the estimate {mu:+.2f} +- {sd:.2f} um (is the "
                        "probe macro's sign convention the model's?)"), **base))
                    continue
                agree = self._changed(mem, z - mu)
                if not agree:
                    mem.beyond.append((nu, z - mu))
                    mem.rejected += 1
                    out.append(ProbeDecision(accepted=False, reason=(
                        f"outlier: {z:+.2f} um is {nu:+.1f} sigma from the estimate {mu:+.2f} +- {sd:.2f} um "
                        f"(gate {gate:g} sigma)"), **base))
                    continue
                # probes in a row beyond the gate, on the same side and telling the same story (within a
                # factor of two) are no outliers: conditions changed (a slow part warmed, the room moved) faster
                # than the bank expected. Re-anchor: every member's uncertainty widened by its prior, the
                # weights even, then the probe is applied.
                seen = ", ".join(f"{d:+.2f}" for d in agree)
                self._reanchor(i)
                mean, var, w = self._members(c)
                mem.reanchored += 1
                base["reason"] = (
                    f"re-anchored: this probe is {nu:+.1f} sigma ({z - mu:+.2f} um) from the estimate and "
                    f"{len(agree)} refused since the last one applied were off the same way ({seen} um): "
                    "conditions changed; the uncertainty was widened by its prior and this probe applied")
            self._update(i, c[i], float(z), R, probe.time_s, mean[i], var[i])
            mem.applied += 1
            mem.beyond.clear()
            out.append(ProbeDecision(accepted=True, **({"reason": ""} | base)))
        return out

    def _changed(self, mem: _AxisMemory, dev_um: float) -> list[float]:
        """The refused deviations that, with this one, say conditions changed (``[]``: they do not).

        Conditions changed when ``reanchor_after - 1`` probes refused since the last one applied were off the
        same way as this one, within a factor of two. A gross outlier does not agree with a real change, so it
        is never applied, never makes a later probe applied, and never hides a change either.
        """
        agree = [d for _, d in mem.beyond
                 if math.copysign(1.0, d) == math.copysign(1.0, dev_um) and 0.5 <= abs(d) / abs(dev_um) <= 2.0]
        return agree if len(agree) >= self.settings.reanchor_after - 1 else []

    def _reanchor(self, i: int) -> None:
        """Axis ``i``: every member's covariance at least its prior, the bank's weights back to their prior."""
        self.P[i] = self.P[i] + self.P_reanchor[i]  # a sum stays a covariance; an element-wise max need not
        self.logw[i] = self.log_prior[i]

    def _has_residual(self, i: int) -> bool:
        return self.residual_lik is not None and bool(np.all(np.isfinite(self.residual_lik[i])))

    def _resolution_prior(self, i: int, interval_s: float, R: float) -> np.ndarray:
        """Axis ``i``'s log prior: the identification's evidence shares out the unresolved scales' even weight."""
        s = self.settings
        _, q, _ = _drift_model(s, max(interval_s, self.window_s))
        below = self.levels * q[0, 0] < R
        f = np.ones(self.levels.size)
        if below.any():
            lik = np.where(below, self.residual_lik[i], 0.0)
            lik = lik / lik.sum() if lik.sum() > 0 else below / below.sum()
            g = below.sum()
            f[below] = (s.residual_prior_weight * lik[below] + (1.0 - s.residual_prior_weight) / g) * g
        p = self.base_prior[i] * f[self.level_of]
        return np.log(p / p.sum())

    def _update(self, i: int, c: np.ndarray, z: float, R: float, t_s: float, mean: np.ndarray,
                var: np.ndarray) -> None:
        """The Kalman update of every member of axis ``i``, then the bank's weights."""
        h = np.concatenate([c, [1.0, 0.0]])
        S = var + R  # (members,)
        nu = z - mean
        P = self.P[i]
        PH = P @ h  # (members, n)
        K = PH / S[:, None]
        self.x[i] = self.x[i] + K * nu[:, None]
        n = h.size
        IKH = np.eye(n)[None] - K[:, :, None] * h[None, None, :]
        P = IKH @ P @ IKH.transpose(0, 2, 1) + R * K[:, :, None] * K[:, None, :]
        self.P[i] = (P + P.transpose(0, 2, 1)) / 2.0
        mem = self.memory[i]
        s = self.settings
        if mem.last_probe_s is None and self._has_residual(i):
            # the first probe: what the probes could resolve since the start decides the prior, and the weights
            # (nothing learned yet) start there
            self.log_prior[i] = self._resolution_prior(i, t_s - (self.start_s or 0.0), R)
            self.logw[i] = self.log_prior[i].copy()
        if mem.last_probe_s is not None:
            alpha = math.exp(-max(t_s - mem.last_probe_s, 0.0) / (s.weight_memory_h * 3600.0))
            # forget toward the prior (for an even prior the same as toward even weights)
            if self._has_residual(i):
                self.log_prior[i] = self._resolution_prior(i, t_s - mem.last_probe_s, R)
            self.logw[i] = alpha * self.logw[i] + (1.0 - alpha) * self.log_prior[i]
        mem.last_probe_s = t_s
        self.logw[i] += -0.5 * (np.log(2 * math.pi * S) + nu * nu / S)
        w = np.exp(self.logw[i] - self.logw[i].max())
        w /= w.sum()
        w = (1.0 - s.weight_floor) * w + s.weight_floor / w.size
        self.logw[i] = np.log(w)


@dataclass(frozen=True, kw_only=True)
class Replay:
    """Every window of a batch run through :class:`AdaptiveEstimator` (arrays are (axes, N))."""

    axes: tuple[str, ...]
    time_s: np.ndarray
    estimate_um: np.ndarray
    sd_um: np.ndarray
    model_um: np.ndarray
    decisions: tuple[ProbeDecision, ...] = field(default=())

    def band_um(self) -> tuple[np.ndarray, np.ndarray]:
        return self.estimate_um - Z95 * self.sd_um, self.estimate_um + Z95 * self.sd_um


def replay(model: ThermalModel, contributions: np.ndarray, time_s: Sequence[float], probes: Sequence[Probe], *,
           window_s: float, settings: DriftSettings | None = None, beyond: np.ndarray | None = None) -> Replay:
    """Run the estimator over ``contributions`` (axes, inputs, N) at window ends ``time_s`` with ``probes``.

    A probe taken in ``(time_s[k-1], time_s[k]]`` is applied after window k is stepped, as live. ``beyond``
    (inputs, N): how far each window lies beyond the model's coverage (:meth:`AdaptiveEstimator.step`).
    """
    est = AdaptiveEstimator(model, window_s=window_s, settings=settings)
    t = np.asarray(time_s, dtype=float)
    n = t.size
    order = sorted(probes, key=lambda p: p.time_s)
    out = np.empty((3, len(model.axes), n))
    q = 0
    for k in range(n):
        est.step(contributions[:, :, k], t[k], None if beyond is None else beyond[:, k])
        while q < len(order) and order[q].time_s <= t[k] + 1e-9:
            est.probe(order[q])
            q += 1
        for i, e in enumerate(est.estimate()):
            out[0, i, k], out[1, i, k], out[2, i, k] = e.estimate_um, e.sd_um, e.model_um
    return Replay(axes=tuple(model.axes), time_s=t, estimate_um=out[0], sd_um=out[1], model_um=out[2],
                  decisions=tuple(est.decisions))
