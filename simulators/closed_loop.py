"""The live gateway against the bundled simulated machine: its profile with live addresses, its CNC settings.

Used by ``cncgw demo``, the tests and ``bench/runtime.py``: :func:`live_profile` writes the bundled profile
with the running simulated devices' addresses (:func:`simulators.devices.profile_out.profile_for`) plus a
``[compensation]`` section for the simulated CNC (int32 offsets in 0.1 um at holding 0-5, heartbeat at
holding 6, read-back at input 0-5, status at input 6; the CNC adds the offset: ``sign = -1``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


def live_profile(devices: Any, out: str | Path, *, enabled: bool = True, period_s: float | None = None,
                 opcua_port: int | None = 0, live: str = "", **compensation: Any) -> Path:
    """Write the bundled profile reading ``devices``' ADC board over Modbus TCP and compensating on its CNC.

    ``period_s`` overrides the ADC's fast period; ``opcua_port`` adds an ``[opcua]`` section on 127.0.0.1
    (``None``: none, OPC UA off); ``live`` is extra ``[live]`` keys; the rest are ``[compensation]`` keys
    (:func:`simulators.devices.profile_out.compensation_toml`).
    """
    from simulators.devices.profile_out import profile_for

    text = profile_for(devices, "adc-tcp", compensate=enabled, **compensation)
    if period_s is not None:
        text = re.sub(r"(\[devices\.adc\]\n)", rf"\g<1>period_s = {period_s!r}\n", text)
    if live:
        text += f"\n[live]\n{live}\n"
    text += ("\n[opcua]\nenabled = false\n" if opcua_port is None else
             f'\n[opcua]\nenabled = true\nhost = "127.0.0.1"\nport = {opcua_port}\n')
    path = Path(out)
    path.write_text(text, encoding="utf-8")
    return path


@dataclass(frozen=True, kw_only=True)
class ClosedLoopErrors:
    """The simulated machine's tool-to-table error over a run, without and with the offsets it applied."""

    time_s: np.ndarray
    without_um: dict[str, np.ndarray]  # the thermal displacement (no compensation)
    with_um: dict[str, np.ndarray]  # displacement + the offset the CNC applied at that instant
    offset_um: dict[str, np.ndarray]

    @property
    def max_without_um(self) -> dict[str, float]:
        return {a: float(np.max(np.abs(v))) for a, v in self.without_um.items()}

    @property
    def max_with_um(self) -> dict[str, float]:
        return {a: float(np.max(np.abs(v))) for a, v in self.with_um.items()}

    def reduction(self, axis: str) -> float:
        """1 - max error with / max error without."""
        return 1.0 - self.max_with_um[axis] / self.max_without_um[axis]


def closed_loop_errors(machine: Any, end_s: float, *, start_s: float = 0.0, step_s: float = 10.0) -> ClosedLoopErrors:
    """Evaluate a :class:`~simulators.machine.LiveMachine` run every ``step_s`` from its ground truth.

    The offset in force at each instant comes from the machine's own log of what the CNC applied (its
    watchdog ramps included), not from what the gateway believes it wrote.
    """
    log = machine.compensation_log
    times = np.array([t for t, _ in log])
    ts = np.arange(start_s, end_s + 1e-9, step_s)
    axes = tuple(machine.true_displacement_um(start_s))
    without = {a: np.empty(len(ts)) for a in axes}
    offset = {a: np.zeros(len(ts)) for a in axes}
    for i, t in enumerate(ts):
        d = machine.true_displacement_um(float(t))
        k = int(np.searchsorted(times, t, side="right")) - 1
        for a in axes:
            without[a][i] = d[a]
            if k >= 0:
                offset[a][i] = log[k][1][a]
    return ClosedLoopErrors(time_s=ts, without_um=without, with_um={a: without[a] + offset[a] for a in axes},
                            offset_um=offset)


def plot_closed_loop(errs: ClosedLoopErrors, path: str | Path, *, title: str = "") -> Path:
    """Per axis: the error without compensation, with it, and the offset applied, against time (h)."""
    from gateway.plotting import pyplot

    plt = pyplot()

    axes = tuple(errs.without_um)
    fig, grid = plt.subplots(len(axes), 1, figsize=(10, 2.8 * len(axes)), sharex=True, squeeze=False)
    hours = errs.time_s / 3600.0
    for row, a in zip(grid[:, 0], axes, strict=True):
        row.plot(hours, errs.without_um[a], color="C3", lw=1.2,
                 label=f"without compensation (max {errs.max_without_um[a]:.2f} um)")
        row.plot(hours, errs.with_um[a], color="C2", lw=1.4,
                 label=f"with compensation (max {errs.max_with_um[a]:.2f} um)")
        row.plot(hours, errs.offset_um[a], color="C0", lw=0.8, ls="--", label="offset the CNC applied")
        row.axhline(0, color="k", lw=0.5)
        row.set_ylabel(f"{a} error (um)")
        row.legend(fontsize=7, loc="best")
    grid[-1, 0].set_xlabel("time (h)")
    if title:
        fig.suptitle(f"{title}: tool-to-table thermal error", fontsize=10)
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
