"""Plots of a run: the factors the CNC gives and the displacement they cause, over time."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gateway.errors import RecordingError, SimulationError
from gateway.recording import read_recording
from simulators.machine.drives import FACTORS
from simulators.machine.params import AXES
from simulators.machine.run import SimulationResult, simulate
from simulators.machine.scenario import load_scenario


@dataclass(frozen=True, kw_only=True)
class PlotData:
    """What a plot shows: per-window rows (a run or a recording read back)."""

    title: str
    time_s: np.ndarray
    factors: Mapping[str, np.ndarray]
    measured_um: np.ndarray  # rows x 3
    true_um: np.ndarray | None = None
    room_c: np.ndarray | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @classmethod
    def from_result(cls, result: SimulationResult) -> PlotData:
        sc = result.scenario
        return cls(title=f"{sc.name}: {sc.description}" if sc.description else sc.name, time_s=result.time_s,
                   factors=result.factors, measured_um=result.measured_um, true_um=result.true_um,
                   room_c=result.room_c if sc.room.thermometer or sc.effects.room_cycle else None,
                   notes=(f"effects: {', '.join(sc.effects.enabled) or 'none'}",))

    @classmethod
    def from_csv(cls, path: str | Path) -> PlotData:
        """A recording written by ``cncgw simulate record``, with its truth file when it lies beside it."""
        path = Path(path)
        rec = read_recording(path, factor_columns={f: f for f in FACTORS},
                             displacement_columns={a: f"{a}_um" for a in AXES})
        measured = np.column_stack([rec.displacement[a] for a in AXES])
        truth_path = path.with_name(path.name.removesuffix(".csv") + ".truth.csv")
        true_um = None
        notes: tuple[str, ...] = ()
        if truth_path.is_file():
            truth = read_recording(truth_path, factor_columns={},
                                   displacement_columns={a: f"{a}_true_um" for a in AXES})
            if len(truth) == len(rec):
                true_um = np.column_stack([truth.displacement[a] for a in AXES])
            notes = (f"effects: {truth.meta.get('effects', '?')}",)
        return cls(title=rec.meta.get("scenario", rec.name), time_s=rec.time_s, factors=dict(rec.factors),
                   measured_um=measured, true_um=true_um, room_c=rec.extras.get("room_c"), notes=notes)


def plot(data: PlotData, out: str | Path) -> Path:
    """Write a PNG: spindle speed, spindle currents squared, feeds, feed currents squared, displacement."""
    from gateway.plotting import pyplot

    plt = pyplot()

    out = Path(out)
    h = data.time_s / 3600.0
    if len(h) and h[0] > 24 * 365:  # clock times (a scenario's start_time_s, an export): hours from the start
        h = h - h[0] + (h[1] - h[0] if len(h) > 1 else 0.0)
    fig, ax = plt.subplots(5, 1, figsize=(11, 13), sharex=True, constrained_layout=True)
    ax[0].plot(h, data.factors["spindle_speed"], color="k", lw=1)
    ax[0].set_ylabel("spindle speed\nmean (rpm)")
    ax[1].plot(h, data.factors["spindle_i1_sq"], label="stator I1^2", lw=1)
    ax[1].plot(h, data.factors["spindle_i2_sq"], label="rotor I2^2", lw=1)
    ax[1].set_ylabel("spindle current^2\nmean (A^2)")
    colours = dict(zip(AXES, ("tab:blue", "tab:orange", "tab:green"), strict=True))
    for a in AXES:
        ax[2].plot(h, data.factors[f"{a}_feed"], label=a.upper(), color=colours[a], lw=1)
        ax[3].plot(h, data.factors[f"{a}_i_sq"], label=a.upper(), color=colours[a], lw=1)
    ax[2].set_ylabel("feed speed\nmean |v| (mm/min)")
    ax[3].set_ylabel("feed motor current^2\nmean (A^2)")
    for i, a in enumerate(AXES):
        ax[4].plot(h, data.measured_um[:, i], color=colours[a], lw=0.8, label=f"{a} measured")
        if data.true_um is not None:
            ax[4].plot(h, data.true_um[:, i], color=colours[a], lw=1.5, ls="--", label=f"{a} true")
    ax[4].set_ylabel("tool-to-table\ndisplacement (um)")
    ax[4].set_xlabel("time (h)")
    if data.room_c is not None:
        room = ax[4].twinx()
        room.plot(h, data.room_c, color="grey", lw=0.8, ls=":", label="room")
        room.set_ylabel("room (deg C)", color="grey")
    for a in ax[1:]:
        a.legend(loc="upper right", fontsize=8, ncols=3)
    for a in ax:
        a.grid(alpha=0.3)
    fig.suptitle(data.title + ("\n" + "; ".join(data.notes) if data.notes else ""), fontsize=10)
    try:
        fig.savefig(out, dpi=110)
    except OSError as exc:
        raise SimulationError(f"{out}: cannot write the plot: {exc}") from None
    finally:
        plt.close(fig)
    return out


def load_plot_data(source: str | Path) -> PlotData:
    """A CSV recording (``*.csv``) or a scenario to run (bundled name or TOML file)."""
    if str(source).endswith(".csv"):
        if not Path(source).is_file():
            raise RecordingError(f"{source}: file not found")
        return PlotData.from_csv(source)
    return PlotData.from_result(simulate(load_scenario(source), progress=True))
