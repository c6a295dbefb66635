"""Pieces the commands share: reading recordings for a profile, loading a model that fits the profile."""

from __future__ import annotations

import argparse
import itertools
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from gateway.errors import GatewayError, ModelError, UsageError, did_you_mean
from gateway.model import ThermalModel, load_model
from gateway.model.inputs import hold_missing
from gateway.profile import Profile
from gateway.recording import Recording, read_for_profile, recording_name, unread_displacement


def plain(doc: str | None) -> str:
    """A docstring as argparse should show it: reST markup (``code``, `ref`, :mod:`x`) as plain text."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc or "")
    return re.sub(r"``([^`]+)``|`([^`]+)`", lambda m: m.group(1) or m.group(2), text)


def positive_float(text: str) -> float:
    """Argparse type: a number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def warn_other_machine(model: ThermalModel, model_path: Path, profile: Profile, what: str) -> str:
    """Warn (stderr) when the model names another machine than the profile; return the warning ("" if none).

    Offline it may be what the user wants (a twin machine); ``cncgw run`` refuses it.
    """
    if not model.machine or model.machine == profile.name:
        return ""
    text = (f'{model_path}: the model names machine "{model.machine}", this profile is machine "{profile.name}": '
            f"{what} (`cncgw run` refuses it)")
    print(f"cncgw: warning: {text}", file=sys.stderr)
    return text


def refuse_duplicates(recs: Sequence[Recording], factors: Sequence[str], *, counts: str) -> dict[str, str]:
    """Refuse a recording given twice (by content: a copy or another path to it too); ``counts``: what it does.

    Returns each recording's fingerprint (:meth:`Recording.fingerprint`) -> its source.
    """
    seen: dict[str, str] = {}
    for r in recs:
        fp = r.fingerprint(factors)
        if fp in seen:
            what = "given twice" if seen[fp] == r.source else (
                f"the same data as {seen[fp]} (the same factors and displacement, whatever the file's name)")
            raise UsageError(f"{r.source}: {what}: a recording given twice {counts}; give each recording once")
        seen[fp] = r.source
    return seen


