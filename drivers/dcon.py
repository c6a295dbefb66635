"""ASCII serial ADC modules in ADAM-4000 (DCON) style on one RS-485 line (pyserial): ``driver = "dcon"``.

One ``[devices.NAME]`` is one serial line; its channels name the ``module`` (address 0..255) and the
``input`` they are wired to. A scan sends ``#AA`` once per module used and reads every input from the
answer (``>+05.123+04.567...``).

Device keys: ``port`` (required), ``baudrate`` (9600), ``checksum`` (false: when true, two hex digits, the
sum of the characters modulo 256, end every command and answer, and an answer whose checksum is wrong is
rejected), ``inputs`` (8: inputs per module, for the link budget), and the common keys.
Channel keys: ``module``, ``input``, ``scale`` (1), ``offset`` (0): ``value = reading * scale + offset``,
e.g. a 0..10 V input for 0..15000 rpm has ``scale = 1500``.

Quality: a value printed as all nines (``+99.999``) does not fit the module's format: ``SATURATED``. An
answer that is malformed or fails its checksum makes that module's values ``BAD`` for this scan (counted
in ``bad_answers``). A module that does not answer within ``timeout_s`` while another one does is taken
off-scan on its own (:class:`drivers.base.SharedLine`); when no module answers, the line has failed: a
device timeout.

Link budget at 9600 baud 8N1: ``#01`` and its 8-input answer are 62 characters, 65 ms, per module.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import serial

from drivers.base import (
    DeviceOptions,
    Driver,
    LinkBudget,
    Quality,
    SharedLine,
    parse_common_options,
    parse_scaling,
    serial_char_s,
)
from gateway.errors import DeviceTimeout

BAUDRATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
VALUE_CHARS = 7  # "+dd.ddd": the 4017's engineering-units format, used for the link budget
_ANSWER = re.compile(r">((?:[+-][0-9]+(?:\.[0-9]+)?)+)")
_VALUE = re.compile(r"[+-][0-9]+(?:\.[0-9]+)?")


def checksum(text: str) -> str:
    """DCON checksum: the sum of the characters modulo 256 as two upper-case hex digits."""
    return f"{sum(text.encode('ascii')) % 256:02X}"


def parse_answer(answer: bytes, *, with_checksum: bool) -> list[tuple[str, float]] | None:
    """The readings in a module's answer to ``#AA`` (its bytes before the CR); ``None`` when malformed.

    Each reading is ``(text, value)``: a sign and digits (``+05.123``). A wrong checksum, any other character
    or a reading too long to be a finite number makes the whole answer malformed.
    """
    if with_checksum:
        body, given = answer[:-2], answer[-2:]
        if len(answer) < 3 or given.upper() != f"{sum(body) % 256:02X}".encode("ascii"):
            return None
        answer = body
    match = _ANSWER.fullmatch(answer.decode("ascii", "replace"))
    if match is None:
        return None
    readings = [(v, float(v)) for v in _VALUE.findall(match.group(1))]
    return readings if all(math.isfinite(x) for _, x in readings) else None


@dataclass(frozen=True, kw_only=True, slots=True)
class DconOptions(DeviceOptions):
    """A DCON line: its serial port and format."""

    port: str
    baudrate: int = 9600
    checksum: bool = False
    inputs: int = 8


@dataclass(frozen=True, kw_only=True, slots=True)
class DconInput:
    """One module input and its scaling to engineering units."""

    module: int
    input: int
    scale: float = 1.0
    offset: float = 0.0


class DconDriver(Driver):
    """Reads DCON modules on one line with ``#AA``; see the module docstring."""

    kind: ClassVar[str] = "DCON"

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._modules: dict[int, list[int]] = {}
        for i, a in enumerate(self.addresses):
            self._modules.setdefault(a.module, []).append(i)
        self._serial: serial.Serial | None = None
        self._line = SharedLine(self)
        #: answers rejected for a bad format or checksum
        self.bad_answers = 0

    @classmethod
    def parse_device_options(cls, table: Any) -> DconOptions | None:
        port = table.str("port", expected='a serial device path such as "/dev/ttyUSB0"')
        baudrate = table.int("baudrate", default=9600, expected="one of " + ", ".join(map(str, BAUDRATES)))
        if baudrate is not None and baudrate not in BAUDRATES:
            table.problem("baudrate", f"expected one of {', '.join(map(str, BAUDRATES))}, got {baudrate} (an integer)")
            baudrate = None
        use_checksum = table.bool("checksum", default=False)
        inputs = table.int("inputs", default=8, min=1, max=16)
        common = parse_common_options(table)
        if None in (port, baudrate, use_checksum, inputs):
            return None
        return DconOptions(port=port, baudrate=baudrate, checksum=use_checksum, inputs=inputs, **common)

    @classmethod
    def parse_channel_address(cls, table: Any) -> DconInput | None:
        module = table.int("module", min=0, max=255, expected="a module address in 0..255")
        number = table.int("input", min=0, max=15, expected="an input number in 0..15")
        scale, offset = parse_scaling(table, "reading")
        if None in (module, number, scale, offset):
            return None
        return DconInput(module=module, input=number, scale=scale, offset=offset)

    @classmethod
    def link_budget(cls, options: DconOptions, addresses: Sequence[DconInput]) -> LinkBudget:
        modules = sorted({a.module for a in addresses})
        extra = 2 if options.checksum else 0
        per_module = (4 + extra) + (1 + options.inputs * VALUE_CHARS + 1 + extra)
        chars = per_module * len(modules)
        seconds = chars * serial_char_s(options.baudrate)
        return LinkBudget(
            min_period_s=seconds,
            detail=f"DCON at {options.baudrate} baud: one scan reads {len(modules)} module"
                   f"{'s' if len(modules) != 1 else ''} ({', '.join(f'{m:02X}' for m in modules)}), "
                   f"{per_module} characters each ({options.inputs} inputs of {VALUE_CHARS} characters), "
                   f"{chars} characters = {seconds * 1000:.1f} ms")

    # -- transport ----------------------------------------------------------------------------------------
    def _connect(self) -> None:
        o = self.options
        self._serial = serial.Serial(o.port, baudrate=o.baudrate, bytesize=8, parity="N", stopbits=1,
                                     timeout=o.timeout_s, write_timeout=o.timeout_s)

    def _disconnect(self) -> None:
        port, self._serial = self._serial, None
        if port is not None:
            with contextlib.suppress(Exception):  # closing after an error must never raise
                port.close()

    def _read_raw(self) -> tuple[list[float], list[Quality]]:
        port = self._serial
        assert port is not None
        values = [math.nan] * len(self.addresses)
        quality = [Quality.BAD] * len(self.addresses)

        def read(module: int) -> None:
            readings = self._ask(port, module)
            if readings is None:
                return  # malformed: this module's values stay BAD for this scan (counted)
            for i in self._modules[module]:
                a = self.addresses[i]
                if a.input >= len(readings):
                    continue  # the module has fewer inputs than the profile says: BAD
                text, number = readings[a.input]
                values[i] = number * a.scale + a.offset
                quality[i] = Quality.SATURATED if set(text[1:]) <= {"9", "."} else Quality.GOOD

        def clear(module: int) -> None:
            for i in self._modules[module]:
                values[i], quality[i] = math.nan, Quality.BAD

        if len(self._modules) > 1:  # a silent module goes off-scan alone (see SharedLine)
            self._line.scan(list(self._modules), read, clear, lambda m: f"module {m:02X}")
        else:
            for module in self._modules:
                read(module)
        return values, quality

    def _ask(self, port: serial.Serial, module: int) -> list[tuple[str, float]] | None:
        """Send ``#AA`` and parse the answer; ``None`` for a malformed one (counted)."""
        command = f"#{module:02X}"
        if self.options.checksum:
            command += checksum(command)
        port.reset_input_buffer()  # a late answer to an earlier command must not pass for this one
        port.write(command.encode("ascii") + b"\r")
        answer = port.read_until(b"\r")
        if not answer.endswith(b"\r"):
            raise DeviceTimeout(f'device "{self.name}" (DCON {self.options.port}): module {module:02X} did not '
                                f"answer {command!r} within {self.options.timeout_s:g} s"
                                + (f" (got {answer!r})" if answer else ""))
        readings = parse_answer(answer[:-1], with_checksum=self.options.checksum)
        if readings is None:
            self.bad_answers += 1
        return readings
