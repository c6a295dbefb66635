"""What Modbus TCP and Modbus RTU share: register addresses, request planning, decoding (pymodbus 3.x).

A channel says where its value sits (``address``, 0-based as on the wire; ``function`` 3 holding or 4
input registers), how it is encoded (``data_type`` int16/uint16/int32/uint32/float32, ``word_order`` and
``byte_order``) and how raw numbers become engineering units (``value = raw * scale + offset``).

Channels on contiguous registers of one function are merged into one request (at most 125 registers,
the protocol's limit), so eight int16 inputs on registers 0..7 cost one round trip.

Several units behind one device (an RS-485 line with several Modbus RTU boards, or a Modbus TCP gateway in
front of them): a channel's ``unit_id`` names its unit (default: the device's ``unit_id``); requests are
planned per unit and a scan reads every unit in turn. A unit that stops answering while the others answer
is taken off-scan on its own (its channels ``BAD``, the reason in ``Reading.errors``, retried after a
doubling back-off) and the line reads on; when no unit answers, the line is down and the scan fails like
any device's. A raw value at the
limit of an integer type is flagged ``SATURATED`` (a converter at over-range sits there); a NaN float is
``BAD``. pymodbus clients are not thread-safe: a driver and its client belong to the one thread that
samples the device.

Writes (:meth:`drivers.base.Driver.write` with a :class:`RegisterWrite`): one coil (fc5), one register
(fc6) or a block of contiguous registers (fc16) in one request, so a device that refuses one value
refuses the whole block; a refusal is a :class:`~gateway.errors.DeviceRefused`. Raw blocks outside the
channel scan (a block a CNC macro writes) are read with :meth:`ModbusDriver.read_registers`.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from drivers.base import Driver, Quality, SharedLine, parse_common_options, parse_scaling, unpack_words
from gateway.errors import DeviceRefused, DeviceTimeout, DriverError

DATA_TYPES = ("int16", "uint16", "int32", "uint32", "float32")
ORDERS = ("big", "little")
FUNCTIONS = (3, 4)
#: write functions: one coil, one register, a block of registers
WRITE_FUNCTIONS = (5, 6, 16)
MAX_REGISTERS = 125  # per read request (Modbus application protocol, 6.3/6.4)
_WORDS = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
#: raw values a converter reports when it sits at its limit (unsigned zero is a normal reading)
_SATURATED = {"int16": (-32768, 32767), "uint16": (None, 65535), "int32": (-(2**31), 2**31 - 1),
              "uint32": (None, 2**32 - 1)}


@dataclass(frozen=True, kw_only=True, slots=True)
class RegisterAddress:
    """Where a channel's value sits in a Modbus device and how to turn it into engineering units."""

    address: int
    function: int = 4
    data_type: str = "int16"
    word_order: str = "big"
    byte_order: str = "big"
    scale: float = 1.0
    offset: float = 0.0
    unit_id: int | None = None  # None: the device's unit_id

    @property
    def n_registers(self) -> int:
        return _WORDS[self.data_type]

    def decode(self, words: Sequence[int]) -> tuple[float, Quality]:
        """Engineering value and quality from this channel's registers."""
        raw = unpack_words(words, self.data_type, word_order=self.word_order, byte_order=self.byte_order)
        if self.data_type == "float32":
            if math.isnan(raw):
                return math.nan, Quality.BAD
            quality = Quality.SATURATED if math.isinf(raw) else Quality.GOOD
        else:
            lo, hi = _SATURATED[self.data_type]
            quality = Quality.SATURATED if raw in (lo, hi) else Quality.GOOD
        return raw * self.scale + self.offset, quality


@dataclass(frozen=True, kw_only=True, slots=True)
class RegisterWrite:
    """Where a write goes: a coil (fc5), one register (fc6) or registers from ``address`` on (fc16).

    The value written: a bool (fc5), an int (fc6), a sequence of at most 123 ints (fc16). ``label`` says
    what the write is for in messages (``heartbeat fc6 120``); ``unit_id`` ``None``: the device's.
    """

    function: int
    address: int
    label: str = ""
    unit_id: int | None = None

    def __post_init__(self) -> None:
        if self.function not in WRITE_FUNCTIONS:
            raise ValueError(f"a Modbus write is function 5, 6 or 16. Got {self.function}")


