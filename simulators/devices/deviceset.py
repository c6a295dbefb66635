"""Start, list and stop all simulated devices of one machine together.

>>> with serve(source, clock) as devices:       # doctest: +SKIP
...     print(devices.describe())
...     host, port = devices.adc_tcp.address

:func:`serve` (or :class:`DeviceSet` and :meth:`DeviceSet.start`) starts every device the
:class:`DeviceSetConfig` names in one asyncio loop in one thread; :meth:`DeviceSet.stop` stops them all
and joins the thread (idempotent; the context manager calls it). Serial devices get stable paths in a
fresh temporary directory (``/tmp/cncgw-sim-*/adc-rtu``, ``dcon``, ``slcan``), removed on stop.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from gateway.clock import Clock
from simulators.devices.analog import DEFAULT_ADC_CONFIG, AdcBoardConfig
from simulators.devices.can_module import DEFAULT_CAN_CONFIG, CanModule, CanModuleConfig
from simulators.devices.cnc import CompensationConfig, CompensationServer
from simulators.devices.dcon import DEFAULT_DCON_CONFIG, DconLine, DconLineConfig
from simulators.devices.faults import Faults
from simulators.devices.modbus_adc import ModbusAdc
from simulators.devices.modbus_base import RtuBus, RtuTransport, TcpTransport
from simulators.devices.opcua_cnc import OpcUaCnc, OpcUaCncConfig
from simulators.devices.runtime import DeviceLoop, check_loopback
from simulators.live import LiveSource

log = logging.getLogger(__name__)


#: how long a device may take to start (wall seconds)
START_TIMEOUT_S = 60.0


class Device(Protocol):
    """What the set needs of a device."""

    name: str
    kind: str
    faults: Faults

    @property
    def endpoint(self) -> str: ...

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    def disconnect_clients(self) -> None: ...


@dataclass(frozen=True, kw_only=True)
class DeviceSetConfig:
    """Which devices to serve and how. ``None`` leaves a device out.

    Ports are TCP ports on ``host`` (loopback only); 0 picks a free one (see :meth:`DeviceSet.describe`).
    """

    host: str = "127.0.0.1"
    adc: AdcBoardConfig = DEFAULT_ADC_CONFIG  # the register map of both ADC boards
    adc_tcp_port: int | None = 0
    adc_rtu: RtuTransport | None = field(default_factory=RtuTransport)
    #: more ADC boards on adc-rtu's RS-485 line (multi-drop), each its own device id and register map:
    #: served as adc-rtu-<device id>; one port for all, each board answers its own address
    adc_rtu_more: tuple[AdcBoardConfig, ...] = ()
    can: CanModuleConfig | None = DEFAULT_CAN_CONFIG
    can_virtual_channel: str | None = "cncgw-sim"
    can_slcan: bool = True
    dcon: DconLineConfig | None = DEFAULT_DCON_CONFIG
    cnc: CompensationConfig | None = field(default_factory=CompensationConfig)
    cnc_port: int = 0
    #: the CNC's own OPC UA server with the drive signals (off by default: its start takes about a second)
    cnc_opcua: OpcUaCncConfig | None = None

    def __post_init__(self) -> None:
        check_loopback(self.host)
        if self.can is not None and self.can_virtual_channel is None and not self.can_slcan:
            raise ValueError("the CAN module needs a virtual channel, slcan, or both")
        if self.adc_rtu_more:
            if self.adc_rtu is None:
                raise ValueError("adc_rtu_more puts boards on adc-rtu's line: adc_rtu is needed too")
            ids = [self.adc.device_id, *(b.device_id for b in self.adc_rtu_more)]
            if len(set(ids)) != len(ids):
                raise ValueError(f"the boards on one RS-485 line need distinct device ids. Got {ids}")


class DeviceSet:
    """The simulated devices of one machine, served together; see the module docstring.

    Attributes (``None`` when left out by the config): ``adc_tcp``, ``adc_rtu`` (:class:`ModbusAdc`; and
    ``adc_rtu_more``, a list, the boards on its line),
    ``can`` (:class:`CanModule`), ``dcon`` (:class:`DconLine`), ``cnc`` (:class:`CompensationServer`),
    ``cnc_opcua`` (:class:`~simulators.devices.opcua_cnc.OpcUaCnc`).
    Each has ``faults`` and ``disconnect_clients()`` for fault injection.
    """

    def __init__(self, *, source: LiveSource, clock: Clock, config: DeviceSetConfig | None = None) -> None:
        config = config or DeviceSetConfig()
        self.config = config
        self.link_dir = Path(tempfile.mkdtemp(prefix="cncgw-sim-"))
        # a set that is dropped without stop() must not leave its directory behind
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.link_dir, ignore_errors=True)
        self._loop = DeviceLoop()
        self._lock = threading.Lock()
        self._state = "new"
        common: dict[str, Any] = {"source": source, "clock": clock}
        try:
            # devices check their maps against the machine here, before any thread starts
            self.adc_tcp = None if config.adc_tcp_port is None else ModbusAdc(
                **common, config=config.adc, name="adc-tcp",
                transport=TcpTransport(host=config.host, port=config.adc_tcp_port))
            line = None if config.adc_rtu is None else RtuBus(self.link_dir / "adc-rtu", config.adc_rtu)
            self.adc_rtu = None if line is None else ModbusAdc(
                **common, config=config.adc, name="adc-rtu", transport=config.adc_rtu, serial_link=line)
            self.adc_rtu_more = [ModbusAdc(**common, config=b, name=f"adc-rtu-{b.device_id}",
                                           transport=config.adc_rtu, serial_link=line)
                                 for b in config.adc_rtu_more] if line is not None else []
            self.can = None if config.can is None else CanModule(
                **common, config=config.can, name="can", virtual_channel=config.can_virtual_channel,
                slcan_link=self.link_dir / "slcan" if config.can_slcan else None)
            self.dcon = None if config.dcon is None else DconLine(
                **common, config=config.dcon, name="dcon", serial_link=self.link_dir / "dcon")
            self.cnc = None if config.cnc is None else CompensationServer(
                **common, config=config.cnc, name="cnc",
                transport=TcpTransport(host=config.host, port=config.cnc_port))
            self.cnc_opcua = None if config.cnc_opcua is None else OpcUaCnc(
                **common, config=config.cnc_opcua, name="cnc-opcua")
        except BaseException:
            self._cleanup()
            raise
        self._started: list[Device] = []

    @property
    def devices(self) -> list[Device]:
        """Every device of the set, in start order."""
        found = [self.adc_tcp, self.adc_rtu, *self.adc_rtu_more, self.can, self.dcon, self.cnc, self.cnc_opcua]
        return [d for d in found if d is not None]

    def start(self) -> DeviceSet:
        """Start the loop thread and every device; on any failure stop what started and re-raise."""
        with self._lock:
            if self._state != "new":
                raise RuntimeError(f"a device set starts once; this one is {self._state}")
            self._state = "running"
        self._loop.start()
        try:
            for device in self.devices:
                # a device's start binds its port and builds its address space (the OPC UA server's took
                # over the 10 s call timeout at a load average of 12): a slow start is not a failure
                self._loop.run(device.start(), timeout_s=START_TIMEOUT_S)
                self._started.append(device)
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Stop every device, the loop thread, and remove the serial links (idempotent)."""
        with self._lock:
            if self._state == "stopped":
                return
            self._state = "stopped"
        started, self._started = self._started, []
        for device in reversed(started):
            try:
                self._loop.run(device.stop())
            except Exception:  # stop the others regardless
                log.exception("%s: cannot stop cleanly", device.name)
        self._loop.stop()
        self._cleanup()

    def __enter__(self) -> DeviceSet:
        return self.start() if self._state == "new" else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def describe(self) -> str:
        """One line per device: name, kind, where clients find it."""
        width = max((len(d.name) for d in self.devices), default=0)
        return "\n".join(f"{d.name:<{width}} {d.kind:<28} {d.endpoint}" for d in self.devices)


def serve(source: LiveSource, clock: Clock, config: DeviceSetConfig | None = None) -> DeviceSet:
    """Start the simulated devices of ``config`` (default: all) in front of ``source``.

    Returns the running :class:`DeviceSet`: use it as a context manager, or call ``stop()``.
    """
    return DeviceSet(source=source, clock=clock, config=config).start()
