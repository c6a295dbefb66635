"""The simulated machine behind its devices: real clients read the machine's live values, and the CNC's
compensation registers move the machine's tool-to-table error."""

from __future__ import annotations

import struct

import pytest
from pymodbus.client import ModbusTcpClient

from gateway.clock import ManualClock
from simulators.devices import DeviceSetConfig, serve
from simulators.machine import LiveMachine

MINUTE = 60.0


def float32(regs: list[int]) -> float:
    return struct.unpack(">f", struct.pack(">HH", *regs))[0]


def int32_regs(value_01um: int) -> list[int]:
    return list(struct.unpack(">HH", struct.pack(">i", value_01um)))


@pytest.fixture
def running():
    """spindle-1000rpm: 30 min idle, then 1000 rpm; the clock stands at 45 min, in the heating phase."""
    clock = ManualClock(45 * MINUTE)
    machine = LiveMachine("spindle-1000rpm", clock=clock)
    config = DeviceSetConfig(adc_rtu=None, can=None, dcon=None)
    with serve(machine, clock, config) as devices:
        yield machine, clock, devices


def client(address) -> ModbusTcpClient:
    c = ModbusTcpClient(address[0], port=address[1], timeout=2.0, retries=0)
    assert c.connect()
    return c


def test_adc_board_serves_the_machines_live_signals(running):
    machine, clock, devices = running
    c = client(devices.adc_tcp.address)
    try:
        rr = c.read_input_registers(100, count=18, device_id=1)
        assert not rr.isError()
        speed, _, _, _, _, _, _, _, z_current = (float32(rr.registers[k:k + 2]) for k in range(0, 18, 2))
        live = machine.values(clock.now())
        assert speed == pytest.approx(1000.0, abs=1.0)
        assert speed == pytest.approx(live["spindle_speed"], rel=1e-6)
        assert abs(z_current) > 1.0  # Z holds the head against gravity
        counts = c.read_input_registers(0, count=1, device_id=1).registers[0]
        assert counts * 15000 / 32000 == pytest.approx(live["spindle_speed"], abs=0.5)  # int16, 0.47 rpm/count
    finally:
        c.close()


def test_cnc_offsets_move_the_machines_tool_to_table_error(running):
    machine, clock, devices = running
    true = machine.true_displacement_um(clock.now())
    assert true["z"] < -3.0  # 15 min into the 1000 rpm run the head has grown
    wanted = {"x": -true["x"], "y": -true["y"], "z": -true["z"]}
    c = client(devices.cnc.address)
    try:
        regs = [r for a in "xyz" for r in int32_regs(round(wanted[a] * 10))]
        assert not c.write_registers(0, values=[*regs, 1], device_id=1).isError()  # offsets + a heartbeat
        assert not c.write_coil(0, True, device_id=1).isError()
        back = c.read_input_registers(0, count=6, device_id=1).registers
        applied = [struct.unpack(">i", struct.pack(">HH", *back[k:k + 2]))[0] / 10 for k in (0, 2, 4)]
        assert applied == pytest.approx([wanted[a] for a in "xyz"], abs=0.051)
    finally:
        c.close()
    left = machine.residual_um(clock.now())
    assert max(abs(v) for v in left.values()) < 0.06  # only the 0.1 um register resolution remains
    assert machine.compensation_log[-1][1]["z"] == pytest.approx(wanted["z"], abs=0.051)
