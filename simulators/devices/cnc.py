"""The CNC's compensation interface as a Modbus server.

The gateway writes per-axis offsets, keeps a heartbeat register changing and enables compensation; the
CNC checks every write against its limits, applies accepted offsets while enabled, and drops them when
the heartbeat stops. Applied offsets go to :meth:`LiveSource.set_compensation`, so the residual error
with compensation is observable in the simulated machine.

Default map (addresses 0-based as on the wire; int32 offsets in 0.1 um, high word first):

==========  ========  =====================================================================
table       address   content
==========  ========  =====================================================================
coil        0         enable (1: apply offsets; writing 1 also clears a watchdog trip)
holding     0-1       X offset command, int32, 0.1 um (int16 encoding: X at 0, Y at 1, Z at 2)
holding     2-3       Y offset command
holding     4-5       Z offset command
holding     6         heartbeat: any *change* of value counts as a beat
input       0-5       applied offsets read-back, same encoding as the commands
input       6         status word (bits below)
input       7         watchdog trips since start
input       10-18     probe block (only with ``probes``): sequence number, axis mask (bit 0 x, 1 y,
                      2 z), x, y, z (int32, ``offset_unit_um``, high word first), uncertainty
                      (uint16, 1 sigma, ``offset_unit_um``); see :mod:`gateway.adaptive.probes`
discrete    0-4       the status bits, one input each
==========  ========  =====================================================================

Probe cycles (``CompensationConfig.probes``, a :class:`ProbeCycles`): every ``every_s`` of clock time from
``first_s`` a macro probes a reference artefact and writes the block as a real one would: the measured
tool-to-table displacement with the compensation in force taken out (the residual minus the applied
offset: the thermal displacement the gateway estimates), plus normal noise of ``sd_um``, rounded to the
register unit; the sequence number last, one up from the previous. :meth:`CompensationServer.write_probe`
writes any block (fault injection: a wrong sign, a repeated number, values out of range).

Status bits: 0 ACTIVE (enabled, offsets applied), 1 WATCHDOG_TRIPPED (latched until enable is written
1 again), 2 RAMPING (applied offsets on their way to zero), 3 LAST_WRITE_REJECTED (cleared by the next
accepted offset write), 4 HEARTBEAT_OK (a beat within the timeout).

Rules:

- An offset write whose value exceeds ``limit_um`` on any axis is answered with exception 3 (illegal
  data value) and changes nothing: no offset, no heartbeat in the same request. A write covering half
  of an int32 offset is answered with exception 2 (illegal data address).
- Accepted offsets apply at once while enabled.
- Watchdog (in clock time, like everything the machine sees): once enabled, if the heartbeat does not
  change for ``heartbeat_timeout_s``, the CNC trips: enable drops to 0, WATCHDOG_TRIPPED is set and the
  applied offsets ramp linearly to zero over ``drop_ramp_s`` from the moment the beat was due (0: at
  once). Disabling (writing 0 to the enable coil) ramps the same way.
- Writing 1 to the enable coil clears a trip, re-arms the watchdog from that moment and applies the
  commanded offsets at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from gateway.adaptive.probes import PROBE_BLOCK_WORDS, encode_probe_block
from gateway.clock import Clock
from simulators.devices.faults import Faults
from simulators.devices.modbus_base import ModbusDevice, RtuBus, RtuTransport, TcpTransport
from simulators.live import LiveSource

ACTIVE, WATCHDOG_TRIPPED, RAMPING, LAST_WRITE_REJECTED, HEARTBEAT_OK = (1 << i for i in range(5))
STATUS_BITS = {"ACTIVE": ACTIVE, "WATCHDOG_TRIPPED": WATCHDOG_TRIPPED, "RAMPING": RAMPING,
               "LAST_WRITE_REJECTED": LAST_WRITE_REJECTED, "HEARTBEAT_OK": HEARTBEAT_OK}
_COIL_CODES = {1, 5, 15}
_HOLDING_CODES = {3, 6, 16, 22, 23}


@dataclass(frozen=True, kw_only=True)
class ProbeCycles:
    """The CNC's probe cycles on a schedule (see the module docstring)."""

    every_s: float = 7200.0
    first_s: float | None = None  # clock time of the first cycle (default: every_s after the start)
    axes: tuple[str, ...] = ("x", "y", "z")
    sd_um: float = 0.3
    seed: int = 0
    address: int = 10  # input registers address .. address + 8

    def __post_init__(self) -> None:
        if not self.every_s > 0 or not self.sd_um >= 0:
            raise ValueError(f"every_s must be > 0 and sd_um >= 0. Got {self.every_s!r}, {self.sd_um!r}")
        if not self.axes or not set(self.axes) <= {"x", "y", "z"}:
            raise ValueError(f"axes must be some of x, y, z. Got {self.axes!r}")