def parse_register_address(table: Any) -> RegisterAddress | None:
    """Check the address keys of a ``[channels.NAME]`` table on a Modbus device."""
    address = table.int("address", min=0, max=65535, expected="a register address in 0..65535 (0-based, as on "
                                                              "the wire)")
    function = table.int("function", default=4, expected="4 (input registers) or 3 (holding registers)")
    if function is not None and function not in FUNCTIONS:
        table.problem("function", f"expected 4 (input registers) or 3 (holding registers), got {function} (an integer)")
        function = None
    data_type = table.str("data_type", default="int16", choices=DATA_TYPES)
    word_order = table.str("word_order", default="big", choices=ORDERS)
    byte_order = table.str("byte_order", default="big", choices=ORDERS)
    scale, offset = parse_scaling(table, "count")
    unit_id = table.int("unit_id", default=None, min=1, max=247,
                        expected="a Modbus unit address in 1..247 (the unit on the device's line or behind its "
                                 "gateway; default: the device's unit_id)")
    if None in (address, function, data_type, word_order, byte_order, scale, offset):
        return None
    if "unit_id" in table and unit_id is None:  # a bad value, reported
        return None
    if address + _WORDS[data_type] - 1 > 65535:
        table.problem("address", f"a {data_type} at {address} runs past register 65535")
        return None
    return RegisterAddress(address=address, function=function, data_type=data_type, word_order=word_order,
                           byte_order=byte_order, scale=scale, offset=offset, unit_id=unit_id)


@dataclass(frozen=True, slots=True)
class Request:
    """One read request to one unit and the channels it serves: ``(channel index, first word in the answer)``."""

    function: int
    start: int
    count: int
    members: tuple[tuple[int, int], ...]
    unit: int = 1


def plan_requests(addresses: Sequence[RegisterAddress], default_unit: int = 1) -> list[Request]:
    """Merge channels on contiguous (or shared) registers of one unit and function into as few requests as possible."""
    def unit_of(a: RegisterAddress) -> int:
        return a.unit_id if a.unit_id is not None else default_unit

    requests: list[Request] = []
    for unit in sorted({unit_of(a) for a in addresses}):
        for function in FUNCTIONS:
            chans = sorted((a.address, i) for i, a in enumerate(addresses)
                           if a.function == function and unit_of(a) == unit)
            start = end = -1
            members: list[tuple[int, int]] = []
            for addr, i in chans:
                last = addr + addresses[i].n_registers  # one past the channel's last register
                if members and addr <= end and max(end, last) - start <= MAX_REGISTERS:
                    end = max(end, last)
                else:
                    if members:
                        requests.append(_request(unit, function, start, end, members))
                    start, end, members = addr, last, []
                members.append((i, addr))
            if members:
                requests.append(_request(unit, function, start, end, members))
    return requests


def _request(unit: int, function: int, start: int, end: int, members: list[tuple[int, int]]) -> Request:
    return Request(function=function, start=start, count=end - start,
                   members=tuple((i, addr - start) for i, addr in members), unit=unit)


def describe_request(r: Request, *, with_unit: bool = False) -> str:
    """``fc4 0..8`` (``unit 2 fc4 0..8`` with the unit)."""
    return (f"unit {r.unit} " if with_unit else "") + f"fc{r.function} {r.start}..{r.start + r.count - 1}"


def describe_requests(requests: Sequence[Request]) -> str:
    """``2 requests (fc4 0..8, fc4 100..117)``, for messages; units named when there are several."""
    several = len({r.unit for r in requests}) > 1
    parts = [describe_request(r, with_unit=several) for r in requests]
    return f"{len(requests)} request{'s' if len(requests) != 1 else ''} ({', '.join(parts)})"


