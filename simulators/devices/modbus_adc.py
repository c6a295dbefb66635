"""The ADC board: analog inputs in Modbus input registers, read live from the machine.

Every read request samples the :class:`~simulators.live.LiveSource` at ``clock.now()`` and encodes the
addressed channels per the :class:`~simulators.devices.analog.AdcBoardConfig` map, so a client sees the
machine's instantaneous values at the moment of its request. Over TCP or RTU (see
:mod:`simulators.devices.modbus_base`).

Faults: ``drop_replies`` (request ignored: timeout), ``reply_delay_s``, ``corrupt_replies`` (RTU: bad
CRC; TCP: bad protocol id), ``garbage_replies``, ``freeze``/``force`` per channel (a forced value
beyond the range saturates int16/uint16 counts, as a converter does), ``disconnect_clients()``.
"""

from __future__ import annotations

from pathlib import Path

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from gateway.clock import Clock
from simulators.devices.analog import DEFAULT_ADC_CONFIG, AdcBoardConfig, RegisterChannel
from simulators.devices.faults import Faults
from simulators.devices.modbus_base import ModbusDevice, RtuBus, RtuTransport, TcpTransport
from simulators.devices.sources import require_channels
from simulators.live import LiveSource


class ModbusAdc(ModbusDevice):
    """A Modbus ADC board fed by a :class:`LiveSource`.

    Args:
        source: the machine.
        clock: the shared clock; values are taken at ``clock.now()`` when a request arrives.
        config: the register map (default: :data:`~simulators.devices.analog.DEFAULT_ADC_CONFIG`).
        transport: :class:`TcpTransport` (default) or :class:`RtuTransport`.
        serial_link: for RTU, the path (a symlink) clients open.
        faults: the fault switches (a fresh :class:`Faults` by default).
        name: for messages and logs.

    """

    kind = "ADC board"

    def __init__(self, *, source: LiveSource, clock: Clock, config: AdcBoardConfig = DEFAULT_ADC_CONFIG,
                 transport: TcpTransport | RtuTransport | None = None, serial_link: Path | RtuBus | None = None,
                 faults: Faults | None = None, name: str = "adc") -> None:
        super().__init__(name=name, transport=transport or TcpTransport(), device_id=config.device_id,
                         serial_link=serial_link, faults=faults)
        require_channels(source, config.channel_names(), device=name)
        self.config = config
        self._source = source
        self._clock = clock
        self._read_codes = {3, 4} if config.holding_mirror else {4}
        # register address -> (channel, word index within the channel's registers)
        self._slots: dict[int, tuple[RegisterChannel, int]] = {
            ch.address + k: (ch, k) for ch in config.channels for k in range(ch.n_registers)
        }

    def _sim_device(self) -> SimDevice:
        blocks = [SimData(ch.address, count=ch.n_registers, datatype=DataType.REGISTERS)
                  for ch in self.config.channels]
        # id 0: the catch-all device; the RTU address filter lives in the trace hook
        return SimDevice(0, simdata=blocks, action=self._action)

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        if set_values is not None or function_code not in self._read_codes:
            return ExcCodes.ILLEGAL_FUNCTION
        await self._reply_delay(function_code, writing=False)
        values = self.faults.apply(self._source.values(self._clock.now()))
        encoded: dict[int, list[int]] = {}
        for addr in range(address, address + count):
            ch, k = self._slots[addr]
            words = encoded.get(ch.address)
            if words is None:
                words = encoded[ch.address] = ch.encode(values[ch.channel])
            registers[addr - start_address] = words[k]
        return None
