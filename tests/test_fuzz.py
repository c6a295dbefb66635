"""Fuzz suite: malformed profiles, model files, recordings and device answers end in a result or one error.

Every input either succeeds or raises a :class:`~gateway.errors.GatewayError` whose message names the file
(for files) or the device; never another exception, within 10 s an input and without the process growing by
more than 512 MiB. Where an input succeeds, what comes out is usable: a model gives finite estimates, a
recording finite bounded numbers, a decoder a finite value unless it flags it BAD or SATURATED.

Hypothesis runs derandomised with no example database, so CI sees the same inputs every run; each property
takes a few seconds. ``bench/fuzz.py`` runs a larger budget through the command line.
"""

from __future__ import annotations

import math
import resource
import socket
import struct
import threading
from datetime import timedelta

import numpy as np
import pytest
from fuzz_inputs import MODEL_BASES, SIM_PROFILE, model_text, profile_text, recording_text
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.base import OFFSET_MAX, SCALE_MAX, Quality, unpack_words
from drivers.can import CanSignalAddress
from drivers.dcon import checksum, parse_answer
from drivers.modbus_common import DATA_TYPES, RegisterAddress
from drivers.modbus_tcp import ModbusTcpDriver, ModbusTcpOptions
from gateway.errors import DriverError, GatewayError, ModelError, ProfileError, RecordingError
from gateway.model import load_model, save_model
from gateway.profile import load_profile
from gateway.recording import MAX_ABS_VALUE, MAX_MISSING_WINDOWS, read_for_profile, read_recording
from gateway.replay import estimate

FUZZ = settings(derandomize=True, database=None, deadline=timedelta(seconds=10), max_examples=150,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])
SEEDS = st.randoms(use_true_random=False)
GROWTH_LIMIT_KIB = 512 * 1024


