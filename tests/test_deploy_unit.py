"""The systemd unit agrees with the program: no restart into a bad profile, state where run writes, serial group."""

from __future__ import annotations

from tests_paths import ROOT

from gateway.cli import main
from gateway.errors import ModelError, ProfileError

UNIT = ROOT / "deploy" / "cncgw@.service"


def settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key.strip(), []).append(value.strip())
    return out


def test_a_bad_profile_exits_with_a_status_the_unit_does_not_restart(tmp_path, capsys):
    bad = tmp_path / "vmc-3.toml"
    bad.write_text('[machine]\nnmae = "vmc-3"\n')
    code = main(["run", "--profile", str(bad), "--data", str(tmp_path / "data")])
    assert code == ProfileError.exit_code == 3
    assert "machine.nmae: unknown key" in capsys.readouterr().err
    prevent = settings()["RestartPreventExitStatus"][0].split()
    assert str(ProfileError.exit_code) in prevent
    assert str(ModelError.exit_code) in prevent
    assert not (tmp_path / "data").exists()  # refused before anything was written


def test_the_unit_writes_only_its_state_directory_and_reaches_serial_ports():
    s = settings()
    assert s["StateDirectory"] == ["cncgw/%i"]
    assert "--data /var/lib/cncgw/%i" in s["ExecStart"][0]  # StateDirectory= is /var/lib/<that>
    assert "--profile /etc/cncgw/%i.toml" in s["ExecStart"][0]
    assert s["ConfigurationDirectory"] == ["cncgw"]
    assert s["ProtectSystem"] == ["strict"]
    assert s["SupplementaryGroups"] == ["dialout"]
    assert "char-ttyUSB rw" in s["DeviceAllow"]
    assert s["DevicePolicy"] == ["closed"]
    assert s["CapabilityBoundingSet"] == [""]
