"""The simulated Modbus ADC board, over TCP and RTU, against pymodbus's own clients.

Values are decoded here independently of the device's encoder (struct on the raw register bytes), and
compared with what the source gives at the clock's time, within the encoding's resolution.
"""

from __future__ import annotations

import struct

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from test_sim_devices_support import SIM_VMC_CHANNELS, WaveSource

from gateway.clock import ManualClock
from gateway.errors import SimulationError
from simulators.devices import (
    DEFAULT_ADC_CONFIG,
    SIM_VMC_ANALOG,
    AdcBoardConfig,
    DeviceSet,
    DeviceSetConfig,
    RegisterChannel,
    RtuTransport,
)

ONLY_ADC = {"can": None, "dcon": None, "cnc": None}


@pytest.fixture
def clock():
    return ManualClock(12.5)


@pytest.fixture
def source():
    return WaveSource()


@pytest.fixture
def devices(source, clock):
    with DeviceSet(source=source, clock=clock, config=DeviceSetConfig(**ONLY_ADC)) as devs:
        yield devs


def tcp_client(device, timeout_s=2.0):
    client = ModbusTcpClient("127.0.0.1", port=device.address[1], timeout=timeout_s, retries=0)
    assert client.connect()
    return client


def rtu_client(device, timeout_s=1.0, **kwargs):
    client = ModbusSerialClient(device.serial_port, baudrate=115200, timeout=timeout_s, retries=0, **kwargs)
    assert client.connect()
    return client


def decode_counts(word, *, signed=True, swap=False):
    raw = word.to_bytes(2, "big")
    if swap:
        raw = raw[::-1]
    return struct.unpack(">h" if signed else ">H", raw)[0]


def counts_to_eng(counts, name):
    (e0, e1), (v0, v1) = SIM_VMC_ANALOG[name].eng_range, SIM_VMC_ANALOG[name].volt_range
    c0, c1 = v0 * 3200, v1 * 3200
    return e0 + (counts - c0) * (e1 - e0) / (c1 - c0)


def check_default_map(client, source, clock, device_id=1):
    expected = source.values(clock.now())
    counts = client.read_input_registers(0, count=9, device_id=device_id)
    floats = client.read_input_registers(100, count=18, device_id=device_id)
    assert not counts.isError()
    assert not floats.isError()
    for i, name in enumerate(SIM_VMC_CHANNELS):
        scale = SIM_VMC_ANALOG[name]
        resolution = (scale.eng_range[1] - scale.eng_range[0]) / ((scale.volt_range[1] - scale.volt_range[0]) * 3200)
        assert counts_to_eng(decode_counts(counts.registers[i]), name) == pytest.approx(
            expected[name], abs=resolution / 2 + 1e-9), name
        as_float = struct.unpack(">f", struct.pack(">HH", *floats.registers[2 * i : 2 * i + 2]))[0]
        assert as_float == pytest.approx(expected[name], rel=1e-6), name


def test_tcp_board_serves_live_values_in_both_encodings(devices, source, clock):
    client = tcp_client(devices.adc_tcp)
    try:
        check_default_map(client, source, clock)
        clock.advance(7.25)  # every channel moves: the board must follow, not repeat
        check_default_map(client, source, clock)
        check_default_map(client, source, clock, device_id=17)  # TCP: any unit id is answered
    finally:
        client.close()


def test_rtu_board_serves_live_values_and_ignores_other_addresses(devices, source, clock):
    client = rtu_client(devices.adc_rtu, timeout_s=0.3)
    try:
        check_default_map(client, source, clock)
        clock.advance(31.0)
        check_default_map(client, source, clock)
        with pytest.raises(ModbusIOException):
            client.read_input_registers(0, count=2, device_id=2)  # someone else's address: silence
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_word_and_byte_order_variants_decode(source, clock):
    variants = {  # (word_order, byte_order): byte permutation of the big-endian float ABCD
        ("big", "big"): (0, 1, 2, 3), ("little", "big"): (2, 3, 0, 1),
        ("big", "little"): (1, 0, 3, 2), ("little", "little"): (3, 2, 1, 0),
    }
    channels = [RegisterChannel(channel="x_velocity", address=10 + 2 * i, encoding="float32", word_order=w,
                                byte_order=b) for i, (w, b) in enumerate(variants)]
    channels += [
        RegisterChannel(channel="x_current", address=0, encoding="int16", eng_range=(-50, 50),
                        counts_range=(-27648, 27648), byte_order="little"),  # S7-style nominal range
        RegisterChannel(channel="spindle_speed", address=1, encoding="uint16", eng_range=(0, 12000),
                        counts_range=(0, 65535)),
    ]
    config = DeviceSetConfig(**ONLY_ADC, adc_rtu=None, adc=AdcBoardConfig(channels=tuple(channels)))
    with DeviceSet(source=source, clock=clock, config=config) as devs:
        client = tcp_client(devs.adc_tcp)
        try:
            expected = source.values(clock.now())
            regs = client.read_input_registers(10, count=8, device_id=1).registers
            for i, order in enumerate(variants.values()):
                wire = b"".join(r.to_bytes(2, "big") for r in regs[2 * i : 2 * i + 2])
                abcd = bytes(wire[order.index(k)] for k in range(4))
                assert struct.unpack(">f", abcd)[0] == pytest.approx(expected["x_velocity"], rel=1e-6), order
            # the word-order-only variant also decodes with pymodbus's own converter
            little = client.convert_from_registers(regs[2:4], client.DATATYPE.FLOAT32, word_order="little")
            assert little == pytest.approx(expected["x_velocity"], rel=1e-6)
            words = client.read_input_registers(0, count=2, device_id=1).registers
            current = decode_counts(words[0], swap=True) * 100 / (2 * 27648)
            assert current == pytest.approx(expected["x_current"], abs=100 / (2 * 27648))
            speed = decode_counts(words[1], signed=False) * 12000 / 65535
            assert speed == pytest.approx(expected["spindle_speed"], abs=12000 / 65535)
        finally:
            client.close()


