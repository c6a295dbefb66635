"""The model updated by probes (gateway.adaptive): what it learns, how far to trust it, what it refuses."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import math
import sys
from types import MappingProxyType

import numpy as np
import pytest
from tests_paths import PROFILES, ROOT

from gateway.adaptive import AdaptiveEstimator, DriftSettings, Probe, replay
from gateway.adaptive.filter import Z95, detrended_drift_variance, identification_scale_likelihood
from gateway.adaptive.probes import SEQ_MODULUS
from gateway.model import FirstOrder, PathTF, ThermalModel, load_model

DT = 60.0
H = 60  # windows an hour


def small_model(gain_sd: float = 0.05) -> ThermalModel:
    """z grows 0.01 um per unit of heat q with a 1 h time constant (10 um at q = 1000)."""
    path = PathTF(axis="z", factor="q", terms=(FirstOrder(gain=0.01, tau_s=3600.0),),
                  sd=MappingProxyType({"gain": 0.01 * gain_sd}))
    return ThermalModel(axes=("z",), factors=("q",), units={"q": "W"}, reference={"q": 0.0},
                        paths={("z", "q"): path})


def work_day(hours: int = 16) -> np.ndarray:
    """Heat q: 2 h at rest, then on 3 h / off 1 h."""
    k = np.arange(hours * H)
    return np.where((k >= 2 * H) & ((k - 2 * H) % (4 * H) < 3 * H), 1000.0, 0.0)[None, :]


def run(truth_extra, *, probes_every_h: float = 1.0, extra_probes=(), sd_um: float = 0.3, seed: int = 3,
        hours: int = 16):
    """The small model over a work day; truth = model + ``truth_extra(t_h)``; hourly probes of the truth."""
    model = small_model()
    du = work_day(hours)
    C = model.discretize(DT).contributions(du)
    t = DT * np.arange(1, du.shape[1] + 1)
    truth = C.sum(axis=1)[0] + truth_extra(t / 3600.0)
    rng = np.random.default_rng(seed)
    step = round(probes_every_h * H)
    probes = [Probe(seq=q + 1, time_s=float(t[k]), values_um={"z": float(truth[k] + sd_um * rng.standard_normal())},
                    sd_um=sd_um) for q, k in enumerate(range(step - 1, len(t), step))]
    rp = replay(model, C, t, [*probes, *extra_probes], window_s=DT)
    return rp, truth, probes, t


def drift(t_h):
    """A part that warms 2 um/h from hour 3 to hour 9, then stays."""
    return 2.0 * np.clip(t_h - 3.0, 0.0, 6.0)


def test_probes_teach_a_drift_the_model_does_not_know():
    rp, truth, _, t = run(drift)
    err_updated = truth - rp.estimate_um[0]
    err_model = truth - rp.model_um[0]
    late = t >= 4 * 3600
    assert np.sqrt(np.mean(err_model[late] ** 2)) > 8.0  # the drift the model misses (up to 12 um)
    assert np.sqrt(np.mean(err_updated[late] ** 2)) < 1.0
    # the drift stops at hour 9: the next hour overshoots (its rate is extrapolated), the probe after fixes it
    assert np.abs(err_updated[t >= 11 * 3600]).max() < 0.7
    lo, hi = rp.band_um()
    covered = (truth >= lo[0]) & (truth <= hi[0])
    assert covered[late].mean() >= 0.85
    assert all(d.accepted for d in rp.decisions), [d.describe() for d in rp.decisions if not d.accepted]


def test_the_band_narrows_with_probes_and_widens_between_them():
    rp, _, probes, t = run(drift)
    sd = rp.sd_um[0]
    k_probe = int(np.searchsorted(t, probes[5].time_s))
    assert sd[k_probe] < sd[k_probe - 1]  # a probe narrows it
    assert sd[k_probe + H - 1] > sd[k_probe]  # an hour later it has widened again
    assert sd[k_probe] < 1.0


def test_the_updated_model_beats_zeroing_at_each_probe():
    rp, truth, probes, t = run(drift, probes_every_h=2.0)
    zap = np.zeros_like(truth)
    for p in probes:
        zap[t >= p.time_s] = p.values_um["z"]
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    assert rms(truth - rp.estimate_um[0]) < 0.5 * rms(truth - zap)


def _bad(seq: int, t_s: float, z: float) -> Probe:
    return Probe(seq=seq, time_s=t_s, values_um={"z": z}, sd_um=0.3)


def test_a_gross_outlier_is_refused_and_changes_nothing():
    clean, truth, probes, t = run(drift)
    k = int(np.searchsorted(t, probes[6].time_s)) + 30  # half an hour after probe 7
    # numbers between the good ones: renumber the good ones 10, 20, ...
    model = small_model()
    C = model.discretize(DT).contributions(work_day())
    good = [Probe(seq=10 * p.seq, time_s=p.time_s, values_um=p.values_um, sd_um=p.sd_um) for p in probes]
    base = replay(model, C, t, good, window_s=DT)
    np.testing.assert_array_equal(base.estimate_um, clean.estimate_um)
    outlier = _bad(75, float(t[k]), float(truth[k] + 25.0))
    dirty = replay(model, C, t, [*good, outlier], window_s=DT)
    refused = [d for d in dirty.decisions if not d.accepted]
    assert len(refused) == 1
    assert refused[0].seq == 75
    assert refused[0].reason.startswith("outlier:")
    assert refused[0].innovation_sigma > 3.0
    np.testing.assert_array_equal(dirty.estimate_um, base.estimate_um)
    np.testing.assert_array_equal(dirty.sd_um, base.sd_um)


def test_a_reversed_sign_is_named():
    model = small_model()
    C = model.discretize(DT).contributions(work_day())
    t = DT * np.arange(1, C.shape[2] + 1)
    est = AdaptiveEstimator(model, window_s=DT)
    k = 5 * H  # the machine has worked 3 h: the model says +9.5 um
    for j in range(k):
        est.step(C[:, :, j], t[j])
        if (j + 1) % H == 0 and j + 1 < k:  # hourly probes that agree with the model
            assert est.probe(_bad(j // H + 1, float(t[j]), float(C[0, 0, j])))[0].accepted
    y = est.estimate()[0].estimate_um
    assert y > 5.0
    (d,) = est.probe(_bad(10, float(t[k - 1]), -y))
    assert not d.accepted
    assert d.reason.startswith("wrong sign:"), d.reason
    assert est.estimate()[0].estimate_um == y


def _estimator_with_one_probe():
    model = small_model()
    est = AdaptiveEstimator(model, window_s=DT)
    est.step(np.zeros((1, 1)), 60.0)
    est.step(np.zeros((1, 1)), 120.0)
    (d,) = est.probe(_bad(7, 120.0, 0.1))
    assert d.accepted
    return est


@pytest.mark.parametrize(("probe", "reason"), [
    (_bad(7, 120.0, 0.4), "repeated sequence number 7 with other values"),
    (_bad(6, 120.0, 0.1), "stale sequence number 6: the last probe applied was 7"),
    (_bad(7 + SEQ_MODULUS // 2, 120.0, 0.1), "stale sequence number"),
    (_bad(8, 30.0, 0.1), "before the last probe's 120 s"),
    (_bad(8, 240.0, 0.1), "after the last estimated window (120 s)"),
    (_bad(8, 120.0, 1500.0), "axis z: value 1500.0 um is outside +-1000 um"),
    (_bad(8, 120.0, math.nan), "axis z: value nan um"),
    (Probe(seq=8, time_s=120.0, values_um={"z": 0.1}, sd_um=0.0), "uncertainty 0.0 um: expected > 0"),
    (Probe(seq=8, time_s=120.0, values_um={"w": 0.1}, sd_um=0.3), "axis 'w' is not one of the model's axes z"),
    (Probe(seq=8, time_s=120.0, values_um={}, sd_um=0.3), "no axis probed"),
    (_bad(SEQ_MODULUS, 120.0, 0.1), "sequence number 65536 is outside 0..65535"),
])
def test_bad_probes_are_refused_with_their_reason(probe, reason):
    est = _estimator_with_one_probe()
    before = est.estimate()
    decisions = est.probe(probe)
    assert len(decisions) == 1
    assert not decisions[0].accepted
    assert reason in decisions[0].reason, decisions[0].reason
    assert est.estimate() == before


def test_the_same_probe_read_again_is_ignored_and_numbers_wrap():
    est = _estimator_with_one_probe()
    assert est.probe(_bad(7, 120.0, 0.1)) == []  # the register block read twice: nothing to say
    est.step(np.zeros((1, 1)), 180.0)
    est2 = AdaptiveEstimator(small_model(), window_s=DT)
    est2.step(np.zeros((1, 1)), 60.0)
    assert est2.probe(_bad(SEQ_MODULUS - 1, 60.0, 0.0))[0].accepted
    est2.step(np.zeros((1, 1)), 120.0)
    assert est2.probe(_bad(0, 120.0, 0.0))[0].accepted  # 65535 -> 0 is the next number


def test_a_real_step_is_learned_after_two_probes_agree():
    """A fixture re-clamped: +15 um at hour 6. One probe off is an outlier; two that agree are a change."""
    rp, truth, _probes, t = run(lambda t_h: np.where(t_h >= 6.0, 15.0, 0.0), hours=12)
    after = [d for d in rp.decisions if d.time_s >= 6 * 3600]
    assert not after[0].accepted
    assert after[0].reason.startswith("outlier:")
    assert after[1].accepted
    assert after[1].reason.startswith("re-anchored:"), after[1].reason
    k = int(np.searchsorted(t, after[1].time_s))
    assert np.abs(truth[k:] - rp.estimate_um[0, k:]).max() < 1.5


def test_without_probes_the_band_is_the_identification_gain_uncertainty_and_the_drift():
    _rp, _truth, _, t = run(lambda t_h: 0.0 * t_h, extra_probes=())
    model = small_model(gain_sd=0.05)
    C = model.discretize(DT).contributions(work_day())
    alone = replay(model, C, t, [], window_s=DT)
    np.testing.assert_allclose(alone.estimate_um, alone.model_um, atol=1e-12)
    # the band starts at the gain's share (5 % of the model's output over the bank's gain scales) and grows
    assert alone.sd_um[0, 0] < 0.05
    assert alone.sd_um[0, -1] > alone.sd_um[0, 3 * H]


@pytest.mark.parametrize("sd_um", [0.3, 1.0])
def test_the_band_is_about_the_truth_not_the_probe_noise(sd_um):
    # a model that is right, probed every hour for two days: after a day the band is narrower than a single
    # probe's own 95 % interval (the probes' noise is averaged out; it belongs in the innovation, not the band),
    # and it still covers the truth
    rp, truth, _, _ = run(lambda t_h: 0.0 * t_h, hours=48, sd_um=sd_um)
    half = Z95 * rp.sd_um[0]
    err = np.abs(truth - rp.estimate_um[0])
    day = 24 * H
    assert half[day:].max() < Z95 * sd_um
    assert np.sqrt(np.mean(err[day:] ** 2)) < sd_um / 2
    assert np.mean(err[H:] <= half[H:]) >= 0.95


def test_the_band_widens_beyond_the_models_coverage_as_much_as_probes_there_support():
    # identified up to 1000 W; a day inside, probes every 4 h; then two 4 h excursions at 3000 W (hours 25-29 and
    # 37-41). The bank's members differ in how much they widen beyond coverage (none, or a 10 % gain sd per log
    # distance beyond, prior weight 0.1); the probes beyond weigh them.
    from dataclasses import replace

    from gateway.adaptive.offline import model_beyond
    from gateway.model.coverage import Coverage

    model = replace(small_model(), coverage=Coverage(ranges={"q": (0.0, 1000.0)}))
    k = np.arange(48 * H)
    q = np.where((k // H) % 4 < 2, 0.0, 1000.0)
    first = (k >= 25 * H) & (k < 29 * H)
    second = (k >= 37 * H) & (k < 41 * H)
    q[first | second] = 3000.0
    q = q[None, :]
    C = model.discretize(DT).contributions(q)
    t = DT * (k + 1.0)
    beyond = model_beyond(model, q)
    out = beyond[0] > 0
    assert out.sum() == 8 * H
    bank = DriftSettings(extrapolation_gain_sds=(0.0, 0.1), extrapolation_prior=0.1)
    off = DriftSettings(extrapolation_gain_sds=(0.0,))

    def runs(gain_error):
        truth = model.discretize(DT).contributions(q * np.where(q > 1000.0, 1.0 + gain_error, 1.0)).sum(axis=1)[0]
        rng = np.random.default_rng(1)
        probes = [Probe(seq=n + 1, time_s=float(t[j]), values_um={"z": float(truth[j] + 0.3 * rng.standard_normal())},
                        sd_um=0.3) for n, j in enumerate(range(4 * H - 1, len(t), 4 * H))]
        return truth, *(replay(model, C, t, probes, window_s=DT, beyond=beyond, settings=s) for s in (off, bank))

    # out there the heat acts 8 % more than the model extrapolates (2.1 um at most on a 33 um peak)
    truth, rp_off, rp_bank = runs(0.08)
    covered_off, covered = (np.abs(truth - rp.estimate_um[0]) <= Z95 * rp.sd_um[0] for rp in (rp_off, rp_bank))
    assert covered_off[first].mean() < 0.5  # the band learned inside is too narrow out there
    assert covered[first].mean() >= 0.9
    assert covered[second].mean() >= 0.9
    # inside, before the first excursion, nothing changed (but for the weight floor, shared evenly by twice as
    # many members: 4e-5 relative); 4 h (4 time constants) after each, back inside, the
    # band is within 1.25x the band that never widened (the extrapolated heat has gone, and so has the widening)
    np.testing.assert_allclose(rp_bank.sd_um[0, : 25 * H], rp_off.sd_um[0, : 25 * H], rtol=1e-4)
    settled = ((k >= 33 * H) & (k < 37 * H)) | (k >= 45 * H)
    assert (rp_bank.sd_um[0, settled] / rp_off.sd_um[0, settled]).max() < 1.25
    # out there the band is a fraction of the output, not a multiple
    assert (Z95 * rp_bank.sd_um[0, out]).max() < 0.25 * np.abs(rp_bank.model_um[0, out]).max()

    # the model right out there: the first excursion widens the band (nothing told the bank yet), its probe
    # beyond finds no error, and the second excursion's band is within 1.25x of the band that never widened
    _, rp_off, rp_bank = runs(0.0)
    ratio = rp_bank.sd_um[0] / rp_off.sd_um[0]
    assert np.median(ratio[first]) > 1.5
    assert ratio[second].max() < 1.25


def test_settings_are_checked():
    with pytest.raises(ValueError, match="rate_tau_h must be finite and > 0"):
        DriftSettings(rate_tau_h=0.0)
    with pytest.raises(ValueError, match="scales must be positive"):
        DriftSettings(scales=())
    with pytest.raises(ValueError, match="reanchor_after must be >= 2"):
        DriftSettings(reanchor_after=1)
    with pytest.raises(ValueError, match=r"extrapolation_gain_sds must be one or more values >= 0. Got \(0.0, -0.1\)"):
        DriftSettings(extrapolation_gain_sds=(0.0, -0.1))
    with pytest.raises(ValueError, match=r"gain_scale_prior_decades must be None or finite and > 0. Got 0.0"):
        DriftSettings(gain_scale_prior_decades=0.0)
    with pytest.raises(ValueError, match=r"residual_prior_weight must be in \[0, 1\). Got 1.0"):
        DriftSettings(residual_prior_weight=1.0)


def test_gain_scale_prior_weighs_the_identifications_covariance_most():
    """With gain_scale_prior_decades the bank's weights start log-normal about the identification's own gain sd."""
    model = small_model()
    even = AdaptiveEstimator(model, window_s=DT)
    prior = AdaptiveEstimator(model, window_s=DT, settings=DriftSettings(gain_scale_prior_decades=0.5))
    for est in (even, prior):
        est.step(np.zeros((1, 1)), DT)
    g = DriftSettings().gain_scales  # variance factors 0.01 .. 100: sd factors 0.1 .. 10
    w_even = even.weights()[0].reshape(-1, len(g)).sum(axis=0)
    w_prior = prior.weights()[0].reshape(-1, len(g)).sum(axis=0)
    np.testing.assert_allclose(w_even, 1.0 / len(g), rtol=1e-9)
    want = np.exp(-0.5 * (np.log10(np.sqrt(g)) / 0.5) ** 2)
    np.testing.assert_allclose(w_prior, want / want.sum(), rtol=1e-9)
    assert w_prior[g.index(1.0)] > 0.4
    assert w_prior[g.index(100.0)] < 0.06  # a tenfold sd is a 2 sigma event


def with_residual(model: ThermalModel, rho: float = 0.0, **axis) -> ThermalModel:
    """``model`` with identification's residual figures for z: 0.1 um RMS, lag-1 autocorrelation ``rho``."""
    figures = {"rms_um": 0.1, "residual_lag1_autocorrelation": rho, "effective_samples": 6000.0, **axis}
    return dataclasses.replace(model, info={"longest_experiment_s": 43200.0, "window_s": DT, "axis_z": figures})


