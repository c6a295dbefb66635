"""The CNC's compensation registers: limits, enable, read-back, heartbeat watchdog, faults.

Time is a ManualClock: the watchdog and the ramp run in clock time, so every expectation below is exact
and no test waits for wall time to pass.
"""

from __future__ import annotations

import struct

import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusIOException
from test_sim_devices_support import WaveSource

from gateway.clock import ManualClock
from simulators.devices import CompensationConfig, DeviceSet, DeviceSetConfig
from simulators.devices.cnc import ACTIVE, HEARTBEAT_OK, LAST_WRITE_REJECTED, RAMPING, WATCHDOG_TRIPPED

ONLY_CNC = {"adc_tcp_port": None, "adc_rtu": None, "can": None, "dcon": None}


@pytest.fixture
def clock():
    return ManualClock(100.0)


@pytest.fixture
def source():
    return WaveSource()


def start(source, clock, **cnc):
    return DeviceSet(source=source, clock=clock,
                     config=DeviceSetConfig(**ONLY_CNC, cnc=CompensationConfig(**cnc))).start()


@pytest.fixture
def cnc(source, clock):
    devices = start(source, clock, drop_ramp_s=0.0, heartbeat_timeout_s=5.0, limit_um=500.0)
    yield devices.cnc
    devices.stop()


@pytest.fixture
def client(cnc):
    client = ModbusTcpClient("127.0.0.1", port=cnc.address[1], timeout=2.0, retries=0)
    assert client.connect()
    yield client
    client.close()


def int32_words(*values, word_order="big"):
    out = []
    for v in values:
        hi, lo = struct.unpack(">HH", struct.pack(">i", v))
        out += [hi, lo] if word_order == "big" else [lo, hi]
    return out


def int32_values(words, word_order="big"):
    pairs = [words[i : i + 2] if word_order == "big" else words[i : i + 2][::-1] for i in range(0, len(words), 2)]
    return [struct.unpack(">i", struct.pack(">HH", *p))[0] for p in pairs]


def readback(client):
    """Applied offsets (counts), status word, trips, read over Modbus."""
    regs = client.read_input_registers(0, count=8, device_id=1).registers
    return int32_values(regs[:6]), regs[6], regs[7]


def um(counts, unit=0.1):
    return {axis: c * unit for axis, c in zip("xyz", counts, strict=True)}


def beat(client, value):
    assert not client.write_register(6, value, device_id=1).isError()


def test_offsets_apply_only_when_enabled_and_read_back(client, source):
    assert source.last_compensation() == {"x": 0.0, "y": 0.0, "z": 0.0}
    write = client.write_registers(0, [*int32_words(123, -456, 789), 1], device_id=1)  # offsets + heartbeat
    assert not write.isError()
    assert int32_values(client.read_holding_registers(0, count=6, device_id=1).registers) == [123, -456, 789]
    applied, status, _ = readback(client)
    assert applied == [0, 0, 0]
    assert not status & ACTIVE
    assert source.last_compensation() == {"x": 0.0, "y": 0.0, "z": 0.0}  # commanded, not enabled

    assert not client.write_coil(0, True, device_id=1).isError()
    applied, status, _ = readback(client)
    assert applied == [123, -456, 789]
    assert status & ACTIVE
    assert status & HEARTBEAT_OK
    assert client.read_coils(0, count=1, device_id=1).bits[0]
    assert client.read_discrete_inputs(0, count=5, device_id=1).bits[:5] == [True, False, False, False, True]
    assert source.last_compensation() == pytest.approx(um([123, -456, 789]))

    # a new command applies at once while enabled
    assert not client.write_registers(2, int32_words(-1000), device_id=1).isError()
    assert readback(client)[0] == [123, -1000, 789]
    assert source.last_compensation() == pytest.approx(um([123, -1000, 789]))


def test_out_of_range_offsets_are_rejected_with_an_exception_and_not_applied(client, source):
    client.write_registers(0, int32_words(10, 20, 30), device_id=1)
    client.write_coil(0, True, device_id=1)
    reply = client.write_registers(0, [*int32_words(10, 5001, 30), 9], device_id=1)  # 500.1 um > 500 um
    assert reply.isError()
    assert reply.exception_code == 3  # illegal data value
    assert int32_values(client.read_holding_registers(0, count=6, device_id=1).registers) == [10, 20, 30]
    assert client.read_holding_registers(6, count=1, device_id=1).registers == [0]  # heartbeat not taken either
    applied, status, _ = readback(client)
    assert applied == [10, 20, 30]
    assert status & LAST_WRITE_REJECTED
    assert source.last_compensation() == pytest.approx(um([10, 20, 30]))
    # the limit itself is allowed, and an accepted write clears the flag
    assert not client.write_registers(0, int32_words(-5000), device_id=1).isError()
    applied, status, _ = readback(client)
    assert applied == [-5000, 20, 30]
    assert not status & LAST_WRITE_REJECTED


def test_half_an_int32_offset_or_an_unknown_register_cannot_be_written(client):
    half = client.write_register(1, 7, device_id=1)
    assert half.isError()
    assert half.exception_code == 2
    unknown = client.write_register(9, 7, device_id=1)
    assert unknown.isError()
    assert unknown.exception_code == 2
    spare_coil = client.write_coil(3, True, device_id=1)
    assert spare_coil.isError()
    assert spare_coil.exception_code == 2