class ModbusDriver(Driver):
    """Reads register channels with a pymodbus sync client (made by :meth:`_make_client`).

    A transport (TCP, RTU) names its options type and unit-address range and parses its own link keys
    (:meth:`_parse_link_options`); ``unit_id``, the common keys and the channel addresses are parsed here.
    """

    kind: ClassVar[str] = "Modbus"
    #: the frozen options type of the transport (its link keys, ``unit_id`` and the common keys)
    options_type: ClassVar[type]
    #: the unit addresses the transport allows for the device's ``unit_id``
    unit_ids: ClassVar[tuple[int, int]] = (1, 247)

    @classmethod
    def parse_device_options(cls, table: Any) -> Any:
        link = cls._parse_link_options(table)
        lo, hi = cls.unit_ids
        unit_id = table.int("unit_id", default=1, min=lo, max=hi)
        common = parse_common_options(table)
        if unit_id is None or None in link.values():
            return None
        return cls.options_type(**link, unit_id=unit_id, **common)

    @classmethod
    def _parse_link_options(cls, table: Any) -> dict[str, Any]:
        """The transport's own keys (``host``, ``port``; ``baudrate``, ...): a bad one is reported and ``None``."""
        raise NotImplementedError

    @classmethod
    def parse_channel_address(cls, table: Any) -> RegisterAddress | None:
        return parse_register_address(table)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.requests = plan_requests(self.addresses, self.options.unit_id)
        self._several_units = len({r.unit for r in self.requests}) > 1
        self._client: Any = None
        self._line = SharedLine(self) if self._several_units else None

    def _make_client(self) -> Any:
        raise NotImplementedError

    def _where(self) -> str:
        raise NotImplementedError

    def _connect(self) -> None:
        client = self._make_client()
        self._client = client
        if not client.connect():
            raise DriverError(f'device "{self.name}" ({self.kind}): cannot connect to {self._where()}')

    def _disconnect(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):  # closing after an error must never raise
                client.close()

    def _read_raw(self) -> tuple[list[float], list[Quality]]:
        values = [math.nan] * len(self.addresses)
        quality = [Quality.BAD] * len(self.addresses)
        if self._line is None:
            for req in self.requests:
                self._read_request(req, values, quality)
            return values, quality

        def read(unit: int) -> None:
            for req in self.requests:
                if req.unit == unit:
                    self._read_request(req, values, quality)

        def clear(unit: int) -> None:
            for req in self.requests:
                if req.unit == unit:
                    for i, _ in req.members:
                        values[i], quality[i] = math.nan, Quality.BAD

        self._line.scan(list(dict.fromkeys(r.unit for r in self.requests)), read, clear, lambda u: f"unit {u}")
        return values, quality

    def _read_request(self, req: Request, values: list[float], quality: list[Quality]) -> None:
        regs = self._read_words(req, describe_request(req, with_unit=self._several_units))
        for i, first in req.members:
            a = self.addresses[i]
            values[i], quality[i] = a.decode(regs[first:first + a.n_registers])

    def _read_words(self, req: Request, what: str) -> list[int]:
        client = self._client
        call = client.read_input_registers if req.function == 4 else client.read_holding_registers
        rr = self._answer(what, lambda: call(req.start, count=req.count, device_id=req.unit))
        if rr.isError():
            raise DriverError(f'device "{self.name}" ({self.kind}): {what} answered with exception '
                              f"{_exception(rr)}")
        regs = rr.registers
        if len(regs) < req.count:
            raise DriverError(f'device "{self.name}" ({self.kind}): {what}: '
                              f"expected {req.count} registers, got {len(regs)}")
        return list(regs[:req.count])

    def _answer(self, what: str, call: Callable[[], Any]) -> Any:
        """One request's answer; no valid answer (pymodbus gave up after its retries) is a :class:`DeviceTimeout`."""
        from pymodbus.exceptions import ModbusIOException

        try:
            return call()
        except ModbusIOException as exc:
            opt = self.options
            raise DeviceTimeout(
                f'device "{self.name}" ({self.kind}): no valid answer to {what} within {opt.timeout_s:g} s x '
                f"{opt.retries + 1} attempt{'s' if opt.retries else ''}: {exc}") from exc

    # -- beyond the channel scan ----------------------------------------------------------------------------
    def read_registers(self, address: int, count: int, *, function: int = 4) -> list[int]:
        """``count`` raw registers from ``address`` in one request, outside the channel scan.

        Errors as :meth:`read`'s (the link is closed and reopened on the next call).
        """
        if function not in FUNCTIONS:
            raise ValueError(f"function must be one of {FUNCTIONS}. Got {function}")
        if not 1 <= count <= MAX_REGISTERS:
            raise ValueError(f"count must be 1..{MAX_REGISTERS}. Got {count}")
        if not self.is_open:
            self.open()
        req = Request(function=function, start=address, count=count, members=(), unit=self.options.unit_id)
        what = describe_request(req)
        return self._transaction(what, lambda: self._read_words(req, what))

    def _write_raw(self, target: RegisterWrite, value: Any) -> None:
        client, what = self._client, self._write_what(target, value)
        unit = self.options.unit_id if target.unit_id is None else target.unit_id
        if target.function == 16:
            rr = self._answer(what, lambda: client.write_registers(target.address, values=list(value),
                                                                    device_id=unit))
        elif target.function == 6:
            rr = self._answer(what, lambda: client.write_register(target.address, int(value), device_id=unit))
        else:
            rr = self._answer(what, lambda: client.write_coil(target.address, bool(value), device_id=unit))
        if rr.isError():
            raise DeviceRefused(f'device "{self.name}" ({self.kind}): {what} refused with exception {_exception(rr)}')

    def _write_what(self, target: RegisterWrite, value: Any) -> str:
        last = target.address + len(value) - 1 if target.function == 16 else None
        where = f"fc{target.function} {target.address}" + (f"..{last}" if last is not None else "")
        return f"{target.label} {where}" if target.label else where


def _exception(rr: Any) -> str:
    """``3 (illegal data value)``: a Modbus exception answer's code and meaning."""
    code = getattr(rr, "exception_code", None)
    return f"{code} ({_EXCEPTIONS.get(code, 'unknown')})"


_EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
               4: "device failure", 6: "device busy", 10: "gateway path unavailable",
               11: "gateway target failed to respond"}
