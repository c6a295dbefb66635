"""The simulated CAN analog-input module: python-can clients on the virtual bus and over slcan.

Frames are decoded here bit by bit (Intel order), independently of the module's encoder. The slcan
test runs its client in another process, to show the transport crosses processes.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import can
import pytest
import serial
from test_sim_devices_support import WaveSource, wait_for

from gateway.clock import ManualClock
from simulators.devices import DEFAULT_CAN_CONFIG, CanFrame, CanModuleConfig, CanSignal, DeviceSet, DeviceSetConfig

ONLY_CAN = {"adc_tcp_port": None, "adc_rtu": None, "dcon": None, "cnc": None}
RECV_TIMEOUT_S = 2.0


@pytest.fixture
def clock():
    return ManualClock(42.0)


@pytest.fixture
def source():
    return WaveSource()


@pytest.fixture
def devices(source, clock, request):
    channel = f"cncgw-test-{request.node.name}"  # one virtual bus per test: no cross-talk
    config = DeviceSetConfig(**ONLY_CAN, can_virtual_channel=channel)
    with DeviceSet(source=source, clock=clock, config=config) as devs:
        yield devs


@pytest.fixture
def bus(devices):
    with can.Bus(interface="virtual", channel=devices.can.virtual_channel) as bus:
        yield bus


def decode(frame: CanFrame, data: bytes) -> dict[str, float]:
    """Intel-order decoding, bit by bit."""
    out = {}
    for s in frame.signals:
        raw = 0
        for k in range(s.length_bits):
            bit = s.start_bit + k
            raw |= ((data[bit // 8] >> (bit % 8)) & 1) << k
        if s.signed and raw & (1 << (s.length_bits - 1)):
            raw -= 1 << s.length_bits
        out[s.channel] = raw * s.scale + s.offset
    return out


FRAMES = {f.frame_id: f for f in DEFAULT_CAN_CONFIG.frames}


def receive_all_frames(bus, ids=tuple(FRAMES)):
    """The next frame of every id (fails after a generous limit)."""
    got = {}
    for _ in range(200):
        msg = bus.recv(timeout=RECV_TIMEOUT_S)
        assert msg is not None, "the module fell silent"
        if msg.arbitration_id in ids:
            got[msg.arbitration_id] = msg
        if len(got) == len(ids):
            return got
    raise AssertionError(f"not every frame came: {sorted(got)}")


def drain(bus):
    while bus.recv(timeout=0) is not None:
        pass


def check_values(messages, source, clock, config=DEFAULT_CAN_CONFIG):
    expected = source.values(clock.now())
    frames = {f.frame_id: f for f in config.frames}
    for frame_id, msg in messages.items():
        frame = frames[frame_id]
        assert msg.dlc == frame.dlc
        for s in frame.signals:
            got = decode(frame, bytes(msg.data))[s.channel]
            assert got == pytest.approx(expected[s.channel], abs=abs(s.scale) / 2 + 1e-9), s.channel


def test_virtual_bus_carries_live_values(devices, bus, source, clock):
    check_values(receive_all_frames(bus), source, clock)
    clock.advance(17.0)
    wait_for(lambda: devices.can.frames_sent > 10)
    drain(bus)  # frames sampled before the clock moved
    check_values(receive_all_frames(bus), source, clock)


def test_signal_packing_offsets_signs_and_saturation(source, clock, request):
    frame = CanFrame(frame_id=0x1ABCDE, extended_id=True, dlc=6, signals=(
        CanSignal(channel="z_current", start_bit=3, length_bits=11, signed=True, scale=0.05, offset=2.0),
        CanSignal(channel="spindle_speed", start_bit=14, length_bits=13, signed=False, scale=2.0),
        CanSignal(channel="x_velocity", start_bit=30, length_bits=8, signed=True, scale=1.0),  # saturates
    ))
    config = CanModuleConfig(frames=(frame,), period_s=0.005)
    settings = DeviceSetConfig(**ONLY_CAN, can=config, can_slcan=False, can_virtual_channel=request.node.name)
    with DeviceSet(source=source, clock=clock, config=settings) as devs, \
            can.Bus(interface="virtual", channel=devs.can.virtual_channel) as bus:
        msg = receive_all_frames(bus, ids=(0x1ABCDE,))[0x1ABCDE]
        assert msg.is_extended_id
        values = decode(frame, bytes(msg.data))
        expected = source.values(clock.now())
        assert values["z_current"] == pytest.approx(expected["z_current"], abs=0.025 + 1e-9)
        assert values["spindle_speed"] == pytest.approx(expected["spindle_speed"], abs=1.0 + 1e-9)
        assert abs(expected["x_velocity"]) > 128
        assert values["x_velocity"] == (127 if expected["x_velocity"] > 0 else -128)


def test_frozen_and_forced_values(devices, bus, source, clock):
    devices.can.faults.freeze("spindle_speed")
    devices.can.faults.force("x_current", -1000.0)  # beyond the 16-bit signal's -327.68 A
    wait_for(lambda: devices.can.frames_sent > 10)  # the freeze has taken its value
    before = decode(FRAMES[0x181], bytes(receive_all_frames(bus, ids=(0x181,))[0x181].data))
    clock.advance(100.0)
    wait_for(lambda: devices.can.frames_sent > 30)
    drain(bus)
    got = receive_all_frames(bus)
    spindle = decode(FRAMES[0x181], bytes(got[0x181].data))
    assert spindle["spindle_speed"] == before["spindle_speed"]
    assert spindle["spindle_i1"] != before["spindle_i1"]
    assert decode(FRAMES[0x381], bytes(got[0x381].data))["x_current"] == pytest.approx(-327.68)


def test_dropped_frames_leave_the_bus_silent(devices, bus):
    devices.can.faults.drop_replies = True
    wait_for(lambda: devices.can.faults.counts["dropped"] >= 2)
    drain(bus)
    assert bus.recv(timeout=0.3) is None
    devices.can.faults.drop_replies = False
    assert bus.recv(timeout=RECV_TIMEOUT_S) is not None


def test_delayed_frames_leave_a_gap_then_arrive(devices, bus):
    devices.can.faults.reply_delay_s = 2.0
    wait_for(lambda: devices.can.faults.counts["delayed"] >= 1)
    drain(bus)
    assert bus.recv(timeout=0.3) is None  # nothing for ~2 s...
    assert bus.recv(timeout=10.0) is not None  # ...then the late frames


def test_corrupt_and_garbage_frames_on_the_virtual_bus(devices, bus):
    devices.can.faults.corrupt_replies = True
    wait_for(lambda: devices.can.faults.counts["corrupted"] >= 3)
    drain(bus)
    msg = bus.recv(timeout=RECV_TIMEOUT_S)
    assert msg.dlc == 7  # one byte short: a decoder expecting 8 must refuse it
    devices.can.faults.corrupt_replies = False
    devices.can.faults.garbage_replies = True
    wait_for(lambda: devices.can.faults.counts["garbage"] >= 3)
    drain(bus)
    got = receive_all_frames(bus)
    spindle = decode(FRAMES[0x181], bytes(got[0x181].data))
    assert got[0x181].dlc == 8
    assert spindle != decode(FRAMES[0x181], FRAMES[0x181].encode(WaveSource().values(42.0)))


def slcan_bus(path):
    return can.Bus(interface="slcan", channel=path, bitrate=500000, sleep_after_open=0, timeout=0.05)


def test_slcan_client_in_another_process_receives_the_frames(devices, source, clock):
    script = textwrap.dedent("""
        import json, sys, can
        bus = can.Bus(interface="slcan", channel=sys.argv[1], bitrate=500000, sleep_after_open=0)
        got = {}
        try:
            for _ in range(300):
                msg = bus.recv(timeout=2.0)
                if msg is None:
                    break
                got[msg.arbitration_id] = msg.data.hex()
                if len(got) == 3:
                    break
        finally:
            bus.shutdown()
        print(json.dumps(got))
    """)
    done = subprocess.run([sys.executable, "-c", script, devices.can.slcan_port], capture_output=True, text=True,
                          timeout=60, check=True)
    frames = json.loads(done.stdout)
    messages = {int(k): can.Message(arbitration_id=int(k), data=bytes.fromhex(v)) for k, v in frames.items()}
    assert set(messages) == set(FRAMES)
    check_values(messages, source, clock)


def test_slcan_frames_flow_only_while_the_channel_is_open(devices):
    with serial.Serial(devices.can.slcan_port, timeout=0.3) as port:
        assert port.read(64) == b""  # closed: the adapter keeps quiet
        port.write(b"V\r")
        assert port.read_until(b"\r") == b"V1013\r"
        port.write(b"S6\rO\r")
        assert port.read(2) == b"\r\r"  # ok, ok
        line = port.read_until(b"\r")
        assert line[:1] == b"t"
        assert int(line[1:4], 16) in FRAMES
        port.write(b"S4\r")
        assert b"\a" in port.read_until(b"\a")  # no bitrate change while open
        port.write(b"C\r")
        wait_for(lambda: port.read(4096) == b"")  # flushes what was on the way, then silence


def first_error(bus, limit=300):
    """Receive until the client raises; return what it raised."""
    for _ in range(limit):
        try:
            bus.recv(timeout=RECV_TIMEOUT_S)
        except Exception as exc:
            return exc
    raise AssertionError("the client never noticed the fault")


def test_slcan_corrupt_line_is_refused_by_the_client(devices):
    with slcan_bus(devices.can.slcan_port) as bus:
        assert bus.recv(timeout=RECV_TIMEOUT_S) is not None
        devices.can.faults.corrupt_replies = True
        exc = first_error(bus)
        devices.can.faults.corrupt_replies = False
    assert isinstance(exc, ValueError)
    assert "non-hexadecimal" in str(exc)


def test_slcan_garbage_is_refused_by_the_client(devices):
    with slcan_bus(devices.can.slcan_port) as bus:
        assert bus.recv(timeout=RECV_TIMEOUT_S) is not None
        devices.can.faults.garbage_replies = True
        exc = first_error(bus)
        devices.can.faults.garbage_replies = False
    assert isinstance(exc, can.CanOperationError)
    assert isinstance(exc.__cause__ or exc.__context__, UnicodeDecodeError)


def test_slcan_disconnect_is_seen_and_the_same_path_works_again(devices, source, clock):
    path = devices.can.slcan_port
    bus = slcan_bus(path)
    try:
        assert bus.recv(timeout=RECV_TIMEOUT_S) is not None
        devices.can.disconnect_clients()
        assert isinstance(first_error(bus), can.CanOperationError)
    finally:
        with pytest.raises(can.CanOperationError):
            bus.shutdown()  # its "C" goes to a port that is gone
    assert devices.can.slcan_port == path
    with slcan_bus(path) as bus:
        check_values(receive_all_frames(bus), source, clock)


def test_module_map_is_checked():
    with pytest.raises(ValueError, match="overlaps"):
        CanFrame(frame_id=1, signals=(CanSignal(channel="a", start_bit=0, length_bits=9),
                                      CanSignal(channel="b", start_bit=8, length_bits=8)))
    with pytest.raises(ValueError, match="beyond byte 2"):
        CanFrame(frame_id=1, dlc=2, signals=(CanSignal(channel="a", start_bit=4, length_bits=16),))
    with pytest.raises(ValueError, match="out of range"):
        CanFrame(frame_id=0x800, signals=())
