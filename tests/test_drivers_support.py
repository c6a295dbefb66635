"""Support for the acquisition tests (no tests here): profiles for running simulated devices, sources.

``live_profile`` writes the bundled profile with the live address of one simulated device (the same text
``cncgw simulate serve --profile-out`` writes) and loads it, optionally with changes to its sampling keys.
``ReplaySource`` plays columns of a real CSV recording against the clock (sample and hold), so a simulated
ADC board serves real signals.
"""

from __future__ import annotations

import csv
import math
import re
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path

from gateway.profile import Profile, load_profile
from simulators.devices.profile_out import profile_for


def live_profile(devices, tmp_path: Path, via: str = "adc-tcp", *, displacement: bool = False,
                 sampling: Mapping[str, object] | None = None, name: str = "live.toml",
                 device_keys: Mapping[str, object] | None = None) -> Profile:
    """The bundled profile reading ``via`` of the running ``devices``; ``sampling``/``device_keys`` override keys."""
    text = profile_for(devices, via, displacement=displacement)
    for key, value in (sampling or {}).items():
        text = _set_key(text, "[sampling]", key, value)
    for key, value in (device_keys or {}).items():
        head = re.search(r"^\[devices\.\w+\]$", text, flags=re.M)
        assert head is not None
        text = _set_key(text, head.group(0), key, value)
    path = tmp_path / name
    path.write_text(text)
    return load_profile(path)


def _toml(value: object) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def _set_key(text: str, section: str, key: str, value: object) -> str:
    lines = text.split("\n")
    start = lines.index(section)
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("[")), len(lines))
    for i in range(start + 1, end):
        if re.match(rf"{key}\s*=", lines[i]):
            lines[i] = f"{key} = {_toml(value)}"
            return "\n".join(lines)
    lines.insert(start + 1, f"{key} = {_toml(value)}")
    return "\n".join(lines)


class ReplaySource:
    """A LiveSource that replays columns of a CSV file against simulated time, holding each row's values.

    Row ``k`` (``k = 0, 1, ...``) is in force for ``t`` in ``[t0 + k * period_s, t0 + (k + 1) * period_s)``;
    after the last row the last values hold. ``columns`` maps channel -> CSV column.
    """

    def __init__(self, path: Path, columns: Mapping[str, str], *, period_s: float, t0: float = 0.0) -> None:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
        self.columns = dict(columns)
        self.data = {ch: [float(r[col]) for r in rows] for ch, col in columns.items()}
        self.n = len(rows)
        self.period_s = period_s
        self.t0 = t0
        self._lock = threading.Lock()

    def channel_names(self) -> tuple[str, ...]:
        return tuple(self.data)

    def row(self, t: float) -> int:
        k = math.floor((t - self.t0) / self.period_s + 1e-9)
        return min(max(k, 0), self.n - 1)

    def values(self, t: float) -> Mapping[str, float]:
        k = self.row(t)
        with self._lock:
            return {ch: col[k] for ch, col in self.data.items()}

    def set_compensation(self, offsets_um: Mapping[str, float]) -> None:
        pass


class RunoutSource:
    """Another source's channels, with a once-per-revolution runout added to the displacement channels.

    The spindle's angle is integrated from ``spindle_speed`` only approximately: the test sources hold the
    speed constant, so the angle is ``speed * t / 60`` revolutions.
    """

    def __init__(self, inner, *, amplitude_um: float, channels: Sequence[str] = ("x_um", "y_um", "z_um")) -> None:
        self.inner = inner
        self.amplitude_um = amplitude_um
        self.runout_channels = tuple(channels)

    def channel_names(self) -> tuple[str, ...]:
        return self.inner.channel_names()

    def values(self, t: float) -> Mapping[str, float]:
        out = dict(self.inner.values(t))
        turns = out["spindle_speed"] * t / 60.0
        for i, ch in enumerate(self.runout_channels):
            out[ch] += self.amplitude_um * math.sin(2 * math.pi * turns + i)
        return out

    def set_compensation(self, offsets_um: Mapping[str, float]) -> None:
        self.inner.set_compensation(offsets_um)


def make_driver(profile: Profile, device: str, clock, channels: Sequence[str] | None = None):
    """The registry's driver for ``device`` of ``profile`` (all its channels, or those named)."""
    from drivers import registry

    d = profile.device(device)
    chans = [c for c in profile.channels_of(device) if channels is None or c.name in channels]
    return registry.load(d.driver)(name=d.name, options=d.options, channels=[(c.name, c.address) for c in chans],
                                   clock=clock)


def combined_profile(devices, tmp_path: Path, parts: Mapping[str, Sequence[str]], *,
                     sampling: Mapping[str, object] | None = None, name: str = "combined.toml") -> Profile:
    """The bundled profile with the channels split between several simulated devices.

    ``parts`` maps a ``via`` (see :data:`simulators.devices.profile_out.VIAS`) to the channels read through it.
    """
    from simulators.devices.profile_out import acquisition_toml

    text = profile_for(devices, "adc-tcp")
    text = text[:text.index("# generated from the running simulated devices")]
    for via, wanted in parts.items():
        blocks = acquisition_toml(devices, via).strip().split("\n\n")
        text += "\n\n" + blocks[0]
        for block in blocks[1:]:
            if block.split("\n")[0][len("[channels."):-1] in wanted:
                text += "\n\n" + block
    text += "\n"
    for key, value in (sampling or {}).items():
        text = _set_key(text, "[sampling]", key, value)
    path = tmp_path / name
    path.write_text(text)
    return load_profile(path)
