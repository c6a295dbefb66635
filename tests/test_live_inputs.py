"""A diagnosed model (derived inputs) in the live estimator: the same numbers as `cncgw estimate` on the exported
records, through a gap and a bad window, after a restart, and a clear refusal when a column has no channel."""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np
import pytest

from gateway.errors import ModelError
from gateway.live.tracking import DisplacementTracker
from gateway.model import ModelStepper, PathTF, ThermalModel
from gateway.model.inputs import Column, Periodic, Product
from gateway.model.terms import FirstOrder
from gateway.profile import load_profile
from gateway.profile.live import Live
from gateway.record_store import STORE_NAME, RecordStore, export_recording
from gateway.recording import read_for_profile
from gateway.windows import ChannelStats, DeviceQuality, WindowRecord

WINDOW_S = 60.0
T0 = 1_790_000_040.0  # a whole minute of epoch time: windows are stamped like a real clock's

PROFILE = """
[machine]
name = "derived"
axes = ["x", "z"]

[sampling]
fast_period_s = 0.01
window_s = 60.0

[recording]
time_column = "time_s"
period_s = 60.0

[factors.spindle_speed]
unit = "rpm"
channel = "speed"
stat = "mean"

[factors.spindle_i1_sq]
unit = "A^2"
channel = "current"
stat = "mean_square"

[devices.adc]
driver = "modbus_tcp"
host = "127.0.0.1"
port = 5020

[channels.speed]
device = "adc"
unit = "rpm"
address = 0

[channels.current]
device = "adc"
unit = "A"
address = 1
{room}
"""

ROOM_CHANNEL = """
[channels.room_c]
device = "adc"
unit = "degC"
address = 2
"""


def diagnosed_model() -> ThermalModel:
    """Every kind of derived input a diagnosis writes that depends on live data: a square, a product with a
    lag, a recorded column, a time of day."""
    inputs = (Product(name="speed_sq", of=("spindle_speed", "spindle_speed")),
              Product(name="speed_x_lag", of=("spindle_speed", "spindle_speed"), lag_s=(0.0, 1800.0)),
              Column(name="room", column="room_c"),
              Periodic(name="day_sin", period_s=86400.0, phase="sin"))
    gains = {"spindle_speed": 0.004, "spindle_i1_sq": 0.01, "speed_sq": -2e-6, "speed_x_lag": 1e-6,
             "room": 1.5, "day_sin": 0.8}
    paths = []
    for k, (name, gain) in enumerate(gains.items()):
        for a, sign in (("x", 1.0), ("z", -1.0)):
            term = FirstOrder(gain=sign * gain, tau_s=600.0 * (k + 1))
            paths.append(PathTF(axis=a, factor=name, terms=(term,), delay_s=120.0 if name == "room" else 0.0))
    return ThermalModel(axes=("x", "z"), factors=("spindle_speed", "spindle_i1_sq"),
                        units={"spindle_speed": "rpm", "spindle_i1_sq": "A^2"},
                        reference={"spindle_speed": 0.0, "spindle_i1_sq": 4.0},
                        paths={(p.axis, p.factor): p for p in paths}, inputs=inputs, machine="derived")


def stats(value: float) -> ChannelStats:
    return ChannelStats(count=6000, coverage=1.0, mean=value, mean_square=value * value, mean_abs=abs(value),
                        min=value, max=value, saturated=0, bad=0)


