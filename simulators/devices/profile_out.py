"""The bundled profile with the live addresses of running simulated devices filled in.

Ports are 0 (any free port) and pseudo-terminal paths are temporary, so a gateway cannot be pointed at the
simulators by a fixed profile. :func:`profile_for` takes ``profiles/sim-vmc.toml``, drops its own
``[devices]``/``[channels]`` tables and writes one device, ``VIA``, with channel tables generated from the
device's live map (so the profile always matches what is served): the ADC board over Modbus TCP or RTU,
the CAN module over slcan or the in-process virtual bus, the DCON line, or the CNC's own OPC UA server.

``displacement=True`` also serves and reads the displacement sensors: :func:`adc_with_displacement` adds
``x_um``, ``y_um``, ``z_um`` as float32 um at input registers 120-125 to an ADC map, and the profile
reads them as bursts (``[sampling] displacement_channels``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gateway import BUNDLED
from simulators.devices.analog import AdcBoardConfig, RegisterChannel

if TYPE_CHECKING:
    from simulators.devices.deviceset import DeviceSet

BUNDLED_PROFILE = BUNDLED / "sim-vmc.toml"
VIAS = ("adc-tcp", "adc-rtu", "adc-rtu-line", "can-slcan", "can-virtual", "dcon", "opcua")
#: ``adc-rtu-line``: the feed axes' motor currents on a second board (this address) on the ADC's RS-485 line
LINE_BOARD_ID = 2
LINE_BOARD_CHANNELS = ("x_current", "y_current", "z_current")
UNITS = {"spindle_speed": "rpm", "spindle_i1": "A", "spindle_i2": "A", "x_velocity": "mm/min",
         "y_velocity": "mm/min", "z_velocity": "mm/min", "x_current": "A", "y_current": "A", "z_current": "A",
         "x_um": "um", "y_um": "um", "z_um": "um"}
DISPLACEMENT = ("x_um", "y_um", "z_um")
DISPLACEMENT_ADDRESS = 120


def adc_with_displacement(config: AdcBoardConfig) -> AdcBoardConfig:
    """``config`` plus the displacement sensors as float32 um at input registers 120-125 (high word first)."""
    extra = tuple(RegisterChannel(channel=name, address=DISPLACEMENT_ADDRESS + 2 * i, encoding="float32")
                  for i, name in enumerate(DISPLACEMENT))
    return dataclasses.replace(config, channels=(*config.channels, *extra))


def rtu_line_boards(config: AdcBoardConfig) -> tuple[AdcBoardConfig, AdcBoardConfig]:
    """``config`` split over two boards on one RS-485 line.

    The feed axes' currents move to a second board (address :data:`LINE_BOARD_ID`, float32 from register 0);
    everything else stays on the first.
    """
    first = tuple(ch for ch in config.channels if ch.channel not in LINE_BOARD_CHANNELS)
    second = tuple(RegisterChannel(channel=name, address=2 * i, encoding="float32")
                   for i, name in enumerate(LINE_BOARD_CHANNELS))
    return (dataclasses.replace(config, channels=first),
            AdcBoardConfig(channels=second, device_id=LINE_BOARD_ID))


def _num(x: float) -> str:
    return repr(float(x))


def _adc_channels(config: AdcBoardConfig, device: str, unit_id: int | None = None) -> list[str]:
    out, seen = [], set()
    for ch in config.channels:
        if ch.channel in seen:
            continue  # the first register of a channel (int16 counts on the default board)
        seen.add(ch.channel)
        lines = [f"[channels.{ch.channel}]", f'device = "{device}"', f'unit = "{UNITS.get(ch.channel, "")}"',
                 f"address = {ch.address}", f'data_type = "{ch.encoding}"']
        if unit_id is not None:
            lines.append(f"unit_id = {unit_id}  # another board on the same line")
        if ch.word_order != "big":
            lines.append(f'word_order = "{ch.word_order}"')
        if ch.byte_order != "big":
            lines.append(f'byte_order = "{ch.byte_order}"')
        if ch.encoding != "float32":
            (e0, e1), (c0, c1) = ch.eng_range, ch.counts_range
            scale = (e1 - e0) / (c1 - c0)
            lines += [f"scale = {_num(scale)}", f"offset = {_num(e0 - c0 * scale)}"]
        out.append("\n".join(lines))
    return out


def acquisition_toml(devices: DeviceSet, via: str) -> str:
    """``[devices.NAME]`` and ``[channels.*]`` tables for the running device ``via`` (one of :data:`VIAS`)."""
    if via not in VIAS:
        raise ValueError(f"via must be one of {VIAS}. Got {via!r}")
    blocks: list[str] = []
    if via.startswith("adc"):
        adc = devices.adc_tcp if via == "adc-tcp" else devices.adc_rtu
        if adc is None:
            raise ValueError(f"the device set serves no {via}")
        if via == "adc-tcp":
            host, port = adc.address
            head = ['[devices.adc]', 'driver = "modbus_tcp"', f'host = "{host}"', f"port = {port}",
                    "timeout_s = 0.5"]
        else:
            transport = devices.config.adc_rtu
            assert transport is not None
            period = ("period_s = 0.02  # two boards, one request each, on one line" if via == "adc-rtu-line"
                      else "period_s = 0.01  # the line and the client's turnaround do not allow 2 ms")
            head = ['[devices.adc]', 'driver = "modbus_rtu"', f'port = "{adc.serial_port}"',
                    f"baudrate = {transport.baudrate}", f"unit_id = {adc.config.device_id}", period,
                    "timeout_s = 0.2"]
        more = devices.adc_rtu_more if via == "adc-rtu-line" else []
        if via == "adc-rtu-line" and not more:
            raise ValueError("the device set serves no second board on the ADC's RS-485 line")
        blocks = ["\n".join(head), *_adc_channels(adc.config, "adc"),
                  *(b for board in more for b in _adc_channels(board.config, "adc", board.config.device_id))]
    elif via == "opcua":
        server = devices.cnc_opcua
        if server is None:
            raise ValueError("the device set serves no CNC OPC UA server")
        period = max(server.config.update_period_s, 0.01)
        blocks = ["\n".join(['[devices.cnc]', 'driver = "opcua"', f'endpoint = "{server.endpoint}"', 'mode = "poll"',
                             f"period_s = {_num(period)}  # the CNC refreshes its OPC UA variables every "
                             f"{server.config.update_period_s * 1000:g} ms", "timeout_s = 1.0"])]
        for i, n in enumerate(server.config.nodes):
            where = (f'browse_path = "{n.browse_path(server.ns or 2)}"' if i == 0 else
                     f'node_id = "ns={server.ns};s={n.string_id}"')
            blocks.append("\n".join([f"[channels.{n.channel}]", 'device = "cnc"', f'unit = "{n.unit}"', where]))
    elif via.startswith("can"):
        can = devices.can
        if can is None:
            raise ValueError("the device set serves no CAN module")
        if via == "can-slcan":
            head = ['[devices.can]', 'driver = "can"', 'interface = "slcan"', f'channel = "{can.slcan_port}"',
                    "bitrate = 500000", "open_delay_s = 0.0"]
        else:
            if can.virtual_channel is None:
                raise ValueError("the CAN module has no virtual channel")
            head = ['[devices.can]', 'driver = "can"', 'interface = "virtual"', f'channel = "{can.virtual_channel}"']
        head += [f"period_s = {_num(can.config.period_s)}  # the module sends every {can.config.period_s * 1000:g} ms",
                 "timeout_s = 0.2"]
        blocks = ["\n".join(head)]
        for frame in can.config.frames:
            for s in frame.signals:
                lines = [f"[channels.{s.channel}]", 'device = "can"', f'unit = "{UNITS.get(s.channel, "")}"',
                         f"frame_id = {frame.frame_id:#x}", f"start_bit = {s.start_bit}",
                         f"length_bits = {s.length_bits}", f"signed = {str(s.signed).lower()}",
                         f"scale = {_num(s.scale)}", f"offset = {_num(s.offset)}"]
                if frame.extended_id:
                    lines.insert(4, "extended_id = true")
                blocks.append("\n".join(lines))
    else:
        dcon = devices.dcon
        if dcon is None:
            raise ValueError("the device set serves no DCON line")
        cfg = dcon.config
        checksum = any(m.checksum for m in cfg.modules)
        inputs = max(len(m.inputs) for m in cfg.modules)
        head = ['[devices.dcon]', 'driver = "dcon"', f'port = "{dcon.serial_port}"', f"baudrate = {cfg.baudrate}",
                f"checksum = {str(checksum).lower()}", f"inputs = {inputs}",
                "period_s = 0.2  # two modules at 9600 baud: 130 ms on the line", "timeout_s = 0.5"]
        blocks = ["\n".join(head)]
        for m in cfg.modules:
            for n, inp in enumerate(m.inputs):
                if not inp.channel:
                    continue
                if inp.scaling == "voltage":
                    (e0, e1), (v0, v1) = inp.eng_range, inp.volt_range
                    scale = (e1 - e0) / (v1 - v0)
                    offset = e0 - v0 * scale
                else:
                    scale, offset = 1.0, 0.0
                blocks.append("\n".join([f"[channels.{inp.channel}]", 'device = "dcon"',
                                         f'unit = "{UNITS.get(inp.channel, "")}"', f"module = {m.address}",
                                         f"input = {n}", f"scale = {_num(scale)}", f"offset = {_num(offset)}"]))
    return "\n\n".join(blocks) + "\n"


def compensation_toml(host: str, port: int, *, enabled: bool = True, limit_um: float = 200.0,
                      max_step_um: float = 2.0, deadband_um: float = 0.1, heartbeat_period_s: float = 1.0,
                      watchdog_s: float = 5.0, on_fault: str = "hold", fault_hold_s: float = 600.0,
                      extra: str = "") -> str:
    """A ``[compensation]`` section for the bundled simulated CNC at ``host:port`` (its default register map)."""
    axes = "\n".join(f"[compensation.axes.{a}]\nregister = {2 * i}\nreadback = {2 * i}\nsign = -1\nunit_um = 0.1\n"
                     f'data_type = "int32"\nword_order = "big"\n' for i, a in enumerate("xyz"))
    return (f"[compensation]\nenabled = {str(enabled).lower()}\nhost = \"{host}\"\nport = {port}\ntimeout_s = 0.5\n"
            f"reconnect_s = 0.5\nenable_coil = 0\nheartbeat_register = 6\nstatus_register = 6\n"
            f"heartbeat_period_s = {heartbeat_period_s!r}\nwatchdog_s = {watchdog_s!r}\nlimit_um = {limit_um!r}\n"
            f"max_step_um = {max_step_um!r}\ndeadband_um = {deadband_um!r}\non_fault = \"{on_fault}\"\n"
            f"fault_hold_s = {fault_hold_s!r}\n{extra}\n{axes}")


def profile_for(devices: DeviceSet, via: str = "adc-tcp", *, base: Path = BUNDLED_PROFILE,
                displacement: bool = False, compensate: bool = False, **compensation: Any) -> str:
    """The bundled profile's text with ``via``'s live device and channels in place of its own.

    The model file is made absolute (it stays next to the bundled profile). With ``displacement`` the
    ADC's displacement channels are read as bursts of whole spindle revolutions. When the set serves the
    CNC, a ``[compensation]`` section points at it: writing only with ``compensate`` (else a dry run), the
    heartbeat fast enough for the CNC's watchdog; ``compensation`` overrides :func:`compensation_toml`'s keys.
    """
    if displacement and not via.startswith("adc"):
        raise ValueError(f"displacement sensors are served by the ADC board only, not via {via!r}")
    text = base.read_text(encoding="utf-8")
    cut = text.find("\n[devices.")
    if cut >= 0:
        # also drop the comment block that introduces the bundled devices
        head = text[:cut].rstrip("\n").split("\n")
        while head and head[-1].startswith("#"):
            head.pop()
        text = "\n".join(head) + "\n"
    model_dir = base.resolve().parent
    lines = []
    section = ""
    for line in text.split("\n"):
        stripped = line.strip()
        if stripped.startswith("["):
            section = stripped
        if section == "[model]" and stripped.startswith("file"):
            name = stripped.split("=", 1)[1].split("#")[0].strip().strip('"')
            line = f'file = "{(model_dir / name).as_posix()}"'
        lines.append(line)
        if displacement and section == "[sampling]" and stripped.startswith("window_s"):
            lines += ['displacement_channels = { x = "x_um", y = "y_um", z = "z_um" }',
                      "burst_s = 3.0", 'burst_speed_channel = "spindle_speed"']
    out = "\n".join(lines).rstrip("\n") + "\n\n"
    out += f"# generated from the running simulated devices ({via})\n" + acquisition_toml(devices, via)
    if devices.cnc is not None:
        host, port = devices.cnc.address
        watchdog_s = devices.config.cnc.heartbeat_timeout_s
        keys = {"watchdog_s": watchdog_s, "heartbeat_period_s": watchdog_s / 5} | compensation
        out += "\n" + compensation_toml(host, port, enabled=compensate, **keys)
    return out
