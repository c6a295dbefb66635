"""The driver registry: every built-in driver loads; third-party drivers come through the entry-point group,
imported only when used, and a missing dependency breaks only its own driver, with a message naming it."""

from __future__ import annotations

import textwrap

import pytest

from drivers import registry
from drivers.base import Driver
from gateway.errors import DriverError, ProfileError
from gateway.profile import load_profile


@pytest.mark.parametrize("name", sorted(registry.BUILTIN))
def test_every_registered_driver_loads(name):
    cls = registry.load(name)
    assert issubclass(cls, Driver)
    assert cls.__module__ == f"drivers.{name}"  # the registry key equals the module name
    assert cls.__name__.endswith("Driver")
    assert cls.kind != Driver.kind


def test_names_lists_the_builtin_drivers_first():
    assert registry.names()[:5] == ["modbus_tcp", "modbus_rtu", "can", "dcon", "opcua"]


def test_unknown_driver_is_named_with_a_suggestion():
    with pytest.raises(DriverError) as err:
        registry.load("modbus_tpc")
    assert str(err.value).startswith('unknown driver "modbus_tpc" (did you mean "modbus_tcp"?); known: modbus_tcp,')


@pytest.fixture
def third_party(tmp_path, monkeypatch):
    """An installed distribution with two drivers in the entry-point group: one fine, one whose SDK is missing."""
    dist = tmp_path / "vendor_drivers-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: vendor-drivers\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(textwrap.dedent("""\
        [cncgw.drivers]
        vendor_ok = vendor_ok_driver:VendorOkDriver
        vendor_sdk = vendor_sdk_driver:VendorSdkDriver
        modbus_tcp = vendor_ok_driver:VendorOkDriver
        """))
    (tmp_path / "vendor_ok_driver.py").write_text(textwrap.dedent("""\
        from drivers.base import Driver, Quality

        class VendorOkDriver(Driver):
            kind = "vendor"

            @classmethod
            def parse_device_options(cls, table):
                return {"gain": table.float("gain", default=1.0)}

            @classmethod
            def parse_channel_address(cls, table):
                return table.int("slot", min=0)

            def _connect(self):
                pass

            def _read_raw(self):
                return [float(a) * self.options["gain"] for a in self.addresses], [Quality.GOOD] * len(self.addresses)

            def _disconnect(self):
                pass
        """))
    (tmp_path / "vendor_sdk_driver.py").write_text("import vendor_sdk_that_is_not_installed  # noqa: F401\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry._table.cache_clear()
    yield tmp_path
    registry._table.cache_clear()


def test_third_party_drivers_come_from_the_entry_point_group(third_party):
    assert registry.names()[len(registry.BUILTIN):] == ["vendor_ok", "vendor_sdk"]
    assert registry.load("modbus_tcp").__module__ == "drivers.modbus_tcp"  # a built-in name is not taken over
    cls = registry.load("vendor_ok")
    with cls(name="board", options={"gain": 2.0}, channels=[("a", 3), ("b", 5)]) as driver:
        reading = driver.read()
    assert reading.values == (6.0, 10.0)


def test_a_missing_dependency_breaks_only_its_own_driver(third_party):
    with pytest.raises(DriverError) as err:
        registry.load("vendor_sdk")
    assert str(err.value) == ('driver "vendor_sdk" cannot be loaded: importing vendor_sdk_driver failed: '
                              "No module named 'vendor_sdk_that_is_not_installed'")
    assert registry.load("vendor_ok").__name__ == "VendorOkDriver"
    profile = third_party / "p.toml"
    profile.write_text(textwrap.dedent("""\
        [machine]
        name = "m"
        [factors.speed]
        unit = "rpm"
        stat = "mean"
        [devices.good]
        driver = "vendor_ok"
        gain = 2.0
        [devices.bad]
        driver = "vendor_sdk"
        [channels.speed]
        device = "good"
        slot = 1
        """))
    with pytest.raises(ProfileError) as perr:
        load_profile(profile)
    assert perr.value.problems == [
        f'{profile}:10: devices.bad.driver: driver "vendor_sdk" cannot be loaded: importing vendor_sdk_driver '
        "failed: No module named 'vendor_sdk_that_is_not_installed'"]


def test_a_driver_is_closed_for_good_and_says_so(third_party):
    cls = registry.load("vendor_ok")
    driver = cls(name="board", options={"gain": 1.0}, channels=[("a", 1)])
    driver.open()
    driver.close()
    driver.close()  # idempotent
    with pytest.raises(DriverError, match='device "board": the driver was closed; make a new one'):
        driver.read()


def test_a_driver_dropped_open_warns(third_party):
    cls = registry.load("vendor_ok")
    driver = cls(name="board", options={"gain": 1.0}, channels=[("a", 1)])
    driver.open()
    with pytest.warns(ResourceWarning, match="device 'board' was not closed properly"):
        driver.__del__()