@dataclass(frozen=True, kw_only=True)
class CompensationConfig:
    """The CNC's compensation registers and rules (see the module docstring for the map)."""

    axes: tuple[str, ...] = ("x", "y", "z")
    offset_encoding: str = "int32"  # "int32" or "int16"
    offset_unit_um: float = 0.1  # um per count
    word_order: str = "big"  # int32: "big" = high word first
    limit_um: float = 500.0  # |offset| beyond this is rejected
    heartbeat_timeout_s: float = 5.0  # clock seconds
    drop_ramp_s: float = 10.0  # clock seconds to ramp applied offsets to zero; 0: at once
    device_id: int = 1
    offset_address: int = 0  # holding: commands; input: applied read-back, same layout
    heartbeat_address: int = 6  # holding
    status_address: int = 6  # input; the trips counter follows it
    tick_s: float = 0.02  # wall seconds between watchdog evaluations when nobody asks
    probes: ProbeCycles | None = None  # probe cycles on a schedule (None: this CNC never probes)

    def __post_init__(self) -> None:
        if self.offset_encoding not in ("int32", "int16"):
            raise ValueError(f'offset_encoding must be "int32" or "int16". Got {self.offset_encoding!r}')
        if self.word_order not in ("big", "little"):
            raise ValueError(f'word_order must be "big" or "little". Got {self.word_order!r}')
        if not self.offset_unit_um > 0 or not self.limit_um > 0:
            raise ValueError(f"offset_unit_um and limit_um must be > 0. Got {self.offset_unit_um!r}, "
                             f"{self.limit_um!r}")
        top = 2**31 - 1 if self.offset_encoding == "int32" else 2**15 - 1
        if self.limit_um / self.offset_unit_um > top:
            raise ValueError(f"limit_um {self.limit_um} does not fit {self.offset_encoding} counts of "
                             f"{self.offset_unit_um} um")
        if not self.heartbeat_timeout_s > 0 or self.drop_ramp_s < 0 or not self.tick_s > 0:
            raise ValueError("heartbeat_timeout_s and tick_s must be > 0, drop_ramp_s >= 0")
        if not self.axes or len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes must be distinct and not empty. Got {self.axes!r}")
        offsets = set(range(self.offset_address, self.offset_address + self.n_offset_registers))
        if self.heartbeat_address in offsets:
            raise ValueError(f"heartbeat_address {self.heartbeat_address} overlaps the offsets {sorted(offsets)}")
        if offsets & {self.status_address, self.status_address + 1}:
            raise ValueError(f"status_address {self.status_address} overlaps the read-back {sorted(offsets)}")
        if self.probes is not None:
            block = set(range(self.probes.address, self.probes.address + PROBE_BLOCK_WORDS))
            if block & (offsets | {self.status_address, self.status_address + 1}):
                raise ValueError(f"the probe block at {self.probes.address} overlaps the read-back or the status")

    @property
    def words_per_offset(self) -> int:
        """Registers one axis offset takes."""
        return 2 if self.offset_encoding == "int32" else 1

    @property
    def n_offset_registers(self) -> int:
        """Registers all axis offsets take."""
        return self.words_per_offset * len(self.axes)

    def to_registers(self, counts: list[int]) -> list[int]:
        """Register contents for per-axis offset counts."""
        out: list[int] = []
        for c in counts:
            if self.offset_encoding == "int16":
                out.append(c & 0xFFFF)
                continue
            hi, lo = struct.unpack(">HH", struct.pack(">i", c))
            out.extend([hi, lo] if self.word_order == "big" else [lo, hi])
        return out

    def from_registers(self, words: list[int]) -> list[int]:
        """Per-axis offset counts from register contents."""
        if self.offset_encoding == "int16":
            return [struct.unpack(">h", struct.pack(">H", w))[0] for w in words]
        out = []
        for i in range(0, len(words), 2):
            hi, lo = words[i : i + 2] if self.word_order == "big" else words[i : i + 2][::-1]
            out.append(struct.unpack(">i", struct.pack(">HH", hi, lo))[0])
        return out


