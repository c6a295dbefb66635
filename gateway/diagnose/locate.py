"""Where, when and with what the residual (measured - model) departs from noise.

Everything here describes one axis's residual; nothing is fitted to it. The noise is estimated from the
data: the white part from first differences (a thermal residual barely changes from one minute to the
next, the sensor's noise does), with a floor at the quantisation of the displacement reading.

- :func:`located_windows`: stretches where the smoothed residual leaves the noise band.
- :func:`find_steps`: jumps within one window that persist (a knock, a re-zeroing): thermal responses
  cannot move that fast, so these are classified as measurement artefacts.
- :func:`change_points`: where the residual's trend changes (piecewise-linear segmentation).
- :func:`operating_states`: how fast the residual grows while idle and while each combination of drives
  is running.
- :func:`spectral_lines`: periodic components (a 24 h room cycle) standing out of the spectrum.
- :func:`correlations`: with each input, derived signal and recorded column, through a few lags; the
  bound uses the variance of a correlation between two autocorrelated series (Bartlett), since the naive
  1/sqrt(N) bound raises false alarms on slow thermal signals.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.signal
import scipy.stats

from gateway.diagnose.data import Stack

LAGS_S = (0.0, 600.0, 3600.0, 4 * 3600.0, 12 * 3600.0)


@dataclass(frozen=True, kw_only=True)
class Noise:
    """The residual's noise: white part (um), displacement quantum (um, 0 if none) and the band used."""

    sigma_um: float
    quantum_um: float
    band_um: float


def aligned_residual(stack: Stack, axis: int) -> np.ndarray:
    """Measured - model, each recording shifted so its first measured windows average zero."""
    r = stack.y[axis] - stack.base[axis]
    out = r.copy()
    for a, b in stack.bounds:
        seg = r[a:b]
        ok = np.flatnonzero(np.isfinite(seg))
        if ok.size:
            out[a:b] = seg - float(np.mean(seg[ok[:10]]))
    return out


def quantum(y: np.ndarray) -> float:
    """The reading's resolution when it is quantised (most windows repeat the last value), else 0.

    A quantised reading stays put for several windows and then jumps by about one quantum: the quantum is
    the median of the non-zero jumps. Real files are not exact (0.255 and 0.264 um steps in one of them),
    so no exact-multiple test.
    """
    d = np.abs(np.diff(y[np.isfinite(y)]))
    if d.size < 20 or np.mean(d < 1e-9) < 0.3:
        return 0.0
    return float(np.median(d[d >= 1e-9]))


def noise_level(stack: Stack, axis: int, residual: np.ndarray) -> Noise:
    """White noise from first differences (robust: median absolute deviation), floored by quantisation."""
    diffs = []
    for a, b in stack.bounds:
        seg = residual[a:b]
        d = np.diff(seg)
        diffs.append(d[np.isfinite(d)])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2) if d.size else 0.0
    if d.size < 20:
        # measured at probe instants only: no two neighbouring windows to difference; the probes' stated
        # uncertainty, else the spread of successive points' differences (drift included: an upper bound)
        sd = stack.y_sd[axis][np.isfinite(stack.y[axis])] if stack.y_sd is not None else np.zeros(0)
        sd = sd[np.isfinite(sd)]
        if sd.size:
            sigma = max(sigma, float(np.median(sd)))
        else:
            steps = [np.diff(residual[a:b][np.isfinite(residual[a:b])]) for a, b in stack.bounds]
            dd = np.concatenate(steps) if steps else np.zeros(0)
            if dd.size:
                sigma = max(sigma, 1.4826 * float(np.median(np.abs(dd - np.median(dd)))) / math.sqrt(2))
    q = quantum(stack.y[axis])
    sigma = max(sigma, q / math.sqrt(12), 1e-6)
    return Noise(sigma_um=sigma, quantum_um=q, band_um=max(3 * sigma, q))


# ---------------------------------------------------------------------------------------------- windows --
@dataclass(frozen=True, kw_only=True)
class Window:
    """A stretch where the residual leaves its noise band."""

    recording: str
    start_h: float
    end_h: float
    start: int  # stack index
    stop: int
    peak_um: float
    running_share: float  # share of the stretch with some factor active
    active: tuple[str, ...]  # factors active in more than half of it