def test_unmapped_addresses_writes_and_other_tables_are_refused(devices):
    client = tcp_client(devices.adc_tcp)
    try:
        gap = client.read_input_registers(50, count=1, device_id=1)
        assert gap.isError()
        assert gap.exception_code == 2
        write = client.write_register(0, 5, device_id=1)
        assert write.isError()
        assert write.exception_code == 1
        holding = client.read_holding_registers(0, count=1, device_id=1)
        assert holding.isError()
        assert holding.exception_code == 1
    finally:
        client.close()


def test_holding_mirror_serves_the_same_registers(source, clock):
    adc = AdcBoardConfig(channels=DEFAULT_ADC_CONFIG.channels, holding_mirror=True)
    with DeviceSet(source=source, clock=clock, config=DeviceSetConfig(**ONLY_ADC, adc_rtu=None, adc=adc)) as devs:
        client = tcp_client(devs.adc_tcp)
        try:
            held = client.read_holding_registers(0, count=9, device_id=1).registers
            assert held == client.read_input_registers(0, count=9, device_id=1).registers
        finally:
            client.close()


def test_forced_out_of_range_value_saturates_counts_not_floats(devices):
    devices.adc_tcp.faults.force("x_velocity", 1e6)
    devices.adc_tcp.faults.force("y_velocity", -1e6)
    client = tcp_client(devices.adc_tcp)
    try:
        counts = client.read_input_registers(3, count=2, device_id=1).registers
        assert [decode_counts(c) for c in counts] == [32767, -32768]
        floats = client.read_input_registers(106, count=2, device_id=1).registers
        assert struct.unpack(">f", struct.pack(">HH", *floats))[0] == 1e6
    finally:
        client.close()


def test_frozen_channel_stops_moving_until_released(devices, source, clock):
    client = tcp_client(devices.adc_tcp)
    try:
        before = client.read_input_registers(0, count=9, device_id=1).registers
        devices.adc_tcp.faults.freeze("z_current")
        clock.advance(13.0)
        stuck = client.read_input_registers(0, count=9, device_id=1).registers
        assert stuck[8] == before[8]  # z_current stuck
        assert stuck[:8] != before[:8]  # the others move on
        devices.adc_tcp.faults.release("z_current")
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_dropped_replies_time_out_then_recover(devices, source, clock):
    client = tcp_client(devices.adc_tcp, timeout_s=0.3)
    try:
        devices.adc_tcp.faults.drop_replies = True
        with pytest.raises(ModbusIOException):
            client.read_input_registers(0, count=9, device_id=1)
        assert devices.adc_tcp.faults.counts["dropped"] == 1
        devices.adc_tcp.faults.drop_replies = False
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_delayed_replies_miss_a_short_timeout_and_meet_a_long_one(devices, source, clock):
    devices.adc_tcp.faults.reply_delay_s = 0.6
    impatient = tcp_client(devices.adc_tcp, timeout_s=0.2)
    patient = tcp_client(devices.adc_tcp, timeout_s=5.0)
    try:
        with pytest.raises(ModbusIOException):
            impatient.read_input_registers(0, count=9, device_id=1)
        check_default_map(patient, source, clock)
        assert devices.adc_tcp.faults.counts["delayed"] >= 3
    finally:
        impatient.close()
        patient.close()


