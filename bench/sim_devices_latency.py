"""Request latency of the simulated devices on loopback, with pymodbus/pyserial/python-can clients.

    .venv/bin/python bench/sim_devices_latency.py

Prints median and p99 per request (wall time, one client per device, in this process) and the frame
rate the CAN module holds. Figures, not asserts: they depend on the machine.
"""

from __future__ import annotations

import math
import statistics
import time

import can
import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from gateway.clock import ScaledClock
from simulators.devices import CanModuleConfig, DeviceSet, DeviceSetConfig, RtuTransport
from simulators.devices.can_module import DEFAULT_CAN_CONFIG
from simulators.devices.dcon import DEFAULT_DCON_CONFIG, DconLineConfig

CHANNELS = ("spindle_speed", "spindle_i1", "spindle_i2", "x_velocity", "y_velocity", "z_velocity",
            "x_current", "y_current", "z_current")


class Sines:
    """A LiveSource: one sine per channel."""

    def channel_names(self):
        return CHANNELS

    def values(self, t):
        return {name: 10.0 * math.sin(t / (i + 1)) for i, name in enumerate(CHANNELS)}

    def set_compensation(self, offsets_um):
        pass


def timed(fn, n):
    samples = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    samples.sort()
    return statistics.median(samples) * 1e3, samples[int(0.99 * (len(samples) - 1))] * 1e3


def report(label, n, figures):
    print(f"{label:<52} n={n:<5} median {figures[0]:7.3f} ms   p99 {figures[1]:7.3f} ms")


def modbus(line_time: bool, baudrate: int) -> None:
    config = DeviceSetConfig(adc_rtu=RtuTransport(baudrate=baudrate, simulate_line_time=line_time), can=None,
                             dcon=None)
    with DeviceSet(source=Sines(), clock=ScaledClock(60.0), config=config) as devs:
        if line_time and baudrate == 115200:
            tcp = ModbusTcpClient("127.0.0.1", port=devs.adc_tcp.address[1], timeout=2, retries=0)
            tcp.connect()
            report("ADC TCP, read 9 input registers", 2000,
                   timed(lambda: tcp.read_input_registers(0, count=9, device_id=1), 2000))
            report("ADC TCP, read 18 registers (9 float32)", 2000,
                   timed(lambda: tcp.read_input_registers(100, count=18, device_id=1), 2000))
            tcp.close()
            cnc = ModbusTcpClient("127.0.0.1", port=devs.cnc.address[1], timeout=2, retries=0)
            cnc.connect()
            report("CNC TCP, write 3 int32 offsets + heartbeat", 1000,
                   timed(lambda: cnc.write_registers(0, [0, 1, 0, 2, 0, 3, 4], device_id=1), 1000))
            report("CNC TCP, read back offsets + status", 1000,
                   timed(lambda: cnc.read_input_registers(0, count=8, device_id=1), 1000))
            cnc.close()
        rtu = ModbusSerialClient(devs.adc_rtu.serial_port, baudrate=baudrate, timeout=2, retries=0)
        rtu.connect()
        n = 300
        report(f"ADC RTU {baudrate} baud, line time {'on' if line_time else 'off'}, 9 registers", n,
               timed(lambda: rtu.read_input_registers(0, count=9, device_id=1), n))
        rtu.close()


def dcon(baudrate: int) -> None:
    line = DconLineConfig(modules=DEFAULT_DCON_CONFIG.modules, baudrate=baudrate)
    config = DeviceSetConfig(adc_tcp_port=None, adc_rtu=None, can=None, cnc=None, dcon=line)
    with DeviceSet(source=Sines(), clock=ScaledClock(60.0), config=config) as devs, \
            serial.Serial(devs.dcon.serial_port, baudrate=baudrate, timeout=2) as port:
        def ask():
            port.write(b"#01\r")
            assert port.read_until(b"\r").startswith(b">")

        n = 30 if baudrate < 100000 else 300
        report(f"DCON {baudrate} baud, #01 (8 inputs, 58-byte answer)", n, timed(ask, n))


def can_rate(slcan: bool) -> None:
    module = CanModuleConfig(frames=DEFAULT_CAN_CONFIG.frames, period_s=0.002)
    config = DeviceSetConfig(adc_tcp_port=None, adc_rtu=None, dcon=None, cnc=None, can=module,
                             can_slcan=slcan, can_virtual_channel=None if slcan else "bench")
    with DeviceSet(source=Sines(), clock=ScaledClock(60.0), config=config) as devs:
        bus = (can.Bus(interface="slcan", channel=devs.can.slcan_port, bitrate=500000, sleep_after_open=0)
               if slcan else can.Bus(interface="virtual", channel="bench"))
        with bus:
            bus.recv(timeout=2)
            t0, count = time.perf_counter(), 0
            while time.perf_counter() - t0 < 2.0:
                if bus.recv(timeout=1) is not None:
                    count += 1
            rate = count / (time.perf_counter() - t0)
        print(f"CAN {'slcan' if slcan else 'virtual'}, 3 frames every 2 ms (1500/s wanted): "
              f"{rate:.0f} frames/s received, {devs.can.missed_periods} periods skipped")


if __name__ == "__main__":
    modbus(True, 115200)
    modbus(False, 115200)
    modbus(True, 9600)
    dcon(9600)
    dcon(115200)
    can_rate(False)
    can_rate(True)