def active_matrix(stack: Stack, share: float = 0.02) -> dict[str, np.ndarray]:
    """Per factor, windows where it is active: moved by more than ``share`` of its largest move."""
    out = {}
    for f in stack.factors:
        du = np.abs(stack.du[f])
        top = float(np.max(du)) if du.size else 0.0
        out[f] = du > share * top if top > 0 else np.zeros(stack.n, dtype=bool)
    return out


def located_windows(stack: Stack, residual: np.ndarray, noise: Noise, *, min_len: int = 5,
                    merge_gap: int = 10, max_windows: int = 12) -> list[Window]:
    """Stretches (of the 5-window moving median) outside the noise band, largest peak first."""
    act = active_matrix(stack)
    any_active = np.any(np.array(list(act.values())), axis=0) if act else np.zeros(stack.n, dtype=bool)
    out: list[Window] = []
    for r_i, (a, b) in enumerate(stack.bounds):
        seg = residual[a:b]
        sm = _moving_median(seg, 5)
        outside = np.abs(sm) > noise.band_um
        for s, e in _runs(outside, merge_gap, min_len):
            sl = slice(a + s, a + e)
            vals = seg[s:e]
            peak = float(vals[np.nanargmax(np.abs(vals))]) if np.isfinite(vals).any() else 0.0
            active = tuple(f for f, m in act.items() if m[sl].mean() > 0.5)
            t0 = stack.start_s(r_i)
            out.append(Window(recording=stack.labels[r_i], start_h=(stack.time_s[a + s] - t0) / 3600.0,
                              end_h=(stack.time_s[a + e - 1] - t0) / 3600.0, start=a + s, stop=a + e,
                              peak_um=peak, running_share=float(any_active[sl].mean()), active=active))
    out.sort(key=lambda w: -abs(w.peak_um))
    return out[:max_windows]


def _moving_median(x: np.ndarray, width: int) -> np.ndarray:
    filled = np.where(np.isfinite(x), x, 0.0)
    if len(x) < width:
        return filled
    return scipy.signal.medfilt(filled, width)


def _runs(mask: np.ndarray, merge_gap: int, min_len: int) -> list[tuple[int, int]]:
    idx = np.flatnonzero(mask)
    if not idx.size:
        return []
    runs = []
    start = prev = int(idx[0])
    for i in idx[1:]:
        if i - prev > merge_gap:
            runs.append((start, prev + 1))
            start = int(i)
        prev = int(i)
    runs.append((start, prev + 1))
    return [(s, e) for s, e in runs if e - s >= min_len]


# ------------------------------------------------------------------------------------------------ steps --
@dataclass(frozen=True, kw_only=True)
class Step:
    """A jump within one window that persists: a measurement artefact, not thermal physics."""

    axis: str
    index: int  # first window after the jump (stack index)
    recording: str
    time_h: float
    size_um: float

    def column(self, stack: Stack) -> np.ndarray:
        """1 from the jump to the end of its recording: the nuisance column that removes it."""
        c = np.zeros(stack.n)
        for a, b in stack.bounds:
            if a <= self.index < b:
                c[self.index:b] = 1.0
        return c