def crc16(frame: bytes) -> bytes:
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def test_rtu_corrupt_reply_has_a_bad_crc_and_is_refused(devices, source, clock):
    received = []

    def trace(sending, data):
        if not sending:
            received.append(bytes(data))
        return data

    client = rtu_client(devices.adc_rtu, timeout_s=0.3, trace_packet=trace)
    try:
        devices.adc_rtu.faults.corrupt_replies = True
        with pytest.raises(ModbusIOException):
            client.read_input_registers(0, count=4, device_id=1)
        frame = max(received, key=len)
        assert len(frame) == 3 + 8 + 2
        assert frame[:3] == bytes([1, 4, 8])
        assert crc16(frame[:-2]) != frame[-2:]  # ...with a CRC that does not match
        devices.adc_rtu.faults.corrupt_replies = False
        client.close()  # the refused frame may linger in the client's buffer: start clean, as a driver would
        client = rtu_client(devices.adc_rtu, timeout_s=0.3)
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_tcp_corrupt_and_garbage_replies_are_refused(devices, source, clock):
    for fault in ("corrupt_replies", "garbage_replies"):
        client = tcp_client(devices.adc_tcp, timeout_s=0.3)
        try:
            setattr(devices.adc_tcp.faults, fault, True)
            with pytest.raises((ModbusIOException, ConnectionException)):
                client.read_input_registers(0, count=9, device_id=1)
            setattr(devices.adc_tcp.faults, fault, False)
        finally:
            client.close()
    assert devices.adc_tcp.faults.counts["corrupted"] == 1
    assert devices.adc_tcp.faults.counts["garbage"] == 1
    client = tcp_client(devices.adc_tcp)
    try:
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_rtu_dropped_request_times_out_then_recovers(devices, source, clock):
    client = rtu_client(devices.adc_rtu, timeout_s=0.3)
    try:
        devices.adc_rtu.faults.drop_replies = True
        with pytest.raises(ModbusIOException):
            client.read_input_registers(0, count=4, device_id=1)
        assert devices.adc_rtu.faults.counts["dropped"] == 1
        devices.adc_rtu.faults.drop_replies = False
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_rtu_garbage_reply_is_refused(devices):
    client = rtu_client(devices.adc_rtu, timeout_s=0.3)
    try:
        devices.adc_rtu.faults.garbage_replies = True
        with pytest.raises(ModbusIOException):
            client.read_input_registers(0, count=4, device_id=1)
        assert devices.adc_rtu.faults.counts["garbage"] == 1
    finally:
        client.close()


def test_tcp_disconnect_is_seen_and_the_client_reconnects(devices, source, clock):
    client = tcp_client(devices.adc_tcp)
    try:
        check_default_map(client, source, clock)
        devices.adc_tcp.disconnect_clients()
        # the closed connection shows as end-of-stream, or as a reset when the request crossed the close:
        # pymodbus wraps the first and lets the second through, so a driver must handle both
        with pytest.raises((ConnectionException, ConnectionResetError)):
            client.read_input_registers(0, count=9, device_id=1)
        # after a reset the sync client keeps its dead socket: close it, as a driver should on any error
        client.close()
        check_default_map(client, source, clock)  # reconnects on the next call
    finally:
        client.close()


def test_rtu_disconnect_is_seen_and_the_same_path_works_again(devices, source, clock):
    path = devices.adc_rtu.serial_port
    client = rtu_client(devices.adc_rtu)
    try:
        check_default_map(client, source, clock)
        devices.adc_rtu.disconnect_clients()
        with pytest.raises(ConnectionException):
            client.read_input_registers(0, count=9, device_id=1)
    finally:
        client.close()
    assert devices.adc_rtu.serial_port == path
    client = rtu_client(devices.adc_rtu)
    try:
        check_default_map(client, source, clock)
    finally:
        client.close()


def test_rtu_at_a_slow_baud_rate_still_answers(source, clock):
    config = DeviceSetConfig(**ONLY_ADC, adc_tcp_port=None, adc_rtu=RtuTransport(baudrate=9600))
    with DeviceSet(source=source, clock=clock, config=config) as devs:
        client = rtu_client(devs.adc_rtu)
        try:
            check_default_map(client, source, clock)
        finally:
            client.close()


def test_map_naming_a_channel_the_machine_lacks_is_refused_before_starting(clock):
    source = WaveSource(channels=("spindle_speed",))
    adc = AdcBoardConfig(channels=(RegisterChannel(channel="spindle_sped", address=0),))
    with pytest.raises(SimulationError, match='no channel "spindle_sped" \\(did you mean "spindle_speed"\\?\\)'):
        DeviceSet(source=source, clock=clock, config=DeviceSetConfig(**ONLY_ADC, adc=adc))


def test_register_map_is_checked():
    with pytest.raises(ValueError, match="register 1 holds both"):
        AdcBoardConfig(channels=(RegisterChannel(channel="a", address=0, encoding="float32"),
                                 RegisterChannel(channel="b", address=1)))
    with pytest.raises(ValueError, match="encoding"):
        RegisterChannel(channel="a", address=0, encoding="int8")
    with pytest.raises(ValueError, match="counts_range"):
        RegisterChannel(channel="a", address=0, encoding="uint16", counts_range=(-1, 100))
