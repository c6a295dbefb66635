"""profiles/sim-vmc.model.toml is what the project's own identify command makes from the simulator.

To regenerate it (README, "The bundled model"):
    for s in spindle-1000rpm spindle-500rpm spindle-400-600rpm feed-x-fast feed-x-accel feed-y-fast \\
             feed-y-accel feed-z-fast feed-z-accel; do cncgw simulate record $s -o rec/; done
    cncgw identify --profile profiles/sim-vmc.toml rec/spindle-1000rpm.csv ... rec/feed-z-accel.csv
"""

from __future__ import annotations

import pytest
from tests_paths import PROFILES

from gateway.commands._common import load_model_for
from gateway.identify import identify
from gateway.profile import load_profile
from simulators.machine import load_scenario, simulate

EXPERIMENTS = ("spindle-1000rpm", "spindle-500rpm", "spindle-400-600rpm", "feed-x-fast", "feed-x-accel",
               "feed-y-fast", "feed-y-accel", "feed-z-fast", "feed-z-accel")


def test_bundled_model_is_reproduced_by_identification():
    profile = load_profile(PROFILES / "sim-vmc.toml")
    bundled, _ = load_model_for(profile, None)  # also checks it fits the profile
    assert bundled.info["experiments"] == list(EXPERIMENTS)
    recs = [simulate(load_scenario(n)).recording() for n in EXPERIMENTS]
    again = identify(recs, factors=profile.factor_names, axes=profile.axes,
                     units={f.name: f.unit for f in profile.factors}, machine=profile.name).model
    assert again.reference == bundled.reference
    for key, path in bundled.paths.items():
        other = again.paths[key]
        assert other.kind == path.kind, key
        for t_new, t_old in zip(other.terms, path.terms, strict=True):
            assert t_new.gain == pytest.approx(t_old.gain, rel=1e-6, abs=1e-12), key
            assert t_new.time_constants_s == pytest.approx(t_old.time_constants_s, rel=1e-6), key
