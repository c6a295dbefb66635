"""Run a scenario offline, as fast as possible, and write what the gateway reads (and what it must not).

:func:`simulate` walks the scenario window by window: the drives' 2 ms samples give the window's factors
(mean speed, mean of each current squared, mean |feed|), their heat drives the thermal network, and the
network gives the tool-to-table displacement sampled at the window's end, as the paper measures it.
:func:`write_run` writes ``<run>.csv`` in the project's recording format (factors, measured displacement
with sensor noise and artefacts, the room and cabinet thermometers the scenario has) and ``<run>.truth.csv``
beside it: noiseless displacement, node temperatures, heat per source and each effect's contribution.
The gateway's commands never read the truth file.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from tqdm import tqdm

from gateway.recording import Recording, write_recording
from simulators.machine.drives import FACTORS, STAT_INDEX, DriveTimeline
from simulators.machine.effects import Effects
from simulators.machine.params import AXES, DEFAULT_MACHINE, MachineParams
from simulators.machine.scenario import Scenario
from simulators.machine.schedule import compile_drives
from simulators.machine.thermal import ThermalModel, room_deviation
from simulators.machine.variants import variant_machine

_NOISE_BLOCK = 4096


class _Progress(tqdm):
    """A progress bar without tqdm's monitor thread (nothing left running after a run)."""

    monitor_interval = 0


@lru_cache(maxsize=32)
def _noise_block(seed: int, stream: int, block: int) -> np.ndarray:
    draw = np.random.default_rng([seed, stream, block]).standard_normal((_NOISE_BLOCK, 3))
    draw.flags.writeable = False
    return draw