@dataclass(frozen=True, kw_only=True)
class CompensationStatus:
    """A snapshot of the CNC's compensation state."""

    enabled: bool
    tripped: bool
    ramping: bool
    last_write_rejected: bool
    heartbeat_ok: bool
    trips: int
    command_um: dict[str, float]
    applied_um: dict[str, float]

    @property
    def word(self) -> int:
        """The status word as served in the input registers."""
        return ((ACTIVE if self.enabled else 0) | (WATCHDOG_TRIPPED if self.tripped else 0)
                | (RAMPING if self.ramping else 0) | (LAST_WRITE_REJECTED if self.last_write_rejected else 0)
                | (HEARTBEAT_OK if self.heartbeat_ok else 0))


class CompensationServer(ModbusDevice):
    """The CNC's compensation registers as a Modbus server (TCP by default) driving ``source``.

    Args:
        source: the machine; receives the applied offsets (um per axis) whenever they change.
        clock: the shared clock; the watchdog and the ramp run in its time.
        config: map and rules (default :class:`CompensationConfig`).
        transport: :class:`TcpTransport` (default) or :class:`RtuTransport`.
        serial_link: for RTU, the path clients open.
        faults: reply faults apply (drop, delay, corrupt, garbage, disconnect); value faults do not.
        name: for messages and logs.

    """

    kind = "CNC compensation interface"

    def __init__(self, *, source: LiveSource, clock: Clock, config: CompensationConfig | None = None,
                 transport: TcpTransport | RtuTransport | None = None, serial_link: Path | RtuBus | None = None,
                 faults: Faults | None = None, name: str = "cnc") -> None:
        config = config or CompensationConfig()
        super().__init__(name=name, transport=transport or TcpTransport(), device_id=config.device_id,
                         serial_link=serial_link, faults=faults)
        self.config = config
        self._source = source
        self._clock = clock
        self._lock = threading.Lock()
        n = len(config.axes)
        self._command = [0] * n  # counts
        self._enabled = False
        self._tripped = False
        self._trips = 0
        self._rejected = False
        self._heartbeat: int | None = None
        self._heartbeat_t: float | None = None
        self._drop_from_um = [0.0] * n
        self._drop_t0: float | None = None
        self._applied_um = [0.0] * n
        self._pushed: tuple[float, ...] | None = None
        self._tick_task: asyncio.Task[None] | None = None
        pc = config.probes
        if pc is not None and not callable(getattr(source, "residual_um", None)):
            raise ValueError("probe cycles need a machine that tells its residual error (residual_um(t))")
        self._probe_words = [0] * PROBE_BLOCK_WORDS
        self._probe_seq = 0
        self._next_probe_t = None if pc is None else (pc.every_s if pc.first_s is None else pc.first_s)
        self._probe_rng = np.random.default_rng([pc.seed if pc else 0, 16])
        self.probes_taken: list[tuple[float, dict[str, float]]] = []  # (clock time, values written), for tests

    # -- public, thread-safe ----------------------------------------------------------------------------
    def update(self) -> CompensationStatus:
        """Evaluate the watchdog and the ramp at ``clock.now()`` and return the state."""
        with self._lock:
            now = self._clock.now()
            self._evaluate(now)
            return self._status(now)

    # -- lifecycle --------------------------------------------------------------------------------------
    async def _started(self) -> None:
        self.update()  # tell the machine it starts uncompensated
        self._tick_task = asyncio.create_task(self._tick(), name=f"{self.name} watchdog")

    async def _stopping(self) -> None:
        if self._tick_task is not None:
            self._tick_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._tick_task
            self._tick_task = None

    async def _tick(self) -> None:
        # the ramp and the watchdog must move the machine even when no client asks
        while True:
            await asyncio.sleep(self.config.tick_s)
            self.update()

    # -- state (call with the lock held) ----------------------------------------------------------------
    def _evaluate(self, now: float) -> None:
        cfg = self.config
        if (self._enabled and self._heartbeat_t is not None
                and now - self._heartbeat_t > cfg.heartbeat_timeout_s):
            self._tripped, self._enabled = True, False
            self._trips += 1
            self._start_drop(self._heartbeat_t + cfg.heartbeat_timeout_s)
        if self._enabled:
            self._applied_um = [c * cfg.offset_unit_um for c in self._command]
        elif self._drop_t0 is not None:
            left = 0.0 if cfg.drop_ramp_s == 0 else 1.0 - (now - self._drop_t0) / cfg.drop_ramp_s
            left = min(1.0, max(0.0, left))
            self._applied_um = [a * left for a in self._drop_from_um]
            if left == 0.0:
                self._drop_t0 = None
        else:
            self._applied_um = [0.0] * len(cfg.axes)
        applied = tuple(self._applied_um)
        if applied != self._pushed:
            self._pushed = applied
            self._source.set_compensation(dict(zip(cfg.axes, applied, strict=True)))

        self._probe_cycles(now)

    def _probe_cycles(self, now: float) -> None:
        """Run every probe cycle that was due by ``now``, each at its own scheduled time."""
        pc = self.config.probes
        while pc is not None and self._next_probe_t is not None and self._next_probe_t <= now:
            t = self._next_probe_t
            residual = self._source.residual_um(t)  # type: ignore[attr-defined]
            applied = self._applied_at(t)
            values = {a: float(residual[a]) - applied[a] + pc.sd_um * float(self._probe_rng.standard_normal())
                      for a in pc.axes}
            self._probe_seq = (self._probe_seq + 1) & 0xFFFF
            self._probe_words = encode_probe_block(seq=self._probe_seq, values_um=values, sd_um=pc.sd_um,
                                                   unit_um=self.config.offset_unit_um)
            self.probes_taken.append((t, values))
            self._next_probe_t = t + pc.every_s

    def _applied_at(self, t: float) -> dict[str, float]:
        """The offsets in force at ``t`` (the last pushed to the machine; a probe macro reads its own)."""
        del t  # the offsets pushed are the ones in force: cycles run at or before every evaluation
        return dict(zip(self.config.axes, self._applied_um, strict=True)) | {
            a: 0.0 for a in ("x", "y", "z") if a not in self.config.axes}

    def write_probe(self, words: list[int] | None = None, *, values_um: dict[str, float] | None = None,
                    sd_um: float = 0.3, seq: int | None = None) -> None:
        """Write a probe block as given (fault injection): raw ``words``, or values with a sequence number."""
        with self._lock:
            if words is None:
                if values_um is None:
                    raise ValueError("write_probe needs words or values_um")
                s = self._probe_seq + 1 if seq is None else seq
                words = encode_probe_block(seq=s, values_um=values_um, sd_um=sd_um,
                                           unit_um=self.config.offset_unit_um)
            if len(words) != PROBE_BLOCK_WORDS:
                raise ValueError(f"a probe block is {PROBE_BLOCK_WORDS} registers. Got {len(words)}")
            self._probe_words = [int(w) & 0xFFFF for w in words]
            self._probe_seq = self._probe_words[0]

    def _start_drop(self, t0: float) -> None:
        self._drop_from_um = list(self._applied_um)
        self._drop_t0 = t0

    def _status(self, now: float) -> CompensationStatus:
        cfg = self.config
        return CompensationStatus(
            enabled=self._enabled, tripped=self._tripped, ramping=self._drop_t0 is not None,
            last_write_rejected=self._rejected,
            heartbeat_ok=self._heartbeat_t is not None and now - self._heartbeat_t <= cfg.heartbeat_timeout_s,
            trips=self._trips,
            command_um={a: c * cfg.offset_unit_um for a, c in zip(cfg.axes, self._command, strict=True)},
            applied_um=dict(zip(cfg.axes, self._applied_um, strict=True)),
        )

    # -- Modbus -----------------------------------------------------------------------------------------
    def _sim_device(self) -> SimDevice:
        cfg = self.config
        bits = [SimData(0, values=[False] * 16, datatype=DataType.BITS)]
        holding = [SimData(cfg.offset_address, count=cfg.n_offset_registers, datatype=DataType.REGISTERS),
                   SimData(cfg.heartbeat_address, datatype=DataType.REGISTERS)]
        inputs = [SimData(cfg.offset_address, count=cfg.n_offset_registers, datatype=DataType.REGISTERS),
                  SimData(cfg.status_address, count=2, datatype=DataType.REGISTERS)]
        if cfg.probes is not None:
            inputs.append(SimData(cfg.probes.address, count=PROBE_BLOCK_WORDS, datatype=DataType.REGISTERS))
        # four separate tables (coils, discrete inputs, holding, input), as on a real controller
        return SimDevice(0, simdata=(bits, list(bits), holding, inputs), action=self._action)

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        writing = set_values is not None
        await self._reply_delay(function_code, writing)
        with self._lock:
            now = self._clock.now()
            self._evaluate(now)
            if writing:
                assert set_values is not None
                if function_code in _COIL_CODES:
                    result = self._write_coils(address, [bool(v) for v in set_values], now)
                else:
                    result = self._write_holding(address, [int(v) for v in set_values], now)
                if result is not None:
                    return result
                self._evaluate(now)
            self._fill(function_code, start_address, registers, self._status(now))
        return None

    def _write_coils(self, address: int, bits: list[bool], now: float) -> ExcCodes | None:
        if address != 0 or len(bits) != 1:
            return ExcCodes.ILLEGAL_ADDRESS  # coil 0 (enable) is the only output
        if bits[0] and not self._enabled:  # a repeated 1 must not stand in for the heartbeat
            self._enabled, self._tripped = True, False
            self._heartbeat_t = now  # arm the watchdog from now
            self._drop_t0 = None
        elif self._enabled:
            self._enabled = False
            self._start_drop(now)
        return None

    def _write_holding(self, address: int, words: list[int], now: float) -> ExcCodes | None:
        cfg = self.config
        first, end = address, address + len(words)
        lo, hi = cfg.offset_address, cfg.offset_address + cfg.n_offset_registers
        new_command = None
        if first < hi and end > lo:
            step = cfg.words_per_offset
            if (max(first, lo) - lo) % step or (min(end, hi) - lo) % step:
                return ExcCodes.ILLEGAL_ADDRESS  # half an int32 offset
            current = cfg.to_registers(self._command)
            for i, w in enumerate(words):
                if lo <= first + i < hi:
                    current[first + i - lo] = w
            new_command = cfg.from_registers(current)
            if any(abs(c * cfg.offset_unit_um) > cfg.limit_um for c in new_command):
                self._rejected = True
                return ExcCodes.ILLEGAL_VALUE
        if first <= cfg.heartbeat_address < end:
            beat = words[cfg.heartbeat_address - first]
            if beat != self._heartbeat:
                self._heartbeat, self._heartbeat_t = beat, now
        if new_command is not None:
            self._command, self._rejected = new_command, False
        return None

    def _fill(self, function_code: int, start: int, registers: list[int], status: CompensationStatus) -> None:
        cfg = self.config
        if function_code in _COIL_CODES:
            registers[0] = 1 if status.enabled else 0
        elif function_code == 2:
            registers[0] = status.word
        elif function_code in _HOLDING_CODES:
            words = cfg.to_registers(self._command)
            registers[cfg.offset_address - start : cfg.offset_address - start + len(words)] = words
            registers[cfg.heartbeat_address - start] = self._heartbeat or 0
        else:
            applied = [round(um / cfg.offset_unit_um) for um in self._applied_um]
            words = cfg.to_registers(applied)
            registers[cfg.offset_address - start : cfg.offset_address - start + len(words)] = words
            registers[cfg.status_address - start] = status.word
            registers[cfg.status_address + 1 - start] = min(self._trips, 0xFFFF)
            if cfg.probes is not None:
                first = cfg.probes.address - start
                for k, w in enumerate(self._probe_words):
                    if 0 <= first + k < len(registers):
                        registers[first + k] = w
