"""``cncgw estimate``: a model and recordings in, estimated displacement and its errors out."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

from gateway import plotting
from gateway.commands._common import (
    add_recording_options,
    add_split_option,
    check_output,
    load_model_for,
    read_history,
    read_recordings,
    refuse_writing_over_inputs,
    split_those_with,
    warn_other_machine,
)
from gateway.errors import GatewayError, UsageError
from gateway.model.coverage import IMPLAUSIBLE
from gateway.prepare import INITIAL_CHOICES
from gateway.profile import load_profile
from gateway.recording import continued, recording_name, runs_on_from, split_part
from gateway.replay import (
    ALIGN_CHOICES,
    INITIAL_STATES,
    estimate,
    metrics_json,
    plot_estimates,
    starts_warm,
    works_at_start,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``cncgw estimate``."""
    p = sub.add_parser(
        "estimate", help="estimate displacement for recordings and report the errors",
        description="Estimate the thermal displacement for recordings and, where displacement was measured, "
                    "report per axis the RMS error, the max |error|, the peak |displacement| and the max error "
                    "as a percentage of the peak.")
    p.add_argument("--profile", required=True, metavar="PROFILE", help="machine profile (TOML)")
    p.add_argument("--model", metavar="MODEL", help="model file (default: the profile's)")
    p.add_argument("recordings", nargs="+", metavar="RECORDING", help="recordings (CSV)")
    p.add_argument("-o", "--output", metavar="PRED",
                   help="write estimates as CSV: a file for one recording, a directory for several")
    p.add_argument("--json", action="store_true", help="print the metrics as JSON instead of text")
    p.add_argument("--plot", metavar="PNG", help="draw measured vs estimated displacement and the residual")
    p.add_argument("--initial", choices=INITIAL_CHOICES, default="first",
                   help="initial state: in equilibrium with the first window (default) or with the model's "
                        "reference levels (for recordings that start mid-work)")
    p.add_argument("--align", choices=ALIGN_CHOICES, default="start",
                   help="measured zero: equal to the estimate at the first measured window (default), as "
                        "recorded (none), or best constant offset (optimistic)")
    p.add_argument("--initial-state", choices=INITIAL_STATES, default="rest",
                   help="the model's state at the start: at rest (default), or fitted to the first hour of measured "
                        "displacement as the state a heat history of its inputs leaves (fit: a recording that "
                        "starts warm)")
    p.add_argument("--history", metavar="RECORDING",
                   help="a recording that ended before the first one (the previous day): the model runs over it "
                        "first, so the recording starts in the state it left; with several recordings, each "
                        "one is the next one's history (read with --period-s, whose times each count from 0: "
                        "taken to end one window before the recording starts, so give one that ran just before it; "
                        "with --split-by, a file of one run)")
    p.add_argument("--probes", metavar="PROBES",
                   help="a probe CSV (time, seq, x_um, y_um, z_um, sd_um): the estimate is the model updated by "
                        "the probes taken during each recording, with its 95 %% band; -o writes it with "
                        "<axis>_sd_um and <axis>_model_um columns")
    p.add_argument("--force", action="store_true",
                   help="replace prediction files -o would write that exist (refused without it, before any work)")
    add_recording_options(p)
    add_split_option(p)
    p.set_defaults(func=run)


def prediction_paths(output: str, sources: list[str], *, force: bool) -> list[Path]:
    """Where ``-o OUTPUT`` writes each recording's estimates, checked before any work.

    OUTPUT itself for one recording (unless it is a directory), else ``OUTPUT/<recording>.pred.csv`` per
    recording. Refused: two recordings that would write one file (``d1/log.csv``, ``d2/log.csv``: one would
    replace the other), and, without ``--force``, a prediction file that exists (a second run with other
    options silently replaced the first one's file).
    """
    out = Path(output)
    if len(sources) == 1 and not out.is_dir():
        paths = [out]
    else:
        if out.exists() and not out.is_dir():
            raise GatewayError(f"{out}: expected a directory for {len(sources)} recordings")
        files: dict[str, str] = {}  # prediction file name -> the recording written to it
        for source in sources:
            name = f"{recording_name(source)}.pred.csv"
            if name in files:
                raise UsageError(f"-o {out}: {files[name]} and {source} would both be written to {out / name}: "
                                 "expected recordings of distinct file names (estimate them one folder at a time)")
            files[name] = source
        paths = [out / name for name in files]
    there = [p for p in paths if p.is_file()]
    if there and not force:
        more = f" (and {len(there) - 1} more of the {len(paths)} it would write)" if len(there) > 1 else ""
        raise GatewayError(f"{there[0]} exists{more}: pass --force to replace it, or -o another "
                           f"{'file' if len(paths) == 1 and paths[0] == out else 'directory'}")
    return paths


