"""``[probes]``: the CNC's probe block, and the model updated by it (see :mod:`gateway.adaptive`).

```toml
[probes]
enabled = true           # read the probe block on the [compensation] CNC and update the model (default false)
register = 10            # first register of the 9-register block
function = 4             # 4: input registers, 3: holding registers
unit_um = 0.1            # um per count of the values and the uncertainty
poll_s = 1.0             # clock seconds between reads of the block
band_limit_um = 5.0      # write offsets only while every axis's 95 % band is narrower than +- this (um)
gate_sigma = 3.0         # a probe further than this from the estimate is refused (the innovation test)
```
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True, kw_only=True, slots=True)
class Probes:
    """The ``[probes]`` section; ``enabled = false`` (the default) leaves the live estimate the model's alone."""

    enabled: bool = False
    register: int = 10
    function: int = 4
    unit_um: float = 0.1
    poll_s: float = 1.0
    band_limit_um: float | None = None
    gate_sigma: float = 3.0


def parse_probes(root: Any) -> Probes:
    """``[probes]`` from a profile's root table (every problem recorded on the document)."""
    t = root.table("probes")
    if t is None:
        return Probes()
    v = {
        "enabled": t.bool("enabled", default=False),
        "register": t.int("register", default=10, min=0, max=65535 - 8,
                          expected="the first register of the 9-register probe block, 0..65527"),
        "function": t.int("function", default=4, min=3, max=4, expected="4 (input registers) or 3 (holding)"),
        "unit_um": t.float("unit_um", default=0.1, min=1e-6, max=1000.0),
        "poll_s": t.float("poll_s", default=1.0, min=0.05, max=3600.0,
                          expected="clock seconds between reads of the block, 0.05..3600"),
        "band_limit_um": t.float("band_limit_um", default=None, min=0.0, min_exclusive=True, max=1000.0,
                                 expected="the widest 95 % half-band (um) at which offsets are still written"),
        "gate_sigma": t.float("gate_sigma", default=3.0, min=1.0, max=10.0),
    }
    t.done()
    return Probes(**{k: val for k, val in v.items() if val is not None})
