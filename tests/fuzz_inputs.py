"""Malformed inputs for the fuzz suite (``tests/test_fuzz.py``) and its larger budget (``bench/fuzz.py``).

Every generator takes a :class:`random.Random` and returns the text of a file: a valid profile, model or
recording with one to four mutations drawn from what people and broken loggers produce (a value replaced
by an extreme number, a wrong type, an array nested thousands deep, an integer of thousands of digits; a
line deleted, duplicated, swapped or cut; a cell replaced by ``1_000``, Arabic-Indic digits or 200 000
characters; a time jumping by decades). Hypothesis drives the same generators through
``st.randoms(use_true_random=False)``, so a failing input shrinks to fewer and simpler choices; the bench
seeds them for a reproducible run.
"""

from __future__ import annotations

import math
import random
from pathlib import Path

from gateway.model import FirstOrder, PathTF, SecondOrder, ThermalModel, model_to_toml
from gateway.model.inputs import Periodic, Product

ROOT = Path(__file__).resolve().parent.parent
PROFILE_BASES = {
    "sim-vmc": (ROOT / "profiles" / "sim-vmc.toml").read_text(),
    "can-dcon": (ROOT / "tests" / "driver_cases" / "ok-can-dcon" / "profile.toml").read_text(),
    "rtu-multidrop": (ROOT / "tests" / "driver_cases" / "ok-modbus-rtu-multidrop" / "profile.toml").read_text(),
    "offline-full": (ROOT / "tests" / "profile_cases" / "ok-full" / "profile.toml").read_text(),
    "dry-run": (ROOT / "tests" / "compensation_cases" / "ok-dry-run" / "profile.toml").read_text(),
}
#: the profile the model and recording bases belong to (the bundled simulated machine)
SIM_PROFILE = ROOT / "profiles" / "sim-vmc.toml"
SIM_MODEL = (ROOT / "profiles" / "sim-vmc.model.toml").read_text()

_FACTORS = ("spindle_speed", "spindle_i1_sq", "spindle_i2_sq", "x_feed", "x_i_sq", "y_feed", "y_i_sq", "z_feed",
            "z_i_sq")


def _small_model() -> str:
    """A model of the simulated machine with every kind of term, a dead time and derived inputs."""
    sq = Product(name="speed_sq", of=("spindle_speed", "spindle_speed"), lag_s=(0.0, 1800.0), unit="rpm^2")
    day = Periodic(name="day_sin", period_s=86400.0, phase="sin")
    paths = [
        PathTF(axis="z", factor="spindle_speed",
               terms=(SecondOrder.from_time_constants(gain=-0.012, tau1_s=600.0, tau2_s=3000.0),)),
        PathTF(axis="z", factor="z_i_sq", terms=(FirstOrder(gain=0.05, tau_s=900.0), FirstOrder(gain=-0.02, tau_s=9000.0)),
               delay_s=120.0),
        PathTF(axis="x", factor="spindle_i1_sq", terms=(SecondOrder(gain=0.003, zeta=0.45, omega_rad_s=1 / 1500),)),
        PathTF(axis="y", factor="speed_sq", terms=(FirstOrder(gain=1e-7, tau_s=3600.0),)),
        PathTF(axis="x", factor="day_sin", terms=(FirstOrder(gain=0.4, tau_s=7200.0),)),
    ]
    model = ThermalModel(axes=("x", "y", "z"), factors=_FACTORS, units={f: "" for f in _FACTORS},
                         reference={"z_i_sq": 13.3}, paths={(p.axis, p.factor): p for p in paths}, machine="sim-vmc",
                         inputs=(sq, day))
    return model_to_toml(model)


MODEL_BASES = {"sim-vmc": SIM_MODEL, "small": _small_model()}


def _recording(rows: int = 40) -> str:
    """A recording of the simulated machine's columns: a minute a row, warm-up then cool-down."""
    lines = ["# cncgw recording 1", "# scenario: fuzz base",
             ",".join(["time_s", *_FACTORS, "x_um", "y_um", "z_um", "room_c"])]
    for k in range(rows):
        on = 1.0 if 5 <= k < 25 else 0.0
        cells = [60.0 * (k + 1), 1000.0 * on, 200.0 * on, 50.0 * on, 3000.0 * on, 9.0 * on, 2000.0 * on, 12.0 * on,
                 1000.0 * on, 13.3 + 2.0 * on, 0.05 * k * on, -0.02 * k, -0.4 * min(k, 25) * on, 20.0 + 0.01 * k]
        lines.append(",".join(f"{c:.6g}" for c in cells))
    return "\n".join(lines) + "\n"