def _write_predictions(output: str, paths: list[Path], items: list[Any], meta: dict[str, str]) -> None:
    """Each estimate's CSV (``to_csv``) to its path from :func:`prediction_paths`.

    A directory ``-o`` is made if missing; a file's folder must exist (the error says so).
    """
    if paths != [Path(output)]:
        Path(output).mkdir(parents=True, exist_ok=True)
    for path, item in zip(paths, items, strict=True):
        path.write_text(item.to_csv({**meta, "recording": item.recording}))


def run(args: argparse.Namespace) -> int:
    """Estimate every recording; print metrics; write CSV and plot on request."""
    if args.plot:
        plotting.require("--plot")
    refuse_writing_over_inputs({"-o": args.output, "--plot": args.plot},
                               [*args.recordings, args.history, args.probes, args.model, args.profile])
    check_output("--plot", args.plot)
    profile = load_profile(args.profile)
    model, model_path = load_model_for(profile, args.model)
    warn_other_machine(model, model_path, profile, "these are the figures of another machine's model")
    recs = read_recordings(args.recordings, profile, period_s=args.period_s, require_displacement=False)
    if args.split_by:
        recs = split_those_with(recs, args.split_by)
    paths = prediction_paths(args.output, [r.source for r in recs], force=args.force) if args.output else []
    history = read_history(args, profile)
    if history is not None:
        # given as its own history too (a user following "--history A" kept A among the recordings): the history
        # must end before it starts, which said "ends at t=36000 s, not before A starts" of one file
        same = [r.source for r in recs if r.fingerprint(model.factors) == history.fingerprint(model.factors)]
        if same:
            raise UsageError(f"--history {args.history}: the same data as the recording {same[0]}: a history runs "
                             "before the recordings (give it only after --history)")
    if args.probes:
        return _run_probed(args, profile, model, model_path, recs, history, paths)
    ests = []
    for r in recs:
        history = _ran_before(history, r, args)
        e = estimate(model, r, initial=args.initial, gap_policy=args.gap_policy, align=args.align, history=history,
                     initial_state=args.initial_state)
        if history is None and not args.period_s:
            # the one given just before it ended one window before it starts: the machine did not rest between
            # them, yet this one starts at rest (diagnose --validate carries such a one; here --history does)
            before = [p for p in recs if p is not r and runs_on_from(p, r)]
            if before:
                e = dataclasses.replace(e, notes=(*e.notes, f"it starts one window after {before[0].source} ends, yet "
                                                            f"is estimated on its own: --history {before[0].source} "
                                                            "starts it in the state that one left"))
        if history is None and args.initial_state == "rest":
            # a recording that starts mid-work, estimated from rest: its figures are of the wrong start (diagnose
            # --validate estimates such a one from its first hour): said, with the option that does
            warm = starts_warm(model, r, gap_policy=args.gap_policy)
            if warm:
                e = dataclasses.replace(e, notes=(*e.notes, _not_at_rest(warm, working=bool(works_at_start(model, r)),
                                                                          initial=args.initial)))
        ests.append(e)
        history = _carried(history, r)
    if paths:
        _write_predictions(args.output, paths, ests, {"model": str(model_path), "profile": str(profile.path)})
    if args.json:
        print(metrics_json(ests))
    else:
        for e in ests:
            print(f"{e.recording} (model {model_path}):")
            for note in sorted(e.notes, key=lambda n: not n.startswith(IMPLAUSIBLE)):  # warnings first
                print(f"  {'warning' if note.startswith(IMPLAUSIBLE) else 'note'}: {note}")
            if not e.metrics:
                print("  no measured displacement: estimates only")
            for m in e.metrics.values():
                print(f"  {m.line()}")
    if args.plot:
        plot_estimates(ests, args.plot, title=f"{profile.name}: {model_path.name}")
        if not args.json:
            print(f"wrote {args.plot}")
    return 0