def records(n: int, *, missing: set[int], bad: set[int]) -> list[WindowRecord]:
    """``n`` windows of a spindle stepping through speeds while the room warms; ``missing`` ones are not
    there (the gateway was down), ``bad`` ones are insufficient (the board silent; the thermometer read)."""
    rng = np.random.default_rng(7)
    speeds = np.repeat(rng.choice([0.0, 1000.0, 2500.0, 4000.0], size=n // 20 + 1), 20)[:n]
    first = int(T0 // WINDOW_S)
    out = []
    for k in range(n):
        if k in missing:
            continue
        speed, room = float(speeds[k]), 20.0 + 1.5 * math.sin(k / 90.0) + 0.05 * rng.standard_normal()
        i_sq = 4.0 + speed / 100.0
        good = k not in bad
        channels = {"room_c": stats(room)}
        if good:
            channels |= {"speed": stats(speed), "current": stats(math.sqrt(i_sq))}
        factors = {"spindle_speed": speed, "spindle_i1_sq": i_sq} if good else \
            {"spindle_speed": math.nan, "spindle_i1_sq": math.nan}
        device = DeviceQuality(ticks_expected=6000, ticks_run=6000, ticks_skipped=0, reads_ok=6000 if good else 0,
                               reads_failed=0 if good else 6000, timeouts=0, off_scan_ticks=0, largest_gap_s=0.01,
                               lateness_max_s=0.0, read_time_max_s=0.001, tick_s=0.01)
        idx = first + k
        out.append(WindowRecord(index=idx, start_s=idx * WINDOW_S, end_s=(idx + 1) * WINDOW_S,
                                status="good" if good else "insufficient", factors=MappingProxyType(factors),
                                channels=MappingProxyType(channels), devices=MappingProxyType({"adc": device})))
    return out


@pytest.fixture
def profile(tmp_path):
    path = tmp_path / "derived.toml"
    path.write_text(PROFILE.format(room=ROOM_CHANNEL), encoding="utf-8")
    return load_profile(path)


def live_estimates(model, recs, *, channel_names=("speed", "current", "room_c")):
    est = DisplacementTracker(model, window_s=WINDOW_S, live=Live(), channels={"spindle_speed": "speed"},
                    channel_names=channel_names)
    return est, {r.index: axes_of(est.update(r)) for r in recs}


def axes_of(update) -> np.ndarray:
    return np.array(list(update.estimate_um.values()))


def test_live_estimator_with_derived_inputs_equals_estimate_on_the_exported_records(profile, tmp_path):
    from gateway.replay import estimate

    model = diagnosed_model()
    recs = records(400, missing={150, 151}, bad={230})
    _, live = live_estimates(model, recs)
    with RecordStore(tmp_path / STORE_NAME, profile=profile) as store:
        for r in recs:
            store.append(r)
        out = export_recording(store, profile, tmp_path / "export.csv")
    rec = read_for_profile(out, profile, require_displacement=False)
    assert "room_c" in rec.extras  # the thermometer's channel is exported for diagnosis
    assert len(rec.time_s) == 400
    assert np.sum(~rec.present) == 2  # the two missing windows stay explicit
    batch = estimate(model, rec, initial="reference", gap_policy="hold")
    rows = {round(t / WINDOW_S) - 1: k for k, t in enumerate(batch.time_s)}
    worst = max(float(np.max(np.abs(live[i] - batch.estimated[:, rows[i]]))) for i in live)
    assert worst < 1e-9, worst
    peak = max(float(np.max(np.abs(v))) for v in live.values())
    assert peak > 1.0  # the derived inputs move the estimate: the comparison is not between zeros


def test_a_restart_replays_the_derived_inputs_to_the_same_estimate(profile):
    model = diagnosed_model()
    recs = records(300, missing=set(), bad=set())
    _, ref = live_estimates(model, recs)
    cut = 200
    est = DisplacementTracker(model, window_s=WINDOW_S, live=Live(), channel_names=["speed", "current", "room_c"])
    est.rebuild(recs[:cut])
    again = {r.index: axes_of(est.update(r)) for r in recs[cut:]}
    assert max(float(np.max(np.abs(again[i] - ref[i]))) for i in again) < 1e-9

    def truncated(origin):  # the store keeps more than the history the rebuild reads
        e = DisplacementTracker(model, window_s=WINDOW_S, live=Live(), channel_names=["speed", "current", "room_c"])
        e.rebuild(recs[100:cut], origin=origin)
        return max(float(np.max(np.abs(axes_of(e.update(r)) - ref[r.index]))) for r in recs[cut:])

    # the room stays referred to the oldest stored window; without it, to the first window read
    with_origin, without = truncated(recs[0]), truncated(None)
    assert with_origin < 0.5 * without, (with_origin, without)


def test_a_column_input_without_a_channel_is_refused_at_start(tmp_path):
    with pytest.raises(ModelError) as err:
        live_estimates(diagnosed_model(), [], channel_names=("speed", "current"))
    assert str(err.value) == ('model input "room" reads recorded column "room_c", but the profile has no channel '
                              '"room_c" (channels: current, speed): add a [channels.room_c] table that reads it')


def test_peek_is_the_next_step_without_taking_it():
    model = diagnosed_model()
    est = ModelStepper(model.discretize(WINDOW_S))
    rng = np.random.default_rng(3)
    for _ in range(30):
        est.step(rng.normal(size=len(model.input_names)))
    du = rng.normal(size=len(model.input_names))
    before = est.output()
    ahead = est.peek(du)
    assert np.array_equal(est.output(), before)
    assert est.steps == 30
    assert np.array_equal(est.step(du), ahead)
    with pytest.raises(ValueError, match="expected 6 finite input deviations"):
        est.peek(np.full(6, np.nan))


def test_cncgw_run_refuses_such_a_model_before_touching_the_data_directory(tmp_path, capsys):
    from gateway.cli import main
    from gateway.model import save_model

    profile = tmp_path / "derived.toml"
    profile.write_text(PROFILE.format(room=""), encoding="utf-8")
    model = tmp_path / "diagnosed.model.toml"
    save_model(diagnosed_model(), model)
    code = main(["run", "--profile", str(profile), "--data", str(tmp_path / "data"), "--model", str(model)])
    assert code == 5
    assert capsys.readouterr().err.strip() == (
        f'cncgw: error: {model}: model input "room" reads recorded column "room_c", but the profile has no channel '
        '"room_c" (channels: current, speed): add a [channels.room_c] table that reads it')
    assert not (tmp_path / "data").exists()