def test_identification_residual_weighs_the_disturbance_scales():
    """A white residual rules out the scales that would have left it autocorrelated; a coloured one finds its own."""
    s = DriftSettings()
    levels = np.array(sorted(set(s.scales)))
    v = levels * detrended_drift_variance(s, 43200.0, DT)
    for rho in (0.0, 0.1):
        lik = identification_scale_likelihood(with_residual(small_model(), rho), s, levels)[0]
        assert lik.sum() == pytest.approx(1.0)
        implied = v / (v + 0.01 * (1.0 - rho))  # the lag-1 autocorrelation each scale would have left
        assert lik[np.abs(implied - rho) > 0.1].sum() < 1e-6  # 6000 samples: standard error 0.013
        assert int(np.argmax(lik)) == int(np.argmin(np.abs(implied - rho)))
    assert identification_scale_likelihood(small_model(), s, levels) is None  # no figures: not used
    assert np.isnan(identification_scale_likelihood(with_residual(small_model(), rms_um=-1.0), s, levels)).all()


def _replay_48h(model: ThermalModel, extra, every_h: float, settings: DriftSettings | None):
    du = work_day(48)
    C = model.discretize(DT).contributions(du)
    t = DT * np.arange(1, du.shape[1] + 1)
    truth = C.sum(axis=1)[0] + extra(t / 3600.0)
    rng = np.random.default_rng(3)
    step = round(every_h * H)
    probes = [Probe(seq=q + 1, time_s=float(t[k]), values_um={"z": float(truth[k] + 0.3 * rng.standard_normal())},
                    sd_um=0.3) for q, k in enumerate(range(step - 1, len(t), step))]
    rp = replay(model, C, t, probes, window_s=DT, settings=settings)
    err = np.abs(truth - rp.estimate_um[0])[step:]
    half = Z95 * rp.sd_um[0, step:]
    return float(np.median(half[24 * H:])), float(np.mean(err <= half)), float(np.sqrt(np.mean(err ** 2))), rp