def find_steps(stack: Stack, axis: int, residual: np.ndarray, noise: Noise, *, width: int = 8,
               sharpness: float = 0.7, size_sigmas: float = 10.0, most: int = 5) -> list[Step]:
    """Jumps of at least ``size_sigmas`` noise sigmas (and 3 quanta) made mostly within one window.

    A thermal response with a time constant of minutes moves a third of its way in one minute; a jump made
    ``sharpness`` of its way in one window, holding for ``width`` windows on either side, is a sensor.
    More than ``most`` per recording is not a few knocks but a reading that jumps all the time: then
    none is classified (the noise estimate, not the sensor, is what is wrong).
    """
    out = []
    least = max(size_sigmas * noise.sigma_um, 3 * noise.quantum_um)
    for r_i, (a, b) in enumerate(stack.bounds):
        seg = residual[a:b]
        found: list[Step] = []
        k = width
        while k < len(seg) - width:
            d = seg[k] - seg[k - 1]
            if not (np.isfinite(d) and abs(d) >= sharpness * least):
                k += 1
                continue
            before = seg[k - width:k]
            after = seg[k:k + width]
            if not (np.isfinite(before).sum() >= width // 2 and np.isfinite(after).sum() >= width // 2):
                k += 1
                continue
            level = float(np.nanmedian(after) - np.nanmedian(before))
            if abs(level) >= least and np.sign(level) == np.sign(d) and abs(d) >= sharpness * abs(level):
                found.append(Step(axis=stack.axes[axis], index=a + k, recording=stack.labels[r_i],
                                  time_h=(stack.time_s[a + k] - stack.start_s(r_i)) / 3600.0, size_um=level))
                k += width
            else:
                k += 1
        if len(found) <= most:
            out += found
    return out


# ---------------------------------------------------------------------------------------- change points --
@dataclass(frozen=True, kw_only=True)
class ChangePoint:
    """Where the residual's trend changes."""

    recording: str
    time_h: float
    index: int
    slope_before_um_h: float
    slope_after_um_h: float


def change_points(stack: Stack, residual: np.ndarray, *, min_segment: int = 60, max_points: int = 6,
                  min_share: float = 0.1) -> list[ChangePoint]:
    """Greedy binary segmentation into linear pieces; a split must remove ``min_share`` of the SSE left."""
    out = []
    for r_i, (a, b) in enumerate(stack.bounds):
        seg = residual[a:b]
        t = (stack.time_s[a:b] - stack.start_s(r_i)) / 3600.0
        lin = _LinearPieces(t, seg)
        cuts = [0, len(seg)]
        sse_total = lin.sse(0, len(seg))
        for _ in range(max_points):
            best = None
            for i in range(len(cuts) - 1):
                s, e = cuts[i], cuts[i + 1]
                if e - s < 2 * min_segment + 1:
                    continue
                c = np.arange(s + min_segment, e - min_segment)
                gain = lin.sse(s, e) - lin.sse(s, c) - lin.sse(c, e)
                j = int(np.argmax(gain))
                if best is None or gain[j] > best[0]:
                    best = (float(gain[j]), int(c[j]))
            if best is None or best[0] < min_share * max(sse_total, 1e-300):
                break
            cuts = sorted([*cuts, best[1]])
            sse_total -= best[0]
        for i in range(1, len(cuts) - 1):
            c = cuts[i]
            out.append(ChangePoint(recording=stack.labels[r_i], time_h=float(t[c]), index=a + c,
                                   slope_before_um_h=lin.slope(cuts[i - 1], c),
                                   slope_after_um_h=lin.slope(c, cuts[i + 1])))
    return out


class _LinearPieces:
    """SSE and slope of a straight-line fit over any stretch, in O(1) from prefix sums (missing values skipped)."""

    def __init__(self, t: np.ndarray, y: np.ndarray) -> None:
        ok = np.isfinite(y)
        t0 = np.where(ok, t, 0.0)
        y0 = np.where(ok, y, 0.0)
        parts = [ok.astype(float), t0, t0 * t0, y0, t0 * y0, y0 * y0]
        self._c = [np.concatenate([[0.0], np.cumsum(p)]) for p in parts]

    def _sums(self, s: np.ndarray | int, e: np.ndarray | int) -> list[np.ndarray]:
        return [c[e] - c[s] for c in self._c]

    def sse(self, s: np.ndarray | int, e: np.ndarray | int) -> np.ndarray:
        n, st, stt, sy, sty, syy = self._sums(s, e)
        det = n * stt - st * st
        with np.errstate(divide="ignore", invalid="ignore"):
            fit = np.where(det > 1e-12, (stt * sy * sy - 2 * st * sy * sty + n * sty * sty) / det,
                           np.where(n > 0, sy * sy / np.maximum(n, 1), 0.0))
        return np.maximum(syy - fit, 0.0)

    def slope(self, s: int, e: int) -> float:
        n, st, stt, sy, sty, _ = self._sums(s, e)
        det = n * stt - st * st
        return float((n * sty - st * sy) / det) if det > 1e-12 else 0.0


# ------------------------------------------------------------------------------------- operating states --
@dataclass(frozen=True, kw_only=True)
class State:
    """An operating state (which drives run) and how the residual behaves in it."""

    label: str
    windows: int
    growth_um_h: float  # mean change of the residual per hour while in this state
    rms_um: float


def operating_states(stack: Stack, residual: np.ndarray, *, min_windows: int = 10) -> list[State]:
    """Residual growth per state: idle, or the set of drives (factor name prefixes) that are active."""
    act = active_matrix(stack)
    groups: dict[str, np.ndarray] = {}
    for f, m in act.items():
        g = f.split("_")[0]
        groups[g] = groups[g] | m if g in groups else m.copy()
    labels = np.array(["+".join(g for g, m in groups.items() if m[k]) or "idle" for k in range(stack.n)])
    d = np.full(stack.n, np.nan)
    for a, b in stack.bounds:
        d[a + 1:b] = np.diff(residual[a:b]) * 3600.0 / stack.dt_s
    out = []
    for lab in dict.fromkeys(labels):
        m = labels == lab
        dm = d[m]
        rm = residual[m]
        if m.sum() < min_windows or not np.isfinite(dm).any():
            continue
        out.append(State(label=str(lab), windows=int(m.sum()), growth_um_h=float(np.nanmean(dm)),
                         rms_um=float(np.sqrt(np.nanmean(rm ** 2)))))
    out.sort(key=lambda s: -abs(s.growth_um_h) * s.windows)
    return out


# ------------------------------------------------------------------------------------------- spectrum --
@dataclass(frozen=True, kw_only=True)
class Line:
    """A periodic component standing out of the residual's spectrum."""

    period_h: float
    amplitude_um: float
    ratio: float  # power over the local background


def spectrum(stack: Stack, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(frequency per hour, power) of the longest recording's linearly detrended residual."""
    a, b = max(stack.bounds, key=lambda ab: ab[1] - ab[0])
    seg = residual[a:b]
    ok = np.isfinite(seg)
    if ok.sum() < 16:
        return np.zeros(0), np.zeros(0)
    x = np.interp(np.arange(len(seg)), np.flatnonzero(ok), seg[ok])  # gaps: only for the spectrum
    x = scipy.signal.detrend(x)
    f, p = scipy.signal.periodogram(x, fs=3600.0 / stack.dt_s, window="hann", scaling="spectrum")
    return f, p


def spectral_lines(stack: Stack, residual: np.ndarray, *, alpha: float = 0.01, max_lines: int = 5) -> list[Line]:
    """Peaks whose power exceeds the local background by a Bonferroni-corrected exponential quantile.

    A periodogram ordinate of a smooth-spectrum signal is about exponential around the local mean, so
    P(power > k * mean) = exp(-k); testing every frequency, k = ln(n / alpha).
    """
    f, p = spectrum(stack, residual)
    if f.size < 8:
        return []
    span_h = (max(b - a for a, b in stack.bounds)) * stack.dt_s / 3600.0
    period_h = 1.0 / np.maximum(f, 1e-12)
    keep = (f > 0) & (period_h <= span_h / 1.5) & (period_h >= 2 * stack.dt_s / 3600)
    idx = np.flatnonzero(keep)
    k_crit = math.log(max(len(idx), 1) / alpha)
    out = []
    for i in idx:
        if i == 0 or i >= len(p) - 1 or not (p[i] >= p[i - 1] and p[i] >= p[i + 1]):
            continue
        lo, hi = max(1, i - 12), min(len(p), i + 13)
        neigh = np.concatenate([p[lo:max(lo, i - 2)], p[min(hi, i + 3):hi]])
        if neigh.size < 4:
            continue
        bg = float(np.median(neigh)) / math.log(2)  # median of an exponential is mean * ln 2
        if bg > 0 and p[i] / bg > k_crit:
            out.append(Line(period_h=float(1.0 / f[i]), amplitude_um=float(math.sqrt(2 * p[i])),
                            ratio=float(p[i] / bg)))
    out.sort(key=lambda ln: -ln.amplitude_um)
    return out[:max_lines]


# --------------------------------------------------------------------------------------- correlations --
@dataclass(frozen=True, kw_only=True)
class Correlation:
    """The residual's correlation with one signal, at the lag that makes it largest."""

    signal: str
    kind: str  # "input", "derived", "recorded"
    lag_s: float
    r: float
    bound: float  # coloured-signal bound at the Bonferroni-corrected level
    naive_bound: float  # 1.96 / sqrt(N): what a white-noise test would use
    significant: bool


def candidate_signals(stack: Stack, speed_factors: Sequence[str], current_factors: Sequence[str]
                      ) -> dict[str, tuple[str, np.ndarray]]:
    """Modelled inputs, derived signals (speed squared, sum of currents squared, running flags), recorded columns."""
    out: dict[str, tuple[str, np.ndarray]] = {name: ("input", v) for name, v in stack.du.items()}
    for n in speed_factors:
        out[f"{n}^2"] = ("derived", _deviation(stack, stack.raw[n] ** 2))
        out[f"{n} running"] = ("derived", _deviation(stack, (stack.raw[n] > 1.0).astype(float)))
    if len(current_factors) > 1:
        out["sum of currents^2"] = ("derived", _deviation(stack, sum(stack.raw[f] for f in current_factors)))
    for col, v in stack.extras.items():
        if np.isfinite(v).sum() > 0.5 * len(v) and stack.is_signal(col):
            out[col] = ("recorded", _deviation(stack, v))
    return out


def _deviation(stack: Stack, x: np.ndarray) -> np.ndarray:
    out = np.full(stack.n, np.nan)
    for a, b in stack.bounds:
        seg = x[a:b]
        ok = np.flatnonzero(np.isfinite(seg))
        if ok.size:
            out[a:b] = seg - seg[ok[0]]
    return out


def correlations(stack: Stack, residual: np.ndarray, signals: Mapping[str, tuple[str, np.ndarray]], *,
                 alpha: float = 0.05) -> list[Correlation]:
    """Correlation of the residual with every signal through the lags :data:`LAGS_S` (largest |r| kept)."""
    out = []
    n_tests = max(1, len(signals) * len(LAGS_S))
    z = float(scipy.stats.norm.isf(alpha / (2 * n_tests)))
    for name, (kind, x) in signals.items():
        best = None
        for lag_s in LAGS_S:
            xl = _lagged(stack, x, lag_s)
            r, se, n = _corr(stack, residual, xl)
            if n < 10:
                continue
            if best is None or abs(r) > abs(best[1]):
                best = (lag_s, r, se, n)
        if best is None:
            continue
        lag_s, r, se, n = best
        out.append(Correlation(signal=name, kind=kind, lag_s=lag_s, r=r, bound=z * se, naive_bound=1.96 / math.sqrt(n),
                               significant=abs(r) > z * se))
    out.sort(key=lambda c: -abs(c.r))
    return out


def _lagged(stack: Stack, x: np.ndarray, tau_s: float) -> np.ndarray:
    if tau_s == 0:
        return x
    a_ = math.exp(-stack.dt_s / tau_s)
    out = np.full(stack.n, np.nan)
    for a, b in stack.bounds:
        seg = np.where(np.isfinite(x[a:b]), x[a:b], 0.0)
        out[a:b] = scipy.signal.lfilter([1 - a_], [1, -a_], seg)
    return out


def _corr(stack: Stack, y: np.ndarray, x: np.ndarray) -> tuple[float, float, int]:
    """Pearson r (each recording centred) and its standard error for two autocorrelated series (Bartlett)."""
    ys, xs = [], []
    for a, b in stack.bounds:
        m = np.isfinite(y[a:b]) & np.isfinite(x[a:b])
        if m.sum() < 3:
            continue
        ys.append(y[a:b][m] - y[a:b][m].mean())
        xs.append(x[a:b][m] - x[a:b][m].mean())
    if not ys:
        return 0.0, math.inf, 0
    r, se = coloured_correlation(np.concatenate(xs), np.concatenate(ys))
    return r, se, sum(len(v) for v in ys)


def coloured_correlation(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Pearson r of two series and its standard error when both are autocorrelated.

    Bartlett's formula for independent series: var(r) ~ (1/N) sum_k rho_x(k) rho_y(k), summed (tapered) to
    lag N/4. For two slow thermal signals it is many times 1/N, which is why a 1/sqrt(N) bound raises
    false alarms on them.
    """
    xx, yy = x - x.mean(), y - y.mean()
    n = len(yy)
    den = math.sqrt(float(yy @ yy) * float(xx @ xx))
    if den == 0 or n < 3:
        return 0.0, math.inf
    L = max(1, n // 4)
    rx, ry = _acf(xx, L), _acf(yy, L)
    var = (1.0 + 2.0 * float(np.sum(rx[1:] * ry[1:] * (1 - np.arange(1, L + 1) / (L + 1))))) / n
    return float(yy @ xx) / den, math.sqrt(max(var, 1.0 / n))


def _acf(x: np.ndarray, L: int) -> np.ndarray:
    n = len(x)
    f = np.fft.rfft(x - x.mean(), 2 * n)
    c = np.fft.irfft(f * np.conj(f))[: L + 1]
    return c / c[0] if c[0] > 0 else np.zeros(L + 1)
