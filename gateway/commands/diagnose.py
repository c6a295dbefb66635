"""``cncgw diagnose``: where a model and recordings differ, what physics is missing, and a model with it."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gateway import plotting
from gateway.commands._common import (
    add_recording_options,
    add_split_option,
    check_output,
    load_model_for,
    positive_float,
    progress_bar,
    read_history,
    read_recordings,
    refuse_duplicates,
    split_those_with,
    warn_other_machine,
)
from gateway.errors import GatewayError, UsageError
from gateway.profile import Profile, load_profile
from gateway.recording import Recording, displacement_lookalikes


def _share(text: str) -> float:
    try:
        value = positive_float(text)
    except argparse.ArgumentTypeError:
        value = math.nan
    if not 0 < value < 1:  # one message for 0 and for 1.5 ("> 0" of 0 hid the upper bound)
        raise argparse.ArgumentTypeError(f"expected a number between 0 and 1 (exclusive), got {text!r}")
    return value


#: held-out blocks: a signed-rank test needs a few; a block shorter than an hour is no independent sample of a
#: thermal error (batch means: errors are correlated over hours)
MIN_BLOCKS, DEFAULT_BLOCKS, MIN_BLOCK_H = 3, 16, 1.0


def _blocks(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < MIN_BLOCKS:
        raise argparse.ArgumentTypeError(f"expected an integer >= {MIN_BLOCKS} (held-out blocks of time), got {text!r}")
    return value


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw diagnose``."""
    p = sub.add_parser(
        "diagnose", help="find what physics the model misses, add it, and show the fit improve on held-out data",
        description="Compare a model with recordings: judge first whether it is fit for compensation on the "
                    "recordings it did not train on, locate where the residual leaves its noise band, test "
                    "hypotheses of missing physics (room temperature, eddy loss ~ speed^2, a slow mode, cabinet "
                    "heat, bearing preload, dead time, a chiller...) with every path refitted beside them, on "
                    "held-out blocks of time with family-wise error control, classify measurement artefacts, "
                    "re-identify the model on all recordings with what was accepted, and write the best model "
                    "that passes on the held-out blocks.")
    p.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML)")
    p.add_argument("--model", metavar="MODEL", help="model file (default: the profile's)")
    p.add_argument("recordings", nargs="+", metavar="RECORDING", help="recordings with measured displacement (CSV)")
    p.add_argument("-o", "--output", metavar="REPORT_DIR",
                   help="write report.md, report.json, figures and <model>.diagnosed.model.toml here")
    p.add_argument("--json", action="store_true", help="print the report as JSON instead of text")
    p.add_argument("--validate", nargs="+", metavar="RECORDING", default=[],
                   help="recordings never used for fitting or selection: estimated with the identified and the written "
                        "model as cncgw estimate does (a recording that starts warm: its initial state from its "
                        "first hour, said so)")
    p.add_argument("--alpha", type=_share, default=0.05, help="family-wise error rate per round (default 0.05)")
    p.add_argument("--min-effect", type=_share, default=0.02, metavar="SHARE",
                   help="relevance: an accepted term's contribution RMS must reach this share of the largest peak "
                        "displacement of any axis (default 0.02)")
    p.add_argument("--min-gain", type=_share, default=0.1, metavar="SHARE",
                   help="relevance: share of an axis's held-out squared error it must remove (default 0.1)")
    p.add_argument("--blocks", type=_blocks, default=None, metavar="K",
                   help=f"held-out blocks of time (default {DEFAULT_BLOCKS}; at least {MIN_BLOCKS}; more than "
                        f"{DEFAULT_BLOCKS} only where each spans at least {MIN_BLOCK_H:g} h)")
    add_split_option(p, also=", e.g. the experiments,")
    p.add_argument("--history", metavar="RECORDING",
                   help="a recording that ran just before the first --validate recording: it starts in the state "
                        "this one left (recordings given that end one window before another starts are chained "
                        "that way on their own; the runs of a --split-by file never are, nor files read with "
                        "--period-s, whose times each count from 0: a --history read so is taken to end one "
                        "window before the first --validate recording starts)")
    p.add_argument("--use-signal", action="append", default=[], metavar="COLUMN",
                   help="a recorded column whose meaning you have checked (e.g. a temperature of a known part): a "
                        "hypothesis on it may be written into the model; other recorded signals are only named "
                        "(repeatable; room/ambient thermometers are always usable)")
    p.add_argument("--initial-state", choices=("fit", "rest"), default="fit",
                   help="fit (default): a recording that seems not to start at rest (cut while the machine worked; "
                        "while such are a minority, and not one of the model's experiments) runs from the hours of "
                        "work its first hours show, its own levels held from rest, so no fit takes its unknown start "
                        "for missing physics; rest: every recording starts in equilibrium with its first window")
    p.add_argument("--no-reidentify", action="store_true",
                   help="judge hypotheses only as terms on the frozen model and never re-identify its paths "
                        "(the earlier behaviour; faster, wrong when the missing physics acted during identification)")
    p.add_argument("--force", action="store_true", help="overwrite REPORT_DIR's files")
    add_recording_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Diagnose; print the verdict, conclusions and the models compared; write the report on request."""
    from gateway.diagnose import Options, diagnose, factor_infos, write_report
    from gateway.diagnose.api import validate, validation_summary
    from gateway.diagnose.report import to_json
    from gateway.replay import MIN_SCORED_WINDOWS

    check_output("-o", args.output, directory=True)
    if args.history and not args.validate:
        # it was read and dropped without a word: the diagnosed recordings each start on their own
        raise UsageError(f"--history {args.history}: it carries the machine's state into the first --validate "
                         "recording, and no --validate was given (expected --validate RECORDING with it)")
    profile = load_profile(args.profile)
    model, model_path = load_model_for(profile, args.model)
    recs = read_recordings(args.recordings, profile, period_s=args.period_s, require_displacement=False)
    hedges = []
    other = warn_other_machine(model, model_path, profile, "the model written keeps that machine's name")
    if other:
        hedges.append(other)
    out = Path(args.output) if args.output else None
    if out is not None and (out / "report.md").exists() and not args.force:
        raise GatewayError(f"{out}/report.md exists: pass --force to overwrite it")
    # a validation day may lack an axis (its sensor off), as a diagnosed one may: it is judged on the others;
    # one with no measured displacement at all is refused below
    vrecs = read_recordings(args.validate, profile, period_s=args.period_s, require_displacement=False) \
        if args.validate else []
    if args.split_by:
        recs, vrecs = split_those_with(recs, args.split_by, vrecs), split_those_with(vrecs, args.split_by, recs)
    recs, unread = _without_lookalikes(recs, profile, args.use_signal)
    fitted = refuse_duplicates(recs, model.factors,
                               counts="counts twice in the held-out blocks and doubles its evidence")
    _check_signals(args.use_signal, recs)
    options = Options(alpha=args.alpha, min_effect_share=args.min_effect, min_gain=args.min_gain,
                      blocks=_check_blocks(args.blocks, recs), reidentify=not args.no_reidentify,
                      use_signals=tuple(args.use_signal))
    # a validation recording that is also diagnosed would be scored on data the model was fitted on; one of a
    # few windows would be "RMS 0 um ... at rest"
    for v in vrecs:
        measured = int(np.isfinite(np.vstack(list(v.displacement.values()))).any(axis=0).sum()) \
            if v.displacement else 0
        if measured < MIN_SCORED_WINDOWS:
            columns = ", ".join(f'"{c}"' for c in profile.recording.displacement_columns.values())
            raise UsageError(f"--validate {v.source}: {measured} window(s) with measured displacement ({columns}): a "
                             f"validation needs at least {MIN_SCORED_WINDOWS} to say anything")
        same = fitted.get(v.fingerprint(model.factors))
        if same is not None:
            raise UsageError(f"--validate {v.source}: the same data as {same}, which is diagnosed: validation takes "
                             "recordings never used for fitting or selection (give it only after --validate)")
        for r in recs:  # a part of it diagnosed (days 1-4 diagnosed, the file of days 1-4 given to validate)
            shared = _shared_windows(v, r, model.factors)
            if shared >= max(MIN_SCORED_WINDOWS, SHARED_SHARE * len(r)):
                raise UsageError(f"--validate {v.source}: {shared} of its windows are the same data as {r.source} "
                                 "(the same times, inputs and measured displacement), which is diagnosed: validation "
                                 "takes recordings never used for fitting or selection")
    history = read_history(args, profile)
    # what it tries as it goes (a bar on a terminal, nothing in a pipe): a diagnosis takes tens of seconds
    update, close = progress_bar(None, "diagnose")
    try:
        d = diagnose(model, recs, factors=factor_infos(profile), options=options, gap_policy=args.gap_policy,
                     initial_state=args.initial_state, progress=update)
    finally:
        close()
    d.conclusions += hedges
    if unread:
        d.conclusions.append(f"not tried as signals: {', '.join(unread)} (each may be a measured displacement under "
                             "another name, which explains another axis only by moving with the same heat; "
                             "--use-signal tries one)")
    if args.period_s:
        hedges.append(f"rows were taken as {args.period_s:g} s apart (--period-s): every time constant and dead time "
                      "found scales with the true period")
        d.conclusions.append(hedges[-1])
    # with --period-s every file's times count from 0: one ending where another starts is no sign it ran before
    validations = validate(d, vrecs, earlier=recs, history=history, gap_policy=args.gap_policy,
                           chain=args.period_s is None) if vrecs else []
    if summary := validation_summary(d, validations):
        d.conclusions.append(summary)
    extra = {"model": str(model_path), "profile": str(profile.path)}
    written = {}
    if out is not None:
        # without matplotlib (an install without [engineering]) the report and the model are written all the
        # same: losing a diagnosis's minutes of work over its figures helps no one
        written = write_report(d, out, model_name=model_path.name.removesuffix(".toml").removesuffix(".model"),
                               title=f"{profile.name}, model {model_path.name}", extra=extra,
                               validations=validations, hedges=hedges, figures=plotting.available(),
                               profile=args.profile, recording_options=_recording_options(args))
        if not plotting.available():
            print(f"figures: skipped (matplotlib is not installed: {plotting.INSTALL_HINT})", file=sys.stderr)
    if args.json:
        print(json.dumps(to_json(d, model_file=str(written.get("model", "")), validations=validations) | extra,
                         indent=2))
        return 0
    print(f"diagnosis of {len(recs)} recording(s) with model {model_path} ({d.wall_s:.1f} s):")
    for c in d.conclusions:
        print(f"  {c}")
    print("held-out error per axis (each block predicted from the others), identified -> written model "
          f"({d.comparison.written.title}):")
    for a, b in d.before.items():
        if not b.windows:
            print(f"  {a}: measured in no held-out block")
            continue
        af = d.after.get(a, b)
        print(f"  {a}: RMS {b.rms_um:.3f} -> {af.rms_um:.3f} um, max |error| {b.max_abs_error_um:.3f} -> "
              f"{af.max_abs_error_um:.3f} um ({b.max_error_pct_of_peak:.1f} -> {af.max_error_pct_of_peak:.1f} % of "
              f"peak {b.peak_um:.3f} um)")
    for v in validations:
        print(f"validation {v.label} (never fitted; state at the start {v.start}):")
        for a, m in v.before.metrics.items():
            n = v.after.metrics.get(a)
            if n is not None:
                print(f"  {a}: RMS {m.rms_um:.3f} -> {n.rms_um:.3f} um, max |error| {m.max_abs_error_um:.3f} -> "
                      f"{n.max_abs_error_um:.3f} um")
    for path in written.values():
        print(f"wrote {path}")
    return 0


def _without_lookalikes(recs: list, profile: Profile, use_signals: list[str]) -> tuple[list, list[str]]:
    """``recs`` without the unread columns that may be a missing axis's displacement, and their names.

    ``x_mm`` beside no ``x_um`` (warned of when read) was tried as a recorded signal for y and z, which a
    displacement explains only by following the same heat; ``--use-signal`` keeps one.
    """
    out, names = [], []
    for r in recs:
        drop = {h for alike in displacement_lookalikes(r, profile.recording.displacement_columns).values()
                for h in alike if h in r.extras and h not in use_signals}
        names += [h for h in sorted(drop) if h not in names]
        out.append(dataclasses.replace(r, extras={k: v for k, v in r.extras.items() if k not in drop}) if drop else r)
    return out, names


def _check_signals(columns: list[str], recs: list) -> None:
    """Refuse ``--use-signal`` of a column no recording has, listing the columns they have."""
    have = sorted({c for r in recs for c in r.extras})
    for c in columns:
        if not any(c in r.extras for r in recs):
            raise UsageError(f"--use-signal {c}: no recording has a column {c!r} beside the profile's factors and "
                             f"displacement (recorded columns: {', '.join(have) or 'none'})")


#: a --validate recording holding this share of a diagnosed one's windows holds that recording
SHARED_SHARE = 0.25


def _shared_windows(v: Recording, r: Recording, factors: Sequence[str]) -> int:
    """The windows ``v`` and ``r`` share: the same time, every factor and measured displacement the same.

    Windows at rest with a displacement of zero are not counted (two files timed from 0 meet there by chance).
    """
    _, iv, ir = np.intersect1d(v.time_s, r.time_s, assume_unique=True, return_indices=True)
    if not len(iv):
        return 0
    same = np.ones(len(iv), dtype=bool)
    for f in factors:
        a, b = v.factors.get(f), r.factors.get(f)
        if a is None or b is None:
            return 0
        same &= a[iv] == b[ir]
    measured = np.zeros(len(iv), dtype=bool)
    for axis, a in v.displacement.items():
        b = r.displacement.get(axis)
        if b is None:
            continue
        both = np.isfinite(a[iv]) & np.isfinite(b[ir])
        same &= ~both | (a[iv] == b[ir])
        measured |= both & (a[iv] != 0)
    return int(np.count_nonzero(same & measured))


def _check_blocks(given: int | None, recs: list) -> int:
    """The held-out blocks: the default, or as given when each spans at least MIN_BLOCK_H.

    No more blocks than the default are always allowed: short recordings get the default's shorter blocks, as
    they always did.
    """
    if given is None:
        return DEFAULT_BLOCKS
    hours = sum(r.duration_s for r in recs) / 3600.0
    most = max(DEFAULT_BLOCKS, int(hours // MIN_BLOCK_H))
    if given > most:
        raise UsageError(f"--blocks {given}: these recordings hold {hours:.3g} h, so the blocks would be "
                         f"{hours / given:.2g} h long; a held-out block must span at least {MIN_BLOCK_H:g} h (thermal "
                         f"errors are correlated over hours): at most {most} here")
    return given


def _recording_options(args: argparse.Namespace) -> str:
    """The options the recordings were read with, as ``cncgw estimate`` must be given them to read the same."""
    opts = [f"--period-s {args.period_s:.15g}"] if args.period_s else []
    return " ".join(opts + ([f"--gap-policy {args.gap_policy}"] if args.gap_policy != "hold" else []))