RECORDING_BASE = _recording()

# ---------------------------------------------------------------------------------------------- values --
_NUMBERS = ("0", "-0.0", "1", "-1", "5e-324", "-5e-324", "1e-300", "1e300", "-1e300", "1e308", "-1.7976931348623157e308",
            "1e12", "-1e12", "65535", "65536", "-65536", "4294967296", "9223372036854775808", "0.5", "1e-9", "nan",
            "-nan", "inf", "-inf", "+inf", "0x7fffffff", "0o777", "0b1", "1_000_000")


def toml_value(rng: random.Random) -> str:
    """A TOML value of any kind and size, often extreme; sometimes not TOML at all."""
    pick = rng.randrange(12)
    if pick <= 3:
        return rng.choice(_NUMBERS)
    if pick == 4:
        return repr(rng.choice([-1.0, 1.0]) * 10.0 ** rng.randint(-320, 308))
    if pick == 5:
        return str(rng.randint(-(2**70), 2**70))
    if pick == 6:  # Python refuses integers of more than 4300 digits
        return rng.choice("123456789") + "0" * rng.choice([20, 4299, 4300, 5000])
    if pick == 7:
        depth = rng.choice([1, 2, 10, 100, 400, 5000])
        return "[" * depth + rng.choice(["", "1", '"x"']) + "]" * depth
    if pick == 8:
        return rng.choice(['""', '"x"', '"' + "y" * rng.choice([100, 100_000]) + '"', '"\\u00e9\\u0663"', "'lit'",
                           '"""multi\nline"""', '"unterminated'])
    if pick == 9:
        return rng.choice(["true", "false", "1979-05-27T07:32:00Z", "07:32:00", "{ a = 1 }", "{}", "[1, \"a\"]",
                           "[]", "[1.0, 2.0]", '["x", "y", "z"]', '["x", "x"]'])
    if pick == 10:
        return "".join(rng.choice("0123456789.eE+-_xabc\"'[]{},= #\t") for _ in range(rng.randint(0, 12)))
    return ""


def _toml_mutation(rng: random.Random, lines: list[str]) -> None:
    keyed = [i for i, line in enumerate(lines) if "=" in line and not line.lstrip().startswith("#")]
    op = rng.randrange(10)
    if op <= 3 and keyed:  # a value replaced
        i = rng.choice(keyed)
        key = lines[i].split("=", 1)[0]
        lines[i] = f"{key}= {toml_value(rng)}"
    elif op == 4 and keyed:  # a number scaled by a power of ten, or negated
        i = rng.choice(keyed)
        key, _, value = lines[i].partition("=")
        try:
            number = float(value.split("#")[0])
        except ValueError:
            return
        number = -number if rng.random() < 0.3 else number * 10.0 ** rng.randint(-300, 300)
        lines[i] = f"{key}= {number!r}" if math.isfinite(number) else f"{key}= {number}"
    elif op == 5 and lines:
        del lines[rng.randrange(len(lines))]
    elif op == 6 and lines:
        i = rng.randrange(len(lines))
        lines.insert(i, lines[i])
    elif op == 7 and len(lines) > 1:
        i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif op == 8:
        extra = rng.choice(["[unknown]", "[machine]", "[[path]]", "[channels.x]", "[devices.y]\ndriver = \"nope\"",
                            "[opcua]\nsecurity = [\"Basic256Sha256_SignAndEncrypt\"]\ncertificate = \"no.der\"",
                            "[compensation.axes.x]\nregister = 65535\ndata_type = \"int32\"",
                            "[inputs.q]\nkind = \"periodic\"\nperiod_s = 1e-300", f"x = {toml_value(rng)}"])
        lines.insert(rng.randrange(len(lines) + 1), extra)
    elif lines:  # a line cut short
        i = rng.randrange(len(lines))
        lines[i] = lines[i][: rng.randrange(len(lines[i]) + 1)]


