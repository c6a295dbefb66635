"""Window statistics: cheap running sums on the sampler's thread, everything else at window close.

Window ``k`` covers the clock interval ``(k * window_s, (k + 1) * window_s]`` (right-closed, as a
recording row stamped ``t`` holds the means over ``(t - window, t]``), so boundaries are aligned to the
clock: whole minutes of epoch time on a real clock.

Time weighting: a good sample stands for the time since the channel's previous good sample, at most
:data:`HOLD_TICKS` tick periods, so a missed tick does not bias the mean (the next sample covers it) and a
long outage is not papered over by the first value after it (that time stays uncovered, and the window's
coverage says so). Per channel the sampler keeps weighted sums of ``x``, ``x**2`` and ``|x|``, the
weight, count, min and max: a few float operations per value and tick.

At window close (on the closer's thread, not the sampler's) the partial sums of every device are merged
into a :class:`WindowRecord`: per channel mean, mean of squares, mean of ``|x|``, min, max; the profile's
factors; the displacement bursts averaged over whole spindle revolutions; and the window's quality.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from drivers.base import Quality
from gateway.profile import Profile, Stat

#: a good sample stands for at most this many tick periods since the previous good sample
HOLD_TICKS = 2.5


def window_index(t: float, window_s: float) -> int:
    """The window holding clock time ``t``: ``k`` with ``k * window_s < t <= (k + 1) * window_s``."""
    return math.ceil(t / window_s) - 1


class ChannelSums:
    """Running sums of one channel over one window (the sampler's hot path)."""

    __slots__ = ("count", "max", "min", "n_bad", "n_saturated", "prev_t", "s1", "s2", "sa", "weight")

    def __init__(self, start_s: float) -> None:
        self.count = 0
        self.weight = self.s1 = self.s2 = self.sa = 0.0
        self.min = math.inf
        self.max = -math.inf
        self.n_saturated = 0
        self.n_bad = 0
        self.prev_t = start_s


class DeviceWindow:
    """One device's sums and counters for one window; filled by the device's sampler thread only.

    ``add`` is the per-tick work. ``bursts`` collects ``(t, x)`` of the burst channels during the last
    ``burst_s`` of the window (a few thousand floats at most); averaging happens at close.
    """

    def __init__(self, *, device: str, channels: Sequence[str], index: int, window_s: float, tick_s: float,
                 opened_s: float, burst_channels: Sequence[str] = (), burst_s: float = 0.0) -> None:
        self.device = device
        self.channels = tuple(channels)
        self.index = index
        self.start_s = index * window_s
        self.end_s = (index + 1) * window_s
        self.tick_s = tick_s  # clock seconds between two ticks
        self.opened_s = max(self.start_s, opened_s)  # the device began sampling this window here
        self.hold_s = HOLD_TICKS * tick_s
        self.sums = [ChannelSums(self.opened_s) for _ in self.channels]
        self.ticks_run = 0
        self.ticks_skipped = 0
        self.lateness_max_s = 0.0
        self.last_good_s = self.opened_s
        self.largest_gap_s = 0.0
        self._burst_from = self.end_s - burst_s
        self._burst_idx = [i for i, c in enumerate(self.channels) if c in set(burst_channels)]
        self.bursts: dict[str, list[tuple[float, float]]] = {self.channels[i]: [] for i in self._burst_idx}

    def add(self, t: float, values: Sequence[float], quality: Sequence[Quality]) -> None:
        """One reading at clock time ``t``."""
        gap = t - self.last_good_s
        if gap > self.largest_gap_s:
            self.largest_gap_s = gap
        self.last_good_s = t
        hold = self.hold_s
        for s, x, q in zip(self.sums, values, quality, strict=True):
            if q > Quality.SATURATED:
                s.n_bad += 1
                continue
            w = t - s.prev_t
            if w > hold:
                w = hold
            s.prev_t = t
            s.count += 1
            s.weight += w
            wx = w * x
            s.s1 += wx
            s.s2 += wx * x
            s.sa += wx if x >= 0 else -wx
            if x < s.min:
                s.min = x
            if x > s.max:
                s.max = x
            if q:
                s.n_saturated += 1
        if t > self._burst_from:
            for i in self._burst_idx:
                if quality[i] <= Quality.SATURATED:
                    self.bursts[self.channels[i]].append((t, values[i]))

    def finish(self) -> None:
        """Close the window: the time from the last good read to the window's end is a gap too."""
        gap = self.end_s - self.last_good_s
        if gap > self.largest_gap_s:
            self.largest_gap_s = gap

    @property
    def span_s(self) -> float:
        """The window's clock time.

        Coverage and expected ticks count against the whole window, so a window the gateway joined late
        (its first) is not passed off as a full one.
        """
        return self.end_s - self.start_s

    @property
    def ticks_expected(self) -> int:
        return round(self.span_s / self.tick_s)


@dataclass(frozen=True, kw_only=True, slots=True)
class DevicePartial:
    """What a device's sampler hands over at a window boundary: its sums and its runner's counters."""

    window: DeviceWindow
    reads_ok: int
    reads_failed: int
    timeouts: int
    connects_failed: int
    off_scan_ticks: int
    recoveries: int
    read_time_max_s: float
    errors: tuple[str, ...]
    state: str


@dataclass(frozen=True, kw_only=True, slots=True)
class ChannelStats:
    """One channel over one window: time-weighted statistics of its good samples."""

    count: int
    coverage: float  # share of the window's clock time its samples stand for
    mean: float
    mean_square: float
    mean_abs: float
    min: float
    max: float
    saturated: int
    bad: int

    def stat(self, stat: Stat) -> float:
        return {Stat.MEAN: self.mean, Stat.MEAN_SQUARE: self.mean_square, Stat.MEAN_ABS: self.mean_abs}[stat]


@dataclass(frozen=True, kw_only=True, slots=True)
class DeviceQuality:
    """How one device was sampled during one window."""

    ticks_expected: int
    ticks_run: int
    ticks_skipped: int  # overran: skipped and counted, never queued
    reads_ok: int
    reads_failed: int
    timeouts: int
    off_scan_ticks: int
    largest_gap_s: float
    lateness_max_s: float
    read_time_max_s: float
    tick_s: float  # clock seconds between ticks: what sampling this window really had
    errors: tuple[str, ...] = ()
    reported: bool = True  # False: the device's sampler did not hand this window in

    @property
    def in_error(self) -> bool:
        """Not handed in, a read failed, off-scan, or any error noted (a silent unit on a shared line)."""
        return not self.reported or bool(self.reads_failed or self.off_scan_ticks or self.errors)

    def describe_error(self) -> str:
        """What went wrong with the device in this window (its first error, and the counts)."""
        if not self.reported:
            return "did not report this window"
        counts = [f"{n} {what}" for n, what in ((self.reads_failed, "reads failed"), (self.timeouts, "timeouts"),
                                                 (self.off_scan_ticks, "ticks off-scan")) if n]
        first = self.errors[0] if self.errors else ""
        return "; ".join([x for x in (first, ", ".join(counts)) if x]) or "in error"


@dataclass(frozen=True, kw_only=True)
class WindowRecord:
    """One window, as stored: factors, channel statistics, displacement bursts, quality.

    ``status``: ``"good"`` when every factor channel covers at least ``min_coverage`` of the window and
    every factor is a finite value read within the converters' range; ``"insufficient"`` when a factor
    channel covers less; ``"rejected"`` when a factor channel had saturated samples (the converter sat at
    its limit: the true value, and so the factor, is beyond what was read) or a factor is not finite.
    Exports leave the factors of a window that is not good empty rather than pass them off as good, and the
    live estimator fills it by its gap policy. ``reason`` says why a window is not good (``""`` when it is).
    """

    index: int
    start_s: float
    end_s: float
    status: str
    factors: Mapping[str, float]
    channels: Mapping[str, ChannelStats]
    devices: Mapping[str, DeviceQuality]
    displacement: Mapping[str, float] = field(default_factory=dict)
    burst_revolutions: Mapping[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    reason: str = ""

    def quality(self) -> str:
        """The window's quality in one line.

        Coverage, samples, the devices in error with their first error, and why the window is not good, e.g.
        ``coverage 52 % (8685/30000 samples), device adc: no valid answer ...``.
        """
        parts = [f"coverage {100 * self.coverage:.0f} % ({self.samples_taken}/{self.samples_expected} samples)"]
        for name, d in self.devices.items():
            if d.in_error:
                parts.append(f"device {name}: {d.describe_error()}")
        if self.reason:
            parts.append(self.reason)
        return ", ".join(parts)

    def channel_mean(self, channel: str) -> float:
        """The window mean of ``channel``; NaN when it has no good sample in this window."""
        stats = self.channels.get(channel)
        if stats is None or not stats.count or not math.isfinite(stats.mean):
            return math.nan
        return float(stats.mean)

    @property
    def coverage(self) -> float:
        """The lowest coverage of any channel (0 without channels)."""
        return min((c.coverage for c in self.channels.values()), default=0.0)

    @property
    def samples_expected(self) -> int:
        return sum(d.ticks_expected for d in self.devices.values())

    @property
    def samples_taken(self) -> int:
        return sum(d.reads_ok for d in self.devices.values())

    @property
    def missed_ticks(self) -> int:
        """Expected ticks without a reading (skipped for overrun, failed, off-scan: see ``devices``)."""
        return sum(max(0, d.ticks_expected - d.reads_ok) for d in self.devices.values())

    @property
    def largest_gap_s(self) -> float:
        return max((d.largest_gap_s for d in self.devices.values()), default=0.0)

    @property
    def devices_in_error(self) -> tuple[str, ...]:
        return tuple(n for n, d in self.devices.items() if d.in_error)


def channel_stats(s: ChannelSums, span_s: float) -> ChannelStats:
    """Statistics from one channel's sums (NaN when it had no good sample)."""
    if s.count == 0 or s.weight <= 0:
        nan = math.nan
        return ChannelStats(count=s.count, coverage=0.0, mean=nan, mean_square=nan, mean_abs=nan,
                            min=nan, max=nan, saturated=s.n_saturated, bad=s.n_bad)
    w = s.weight
    return ChannelStats(count=s.count, coverage=min(1.0, w / span_s) if span_s > 0 else 0.0,
                        mean=s.s1 / w, mean_square=s.s2 / w, mean_abs=s.sa / w, min=s.min, max=s.max,
                        saturated=s.n_saturated, bad=s.n_bad)


def revolution_average(samples: Sequence[tuple[float, float]], speed_rpm: float | None) -> tuple[float, float]:
    """Average of a displacement burst over a whole number of spindle revolutions.

    Runout and form error repeat every revolution, so averaging over whole revolutions cancels them
    (the paper's method). Takes the latest whole revolutions that fit in the burst (rounded to whole
    sample intervals), ending half a sample interval after its last sample. Returns ``(mean, revolutions)``;
    with the spindle at rest (or less than one revolution, or no speed) it is the plain mean and
    ``revolutions`` is 0.

    The mean is over time, not over samples: each sample stands for the time from halfway to the one
    before it to halfway to the one after (the typical interval at the burst's ends), cut at the start of
    the averaged span. A burst with missed reads (a tick skipped on a loaded PC, a timeout) or jittered read
    times then still spans whole revolutions, and the neighbours of a gap cover it. Counting samples
    instead left a part of a revolution in (or out) for every missed read.
    """
    if not samples:
        return math.nan, 0.0
    if len(samples) == 1:
        return samples[0][1], 0.0
    ts = np.array([t for t, _ in samples], dtype=float)
    xs = np.array([x for _, x in samples], dtype=float)
    # the sampling interval: the slope of the read times over their tick numbers, counted with the median
    # interval so that missed reads count too (the median alone is off by enough to matter over a thousand
    # ticks when read times jitter)
    gaps = np.diff(ts)
    ticks = np.concatenate(([0.0], np.cumsum(np.maximum(1.0, np.rint(gaps / max(float(np.median(gaps)), 1e-12))))))
    dt = float(np.polyfit(ticks, ts, 1)[0])  # every gap counts one tick at least: two samples give a line
    lo, hi = ts[0] - dt / 2, ts[-1] + dt / 2
    duration = hi - lo
    if speed_rpm is None or not math.isfinite(speed_rpm) or abs(speed_rpm) * duration / 60.0 < 1.0:
        return float(np.mean(xs)), 0.0
    rev_s = 60.0 / abs(speed_rpm)
    revs = math.floor(duration / rev_s + 1e-9)
    # the span is a whole number of sample intervals: the measured speed is rarely better than that (an ADC's
    # step is 0.016 % of 1000 rpm, 0.45 ms over 48 revolutions), and a period that is a whole number of
    # samples is then cancelled exactly
    start = max(lo, hi - max(1, round(revs * rev_s / dt)) * dt)
    bounds = np.concatenate(([lo], (ts[1:] + ts[:-1]) / 2, [hi]))
    weights = np.clip(bounds[1:] - np.maximum(bounds[:-1], start), 0.0, None)
    return float(weights @ xs / weights.sum()), float(revs)


def build_record(profile: Profile, index: int, partials: Mapping[str, DevicePartial | None],
                 channel_order: Sequence[str], *, nominal_tick_s: float | None = None) -> WindowRecord:
    """Merge the devices' partials of window ``index`` into one record (``None``: the device did not report)."""
    window_s = profile.sampling.window_s
    start, end = index * window_s, (index + 1) * window_s
    stats: dict[str, ChannelStats] = {}
    devices: dict[str, DeviceQuality] = {}
    bursts: dict[str, list[tuple[float, float]]] = {}
    notes: list[str] = []
    for dev in profile.devices:
        if dev.name not in partials:
            continue
        p = partials[dev.name]
        if p is None:
            devices[dev.name] = DeviceQuality(ticks_expected=0, ticks_run=0, ticks_skipped=0, reads_ok=0,
                                              reads_failed=0, timeouts=0, off_scan_ticks=0, largest_gap_s=window_s,
                                              lateness_max_s=0.0, read_time_max_s=0.0, tick_s=math.nan,
                                              reported=False)
            notes.append(f"device {dev.name} did not report this window")
            continue
        w = p.window
        w.finish()
        for name, s in zip(w.channels, w.sums, strict=True):
            stats[name] = channel_stats(s, w.span_s)
        bursts.update(w.bursts)
        devices[dev.name] = DeviceQuality(
            ticks_expected=w.ticks_expected, ticks_run=w.ticks_run, ticks_skipped=w.ticks_skipped,
            reads_ok=p.reads_ok, reads_failed=p.reads_failed, timeouts=p.timeouts, off_scan_ticks=p.off_scan_ticks,
            largest_gap_s=w.largest_gap_s, lateness_max_s=w.lateness_max_s, read_time_max_s=p.read_time_max_s,
            tick_s=w.tick_s, errors=p.errors)
        if nominal_tick_s is not None and w.tick_s > 1.5 * nominal_tick_s:
            notes.append(f"device {dev.name} sampled every {w.tick_s * 1000:g} ms of clock time, coarser than the "
                         f"profile's {nominal_tick_s * 1000:g} ms: mean_square and mean_abs factors may be biased")
    nan = math.nan
    missing = ChannelStats(count=0, coverage=0.0, mean=nan, mean_square=nan, mean_abs=nan, min=nan, max=nan,
                           saturated=0, bad=0)
    channels = {c: stats.get(c, missing) for c in channel_order}
    factors = {f.name: channels[f.channel].stat(f.stat) if f.channel in channels else nan for f in profile.factors}
    if nominal_tick_s is not None:
        _coarse_mean_square_notes(profile, channels, devices, nominal_tick_s, notes)
    status = "good"
    reasons: list[str] = []
    floor = profile.sampling.min_coverage
    short: dict[str, float] = {}  # factor channel -> coverage, below the floor
    for f in profile.factors:
        c = channels.get(f.channel, missing)
        if c.coverage < floor:
            status = "insufficient"
            short[f.channel] = c.coverage
            notes.append(f"factor {f.name}: channel {f.channel} covers {c.coverage:.1%} of the window "
                         f"(minimum {floor:.0%})")
        if c.saturated:
            notes.append(f"channel {f.channel}: {c.saturated} saturated samples (the converter sat at its limit)")
    if len(short) == 1:
        (ch, cov), = short.items()
        reasons.append(f"channel {ch} covers {cov:.1%} of the window (minimum {floor:.0%})")
    elif short:
        lowest = min(short, key=short.__getitem__)
        reasons.append(f"{len(short)} factor channels cover less than the {floor:.0%} minimum (lowest: {lowest} "
                       f"{short[lowest]:.1%})")
    if status == "good":  # enough data, but not values to pass off as good
        for f in profile.factors:
            c = channels.get(f.channel, missing)
            if c.saturated:
                status = "rejected"
                reasons.append(f"channel {f.channel} (factor {f.name}) saturated in {c.saturated} samples")
            elif not math.isfinite(factors[f.name]):
                status = "rejected"
                reasons.append(f"factor {f.name} is {factors[f.name]!r}, not a finite value")
    displacement: dict[str, float] = {}
    revolutions: dict[str, float] = {}
    speed_ch = profile.sampling.burst_speed_channel
    speed = None
    if speed_ch is not None and bursts.get(speed_ch):
        speed = sum(x for _, x in bursts[speed_ch]) / len(bursts[speed_ch])
    for axis, ch in profile.sampling.displacement_channels.items():
        displacement[axis], revolutions[axis] = revolution_average(bursts.get(ch, []), speed)
    return WindowRecord(index=index, start_s=start, end_s=end, status=status, factors=MappingProxyType(factors),
                        channels=MappingProxyType(channels), devices=MappingProxyType(devices),
                        displacement=MappingProxyType(displacement), burst_revolutions=MappingProxyType(revolutions),
                        notes=tuple(dict.fromkeys(notes)), reason="; ".join(dict.fromkeys(reasons)))


#: relative standard error of a mean of squares from one sample of a full-wave rectified ripple |A sin wt|:
#: sqrt(var(x^2)) / mean(x^2) = sqrt(A^4 / 8) / (A^2 / 2)
RIPPLE_SQUARE_SPREAD = math.sqrt(0.5)


def _coarse_mean_square_notes(profile: Profile, channels: Mapping[str, ChannelStats],
                              devices: Mapping[str, DeviceQuality], nominal_tick_s: float, notes: list[str]) -> None:
    """Say what a coarser tick does to each mean-of-squares factor (see drivers/opcua.py's docstring)."""
    device_of = {c.name: c.device for c in profile.channels}
    for f in profile.factors:
        if f.stat is not Stat.MEAN_SQUARE or f.channel not in device_of:
            continue
        dq = devices.get(device_of[f.channel])
        c = channels.get(f.channel)
        if dq is None or c is None or not c.count or not dq.tick_s > 1.5 * nominal_tick_s:
            continue
        se = RIPPLE_SQUARE_SPREAD / math.sqrt(c.count)
        notes.append(f"factor {f.name}: the mean of squares of {f.channel} from {c.count} samples every "
                     f"{dq.tick_s * 1000:g} ms is unbiased for a ripple not locked to the sampling, with a relative "
                     f"standard error of up to {se:.1%} (a full-wave rectified ripple); a ripple at a multiple of "
                     f"{1 / dq.tick_s:g} Hz aliases to a constant and can bias it by up to +-100 %")