@pytest.fixture
def memory_bound():
    """Fails the test if the process's peak resident size grew by more than 512 MiB while it ran."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    yield
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown < GROWTH_LIMIT_KIB, f"peak memory grew by {grown / 1024:.0f} MiB"


def assert_names(err: GatewayError, where: str) -> None:
    lines = str(err).splitlines()
    assert lines, f"{type(err).__name__} without a message"
    assert all(line.startswith(where) for line in lines), lines


# --------------------------------------------------------------------------------------------- files --
@FUZZ
@given(rng=SEEDS)
def test_any_profile_loads_or_is_one_error_naming_the_file(rng, tmp_path_factory, memory_bound):
    base, text = profile_text(rng)
    path = tmp_path_factory.mktemp(base) / "profile.toml"
    path.write_text(text)
    try:
        profile = load_profile(path)
    except ProfileError as err:
        assert_names(err, str(path))
        return
    assert profile.sampling.fast_period_s >= 0.0005
    assert all(math.isfinite(getattr(c.address, "scale", 1.0)) for c in profile.channels)


@FUZZ
@given(rng=SEEDS, level=st.floats(-1e9, 1e9))
def test_any_model_loads_or_is_one_error_and_a_loaded_one_gives_finite_estimates(rng, level, memory_bound):
    _, text = model_text(rng)
    try:
        model = load_model("m.toml", text=text)
    except ModelError as err:
        assert_names(err, "m.toml")
        return
    dm = model.discretize(60.0)
    du = np.full((len(model.input_names), 120), level)
    du[:, ::7] = 0.0  # on and off
    assert np.all(np.isfinite(dm.simulate(du)))
    live = dm.stepper()
    for k in range(5):
        assert np.all(np.isfinite(live.step(du[:, k])))


@FUZZ
@given(rng=SEEDS)
def test_any_recording_reads_or_is_one_error_and_what_is_read_is_bounded(rng, memory_bound):
    text = recording_text(rng)
    factors = {f: f for f in ("spindle_speed", "x_feed", "z_i_sq")}
    try:
        rec = read_recording("r.csv", text=text, factor_columns=factors,
                             displacement_columns={a: f"{a}_um" for a in "xyz"})
    except RecordingError as err:
        assert_names(err, "r.csv")
        return
    rows = int(rec.present.sum())
    assert len(rec) <= rows + MAX_MISSING_WINDOWS
    assert np.all(np.isfinite(rec.time_s))
    for column in (*rec.factors.values(), *rec.displacement.values(), *rec.extras.values()):
        known = column[np.isfinite(column)]
        assert np.all(np.abs(known) <= MAX_ABS_VALUE)
        assert np.all(np.isnan(column[~rec.present]))


@settings(FUZZ, max_examples=60)
@given(rng=SEEDS, model_name=st.sampled_from(sorted(MODEL_BASES)))
def test_estimate_of_any_readable_recording_is_finite_or_one_error(rng, model_name, tmp_path_factory, memory_bound):
    profile = load_profile(SIM_PROFILE)
    model = load_model("m.toml", text=MODEL_BASES[model_name])
    path = tmp_path_factory.mktemp("rec") / "r.csv"
    path.write_text(recording_text(rng))
    try:
        result = estimate(model, read_for_profile(path, profile, require_displacement=False))
    except GatewayError as err:
        assert_names(err, str(path))
        return
    assert np.all(np.isfinite(result.estimated))
    for m in result.metrics.values():
        assert math.isfinite(m.rms_um) or m.windows == 0


@settings(FUZZ, max_examples=40)
@given(rng=SEEDS)
def test_identify_on_any_readable_recording_writes_a_loadable_model_or_is_one_error(rng, tmp_path_factory,
                                                                                    memory_bound):
    from gateway.identify.api import identify

    profile = load_profile(SIM_PROFILE)
    folder = tmp_path_factory.mktemp("ident")
    (folder / "r.csv").write_text(recording_text(rng))
    try:
        model = identify([read_for_profile(folder / "r.csv", profile)], factors=profile.factor_names,
                         axes=profile.axes, units={f.name: f.unit for f in profile.factors}, machine=profile.name).model
    except GatewayError as err:
        assert_names(err, "")  # identification names the axis, the reader the file
        return
    save_model(model, folder / "m.toml")
    assert load_model(folder / "m.toml") == model  # what identification writes is inside the loader's ranges


# ------------------------------------------------------------------------------------------- decoders --
SCALES = st.floats(1e-12, SCALE_MAX) | st.floats(-SCALE_MAX, -1e-12)
OFFSETS = st.floats(-OFFSET_MAX, OFFSET_MAX)


@FUZZ
@given(data_type=st.sampled_from(DATA_TYPES), words=st.lists(st.integers(0, 65535), min_size=2, max_size=2),
       word_order=st.sampled_from(("big", "little")), byte_order=st.sampled_from(("big", "little")),
       scale=SCALES, offset=OFFSETS)
def test_modbus_registers_decode_to_a_finite_value_or_a_flag(data_type, words, word_order, byte_order, scale, offset):
    a = RegisterAddress(address=0, data_type=data_type, word_order=word_order, byte_order=byte_order, scale=scale,
                        offset=offset)
    value, quality = a.decode(words[: a.n_registers])
    assert math.isfinite(value) or quality in (Quality.BAD, Quality.SATURATED)
    assert math.isnan(value) == (quality is Quality.BAD)
    if data_type != "float32":  # integers: exactly the raw count scaled
        raw = unpack_words(words[: a.n_registers], data_type, word_order=word_order, byte_order=byte_order)
        assert raw == int(raw)
        assert value == raw * scale + offset


@FUZZ
@given(data=st.data(), signed=st.booleans(), byte_order=st.sampled_from(("little", "big")), scale=SCALES,
       offset=OFFSETS, payload=st.binary(min_size=0, max_size=8))
def test_can_signals_decode_inside_their_range_from_any_payload(data, signed, byte_order, scale, offset, payload):
    length = data.draw(st.integers(1, 64))
    start = data.draw(st.integers(0, 63))
    a = CanSignalAddress(frame_id=0x181, start_bit=start, length_bits=length, signed=signed, byte_order=byte_order,
                         scale=scale, offset=offset)
    if a.bytes_needed() > 8 or len(payload) < a.bytes_needed():
        return  # refused at load (the signal does not fit a frame) or counted as a short frame by the driver
    value = a.decode(payload)
    raw = round((value - offset) / scale) if abs(scale) >= 1e-3 else None
    assert math.isfinite(value)
    if raw is not None and abs(raw) < 2**50:  # where the float arithmetic can be undone exactly
        lo, hi = (-(2 ** (length - 1)), 2 ** (length - 1) - 1) if signed else (0, 2**length - 1)
        assert lo <= raw <= hi


@FUZZ
@given(answer=st.binary(max_size=80) | st.text(alphabet="+-0123456789.>\r\x00\xff", max_size=80).map(str.encode),
       with_checksum=st.booleans())
def test_dcon_answers_parse_to_finite_readings_or_none(answer, with_checksum):
    readings = parse_answer(answer, with_checksum=with_checksum)
    assert readings is None or all(math.isfinite(v) for _, v in readings)


@FUZZ
@given(values=st.lists(st.floats(-99.999, 99.999), min_size=1, max_size=8), with_checksum=st.booleans())
def test_dcon_well_formed_answers_give_back_their_values(values, with_checksum):
    body = ">" + "".join(f"{v:+07.3f}" for v in values)
    answer = (body + checksum(body) if with_checksum else body).encode("ascii")
    readings = parse_answer(answer, with_checksum=with_checksum)
    assert readings is not None
    assert [v for _, v in readings] == [float(f"{v:+07.3f}") for v in values]
    assert parse_answer(b">+" + b"9" * 400, with_checksum=False) is None  # not a finite number: malformed


class AnswerServer:
    """A Modbus TCP server on 127.0.0.1 that answers every request with the bytes it is given."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.answer = b""
        self.close_after = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fuzz-answer-server", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            with conn:
                conn.settimeout(0.2)
                while not self._stop.is_set():
                    try:
                        request = conn.recv(260)
                    except TimeoutError:
                        continue
                    except OSError:
                        break
                    if not request:
                        break
                    answer = self.answer(request) if callable(self.answer) else self.answer
                    try:
                        conn.sendall(answer)
                    except OSError:
                        break
                    if self.close_after:
                        break

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


