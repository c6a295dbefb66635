"""How often can the band land in 90-98 % at all? The bank's band on a truth drawn from its own model.

    .venv/bin/python bench/adaptive_ceiling.py [--draws 3] [--variants 0,1,2] [--seeds 1,2] [--days 4]
                                               [--intervals 1,2,4] [--scale-range 3.05e-5,8] [--set NAME=VALUE]
                                               [--residual-truth P]

``bench/adaptive.py`` counts the case-axes whose 95 % band covers the truth 90-98 % of a 4-day run. That count
mixes two things: how wrong the filter's model of the disturbance is (the room's smooth cycle is no
Gauss-Markov process), and how far one run's coverage scatters even when the model is right. This bench
measures the second: the truth is drawn from the filter's OWN state space, so the bank's Bayesian mixture is
as right as it can be, and whatever it misses is the ceiling of the count, not a fault of the model.

Per production run of the main bench (its factors and the identified model's contributions, effect ``room``:
the schedule does not depend on the effect) and per draw, each axis gets:

- gain errors drawn from the identification's prior (each path's sd, the stored correlation; scale 1),
  constant over the run;
- a disturbance drawn from :func:`gateway.adaptive.filter._drift_model` (offset, Gauss-Markov rate and walk)
  at a scale log-uniform in ``--scale-range`` (between the bank's smallest and largest scales, one grid
  step inside), its noise scaled by the model's motion exactly as the filter assumes;

the truth is the model's contributions with those gains plus the disturbance. With ``--residual-truth P`` an
axis's scale is, with probability P, drawn instead from what the identification's residual supports
(:func:`gateway.adaptive.filter.identification_scale_likelihood`): the truth of
``DriftSettings.residual_prior_weight = P``'s prior, so that setting can be checked against its own world as
well as against the log-uniform one. Probes (0.3 um, every 1, 2, 4 h)
and the replay are those of ``bench/adaptive.py``. Printed: the case-axes in 90-98 %, too wide and too narrow
per interval and axis, pooled per axis, and the same by how far the disturbance moves over one probe interval
against the probe's own noise (what the probes can resolve).
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # one BLAS thread: the matrices are small and the machine is shared
    for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_v, "1")

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from adaptive import (  # noqa: E402
    AXES,
    COVER_HI,
    COVER_LO,
    WINDOW_S,
    _floats,
    _ints,
    identified_model,
    probe_schedule,
    probes_for,
    production_run,
    settings_overrides,
)

from gateway.adaptive import DriftSettings, replay  # noqa: E402
from gateway.adaptive.filter import (  # noqa: E402
    _drift_model,
    gain_correlation,
    gain_sd,
    identification_scale_likelihood,
)


def draw_truth(contributions: np.ndarray, settings: DriftSettings, gsd: np.ndarray, gcorr: np.ndarray,
               scales: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The true displacement (axes, N): the filter's own state space at disturbance scale ``scales`` per axis."""
    n_a, n_in, n = contributions.shape
    phi, q, _ = _drift_model(settings, WINDOW_S)
    # the filter's activity: the model's motion (every path's |change|) in um/h over the reference
    act = (np.abs(np.diff(contributions, axis=2, prepend=contributions[:, :, :1])).sum(axis=1)
           * (3600.0 / WINDOW_S) / settings.activity_ref_um_per_h)
    out = np.empty((n_a, n))
    for i in range(n_a):
        cov = gsd[i][:, None] * gcorr[i] * gsd[i][None, :]
        g = rng.multivariate_normal(np.zeros(n_in), cov, method="eigh")
        chol = np.linalg.cholesky(q * scales[i] + 1e-18 * np.eye(2))
        noise = rng.standard_normal((n, 2))
        x = np.zeros(2)
        d = np.empty(n)
        for k in range(n):
            if k:
                x = phi @ x + np.sqrt(1.0 + act[i, k]) * (chol @ noise[k])
            d[k] = x[0]
        out[i] = ((1.0 + g)[:, None] * contributions[i]).sum(axis=0) + d
    return out


