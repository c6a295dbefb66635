"""An installed gateway (a wheel on an edge PC, no repository beside it) carries the bundled profiles.

``cncgw demo`` and ``cncgw simulate serve --profile-out`` read the simulated machine's profile and model
from ``gateway.BUNDLED``: in the repository a link to ``profiles/``, in a wheel the copies that the
package data of ``pyproject.toml`` puts there. A wheel built without them fails on the first demo.
"""

from __future__ import annotations

import tomllib

from tests_paths import PROFILES, ROOT

from gateway import BUNDLED
from gateway.commands import demo
from simulators.devices import profile_out


def test_the_bundled_profiles_are_package_data_and_the_commands_read_them_there():
    assert BUNDLED.resolve() == PROFILES.resolve()
    assert demo.PROFILE == BUNDLED / "sim-vmc.toml"
    assert profile_out.BUNDLED_PROFILE == BUNDLED / "sim-vmc.toml"
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = config["package-data"]["gateway"]
    shipped = {p.name for pattern in patterns for p in (ROOT / "gateway").glob(pattern)}
    assert shipped == {p.name for p in PROFILES.iterdir() if p.is_file()}
    assert {"sim-vmc.toml", "sim-vmc.model.toml", "paper-vm40iii.toml", "template.toml"} <= shipped


def test_the_license_is_an_spdx_expression_that_the_build_backend_reads_without_a_deprecation():
    # setuptools >= 77 warned on every `pip wheel` that the table form stops building after 2027-02-18
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert doc["project"]["license"] == "Apache-2.0"
    assert [(ROOT / f).is_file() for f in doc["project"]["license-files"]] == [True]
    assert "setuptools>=77" in doc["build-system"]["requires"]