def framed(pdu: bytes):
    """An answer with the request's transaction id and unit (a well-formed MBAP header) and ``pdu``."""
    def build(request: bytes) -> bytes:
        tid, unit = request[:2], request[6:7] or b"\x01"
        return tid + b"\x00\x00" + struct.pack(">H", len(pdu) + 1) + unit + pdu
    return build


ANSWERS = (
    st.binary(max_size=40).map(lambda b: ("raw", b))
    | st.tuples(st.sampled_from([3, 4, 0x83, 0x84, 1, 0x7F]), st.integers(0, 255), st.binary(max_size=40))
    .map(lambda t: ("framed", bytes([t[0], t[1]]) + t[2]))
    | st.lists(st.integers(0, 65535), min_size=0, max_size=12)
    .map(lambda ws: ("framed", bytes([4, 2 * len(ws)]) + b"".join(struct.pack(">H", w) for w in ws)))
)


def test_the_modbus_tcp_driver_survives_any_answer_on_a_real_socket():
    server = AnswerServer()
    options = ModbusTcpOptions(host="127.0.0.1", port=server.port, timeout_s=0.05)
    channels = [("a", RegisterAddress(address=0, data_type="int16", scale=0.5)),
                ("b", RegisterAddress(address=1, data_type="float32")),
                ("c", RegisterAddress(address=3, data_type="uint32", word_order="little"))]
    outcomes: dict[str, int] = {}
    driver = ModbusTcpDriver(name="adc", options=options, channels=channels)
    try:
        @settings(FUZZ, max_examples=60)
        @given(answer=ANSWERS, close_after=st.booleans())
        def check(answer, close_after):
            kind, payload = answer
            server.answer = payload if kind == "raw" else framed(payload)
            server.close_after = close_after
            try:
                if not driver.is_open:
                    driver.open()
                reading = driver.read()
            except DriverError as err:
                message = str(err)
                outcomes["error"] = outcomes.get("error", 0) + 1
                assert message.startswith('device "adc"'), message
                return
            outcomes["read"] = outcomes.get("read", 0) + 1
            for value, quality in zip(reading.values, reading.quality, strict=True):
                assert math.isfinite(value) or quality in (Quality.BAD, Quality.SATURATED)

        check()
    finally:
        driver.close()
        server.close()
    assert outcomes.get("error", 0) > 0  # the fuzzing reached the error paths and the good ones
    assert outcomes.get("read", 0) > 0
