"""Bundled profiles by name from any directory, and `cncgw profile new NAME` (a commented copy of the template)."""

from __future__ import annotations

import pytest

from gateway.cli import main
from gateway.errors import ProfileError
from gateway.profile import bundled_profiles, load_profile


def test_a_bundled_profile_loads_by_name_from_any_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert bundled_profiles() == ["paper-vm40iii", "sim-vmc", "template"]
    for name in ("sim-vmc", "sim-vmc.toml"):
        p = load_profile(name)
        assert p.name == "sim-vmc"
        assert p.model_path.is_file()  # its model comes along
    (tmp_path / "sim-vmc.toml").write_text('[machine]\nname = "mine"\n[factors.s]\nunit = "rpm"\nstat = "mean"\n')
    assert load_profile("sim-vmc.toml").name == "mine"  # a file of that name here wins


def test_an_unknown_bare_name_lists_the_bundled_profiles(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ProfileError) as err:
        load_profile("sim-vmcc")
    assert str(err.value) == ('sim-vmcc: file not found, nor a bundled profile (did you mean "sim-vmc"?) '
                              "(bundled: paper-vm40iii, sim-vmc, template)")
    assert main(["profile", "check", "nothere/sim-vmc.toml"]) == 3  # a path is never taken for a name
    assert "nothere/sim-vmc.toml: file not found" in capsys.readouterr().err


def test_profile_new_writes_the_commented_template_for_the_machine(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["profile", "new", "vmc-3"]) == 0
    text = (tmp_path / "vmc-3.toml").read_text()
    assert text.startswith("# Profile of machine vmc-3, written by `cncgw profile new vmc-3`")
    assert "# Every key is listed with its default" in text  # the template's comments come along
    p = load_profile(tmp_path / "vmc-3.toml")
    assert p.name == "vmc-3"
    assert p.model_path == tmp_path / "vmc-3.model.toml"
    assert "wrote vmc-3.toml" in capsys.readouterr().out
    assert main(["profile", "new", "vmc-3"]) == 1  # never overwritten
    assert "vmc-3.toml: already exists" in capsys.readouterr().err
    assert main(["profile", "new", "lathe 2"]) == 1
    assert 'machine name "lathe 2": expected 1 to 64 letters, digits, - or _' in capsys.readouterr().err
    assert main(["profile", "new", "lathe-2", "-o", "etc/lathe-2.toml"]) == 0
    assert load_profile(tmp_path / "etc" / "lathe-2.toml").name == "lathe-2"
