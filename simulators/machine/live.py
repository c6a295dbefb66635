"""The simulated machine in real (or accelerated) time, behind the device servers.

:class:`LiveMachine` implements :class:`simulators.live.LiveSource`. Channel values at any instant come
from the same closed-form drive pieces as the offline run; the thermal state is advanced window by window
with the same :class:`~simulators.machine.thermal.ThermalStepper` and the same window statistics of the
same 2 ms samples, so a live run and an offline run of one scenario give identical per-minute factors and
displacements at every window boundary. Between two boundaries the displacement is interpolated linearly
(the fastest thermal time constant is minutes); the window that holds ``t`` is computed in full when
``t`` enters it, which is possible because the schedule fixes the drives' future.

Compensation offsets from the CNC are recorded, so the residual tool-to-table error
(``displacement + offset``) can be watched while the gateway compensates. After the scenario's end the
machine stays at rest for as long as it is asked.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from gateway.clock import Clock, ManualClock
from simulators.machine.drives import CHANNELS, FACTORS, STAT_INDEX
from simulators.machine.params import AXES, DEFAULT_MACHINE, MachineParams
from simulators.machine.run import artefacts, room_temperature, sensor_noise
from simulators.machine.scenario import Scenario, load_scenario
from simulators.machine.schedule import compile_drives
from simulators.machine.thermal import ThermalModel, room_deviation
from simulators.machine.variants import variant_machine

DISPLACEMENT_CHANNELS = tuple(f"{a}_um" for a in AXES)


class LiveMachine:
    """A scenario running against a clock; thread-safe.

    ``values(t)`` gives the nine drive channels, the displacement sensors (``x_um``, ``y_um``, ``z_um``:
    what the capacitive sensors read, noise and artefacts included) and the thermometers the scenario has:
    ``room_c`` (the room's), ``cabinet_c`` (the cabinet's air, ``[effects.cabinet] thermometer``).
    """

    def __init__(self, scenario: Scenario | str | Path, *, clock: Clock | None = None,
                 machine: MachineParams = DEFAULT_MACHINE) -> None:
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario, machine=machine)
        machine = variant_machine(self.scenario.variant, machine,
                                  viscous_drag_scale=self.scenario.viscous_drag_scale)
        self.machine = machine
        self.clock: Clock = clock if clock is not None else ManualClock()
        self._drives = compile_drives(self.scenario, machine)
        self._model = ThermalModel(machine, self.scenario.effects)
        self._stepper = self._model.stepper()
        self._states: list[np.ndarray] = [self._model.T0.copy()]  # node rises at boundaries 0, 1, 2, ...
        self._stats: list[np.ndarray] = []
        self._latest_t = 0.0
        self._offsets = dict.fromkeys(AXES, 0.0)
        self._log: list[tuple[float, dict[str, float]]] = []
        self._noise_row, self._noise = -1, np.zeros(3)
        self._lock = threading.RLock()
        names = CHANNELS + DISPLACEMENT_CHANNELS
        self._names = (*names, *self.scenario.thermometers)

    # -- LiveSource --------------------------------------------------------------------------------------
    def channel_names(self) -> tuple[str, ...]:
        return self._names

    def values(self, t: float) -> Mapping[str, float]:
        """Every channel at simulated time ``t`` (s)."""
        with self._lock:
            out = self._drives.values(t)
            measured = self._measured(t)
            out |= {f"{a}_um": float(measured[i]) for i, a in enumerate(AXES)}
            for name in self.scenario.thermometers:
                out[name] = (float(room_temperature(self.scenario, np.array([t]))[0]) if name == "room_c"
                             else self.temperatures_c(t)["cabinet"])
            return out

    def set_compensation(self, offsets_um: Mapping[str, float]) -> None:
        """Offsets (um) the CNC applies from now on; axes not named keep theirs."""
        for axis, value in offsets_um.items():
            if axis not in AXES:
                raise ValueError(f"unknown axis {axis!r}: expected one of {', '.join(AXES)}")
            if not math.isfinite(value):
                raise ValueError(f"compensation offset for {axis} must be finite. Got {value!r}")
        with self._lock:
            self._offsets.update({a: float(v) for a, v in offsets_um.items()})
            self._log.append((self.clock.now(), dict(self._offsets)))

    # -- what tests, the demo and benchmarks watch ------------------------------------------------------
    @property
    def compensation_um(self) -> dict[str, float]:
        with self._lock:
            return dict(self._offsets)

    @property
    def compensation_log(self) -> list[tuple[float, dict[str, float]]]:
        """Every ``set_compensation`` as (clock time, offsets in force afterwards)."""
        with self._lock:
            return list(self._log)

    def true_displacement_um(self, t: float | None = None) -> dict[str, float]:
        """Noiseless tool-to-table displacement (um) relative to the start, without compensation."""
        with self._lock:
            d = self._true(self._when(t))
            return {a: float(d[i]) for i, a in enumerate(AXES)}

    def residual_um(self, t: float | None = None) -> dict[str, float]:
        """The tool-to-table error with the CNC's offsets applied: displacement + offset."""
        with self._lock:
            d = self._true(self._when(t))
            return {a: float(d[i]) + self._offsets[a] for i, a in enumerate(AXES)}

    def temperatures_c(self, t: float | None = None) -> dict[str, float]:
        """Node temperatures (deg C)."""
        with self._lock:
            T = self._state(self._when(t))
            return {n: float(T[i]) + self.scenario.room.temperature_c
                    for i, n in enumerate(self._model.net.names)}

    def window_factors(self) -> dict[str, np.ndarray]:
        """Per-minute factors of every window that has ended by the latest time asked for."""
        with self._lock:
            done = math.floor(self._latest_t / self.machine.window_s + 1e-9)
            rows = np.array(self._stats[:done]).reshape(-1, len(STAT_INDEX))
            return {name: rows[:, STAT_INDEX[name]].copy() for name in FACTORS}

    # -- internals ----------------------------------------------------------------------------------------
    def _when(self, t: float | None) -> float:
        return self.clock.now() if t is None else float(t)

    def _advance(self, boundary: int) -> None:
        """Integrate the thermal state up to window boundary ``boundary``."""
        dt = self.machine.window_s
        n = self.machine.samples_per_window
        while len(self._states) <= boundary:
            w = len(self._stats)
            stats = self._drives.window_stats(w * n + 1, (w + 1) * n)
            room = float(room_deviation(self.scenario.effects, w * dt, (w + 1) * dt))
            self._stats.append(stats)
            self._states.append(self._stepper.step(stats, room).copy())

    def _state(self, t: float) -> np.ndarray:
        if t < 0:
            raise ValueError(f"the simulation starts at t = 0. Got t = {t!r}")
        self._latest_t = max(self._latest_t, t)
        x = t / self.machine.window_s
        k = math.floor(x + 1e-9)
        frac = max(x - k, 0.0)
        self._advance(k + (1 if frac > 0 else 0))
        if frac == 0:
            return self._states[k]
        return self._states[k] + frac * (self._states[k + 1] - self._states[k])

    def _true(self, t: float) -> np.ndarray:
        return self._model.net.S @ (self._state(t) - self._model.T0)

    def _measured(self, t: float) -> np.ndarray:
        row = round(t / self.machine.window_s)  # noise is drawn per measurement, at the boundaries
        if row != self._noise_row:
            self._noise_row = row
            self._noise = self.scenario.noise_um * sensor_noise(self.scenario.seed, 0, np.array([row]))[0]
        out = self._true(t) + self._noise
        if self.scenario.effects.sensor_artefacts is not None:
            out += artefacts(self.scenario, np.array([t]), self.machine.window_s)[0]
        return out