@pytest.mark.parametrize("every_h", [1.0, 4.0])
def test_the_residuals_evidence_narrows_only_what_the_probes_cannot_resolve(every_h):
    """A white identification residual narrows the band of a right model (the probes cannot tell its drift from
    none) and leaves a drift the probes resolve as it was: learned as fast, nothing refused."""
    model, even = with_residual(small_model()), DriftSettings(residual_prior_weight=0.0)
    right = lambda t_h: 0.0 * t_h  # noqa: E731
    half0, _, rms0, _ = _replay_48h(model, right, every_h, even)
    half1, cover1, rms1, _ = _replay_48h(model, right, every_h, None)  # the default: 0.5
    assert half1 < 0.92 * half0
    assert cover1 >= 0.95
    assert rms1 <= rms0
    # a model file without the residual's figures (written by hand): the even prior
    assert _replay_48h(small_model(), right, every_h, None)[0] == pytest.approx(half0, rel=1e-9)
    half0, cover0, rms0, rp0 = _replay_48h(model, drift, every_h, even)
    half1, cover1, rms1, rp1 = _replay_48h(model, drift, every_h, None)
    assert rms1 == pytest.approx(rms0, rel=0.05)
    assert half1 == pytest.approx(half0, rel=0.1)
    assert cover1 >= cover0 - 0.01
    assert all(d.accepted for d in (*rp0.decisions, *rp1.decisions))