def _not_at_rest(why: str, *, working: bool, initial: str) -> str:
    """The note for a recording estimated from rest that seems not to start at rest (``why``).

    ``working``: a factor is away from its rest level at the first window; with ``--initial first`` (the
    default) the recording is then taken in equilibrium with that window, as if it had worked so for ever,
    which is neither a machine that has just started nor one warm from an unknown day.
    """
    if working and initial == "first":
        return (f"it seems not to start at rest ({why}), and is estimated in equilibrium with its first window (as "
                "if it had worked so for ever): --initial reference --initial-state fit estimates its state from "
                "its first hour, as heat since the model's reference levels (what diagnose --validate does); "
                "--initial reference alone starts it cold at those levels, right only for a machine that has just "
                "started")
    return (f"it seems not to start at rest ({why}), and is estimated from rest: --initial-state fit estimates its "
            "initial state from its first hour")


def _ran_before(history: Any, rec: Any, args: argparse.Namespace) -> Any:
    """``history`` as what ``rec`` starts from (as it is, or None).

    Files read with ``--period-s`` each count their times from 0, so a history given or carried is taken to end
    one window before ``rec`` starts.
    """
    return history.ending_before(rec) if args.period_s and history is not None else history


def _carried(history: Any, rec: Any) -> Any:
    """The history the next recording starts from: ``history`` run on through ``rec``.

    None after a run of a ``--split-by`` file: each run starts in its own equilibrium.
    """
    if history is None or split_part(rec.source):
        return None
    return continued(history, rec)


def _run_probed(args: argparse.Namespace, profile: Any, model: Any, model_path: Path, recs: list[Any],
                history: Any, paths: list[Path]) -> int:
    """``--probes``: the model updated by the probe file's probes, per recording (see gateway.adaptive)."""
    from gateway.adaptive.offline import estimate_with_probes
    from gateway.adaptive.probes import read_probes

    if args.initial_state != "rest":
        raise UsageError("--probes: the probes teach the state the model misses; --initial-state fit is not "
                         "used with them (expected --initial-state rest)")
    probes = read_probes(args.probes, axes=model.axes)
    runs, figures = [], []
    for r in recs:
        history = _ran_before(history, r, args)
        base = estimate(model, r, initial=args.initial, gap_policy=args.gap_policy, align=args.align,
                        history=history)
        pr = estimate_with_probes(model, r, probes, initial=args.initial, gap_policy=args.gap_policy,
                                  history=history)
        runs.append(pr)
        figures.append(pr.figures(base.measured))
        history = _carried(history, r)
    if probes and all(pr.outside == len(probes) for pr in runs):
        # the figures below are then the model's alone: most likely the probes' clock is not the recordings'
        spans = "; ".join(f"{r.source}: {r.time_s[0]:.0f}-{r.time_s[-1]:.0f} s" for r in recs if len(r))
        print(f"cncgw: warning: {args.probes}: none of its {len(probes)} probes (time {probes[0].time_s:.0f}-"
              f"{probes[-1].time_s:.0f} s) falls within a recording ({spans}): the estimates below are the model's "
              "alone; expected probe times on the recordings' clock (seconds or ISO 8601, as their time column)",
              file=sys.stderr)
    if paths:
        meta = {"model": str(model_path), "profile": str(profile.path), "probes": str(args.probes)}
        _write_predictions(args.output, paths, runs, meta)
    if args.json:
        print(json.dumps([{"recording": pr.recording, "probes_applied": pr.applied(), "refused": pr.refused(),
                           "probes_outside": pr.outside, "axes": fig} for pr, fig in zip(runs, figures, strict=True)],
                         indent=1))
        return 0
    for pr, fig in zip(runs, figures, strict=True):
        print(f"{pr.recording} (model {model_path}, updated by {args.probes}): {pr.applied()} probe-axes applied, "
              f"{len(pr.refused())} refused" + (f", {pr.outside} probes outside this recording" if pr.outside else ""))
        for line in pr.refused():
            print(f"  refused: {line}")
        if not fig:
            print("  no measured displacement: estimates only")
        for a, f in fig.items():
            print(f"  {a}: RMS {f['rms_um']:.3f} um, max |error| {f['max_abs_error_um']:.3f} um, the 95 % band covers "
                  f"{100 * f['band_coverage']:.1f} % ({f['windows']} windows)")
    return 0