def test_watchdog_drops_offsets_at_once_when_the_heartbeat_stops(client, clock, source, cnc):
    client.write_registers(0, [*int32_words(100, 200, 300), 1], device_id=1)
    client.write_coil(0, True, device_id=1)
    clock.advance(4.0)
    beat(client, 2)
    clock.advance(4.0)  # 8 s since enabling, but only 4 s since the last beat
    beat(client, 2)  # the same value is not a beat
    applied, status, trips = readback(client)
    assert applied == [100, 200, 300]
    assert status & ACTIVE
    assert trips == 0
    clock.advance(1.5)  # 5.5 s since the last change
    applied, status, trips = readback(client)
    assert applied == [0, 0, 0]
    assert status & WATCHDOG_TRIPPED
    assert not status & ACTIVE
    assert not status & HEARTBEAT_OK
    assert trips == 1
    assert not client.read_coils(0, count=1, device_id=1).bits[0]  # the CNC dropped enable itself
    assert source.last_compensation() == {"x": 0.0, "y": 0.0, "z": 0.0}
    # the command stays; writing enable again clears the trip and applies it at once
    assert not client.write_coil(0, True, device_id=1).isError()
    applied, status, trips = readback(client)
    assert applied == [100, 200, 300]
    assert status & ACTIVE
    assert not status & WATCHDOG_TRIPPED
    assert trips == 1


def test_watchdog_trips_without_any_client_asking(cnc, client, clock, source):
    client.write_registers(0, int32_words(50, 60, 70), device_id=1)
    client.write_coil(0, True, device_id=1)
    clock.advance(6.0)
    status = cnc.update()  # what the periodic tick does between requests
    assert status.tripped
    assert source.last_compensation() == {"x": 0.0, "y": 0.0, "z": 0.0}


def test_watchdog_ramps_offsets_to_zero_from_when_the_beat_was_due(source, clock):
    devices = start(source, clock, drop_ramp_s=10.0, heartbeat_timeout_s=5.0)
    client = ModbusTcpClient("127.0.0.1", port=devices.cnc.address[1], timeout=2.0, retries=0)
    try:
        client.write_registers(0, int32_words(1000, -2000, 400), device_id=1)
        client.write_coil(0, True, device_id=1)  # t = 100: watchdog armed
        clock.set(108.0)  # due at 105: 3 s into a 10 s ramp
        applied, status, _ = readback(client)
        assert applied == [700, -1400, 280]
        assert status & WATCHDOG_TRIPPED
        assert status & RAMPING
        assert source.last_compensation() == pytest.approx(um([700, -1400, 280]))
        clock.set(115.0)
        applied, status, _ = readback(client)
        assert applied == [0, 0, 0]
        assert not status & RAMPING
    finally:
        client.close()
        devices.stop()


def test_disabling_ramps_the_same_way(source, clock):
    devices = start(source, clock, drop_ramp_s=4.0)
    client = ModbusTcpClient("127.0.0.1", port=devices.cnc.address[1], timeout=2.0, retries=0)
    try:
        client.write_registers(0, int32_words(400, 800, -1200), device_id=1)
        client.write_coil(0, True, device_id=1)
        client.write_coil(0, False, device_id=1)
        clock.advance(1.0)
        applied, status, _ = readback(client)
        assert applied == [300, 600, -900]
        assert status & RAMPING
        assert not status & WATCHDOG_TRIPPED
    finally:
        client.close()
        devices.stop()


def test_int16_offsets_in_whole_micrometres(source, clock):
    devices = start(source, clock, offset_encoding="int16", offset_unit_um=1.0, limit_um=300.0,
                    heartbeat_address=3, status_address=3)
    client = ModbusTcpClient("127.0.0.1", port=devices.cnc.address[1], timeout=2.0, retries=0)
    try:
        assert not client.write_registers(0, [12, (-34) & 0xFFFF, 56, 1], device_id=1).isError()
        client.write_coil(0, True, device_id=1)
        regs = client.read_input_registers(0, count=5, device_id=1).registers
        assert [struct.unpack(">h", struct.pack(">H", r))[0] for r in regs[:3]] == [12, -34, 56]
        assert regs[3] & ACTIVE
        assert source.last_compensation() == {"x": 12.0, "y": -34.0, "z": 56.0}
        assert client.write_register(1, 301, device_id=1).exception_code == 3
    finally:
        client.close()
        devices.stop()


def test_int32_offsets_low_word_first(source, clock):
    devices = start(source, clock, word_order="little")
    client = ModbusTcpClient("127.0.0.1", port=devices.cnc.address[1], timeout=2.0, retries=0)
    try:
        client.write_registers(0, int32_words(-700, 1, 2, word_order="little"), device_id=1)
        client.write_coil(0, True, device_id=1)
        regs = client.read_input_registers(0, count=6, device_id=1).registers
        assert int32_values(regs, word_order="little") == [-700, 1, 2]
        assert source.last_compensation() == pytest.approx(um([-700, 1, 2]))
    finally:
        client.close()
        devices.stop()


def test_dropped_requests_are_neither_answered_nor_applied(cnc, source):
    client = ModbusTcpClient("127.0.0.1", port=cnc.address[1], timeout=0.3, retries=0)
    try:
        client.write_registers(0, int32_words(10, 10, 10), device_id=1)
        client.write_coil(0, True, device_id=1)
        cnc.faults.drop_replies = True
        with pytest.raises(ModbusIOException):
            client.write_registers(0, int32_words(99, 99, 99), device_id=1)
        cnc.faults.drop_replies = False
        assert readback(client)[0] == [10, 10, 10]
        assert source.last_compensation() == pytest.approx(um([10, 10, 10]))
    finally:
        client.close()


def test_config_is_checked():
    with pytest.raises(ValueError, match="does not fit int16"):
        CompensationConfig(offset_encoding="int16", offset_unit_um=0.01, limit_um=500.0)
    with pytest.raises(ValueError, match="overlaps"):
        CompensationConfig(heartbeat_address=5)