def interval_sd_um(settings: DriftSettings, scale: float, interval_h: float) -> float:
    """How far the disturbance moves (sd) over one probe interval from a known state, at rest, at ``scale``."""
    _, q, _ = _drift_model(settings, interval_h * 3600.0)
    return float(np.sqrt(scale * q[0, 0]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=3, help="truths drawn per production run")
    ap.add_argument("--days", type=int, default=4)
    ap.add_argument("--seeds", type=_ints, default=[1, 2])
    ap.add_argument("--variants", type=_ints, default=[0, 1, 2])
    ap.add_argument("--intervals", type=_floats, default=[1.0, 2.0, 4.0])
    ap.add_argument("--probe-sd-um", type=float, default=0.3)
    ap.add_argument("--scale-range", type=_floats, default=[8.0 ** -5, 8.0],
                    help="the disturbance's variance scale, log-uniform between these two")
    ap.add_argument("--residual-truth", type=float, default=0.0, metavar="P",
                    help="per axis with probability P the disturbance's scale is drawn from the identification "
                         "residual's likelihood instead (production adds nothing the hall did not have: "
                         "DriftSettings.residual_prior_weight's hypothesis), a grid scale times up to half a grid "
                         "step either way; default 0")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="set a DriftSettings field, as bench/adaptive.py --set")
    ap.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "cncgw-bench" / "adaptive")
    args = ap.parse_args(argv)
    if not 0.0 <= args.residual_truth <= 1.0:
        ap.error(f"--residual-truth: expected a probability in [0, 1], got {args.residual_truth}")
    if len(args.scale_range) != 2 or not 0 < args.scale_range[0] < args.scale_range[1]:
        ap.error(f"--scale-range: expected two values 0 < lo < hi, got {args.scale_range}")
    try:
        settings = DriftSettings(**settings_overrides(args.set))
    except ValueError as e:
        ap.error(f"--set: {e}")
    t0 = time.perf_counter()
    rows = []  # (interval, axis, scale, coverage)
    for v in args.variants:
        model = identified_model(v, args.cache)
        gsd, gcorr = gain_sd(model, settings.gain_sd_default), gain_correlation(model)
        levels = np.array(sorted(set(settings.scales)))
        lik = identification_scale_likelihood(model, settings, levels)
        for seed in args.seeds:
            run = production_run("room", v, seed, args.days, args.cache)
            t = run["time_s"]
            u = np.array([run[f"factor_{f}"] for f in model.factors])
            contributions = model.discretize(WINDOW_S).contributions(u - model.reference_vector()[:, None])
            for d in range(args.draws):
                rng = np.random.default_rng([seed, v, d, 77])
                lo, hi = np.log(args.scale_range)
                scales = np.exp(rng.uniform(lo, hi, len(AXES)))
                if args.residual_truth > 0 and lik is not None:
                    step = np.log(levels[1] / levels[0]) if levels.size > 1 else 0.0
                    for i in range(len(AXES)):
                        if rng.random() < args.residual_truth and np.all(np.isfinite(lik[i])):
                            scales[i] = rng.choice(levels, p=lik[i]) * np.exp(rng.uniform(-step / 2, step / 2))
                truth = draw_truth(contributions, settings, gsd, gcorr, scales, rng)
                for ih in args.intervals:
                    probes = probes_for(truth, t, probe_schedule(t, ih), args.probe_sd_um, 1000 * seed + v + 7 * d)
                    rp = replay(model, contributions, t, probes, window_s=WINDOW_S, settings=settings)
                    b_lo, b_hi = rp.band_um()
                    cov = ((truth >= b_lo) & (truth <= b_hi)).mean(axis=1)
                    rows.extend((ih, i, scales[i], cov[i]) for i in range(len(AXES)))
    n_cases = len(args.variants) * len(args.seeds) * args.draws
    print(f"{n_cases} truths drawn from the filter's own model x {len(args.intervals)} intervals x {len(AXES)} axes "
          f"({time.perf_counter() - t0:.0f} s); disturbance scale log-uniform in "
          f"{args.scale_range[0]:.3g}..{args.scale_range[1]:.3g}")
    ih_a = np.array([r[0] for r in rows])
    ax_a = np.array([r[1] for r in rows])
    sc_a = np.array([r[2] for r in rows])
    cv_a = np.array([r[3] for r in rows])

    def counts(mask: np.ndarray) -> str:
        c = cv_a[mask]
        inside = ((c >= COVER_LO) & (c <= COVER_HI)).sum()
        return (f"{inside}/{c.size} in {COVER_LO:.0%}-{COVER_HI:.0%}, {(c > COVER_HI).sum()} too wide, "
                f"{(c < COVER_LO).sum()} too narrow (median {100 * np.median(c):.1f} %, pooled {100 * c.mean():.1f} %)")

    for ih in args.intervals:
        print(f"  every {ih:g} h: "
              + "; ".join(f"{a} {counts((ih_a == ih) & (ax_a == i))}" for i, a in enumerate(AXES)))
    print(f"  all: {counts(np.ones_like(cv_a, bool))}")
    print("  pooled per axis: " + ", ".join(f"{a} {100 * cv_a[ax_a == i].mean():.1f} %" for i, a in enumerate(AXES)))
    print(f"  by how far the disturbance moves over one probe interval (sd, at rest) against the probe's "
          f"{args.probe_sd_um:g} um:")
    ratio = np.array([interval_sd_um(settings, s, ih) for s, ih in zip(sc_a, ih_a, strict=True)]) / args.probe_sd_um
    for lo, hi in ((0.0, 0.5), (0.5, 2.0), (2.0, np.inf)):
        m = (ratio >= lo) & (ratio < hi)
        if m.any():
            print(f"    {lo:g}-{hi:g}x: {counts(m)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
