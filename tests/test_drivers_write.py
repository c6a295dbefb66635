"""The driver base's write hook (``Driver.write``), through the Modbus TCP driver to the simulated CNC.

The base owns writes as it owns reads: a refusal leaves the link open, any other failure closes it and
the next call reconnects; every message names the device and the write.
"""

from __future__ import annotations

import pytest
from test_sim_devices_support import WaveSource

from drivers.base import Driver, backoff_delay_s
from drivers.modbus_common import RegisterAddress, RegisterWrite
from drivers.modbus_tcp import ModbusTcpDriver, ModbusTcpOptions
from gateway.clock import ManualClock
from gateway.errors import DeviceRefused, DeviceTimeout, DriverError
from simulators.devices import CompensationConfig, DeviceSet, DeviceSetConfig
from simulators.devices.cnc import ACTIVE

ONLY_CNC = {"adc_tcp_port": None, "adc_rtu": None, "can": None, "dcon": None}
#: the simulated CNC: offsets int32 at holding 0..5, heartbeat holding 6, enable coil 0; applied offsets at
#: input registers 0..5, the status word at input register 6
OFFSETS = RegisterWrite(function=16, address=0, label="offsets")


@pytest.fixture
def cnc():
    clock = ManualClock(100.0)
    devices = DeviceSet(source=WaveSource(), clock=clock, config=DeviceSetConfig(
        **ONLY_CNC, cnc=CompensationConfig(drop_ramp_s=0.0, heartbeat_timeout_s=1e6, limit_um=500.0))).start()
    channels = [(f"{a}_applied", RegisterAddress(address=2 * i, data_type="int32")) for i, a in enumerate("xyz")]
    channels.append(("status", RegisterAddress(address=6, data_type="uint16")))
    driver = ModbusTcpDriver(name="cnc", channels=channels, clock=clock,
                             options=ModbusTcpOptions(host="127.0.0.1", port=devices.cnc.address[1], timeout_s=0.3))
    yield devices.cnc, driver
    driver.close()
    devices.stop()


def words(*counts):
    return [w for c in counts for w in ((c >> 16) & 0xFFFF, c & 0xFFFF)]


def test_writes_of_a_block_a_register_and_a_coil_reach_the_device(cnc):
    _, driver = cnc
    driver.write(OFFSETS, words(123, -456, 789))
    driver.write(RegisterWrite(function=6, address=6, label="heartbeat"), 1)
    driver.write(RegisterWrite(function=5, address=0, label="enable"), True)
    reading = driver.read()
    assert reading.values[:3] == (123.0, -456.0, 789.0)
    assert int(reading.values[3]) & ACTIVE
    assert driver.read_registers(0, 2, function=3) == words(123)


def test_a_refused_write_names_the_device_and_the_write_and_leaves_the_link_open(cnc):
    _, driver = cnc
    with pytest.raises(DeviceRefused) as err:
        driver.write(OFFSETS, words(10, 5001, 30))  # 500.1 um beyond the CNC's 500 um limit
    assert str(err.value) == ('device "cnc" (Modbus TCP): offsets fc16 0..5 refused with exception 3 '
                              "(illegal data value)")
    assert driver.is_open  # the device answered: no reconnect needed
    driver.write(RegisterWrite(function=6, address=6), 2)  # and the same link writes on


def test_a_silent_device_times_out_closes_the_link_and_the_next_write_reconnects(cnc):
    server, driver = cnc
    driver.write(RegisterWrite(function=6, address=6), 1)
    server.faults.drop_replies = True
    with pytest.raises(DeviceTimeout) as err:
        driver.write(RegisterWrite(function=6, address=6, label="heartbeat"), 2)
    assert str(err.value).startswith('device "cnc" (Modbus TCP): no valid answer to heartbeat fc6 6 within 0.3 s')
    assert not driver.is_open
    server.faults.drop_replies = False
    driver.write(RegisterWrite(function=6, address=6), 3)
    assert driver.is_open
    assert driver.read_registers(6, 1, function=3) == [3]


def test_a_dropped_connection_is_one_failed_write_then_a_reconnect(cnc):
    server, driver = cnc
    driver.write(RegisterWrite(function=6, address=6), 1)
    server.disconnect_clients()
    failures = []
    for value in (2, 3):
        try:
            driver.write(RegisterWrite(function=6, address=6), value)
        except DriverError as exc:
            failures.append((str(exc), driver.is_open))
    # pymodbus notices the reset on the first write after it, or reconnects before it: never both writes fail
    assert len(failures) <= 1
    for message, is_open in failures:
        assert message.startswith('device "cnc" (Modbus TCP): ')
        assert not is_open
    driver.write(RegisterWrite(function=6, address=6), 4)
    assert driver.read_registers(6, 1, function=3) == [4]


class _ReadOnly(Driver):
    """The smallest driver: reads a constant, never overrides the write hook."""

    @classmethod
    def parse_device_options(cls, table):
        return None

    @classmethod
    def parse_channel_address(cls, table):
        return None

    def _connect(self):
        pass

    def _read_raw(self):
        return [1.0], [0]

    def _disconnect(self):
        pass


def test_a_driver_that_does_not_write_says_so_naming_the_device():
    with _ReadOnly(name="board", options=None, channels=[("a", None)]) as driver, \
            pytest.raises(DriverError, match=r'^device "board" \(device\): this driver does not write$'):
        driver.write("anything", 1)


def test_a_write_target_is_a_modbus_write_function():
    with pytest.raises(ValueError, match=r"function 5, 6 or 16\. Got 3"):
        RegisterWrite(function=3, address=0)


def test_the_back_off_doubles_per_failure_up_to_its_cap():
    options = ModbusTcpOptions(host="h", backoff_s=1.5, backoff_max_s=10.0)
    assert [backoff_delay_s(options, n) for n in (-1, 0, 1, 2, 3, 100)] == [1.5, 1.5, 3.0, 6.0, 10.0, 10.0]