def test_live_contributions_equal_batch_and_sum_to_the_estimate():
    model = load_model(PROFILES / "sim-vmc.model.toml")
    rng = np.random.default_rng(5)
    du = np.abs(rng.normal(size=(len(model.factors), 300))) * np.array([800, 300, 40, 3000, 2, 3000, 2, 500, 2])[:, None]
    dm = model.discretize(DT)
    batch = dm.contributions(du)
    live = dm.stepper()
    for k in range(du.shape[1]):
        y = live.step(du[:, k])
        c = live.contributions()
        np.testing.assert_allclose(c, batch[:, :, k], atol=1e-9)
        np.testing.assert_allclose(c.sum(axis=1), y, atol=1e-9)


@contextlib.contextmanager
def bench_module(name: str):
    """``bench/<name>.py`` imported as a module (registered while in use: its dataclasses need it)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]


@pytest.fixture(scope="module")
def bench():
    with bench_module("adaptive") as module:
        yield module


def test_on_the_simulated_machine_with_the_room_cycle(bench):
    """Two production days in a cycling room, the bundled model, probes every 2 h (the bench's case)."""
    from simulators.machine.run import simulate
    from simulators.machine.scenario import parse_scenario_text

    r = simulate(parse_scenario_text(bench.production_scenario("room", 0, 1, 2), source="room"))
    run_ = {"time_s": r.time_s, "true_um": r.true_um.T.copy(), **{f"factor_{k}": v for k, v in r.factors.items()}}
    model = load_model(PROFILES / "sim-vmc.model.toml")
    res = bench.run_case(model, run_, effect="room", variant=0, seed=1, interval_h=2.0, probe_sd_um=0.3)
    z = 2
    updated, alone, zap = (res.scores[m].rms_um[z] for m in ("updated", "model", "zero at probe"))
    assert alone > 4.0
    assert zap > 4.0
    assert updated < alone / 3
    assert updated < zap / 3
    assert np.all(res.coverage >= 0.85), res.coverage


def test_ceiling_bench_draws_the_filters_own_disturbance():
    """bench/adaptive_ceiling.py's truth is the filter's state space: at rest its variance after T is scale x Q(T)."""
    with bench_module("adaptive_ceiling") as ceiling:
        from gateway.adaptive.filter import _drift_model

        s = DriftSettings()
        n_in, n_w, draws = 2, 120, 300
        C = np.zeros((3, n_in, n_w))  # at rest: no activity, the gains multiply nothing
        gsd, gcorr = np.full((3, n_in), 0.05), np.broadcast_to(np.eye(n_in), (3, n_in, n_in))
        scales = np.array([1e-3, 1.0, 8.0])
        rng = np.random.default_rng(11)
        ends = np.array([ceiling.draw_truth(C, s, gsd, gcorr, scales, rng)[:, -1] for _ in range(draws)])
        # the first window starts at 0, so n_w - 1 steps of the window's dynamics
        want = scales * _drift_model(s, (n_w - 1) * DT)[1][0, 0]
        np.testing.assert_allclose(ends.var(axis=0), want, rtol=0.3)  # 300 draws: +-8 % sd
        assert ceiling.interval_sd_um(s, 1.0, 2.0) == pytest.approx(math.sqrt(_drift_model(s, 7200.0)[1][0, 0]))
