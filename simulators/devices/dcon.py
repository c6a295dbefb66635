"""ASCII serial ADC modules in Advantech ADAM-4000 (DCON) style on one RS-485 line (a pseudo-terminal).

Several modules share the line; each answers only its own address ``AA`` (two hex digits):

==============  =====================================  ==============================================
command         answer                                 meaning
==============  =====================================  ==============================================
``#AA``         ``>+05.123+04.567...``                 every input, in input order
``#AAN``        ``>+05.123``                           input N (one hex digit)
``$AAM``        ``!AA4017``                            module name
``$AAF``        ``!AAA2.10``                           firmware version
``$AA2``        ``!AATTCCFF``                          type 08 (+/-10 V), baud code, format (bit 6:
                                                       checksum on)
anything else   ``?AA``                                invalid command
==============  =====================================  ==============================================

Every command and answer ends with a carriage return. With checksum on, two upper-case hex digits (the
sum of all preceding characters, modulo 256) come before the CR in both directions, and a command whose
checksum is wrong gets no answer at all, like a command for another address.

A value is a sign, zero-padded integer digits, a point and decimals (``+05.123`` for a +/-10 V input);
a value that does not fit shows all nines (``+99.999``). Per input, ``scaling="voltage"`` reports the
voltage the CNC puts out (``eng_range`` -> ``volt_range``), as a real module does; ``"engineering"``
reports the channel in its own units (e.g. ``+07500.0`` rpm with 5 integer digits and 1 decimal).

Line time at ``baudrate`` (8N1) is simulated: an answer arrives when the command and the answer have
crossed the line. Faults: ``drop_replies``, ``reply_delay_s``, ``corrupt_replies`` (checksum modules: a
wrong checksum; others: a digit replaced by ``?``), ``garbage_replies``, ``freeze``/``force``,
``disconnect_clients()`` (the port is unplugged; reopening the path works).
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass
from pathlib import Path

from gateway.clock import Clock
from simulators.devices.analog import SIM_VMC_ANALOG, AnalogScale
from simulators.devices.faults import Faults
from simulators.devices.runtime import LineTime, LineWriter, PtyPort, call_in_loop
from simulators.devices.sources import require_channels
from simulators.live import LiveSource

log = logging.getLogger(__name__)

_BAUD_CODES = {1200: 0x03, 2400: 0x04, 4800: 0x05, 9600: 0x06, 19200: 0x07, 38400: 0x08, 57600: 0x09,
               115200: 0x0A}


def checksum(text: str) -> str:
    """DCON checksum: the sum of the characters modulo 256 as two upper-case hex digits."""
    return f"{sum(text.encode('ascii')) % 256:02X}"


@dataclass(frozen=True, kw_only=True)
class DconChannel:
    """One input of a module and how it reports the channel."""

    channel: str
    scaling: str = "voltage"  # "voltage" or "engineering"
    eng_range: tuple[float, float] = (-10.0, 10.0)
    volt_range: tuple[float, float] = (-10.0, 10.0)
    int_digits: int = 2
    decimals: int = 3

    def __post_init__(self) -> None:
        if self.scaling not in ("voltage", "engineering"):
            raise ValueError(f'input {self.channel!r}: scaling must be "voltage" or "engineering". '
                             f"Got {self.scaling!r}")
        if not 1 <= self.int_digits <= 8 or not 0 <= self.decimals <= 6:
            raise ValueError(f"input {self.channel!r}: need int_digits in 1..8 and decimals in 0..6")
        AnalogScale(eng_range=self.eng_range, volt_range=self.volt_range)  # checks the ranges

    def format(self, value: float) -> str:
        """The value as the module prints it (``+05.123``)."""
        if self.scaling == "voltage":
            value = AnalogScale(eng_range=self.eng_range, volt_range=self.volt_range).volts(value)
        top = 10.0**self.int_digits - 10.0 ** (-self.decimals)
        if value != value:  # NaN: an open input reads as zero
            value = 0.0
        value = max(-top, min(top, value))
        width = 1 + self.int_digits + (1 + self.decimals if self.decimals else 0)
        return f"{value:+0{width}.{self.decimals}f}"


#: an unwired input: reads 0 V
UNWIRED = DconChannel(channel="")


@dataclass(frozen=True, kw_only=True)
class DconModuleConfig:
    """One module on the line: its address, name and inputs (index = input number)."""

    address: int
    inputs: tuple[DconChannel, ...]
    name: str = "4017"
    firmware: str = "A2.10"
    checksum: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.address <= 0xFF:
            raise ValueError(f"module address must be in 0..255. Got {self.address!r}")
        if not 1 <= len(self.inputs) <= 16:
            raise ValueError(f"module {self.address:02X}: needs 1..16 inputs. Got {len(self.inputs)}")

    @property
    def address_text(self) -> str:
        """``AA`` as on the line."""
        return f"{self.address:02X}"


@dataclass(frozen=True, kw_only=True)
class DconLineConfig:
    """The modules sharing one line, and the line's speed."""

    modules: tuple[DconModuleConfig, ...]
    baudrate: int = 9600
    simulate_line_time: bool = True

    def __post_init__(self) -> None:
        addresses = [m.address for m in self.modules]
        if not addresses or len(set(addresses)) != len(addresses):
            raise ValueError(f"module addresses on a line must be unique and at least one. Got {addresses}")
        if self.baudrate not in _BAUD_CODES:
            raise ValueError(f"baudrate must be one of {sorted(_BAUD_CODES)}. Got {self.baudrate!r}")

    def channel_names(self) -> tuple[str, ...]:
        """The machine channels read on this line, without repeats."""
        return tuple(dict.fromkeys(i.channel for m in self.modules for i in m.inputs if i.channel))


