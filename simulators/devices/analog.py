"""Analog scaling and the Modbus ADC board's register map.

The CNC puts each signal out as an analog voltage (:data:`SIM_VMC_ANALOG`: engineering range <->
voltage range); the ADC board converts it to register contents. A :class:`RegisterChannel` says where a
channel sits and how it is encoded; an :class:`AdcBoardConfig` is the whole map. The gateway's driver
profile mirrors these objects field by field.

Encodings (Modbus registers are 16 bit, sent high byte first unless ``byte_order="little"``):

- ``int16`` / ``uint16``: counts, linear from ``eng_range`` onto ``counts_range`` and saturating at the
  type's limits like a real converter at over-range (e.g. 0..15000 rpm -> 0..10 V -> 0..32000 counts);
- ``float32``: the value in engineering units, IEEE 754, two registers; ``word_order="big"`` puts the
  high word first (ABCD), ``"little"`` the low word first (CDAB); ``byte_order="little"`` swaps the
  bytes inside each register (BADC, or DCBA with both).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

ENCODINGS = ("int16", "uint16", "float32")
ORDERS = ("big", "little")
_COUNT_LIMITS = {"int16": (-32768, 32767), "uint16": (0, 65535)}


@dataclass(frozen=True, kw_only=True)
class AnalogScale:
    """How the CNC puts one channel out as a voltage: ``eng_range`` maps linearly onto ``volt_range``."""

    eng_range: tuple[float, float]
    volt_range: tuple[float, float]

    def __post_init__(self) -> None:
        if self.eng_range[0] == self.eng_range[1] or self.volt_range[0] == self.volt_range[1]:
            raise ValueError(f"an analog range must not be empty. Got {self!r}")

    def volts(self, value: float) -> float:
        """The voltage for an engineering value (not clipped)."""
        (e0, e1), (v0, v1) = self.eng_range, self.volt_range
        return v0 + (value - e0) * (v1 - v0) / (e1 - e0)


#: The bundled machine's analog outputs: unipolar 0..10 V for the spindle speed, bipolar +/-10 V for
#: the signed signals. The ranges leave head-room above the simulated machine's ratings.
SIM_VMC_ANALOG: dict[str, AnalogScale] = {
    "spindle_speed": AnalogScale(eng_range=(0.0, 15000.0), volt_range=(0.0, 10.0)),  # rpm
    "spindle_i1": AnalogScale(eng_range=(-100.0, 100.0), volt_range=(-10.0, 10.0)),  # A
    "spindle_i2": AnalogScale(eng_range=(-100.0, 100.0), volt_range=(-10.0, 10.0)),  # A
    "x_velocity": AnalogScale(eng_range=(-50000.0, 50000.0), volt_range=(-10.0, 10.0)),  # mm/min
    "y_velocity": AnalogScale(eng_range=(-50000.0, 50000.0), volt_range=(-10.0, 10.0)),  # mm/min
    "z_velocity": AnalogScale(eng_range=(-50000.0, 50000.0), volt_range=(-10.0, 10.0)),  # mm/min
    "x_current": AnalogScale(eng_range=(-50.0, 50.0), volt_range=(-10.0, 10.0)),  # A
    "y_current": AnalogScale(eng_range=(-50.0, 50.0), volt_range=(-10.0, 10.0)),  # A
    "z_current": AnalogScale(eng_range=(-50.0, 50.0), volt_range=(-10.0, 10.0)),  # A
}

#: counts per volt of the default ADC board: +/-10 V <-> +/-32000 counts (0.3125 mV a count)
COUNTS_PER_VOLT = 3200


@dataclass(frozen=True, kw_only=True)
class RegisterChannel:
    """One channel in the ADC board's input registers (addresses 0-based, as on the wire)."""

    channel: str
    address: int
    encoding: str = "int16"
    #: engineering values at the two ends of ``counts_range`` (int16/uint16 only)
    eng_range: tuple[float, float] = (-10.0, 10.0)
    counts_range: tuple[int, int] = (-32000, 32000)
    word_order: str = "big"
    byte_order: str = "big"

    def __post_init__(self) -> None:
        where = f"register channel {self.channel!r} at {self.address}"
        if self.encoding not in ENCODINGS:
            raise ValueError(f"{where}: encoding must be one of {ENCODINGS}. Got {self.encoding!r}")
        if self.word_order not in ORDERS or self.byte_order not in ORDERS:
            raise ValueError(f"{where}: word_order and byte_order must be one of {ORDERS}. "
                             f"Got {self.word_order!r}, {self.byte_order!r}")
        if not 0 <= self.address <= 0xFFFF - self.n_registers + 1:
            raise ValueError(f"{where}: address out of range 0..65535")
        if self.encoding in _COUNT_LIMITS:
            lo, hi = _COUNT_LIMITS[self.encoding]
            if self.eng_range[0] == self.eng_range[1] or self.counts_range[0] == self.counts_range[1]:
                raise ValueError(f"{where}: eng_range and counts_range must not be empty")
            if not all(lo <= c <= hi for c in self.counts_range):
                raise ValueError(f"{where}: counts_range must lie in {lo}..{hi}. Got {self.counts_range}")

    @property
    def n_registers(self) -> int:
        """Registers this channel occupies."""
        return 2 if self.encoding == "float32" else 1

    @property
    def resolution(self) -> float:
        """Engineering units a count stands for (0 for float32: relative resolution ~6e-8)."""
        if self.encoding == "float32":
            return 0.0
        (e0, e1), (c0, c1) = self.eng_range, self.counts_range
        return abs((e1 - e0) / (c1 - c0))

    def counts(self, value: float) -> int:
        """The converter's output for an engineering value, saturating at the type's limits."""
        lo, hi = _COUNT_LIMITS[self.encoding]
        if math.isnan(value):
            return 0  # a converter has no NaN; an open input reads as zero
        (e0, e1), (c0, c1) = self.eng_range, self.counts_range
        raw = c0 + (value - e0) * (c1 - c0) / (e1 - e0)
        if math.isinf(raw):
            return hi if raw > 0 else lo
        return max(lo, min(hi, round(raw)))

    def encode(self, value: float) -> list[int]:
        """Register contents for an engineering value."""
        if self.encoding == "float32":
            data = struct.pack(">f", value)
        else:
            data = struct.pack(">h" if self.encoding == "int16" else ">H", self.counts(value))
        words = [data[i : i + 2] for i in range(0, len(data), 2)]
        if self.word_order == "little":
            words.reverse()
        if self.byte_order == "little":
            words = [w[::-1] for w in words]
        return [int.from_bytes(w, "big") for w in words]