def sensor_noise(seed: int, stream: int, rows: np.ndarray) -> np.ndarray:
    """Standard normal noise (rows x 3) for window boundaries ``rows``.

    The same value for the same boundary whichever way it is asked for (offline in one go, live one at a
    time): blocks of boundaries are drawn from generators seeded by (seed, stream, block).
    """
    rows = np.asarray(rows, dtype=np.int64)
    out = np.empty((len(rows), 3))
    for block in np.unique(rows // _NOISE_BLOCK):
        sel = rows // _NOISE_BLOCK == block
        out[sel] = _noise_block(seed, stream, int(block))[rows[sel] % _NOISE_BLOCK]
    return out


def artefacts(scenario: Scenario, t_s: np.ndarray, window_s: float) -> np.ndarray:
    """What the sensor artefacts add at times ``t_s`` (rows x 3, um); their noise is drawn per window."""
    sa = scenario.effects.sensor_artefacts
    out = np.zeros((len(t_s), 3))
    if sa is None:
        return out
    out += np.outer(t_s >= sa.step_at_h * 3600.0, sa.step_um)
    out += np.outer(t_s / 3600.0, sa.drift_um_per_h)
    if sa.noise_um > 0:
        out += sa.noise_um * sensor_noise(scenario.seed, 1, np.rint(t_s / window_s).astype(np.int64))
    return out


def room_temperature(scenario: Scenario, t_s: np.ndarray) -> np.ndarray:
    """The room thermometer at ``t_s`` (deg C)."""
    return scenario.room.temperature_c + room_deviation(scenario.effects, t_s, t_s)


@dataclass(frozen=True, kw_only=True, eq=False)
class SimulationResult:
    """One offline run: per-window rows stamped at each window's end (``time_s``, from the run's start).

    Recordings carry ``stamps_s``: the same ends from the scenario's ``start_time_s`` (a clock time).
    """

    scenario: Scenario
    machine: MachineParams
    time_s: np.ndarray
    stats: np.ndarray  #: window statistics, columns as drives.STATS
    true_um: np.ndarray  #: noiseless tool-to-table displacement (rows x 3)
    measured_um: np.ndarray  #: what the displacement sensors read
    artefact_um: np.ndarray  #: the sensor artefacts' share of the reading (step, drift, extra noise)
    node_names: tuple[str, ...]
    temperatures_c: np.ndarray
    room_c: np.ndarray
    heat_w: dict[str, np.ndarray]
    contributions_um: dict[str, np.ndarray]  #: per effect: run with it minus run without it (rows x 3)

    @property
    def stamps_s(self) -> np.ndarray:
        """The time column a recording carries: ``time_s`` from the scenario's ``start_time_s``."""
        return self.time_s + self.scenario.start_time_s if self.scenario.start_time_s else self.time_s

    @property
    def factors(self) -> dict[str, np.ndarray]:
        return {name: self.stats[:, STAT_INDEX[name]] for name in FACTORS}

    def peak_um(self, which: str = "true") -> dict[str, float]:
        """Per axis the displacement of largest magnitude (signed), of ``true`` or ``measured``."""
        d = self.true_um if which == "true" else self.measured_um
        return {a: float(d[np.argmax(np.abs(d[:, i])), i]) for i, a in enumerate(AXES)}

    def recording_columns(self) -> dict[str, np.ndarray]:
        cols = dict(self.factors)
        cols |= {f"{a}_um": self.measured_um[:, i] for i, a in enumerate(AXES)}
        return cols | self.thermometers()

    def thermometers(self) -> dict[str, np.ndarray]:
        """The recorded temperatures: ``room_c`` (a room thermometer), ``cabinet_c`` (one in the cabinet)."""
        read = {"room_c": lambda: self.room_c,
                "cabinet_c": lambda: self.temperatures_c[:, self.node_names.index("cabinet")]}
        return {name: read[name]() for name in self.scenario.thermometers}

    def recording(self, which: str = "measured") -> Recording:
        """The run as a gateway :class:`~gateway.recording.Recording`.

        ``which="measured"``: what the sensors read; ``"true"``: the noiseless displacement (ground truth,
        for benchmarks and tests only).
        """
        if which not in ("measured", "true"):
            raise ValueError(f"which must be 'measured' or 'true'. Got {which!r}")
        disp = self.measured_um if which == "measured" else self.true_um
        extras = self.thermometers()
        return Recording(source=f"{self.scenario.name}.csv", period_s=self.machine.window_s, time_s=self.stamps_s,
                         present=np.ones(len(self.time_s), dtype=bool), factors=self.factors,
                         displacement={a: disp[:, i].copy() for i, a in enumerate(AXES)}, extras=extras,
                         meta=_meta(self.scenario))

    def probe_columns(self, *, every_s: float, sd_um: float = 0.3, seed: int = 0) -> dict[str, np.ndarray]:
        """The probe cycles of a CNC probing every ``every_s`` from the start, as ``record --export-only`` writes them.

        ``probe_seq``, ``probe_<axis>_um``, ``probe_sd_um`` on the row of the window each was applied
        after, empty elsewhere. As the simulated CNC's cycles (:class:`simulators.devices.cnc.ProbeCycles`, no
        compensation in force): the true displacement at the cycle plus normal noise of ``sd_um``, rounded to
        the probe block's 0.1 um.
        """
        if not every_s > 0 or not sd_um > 0:
            raise ValueError(f"every_s and sd_um must be > 0. Got {every_s!r}, {sd_um!r}")
        n = len(self.time_s)
        cycles = np.arange(every_s, float(self.time_s[-1]) + 1e-9, every_s)
        rows = np.searchsorted(self.time_s, cycles + 1e-9, side="right") - 1  # the last window ended by the cycle
        rows = np.unique(rows[rows >= 0])
        rng = np.random.default_rng([seed, 16])
        cols = {"probe_seq": np.full(n, np.nan)}
        cols["probe_seq"][rows] = np.arange(1, len(rows) + 1) % 65536
        for i, a in enumerate(AXES):
            c = np.full(n, np.nan)
            c[rows] = np.round((self.true_um[rows, i] + sd_um * rng.standard_normal(len(rows))) * 10.0) / 10.0
            cols[f"probe_{a}_um"] = c
        cols["probe_sd_um"] = np.where(np.isfinite(cols["probe_seq"]), sd_um, np.nan)
        return cols

    def truth_columns(self) -> dict[str, np.ndarray]:
        cols = {f"{a}_true_um": self.true_um[:, i] for i, a in enumerate(AXES)}
        cols |= {f"{a}_artefact_um": self.artefact_um[:, i] for i, a in enumerate(AXES)}
        cols["room_c"] = self.room_c
        cols |= {f"temp_{n}_c": self.temperatures_c[:, i] for i, n in enumerate(self.node_names)}
        cols |= {f"heat_{n}_w": v for n, v in self.heat_w.items()}
        for name, c in self.contributions_um.items():
            cols |= {f"effect_{name}_{a}_um": c[:, i] for i, a in enumerate(AXES)}
        return cols


def _meta(scenario: Scenario) -> dict[str, str]:
    """Metadata of a run's recording (the variant only when it is not the nominal machine)."""
    out = {"scenario": scenario.name, "seed": str(scenario.seed)}
    if scenario.variant:
        out["plant_variant"] = str(scenario.variant)
    if scenario.viscous_drag_scale != 1.0:
        out["plant_viscous_drag_scale"] = f"{scenario.viscous_drag_scale:g}"
    return out


def window_stats(drives: DriveTimeline, n_windows: int, *, progress: bool = False, fast: bool = True,
                 desc: str = "") -> np.ndarray:
    """Statistics of windows ``0..n_windows-1`` (rows) from the drives' 2 ms samples."""
    n = drives.machine.samples_per_window
    rows = []
    # progress: a bar on a terminal only (disable=None), never in tests or logs
    windows = _Progress(range(n_windows), disable=None, unit="min", desc=desc, leave=False,
                        mininterval=0.5) if progress else range(n_windows)
    for w in windows:
        rows.append(drives.window_stats(w * n + 1, (w + 1) * n, fast=fast))
    return np.array(rows)


def thermal_run(model: ThermalModel, stats: np.ndarray, room_dev: np.ndarray
                ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Node rises at every window's end (rows x nodes) and the state-dependent heats (W)."""
    stepper = model.stepper()
    T = np.empty((len(stats), len(model.net.names)))
    extra: dict[str, list[float]] = {}
    for k in range(len(stats)):
        T[k] = stepper.step(stats[k], float(room_dev[k]))
        for name, value in stepper.extra_w.items():
            extra.setdefault(name, []).append(value)
    return T, {k: np.array(v) for k, v in extra.items()}


def simulate(scenario: Scenario, *, machine: MachineParams = DEFAULT_MACHINE, progress: bool = False,
             fast: bool = True) -> SimulationResult:
    """Run ``scenario`` offline. ``fast=False`` evaluates every 2 ms sample (the reference, for bench).

    The scenario's plant variant (``[plant] variant``) is drawn from ``machine``; the result's ``machine``
    is the variant's.
    """
    machine = variant_machine(scenario.variant, machine, viscous_drag_scale=scenario.viscous_drag_scale)
    dt = machine.window_s
    n_windows = round(scenario.duration_s / dt)
    time_s = dt * np.arange(1, n_windows + 1)
    drives = compile_drives(scenario, machine)
    stats = window_stats(drives, n_windows, progress=progress, fast=fast, desc=scenario.name)

    def displacement(effects: Effects) -> tuple[ThermalModel, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        model = ThermalModel(machine, effects)
        T, extra = thermal_run(model, stats, room_deviation(effects, time_s - dt, time_s))
        return model, T, (T - model.T0) @ model.net.S.T, extra

    model, T, true_um, extra = displacement(scenario.effects)
    contributions = {name: true_um - displacement(scenario.effects.without(name))[2]
                     for name in scenario.effects.enabled if name != "sensor_artefacts"}
    artefact_um = artefacts(scenario, time_s, dt)
    if scenario.effects.sensor_artefacts is not None:
        contributions["sensor_artefacts"] = artefact_um
    noise = scenario.noise_um * sensor_noise(scenario.seed, 0, np.arange(1, n_windows + 1))
    heat, _ = model.heat(stats)
    room_c = room_temperature(scenario, time_s)
    return SimulationResult(
        scenario=scenario, machine=machine, time_s=time_s, stats=stats, true_um=true_um,
        measured_um=true_um + artefact_um + noise, artefact_um=artefact_um, node_names=model.net.names,
        temperatures_c=T + scenario.room.temperature_c, room_c=room_c, heat_w=heat | extra,
        contributions_um=contributions)


def write_run(result: SimulationResult, out_dir: str | Path, *, probe_every_s: float | None = None,
              probe_sd_um: float = 0.3) -> tuple[Path, Path]:
    """Write ``<run>.csv`` (the recording) and ``<run>.truth.csv`` (ground truth) into ``out_dir``.

    ``probe_every_s``: the recording is what a gateway without displacement sensors exports from a CNC that
    probes every ``probe_every_s`` (:meth:`SimulationResult.probe_columns`): no displacement columns, the
    probes in sparse ``probe_*`` columns.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = result.scenario
    meta = _meta(sc) | {"machine": "sim-vmc", "period_s": f"{result.machine.window_s:g}",
                        "source": "cncgw simulate record"}
    columns = result.recording_columns()
    if probe_every_s is not None:
        columns = {k: v for k, v in columns.items() if k not in {f"{a}_um" for a in AXES}}
        columns |= result.probe_columns(every_s=probe_every_s, sd_um=probe_sd_um, seed=sc.seed)
        meta["probes"] = f"every {probe_every_s:g} s, sd {probe_sd_um:g} um (no displacement sensors)"
    rec = write_recording(out / f"{sc.name}.csv", time_s=result.stamps_s, columns=columns, meta=meta)
    truth_meta = meta | {"kind": "ground truth (not a recording: the gateway never reads this)",
                         "effects": ", ".join(sc.effects.enabled) or "none"}
    truth = write_recording(out / f"{sc.name}.truth.csv", time_s=result.stamps_s,
                            columns=result.truth_columns(), meta=truth_meta)
    return rec, truth