def mutate_toml(rng: random.Random, text: str) -> str:
    """``text`` with one to four mutations (see the module docstring)."""
    lines = text.splitlines()
    for _ in range(rng.randint(1, 4)):
        _toml_mutation(rng, lines)
    return "\n".join(lines) + "\n"


def profile_text(rng: random.Random) -> tuple[str, str]:
    """(base name, a mutated profile)."""
    name = rng.choice(sorted(PROFILE_BASES))
    return name, mutate_toml(rng, PROFILE_BASES[name])


def model_text(rng: random.Random) -> tuple[str, str]:
    """(base name, a mutated model file)."""
    name = rng.choice(sorted(MODEL_BASES))
    return name, mutate_toml(rng, MODEL_BASES[name])


# ------------------------------------------------------------------------------------------ recordings --
_CELLS = ("", "nan", "NaN", "-", "1_000", "\u0661\u0662\u0663", "\uff11", "0x10", "1e308", "-1e308", "1e15", "1e16",
          "inf", "-Infinity", " 1 ", "1.5.2", "1e", "e5", "+.5", "5.", "--1", "\x00", '"', '"1,2"', "1;2", "true")
_TIMES = ("-1e9", "1e12", "1e300", "-1e300", "0", "1e11", "nan", "inf", "2024-05-01T08:00:00Z", "2024-02-30T00:00:00",
          "9999-12-31T23:59:59-23:59", "0001-01-01T00:00:00+23:59", "1716000000", "60.0000001")


def _csv_mutation(rng: random.Random, lines: list[str]) -> None:
    header = next((i for i, line in enumerate(lines) if line and not line.startswith("#")), 0)
    rows = list(range(header + 1, len(lines)))
    op = rng.randrange(12)
    if op <= 3 and rows:  # a cell replaced
        i = rng.choice(rows)
        cells = lines[i].split(",")
        j = rng.randrange(len(cells))
        pick = rng.random()
        if pick < 0.35:
            cells[j] = rng.choice(_CELLS)
        elif pick < 0.85:  # a number the reader takes, of any size up to its bound: for what comes after it
            cells[j] = repr(rng.uniform(-1, 1) * 10.0 ** rng.randint(-320, 16))
        else:
            cells[j] = "".join(rng.choice("0123456789.eE+-_ ,;\"'#abc") for _ in range(rng.randint(0, 8)))
        lines[i] = ",".join(cells)
    elif op == 4 and rows:  # a time jumps
        i = rng.choice(rows)
        cells = lines[i].split(",")
        cells[0] = rng.choice(_TIMES)
        lines[i] = ",".join(cells)
    elif op == 5 and rows:  # a long cell or comment
        i = rng.choice(rows)
        lines[i] = (("# " if rng.random() < 0.5 else "1,") + "9" * rng.choice([1000, 131_000, 200_000])
                    + lines[i][lines[i].find(","):])
    elif op == 6 and lines:
        del lines[rng.randrange(len(lines))]
    elif op == 7 and lines:
        i = rng.randrange(len(lines))
        lines.insert(i, lines[i])
    elif op == 8 and len(lines) > 1:
        i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif op == 9 and lines:  # the header loses, doubles or renames a column
        cells = lines[header].split(",")
        j = rng.randrange(len(cells))
        choice = rng.randrange(3)
        if choice == 0:
            del cells[j]
        elif choice == 1:
            cells.append(cells[j])
        else:
            cells[j] = rng.choice(["", "time", "spindle_sped", "x_um ", "\ufefftime_s"])
        lines[header] = ",".join(cells)
    elif op == 10 and rows:  # a row loses or gains a cell
        i = rng.choice(rows)
        lines[i] = lines[i].rsplit(",", 1)[0] if rng.random() < 0.5 else lines[i] + ",1"
    elif lines:  # the file is cut
        i = rng.randrange(len(lines))
        lines[i:] = [lines[i][: rng.randrange(len(lines[i]) + 1)]]


def recording_text(rng: random.Random) -> str:
    """The base recording with one to four mutations."""
    lines = RECORDING_BASE.splitlines()
    for _ in range(rng.randint(1, 4)):
        _csv_mutation(rng, lines)
    return "\n".join(lines) + "\n"