@dataclass(frozen=True, kw_only=True)
class AdcBoardConfig:
    """The ADC board's register map.

    The board answers function code 4 (read input registers); with ``holding_mirror`` also code 3 on
    the same addresses, for drivers that read holding registers only. Everything else (writes, coils)
    is answered with exception 1 (illegal function), unmapped addresses with exception 2.
    """

    channels: tuple[RegisterChannel, ...]
    device_id: int = 1  # the RTU address; over TCP the board answers any unit id, as most do
    holding_mirror: bool = False

    def __post_init__(self) -> None:
        if not self.channels:
            raise ValueError("an ADC board needs at least one channel")
        if not 1 <= self.device_id <= 247:
            raise ValueError(f"device_id must be in 1..247. Got {self.device_id!r}")
        taken: dict[int, str] = {}
        for ch in self.channels:
            for addr in range(ch.address, ch.address + ch.n_registers):
                if addr in taken:
                    raise ValueError(f"register {addr} holds both {taken[addr]!r} and {ch.channel!r}")
                taken[addr] = ch.channel

    def channel_names(self) -> tuple[str, ...]:
        """The machine channels this board reads, without repeats."""
        return tuple(dict.fromkeys(ch.channel for ch in self.channels))


def _default_adc_channels() -> tuple[RegisterChannel, ...]:
    counts = []
    floats = []
    for i, (name, scale) in enumerate(SIM_VMC_ANALOG.items()):
        v0, v1 = scale.volt_range
        counts.append(RegisterChannel(
            channel=name, address=i, encoding="int16", eng_range=scale.eng_range,
            counts_range=(round(v0 * COUNTS_PER_VOLT), round(v1 * COUNTS_PER_VOLT)),
        ))
        floats.append(RegisterChannel(channel=name, address=100 + 2 * i, encoding="float32"))
    return (*counts, *floats)


#: The default board for the bundled machine: input registers 0..8 hold the nine channels as int16
#: counts (+/-10 V <-> +/-32000, ranges in :data:`SIM_VMC_ANALOG`), registers 100..117 the same
#: channels as float32 in engineering units, high word first, in the same order.
DEFAULT_ADC_CONFIG = AdcBoardConfig(channels=_default_adc_channels())