def _voltage_input(name: str) -> DconChannel:
    scale = SIM_VMC_ANALOG[name]
    return DconChannel(channel=name, eng_range=scale.eng_range, volt_range=scale.volt_range)


#: The default line for the bundled machine, 9600 baud, no checksum: module 01 (ADAM-4017 style,
#: 8 inputs) reads spindle speed, I1, I2 and X/Y/Z velocity on inputs 0-5 (6, 7 unwired); module 02
#: reads the X/Y/Z motor currents on inputs 0-2 (3-7 unwired). Voltages as the CNC puts them out
#: (ranges in SIM_VMC_ANALOG), format +dd.ddd.
DEFAULT_DCON_CONFIG = DconLineConfig(modules=(
    DconModuleConfig(address=0x01, inputs=(
        *(_voltage_input(n) for n in ("spindle_speed", "spindle_i1", "spindle_i2",
                                      "x_velocity", "y_velocity", "z_velocity")),
        UNWIRED, UNWIRED)),
    DconModuleConfig(address=0x02, inputs=(
        *(_voltage_input(n) for n in ("x_current", "y_current", "z_current")),
        UNWIRED, UNWIRED, UNWIRED, UNWIRED, UNWIRED)),
))


class DconLine:
    """DCON modules on a pseudo-terminal, fed by ``source``; see the module docstring.

    Args:
        source: the machine.
        clock: the shared clock; values are taken at ``clock.now()`` when a command arrives.
        config: the modules and the line (default :data:`DEFAULT_DCON_CONFIG`).
        serial_link: the path (a symlink) clients open.
        faults: the fault switches, for every module on the line.
        name: for messages and logs.

    """

    kind = "DCON serial ADC line"

    def __init__(self, *, source: LiveSource, clock: Clock, serial_link: Path,
                 config: DconLineConfig = DEFAULT_DCON_CONFIG, faults: Faults | None = None,
                 name: str = "dcon") -> None:
        require_channels(source, config.channel_names(), device=name)
        self.name = name
        self.config = config
        self.faults = faults if faults is not None else Faults()
        #: addresses of modules that have died on the line: they answer nothing (the others still do)
        self.silent_modules: set[int] = set()
        self._source = source
        self._clock = clock
        self._serial_link = serial_link
        self._modules = {m.address_text: m for m in config.modules}
        self._line = LineTime(baudrate=config.baudrate) if config.simulate_line_time else None
        self._pty: PtyPort | None = None
        self._writer: LineWriter | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._buffer = bytearray()

    @property
    def serial_port(self) -> str:
        """The path a client opens."""
        if self._pty is None:
            raise RuntimeError(f"{self.name}: not running")
        return self._pty.path

    @property
    def endpoint(self) -> str:
        """Where clients find the modules, for people."""
        if self._pty is None:
            return "not running"
        modules = ", ".join(f"{m.address_text}{' (checksum)' if m.checksum else ''}" for m in self.config.modules)
        return f"dcon:{self._pty.path} ({self.config.baudrate} baud 8N1, modules {modules})"

    async def start(self) -> None:
        """Open the line (in the device loop)."""
        self._loop = asyncio.get_running_loop()
        self._pty = PtyPort(self._serial_link)
        self._writer = LineWriter(self._loop, self._pty, self._line)
        self._pty.attach(self._loop, self._on_bytes)
        log.info("%s: serving on %s", self.name, self.endpoint)

    async def stop(self) -> None:
        """Close the line (idempotent)."""
        if self._pty is not None:
            self._pty.close()
        self._pty = self._writer = None

    def disconnect_clients(self) -> None:
        """Unplug the port: the client's next read fails; reopening the same path works."""
        loop = self._loop
        if loop is None or self._pty is None:
            raise RuntimeError(f"{self.name}: not running")

        def _hang_up() -> None:
            self.faults.note("disconnected")
            self._buffer.clear()
            if self._pty is not None:
                self._pty.hang_up()

        call_in_loop(loop, _hang_up)

    # -- the line ---------------------------------------------------------------------------------------
    def _on_bytes(self, data: bytes) -> None:
        assert self._loop is not None
        assert self._writer is not None
        arrived = self._loop.time()
        self._buffer.extend(data)
        while b"\r" in self._buffer:
            cut = self._buffer.index(b"\r")
            command = bytes(self._buffer[:cut]).decode("ascii", "replace")
            del self._buffer[: cut + 1]
            try:
                answer = self._answer(command)
            except Exception:  # a broken source must not silence the line for good
                log.exception("%s: cannot answer %r", self.name, command)
                continue
            if answer is None:
                continue
            # the module hears the command's last byte only after it crossed the line
            ready = arrived + (self._line.seconds(len(command) + 1) if self._line else 0.0)
            faults = self.faults
            if faults.drop_replies:
                faults.note("dropped")
                continue
            if faults.reply_delay_s > 0:
                faults.note("delayed")
                ready += faults.reply_delay_s
            self._writer.send(answer, earliest=ready)

    def _answer(self, command: str) -> bytes | None:
        """The module's answer to one command (without CR), or ``None`` for silence."""
        if len(command) < 3:
            return None
        module = self._modules.get(command[1:3].upper())
        if module is None:
            return None  # another address: not ours to answer
        if module.address in self.silent_modules:
            self.faults.note("dropped")
            return None
        if module.checksum:
            body, given = command[:-2], command[-2:]
            if len(command) < 5 or given.upper() != checksum(body):
                return None  # a module ignores a command it cannot trust
            command = body
        text = self._respond(module, command)
        faults = self.faults
        if faults.garbage_replies:
            faults.note("garbage")
            return faults.garbage(len(text) + (2 if module.checksum else 0)) + b"\r"
        suffix = checksum(text) if module.checksum else ""
        if faults.corrupt_replies:
            faults.note("corrupted")
            if module.checksum:
                suffix = f"{(int(suffix, 16) + 1) % 256:02X}"
            else:
                text = text[:-1] + "?"
        return (text + suffix + "\r").encode("ascii")

    def _respond(self, module: DconModuleConfig, command: str) -> str:
        aa = module.address_text
        head, rest = command[:1], command[3:]
        if head == "#" and rest == "":
            values = self.faults.apply(self._source.values(self._clock.now()))
            return ">" + "".join(i.format(values[i.channel] if i.channel else 0.0) for i in module.inputs)
        if head == "#" and len(rest) == 1 and rest in "0123456789ABCDEFabcdef":
            n = int(rest, 16)
            if n >= len(module.inputs):
                return f"?{aa}"
            values = self.faults.apply(self._source.values(self._clock.now()))
            channel = module.inputs[n]
            return ">" + channel.format(values[channel.channel] if channel.channel else 0.0)
        if head == "$" and rest == "M":
            return f"!{aa}{module.name}"
        if head == "$" and rest == "F":
            return f"!{aa}{module.firmware}"
        if head == "$" and rest == "2":
            fmt = 0x40 if module.checksum else 0x00
            return f"!{aa}08{_BAUD_CODES[self.config.baudrate]:02X}{fmt:02X}"
        return f"?{aa}"