def positive_int(text: str) -> int:
    """Argparse type: an integer > 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer > 0, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected an integer > 0, got {text!r}")
    return value


def add_recording_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--period-s", type=positive_float, default=None, metavar="S",
                   help="the files have no time column: rows are S seconds apart")
    p.add_argument("--gap-policy", choices=("hold", "reference"), default="hold",
                   help="factors during missing windows: hold the last window's values (default) or assume "
                        "the machine idle at the reference state; gaps are reported either way")


#: ``--split-by`` refuses a column that makes most runs shorter than this (a measurement, not a run label)
MIN_RUN_ROWS = 10


def split_by(rec: Recording, column: str) -> list[Recording]:
    """The runs of ``rec``: a new one wherever ``column`` changes value (missing cells continue the run)."""
    values = rec.extras.get(column)
    if values is None:
        have = ", ".join(sorted(rec.extras)) or "none"
        raise UsageError(f'{rec.source}: --split-by: no numeric column "{column}" (numeric extra columns: {have})')
    held = hold_missing(np.asarray(values, float))
    cuts = [0, *(np.flatnonzero(np.diff(held) != 0) + 1).tolist(), len(rec)]
    runs = []
    for a, b in itertools.pairwise(cuts):
        # a gap between two runs (the night between two days of a file with a time column) is rows of no
        # window: it belongs to neither, or a day of 207 rows ran to the next day's start, 1440 windows long
        rows = np.flatnonzero(rec.present[a:b])
        if rows.size:
            runs.append((a + int(rows[0]), a + int(rows[-1]) + 1))
    short = sum(b - a < MIN_RUN_ROWS for a, b in runs)
    if len(runs) > 2 and 2 * short > len(runs):  # a measurement, not a label (--split-by Ambient: 1550 runs)
        raise UsageError(f'{rec.source}: --split-by {column}: {len(runs)} runs, {short} of them under {MIN_RUN_ROWS} '
                         f"rows: the column changes value in most rows; expected one that labels runs (a day number, "
                         "a run id)")
    # the value as written (a date 20240105 stays whole, where :g made every run 2.02401e+07)
    return [replace(rec.slice(a, b), source=f"{rec.source}[{column}={held[a]:.15g}]") for a, b in runs]


def split_those_with(recs: list[Recording], column: str, others: Sequence[Recording] = ()) -> list[Recording]:
    """``recs`` with every recording that has ``column`` split into its runs; one without it stays whole.

    The experiments and a validation day given beside a file of several days have no day column: only the
    files that hold several runs are split. ``column`` in none of ``recs`` and ``others`` is a usage error.
    """
    if not any(column in r.extras for r in [*recs, *others]):
        have = "; ".join(f"{r.source}: {', '.join(sorted(r.extras)) or 'none'}" for r in [*recs, *others])
        known = {k for r in [*recs, *others] for k in r.extras}
        raise UsageError(f'--split-by: no recording has a numeric column "{column}"{did_you_mean(column, known)} '
                         f"(numeric extra columns: {have})")
    return [part for r in recs for part in (split_by(r, column) if column in r.extras else [r])]


def add_split_option(p: argparse.ArgumentParser, *, also: str = "") -> None:
    """``--split-by COLUMN``: a file holding several runs one after the other (a day number column)."""
    p.add_argument("--split-by", metavar="COLUMN",
                   help="a recording holds several runs one after the other (e.g. a day number column): start a "
                        "new recording wherever COLUMN changes value; each starts in its own equilibrium "
                        f"(recordings without COLUMN{also} stay whole)")


def read_recordings(paths: Sequence[str], profile: Profile, *, period_s: float | None,
                    require_displacement: bool) -> list[Recording]:
    """Each file as ``profile`` lays it out; warns (stderr) of an axis not measured beside unread look-alikes."""
    recs = [read_for_profile(p, profile, period_s=period_s, require_displacement=require_displacement)
            for p in paths]
    for r in recs:
        for text in unread_displacement(r, profile.recording.displacement_columns):
            print(f"cncgw: warning: {text}", file=sys.stderr)
    return recs


def read_history(args: argparse.Namespace, profile: Profile) -> Recording | None:
    """``--history FILE`` as one recording (None without it); a file of several ``--split-by`` runs is refused.

    Such a file (days 1-12) ran as one machine history only if its runs followed one another: which run came just
    before is for the user to give (a 12-day file taken whole made a day 14 27.7 um RMS off without a word).
    """
    if not args.history:
        return None
    (history,) = read_recordings([args.history], profile, period_s=args.period_s, require_displacement=False)
    split = getattr(args, "split_by", None)
    if split and split in history.extras:
        runs = split_by(history, split)
        if len(runs) > 1:
            names = ", ".join(recording_name(r.source) for r in runs[:3]) + (", ..." if len(runs) > 3 else "")
            raise UsageError(f"--history {args.history}: {len(runs)} runs of --split-by {split} ({names}): expected "
                             "the one run that ran just before (a file of it alone)")
    return history


def profile_arg(profile: Profile) -> str:
    """What to pass as ``--profile`` for ``profile`` in a command we print.

    A bundled one by its name (its path lies inside the installed package), any other by its path.
    """
    from gateway import BUNDLED

    try:
        bundled = profile.path.resolve().parent == BUNDLED.resolve()
    except OSError:
        bundled = False
    return profile.path.stem if bundled else str(profile.path)


def load_model_for(profile: Profile, path: str | Path | None) -> tuple[ThermalModel, Path]:
    """Load the model (default: the profile's) and check it fits the profile's factors, units and axes."""
    path = Path(path) if path else profile.model_path
    if not path.exists():
        folder = path.parent if path.parent.is_dir() else None
        near = did_you_mean(path.name, [p.name for p in folder.glob("*model*.toml")]) if folder is not None else ""
        raise ModelError(f"{path}: model file not found{near}; create it with `cncgw identify --profile "
                         f"{profile_arg(profile)} EXPERIMENTS... -o {path}`")
    model = load_model(path)
    problems = []
    for f in model.factors:
        if f not in profile.factor_names:
            problems.append(f'{path}: factor "{f}" is not in profile {profile.path} '
                            f"(its factors: {', '.join(profile.factor_names)})")
        elif model.units.get(f) and model.units[f] != profile.factor(f).unit:
            problems.append(f'{path}: factor "{f}" is in {model.units[f]} but profile {profile.path} says '
                            f"{profile.factor(f).unit}")
    for a in model.axes:
        if a not in profile.axes:
            problems.append(f"{path}: axis {a} is not among the profile's axes ({', '.join(profile.axes)})")
    foreign = [f for f in model.factors if f not in profile.factor_names]
    if foreign and len(foreign) * 2 >= len(model.factors) and model.machine and model.machine != profile.name:
        # most of its factors unknown: another machine's model, said first (then the lines that show it)
        problems.insert(0, f'{path}: a model of machine "{model.machine}", but profile {profile.path} is machine '
                           f'"{profile.name}" ({len(foreign)} of its {len(model.factors)} factors are not in the '
                           "profile): expected the model identified with this profile (--model, or the profile's "
                           "model file)")
    if problems:
        raise ModelError("\n".join(problems))
    return model, path


def progress_bar(total: int | None, desc: str) -> tuple[Callable[[str], None], Callable[[], None]]:
    """A tqdm bar on stderr (silent when stderr is not a terminal): (update with a message, close)."""
    import tqdm as tqdm_module
    from tqdm import tqdm

    tqdm_module.tqdm.monitor_interval = 0  # no monitor thread: our bars are updated by the work itself
    bar = tqdm(total=total, desc=desc, unit="fit", disable=None, leave=False)

    def update(message: str) -> None:
        bar.set_postfix_str(message, refresh=False)
        bar.update(1)

    return update, bar.close


def refuse_writing_over_inputs(outputs: dict[str, str | None], inputs: Sequence[str | None]) -> None:
    """Refuse an output option that names one of the command's input files (checked before any work).

    ``estimate REC.csv -o REC.csv`` replaced the recording with its estimates, ``--plot REC.csv`` with a PNG:
    recorded data lost to a slip of the keyboard.
    """
    given = [Path(p) for p in inputs if p]
    for option, out in outputs.items():
        if not out:
            continue
        for p in given:
            try:
                same = Path(out).resolve() == p.resolve() or (Path(out).exists() and Path(out).samefile(p))
            except OSError:
                same = False
            if same:
                raise UsageError(f"{option} {out}: that is an input of this command ({p}): expected a new file; "
                                 "it would be replaced")


def check_output(option: str, path: str | None, *, directory: bool = False) -> None:
    """Refuse, before any work, an output the command could not write at its end.

    A file whose folder does not exist, or (``directory``) a file where a directory goes (created if missing).
    """
    if not path:
        return
    p = Path(path)
    if directory:
        if p.exists() and not p.is_dir():
            raise UsageError(f"{option} {p}: a file, not a directory: expected a directory (created if missing)")
    elif not p.parent.is_dir():
        raise UsageError(f"{option} {p}: the folder {p.parent} does not exist: expected a file in an existing folder")


def check_rt_priority(value: int) -> None:
    """``--rt-priority`` of ``run`` and ``record``: 0 (the normal scheduler) or a SCHED_FIFO priority 1-99."""
    if not 0 <= value <= 99:
        raise UsageError(f"--rt-priority must be 0 (the normal scheduler) or 1-99 (SCHED_FIFO). Got {value}")


def fail_if_exists(path: Path, force: bool) -> None:
    """Refuse to replace ``path`` unless ``--force`` (checked before the work, so none is lost).

    Exit 1, as the exit-code table says of an output that exists without --force (and as diagnose's report).
    """
    if path.exists() and not force:
        raise GatewayError(f"{path} exists: pass --force to replace it, or -o another file")
