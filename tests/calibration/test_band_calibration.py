"""The band calibration: a mean shrinkage, a scale, a monotone level map (quantile
recalibration) fixing the shape of heavy-tailed errors, and a pool with the constant band;
the recalibrated and pooled results' answers against each other; save/load; bad input."""
from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import scipy.integrate
import scipy.stats

from bayes_talk.calibration.bands import CALIBRATION_FILE, LEVEL_KNOTS, BandCalibration
from bayes_talk.calibration.recalibrated import RecalibratedResult
from bayes_talk.synthesis.result import SynthesisResult

TAIL_SCALE = np.array([1.0, 0.6, 1.5])


def _heavy_tailed(n, seed, T=25, K=3):
    """Mixtures of K Gaussians per entry; the truths are the mixture mean plus Student-t(3)
    errors of the mixture's standard deviation times a per-parameter factor."""
    rng = np.random.default_rng(seed)
    res, truths = [], []
    for _ in range(n):
        m = rng.normal(size=(1, K, T, TAIL_SCALE.size))
        v = rng.uniform(0.2, 1.0, size=m.shape)
        r = SynthesisResult("laplace", None, m, v)
        truths.append(r.mean + np.sqrt(r.var) * TAIL_SCALE * rng.standard_t(3, size=r.mean.shape))
        res.append(r)
    return res, truths


def _coverage(results, truths, level):
    inside = [np.mean((z >= lo) & (z <= hi)) for r, z in zip(results, truths) for lo, hi in [r.interval(level)]]
    return float(np.mean(inside))


@pytest.fixture(scope="module")
def fitted():
    res, truths = _heavy_tailed(60, seed=0)
    return BandCalibration.fit(res, truths, method="laplace", pool=False), res, truths


def test_level_map_reaches_nominal_coverage_where_one_scale_cannot(fitted):
    cal = fitted[0]
    assert cal.level_raw.shape == (TAIL_SCALE.size, len(LEVEL_KNOTS))
    for q in ("0.5", "0.8", "0.9", "0.95"):                      # in-sample: nominal at the knots
        assert cal.coverage_calibrated[q] == pytest.approx(float(q), abs=0.005)
    fresh, fresh_truths = _heavy_tailed(60, seed=1)
    scale_only = BandCalibration(cal.scale, "laplace")             # stage 1 alone
    two_stage = [cal.apply(r) for r in fresh]
    one_stage = [scale_only.apply(r) for r in fresh]
    for q in (0.5, 0.9):
        assert _coverage(two_stage, fresh_truths, q) == pytest.approx(q, abs=0.02)
    # the single best scale per parameter cannot fit both levels of heavy-tailed errors
    miss = [abs(_coverage(one_stage, fresh_truths, q) - q) for q in (0.5, 0.9)]
    assert max(miss) > 0.03, miss
    # nor can the raw bands
    assert _coverage(fresh, fresh_truths, 0.9) < 0.82


def test_recalibrated_result_answers_agree(fitted):
    cal, res, _ = fitted
    r = cal.apply(res[0])
    assert isinstance(r, RecalibratedResult) and not r.is_gaussian
    mix = r.mixture
    a = cal.mean_scale                                                             # stage 0
    shrunk = SynthesisResult("laplace", None, res[0].draw_mean * a, res[0].draw_var)
    np.testing.assert_allclose(mix.var, shrunk.var * cal.scale**2, rtol=1e-10)    # stage 1
    np.testing.assert_allclose(r.mean, a * res[0].mean, atol=1e-12)
    for q in (0.1, 0.5, 0.9):
        np.testing.assert_allclose(r.cdf(r.quantile(q)), q, atol=1e-9)
    # the calibrated 90 % band is the scaled mixture's band at the mapped raw level
    lo, hi = r.interval(0.9)
    raw_level = np.interp(0.9, np.r_[0, LEVEL_KNOTS, 1], np.r_[0, cal.level_raw[1], 1])
    lo_m, hi_m = SynthesisResult("x", None, mix.draw_mean[..., 1:2], mix.draw_var[..., 1:2]).interval(raw_level)
    np.testing.assert_allclose(np.c_[lo[:, 1], hi[:, 1]], np.c_[lo_m[:, 0], hi_m[:, 0]], rtol=1e-9, atol=1e-9)
    # the density is the derivative of the CDF and integrates to one (frame 0, parameter 2;
    # piecewise between the images of the knots, where the density ratio jumps)
    one = cal.apply(SynthesisResult("laplace", None, res[0].draw_mean[:, :, :1], res[0].draw_var[:, :, :1]))

    def dens(x):
        return float(np.exp(one.logpdf(np.array([[0.0, 0.0, x]]))[0, 2]))

    def cdf(x):
        return float(one.cdf(np.array([[0.0, 0.0, x]]))[0, 2])

    h, x0 = 1e-5, float(one.mean[0, 2]) + 0.1
    assert dens(x0) == pytest.approx((cdf(x0 + h) - cdf(x0 - h)) / (2 * h), rel=1e-5)
    cuts = sorted(float(one.quantile(0.5 + s * q / 2)[0, 2]) for q in LEVEL_KNOTS for s in (-1, 1))
    pieces = [(-np.inf, cuts[0])] + list(itertools.pairwise(cuts)) + [(cuts[-1], np.inf)]
    assert sum(scipy.integrate.quad(dens, a, b)[0] for a, b in pieces) == pytest.approx(1.0, abs=1e-6)
    # draws follow the calibrated distribution; var is their second moment about the mean
    x = r.sample(4000, seed=3)
    assert np.mean((x >= lo) & (x <= hi)) == pytest.approx(0.9, abs=0.01)
    np.testing.assert_allclose(np.mean((x - r.mean) ** 2, axis=(0, 1)), r.var.mean(0), rtol=0.08)
    assert r.predictive_draws(2).shape == (1, 6, r.n_frames, r.n_dims)
    # a post-filter of the mean moves the bands with it, the map staying
    delta = np.full(r.mean.shape, 0.5)
    s = r.shift(delta)
    np.testing.assert_allclose(s.interval(0.9)[1], hi + 0.5, atol=1e-9)
    idata = r.to_inference_data(truth=r.mean)
    assert idata.posterior_predictive["aam"].shape[-2:] == (r.n_frames, r.n_dims)


def test_save_load_round_trip_keeps_the_level_map(fitted, tmp_path):
    cal, res, _ = fitted
    cal.save(tmp_path)
    back = BandCalibration.load(tmp_path)
    np.testing.assert_array_equal(back.level_raw, cal.level_raw)
    assert back.level_cal == cal.level_cal and back.coverage_calibrated == cal.coverage_calibrated
    np.testing.assert_array_equal(back.apply(res[1]).interval(0.9)[0], cal.apply(res[1]).interval(0.9)[0])
    # a version-1 file (scale only) is still read, as stage 1 alone
    d = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    d["version"] = 1
    del d["level_raw"], d["level_cal"]
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(d))
    v1 = BandCalibration.load(tmp_path)
    assert v1.level_raw is None and type(v1.apply(res[1])) is SynthesisResult


@pytest.mark.parametrize("bad, match", [
    (lambda r: np.where(r > 0.5, 1.2, r), r"level_raw must lie in \(0, 1\)"),
    (lambda r: np.where(r > 0.5, np.nan, r), "level_raw contains NaN"),
    (lambda r: r[:, ::-1], "strictly increasing"),
    (lambda r: r[:2], r"level_raw must have shape \(3, 19\)"),
])
def test_bad_level_maps_are_refused_by_name(fitted, tmp_path, bad, match):
    cal = fitted[0]
    d = cal.to_dict()
    d["level_raw"] = bad(cal.level_raw).tolist()
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(d).replace("NaN", "NaN"))
    with pytest.raises(ValueError, match=f"band_calibration.json.*{match}"):
        BandCalibration.load(tmp_path)


def test_bad_levels_in_use_give_clear_errors(fitted):
    cal, res, _ = fitted
    r = cal.apply(res[0])
    for q in (0.0, 1.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"must be in \(0, 1\)"):
            r.interval(q)
    with pytest.raises(ValueError, match="level_cal must lie in"):
        BandCalibration(cal.scale, "laplace", level_raw=cal.level_raw, level_cal=(0.0,) + cal.level_cal[1:])
    with pytest.raises(ValueError, match="expected values of shape"):
        r.cdf(np.zeros((2, 2)))


def _half_predictable(n, seed, T=30):
    """Parameter 0 is the predicted mean plus noise; parameter 1 is noise the predicted
    mean (of the same spread) does not follow."""
    rng = np.random.default_rng(seed)
    res, truths = [], []
    for _ in range(n):
        m = rng.normal(size=(1, 2, T, 2))
        r = SynthesisResult("laplace", None, m, np.full(m.shape, 0.3))
        z = r.mean + 0.5 * rng.normal(size=r.mean.shape)
        z[:, 1] = rng.normal(size=T) * np.std(r.mean[:, 1])
        res.append(r)
        truths.append(z)
    return res, truths


def test_mean_shrinkage_pulls_unpredicted_parameters_to_zero_and_lowers_the_error(tmp_path):
    res, truths = _half_predictable(40, seed=0)
    cal = BandCalibration.fit(res, truths, method="laplace")
    assert cal.mean_scale[0] > 0.9 and cal.mean_scale[1] < 0.15, cal.mean_scale
    fresh, fresh_truths = _half_predictable(40, seed=1)
    mse = lambda rs: np.mean([np.mean((r.mean - z) ** 2, axis=0) for r, z in zip(rs, fresh_truths)], axis=0)
    before, after = mse(fresh), mse([cal.apply(r) for r in fresh])
    assert after[1] < 0.7 * before[1] and after[0] < 1.05 * before[0]
    np.testing.assert_allclose(cal.apply(fresh[0]).mean[:, 1], cal.mean_scale[1] * fresh[0].mean[:, 1], atol=1e-12)
    # bands still calibrated on fresh data after the shrinkage
    assert _coverage([cal.apply(r) for r in fresh], fresh_truths, 0.9) == pytest.approx(0.9, abs=0.03)
    off = BandCalibration.fit(res, truths, method="laplace", shrink_mean=False)
    assert off.mean_scale is None
    cal.save(tmp_path)
    back = BandCalibration.load(tmp_path)
    np.testing.assert_array_equal(back.mean_scale, cal.mean_scale)
    d = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    d["mean_scale"] = [0.5, 1.5]
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(d))
    with pytest.raises(ValueError, match="mean_scale"):
        BandCalibration.load(tmp_path)


def _with_spread(n, seed, informative, T=30, D=3):
    """Gaussian predictives whose variance v_td varies 25-fold over entries; the truth's error
    has variance v_td (``informative``: the posterior knows where it is unsure) or the
    entries' average variance (the variance pattern carries nothing)."""
    rng = np.random.default_rng(seed)
    res, truths = [], []
    for _ in range(n):
        m = rng.normal(size=(T, D))
        v = np.exp(rng.uniform(np.log(0.1), np.log(2.5), size=(T, D)))
        err_var = v if informative else np.full_like(v, 0.8)
        truths.append(m + np.sqrt(err_var) * rng.standard_normal((T, D)))
        res.append(SynthesisResult.gaussian(m, v, method="laplace"))
    return res, truths


@pytest.mark.parametrize("informative", [True, False])
def test_constant_band_control_is_beaten_only_by_an_informative_spread(informative):
    """The control (the calibrated mean with one constant band per parameter, calibrated the
    same way) has a constant variance over frames, equal to the held-out mean squared error
    before its own calibration; a predictive whose variance tracks its error beats it on NLPD
    and CRPS on fresh data, one whose variance pattern is noise does not."""
    from bayes_talk.evaluation.calibration import (
        control_verdict,
        score_utterance,
        summarise_calibration,
    )

    res, truths = _with_spread(80, seed=3, informative=informative)
    cal = BandCalibration.fit(res, truths, method="laplace", pool=False)
    resid = np.concatenate([z - cal.apply(r).mean for r, z in zip(res, truths)])
    np.testing.assert_allclose(cal.control_var, np.mean(resid ** 2, axis=0), rtol=1e-10)
    fresh, fresh_truths = _with_spread(60, seed=4, informative=informative)
    entry = {}
    for key, make in (("calibration", cal.apply), ("calibration_control", cal.control_result)):
        entry[key] = summarise_calibration([score_utterance(make(r), z) for r, z in zip(fresh, fresh_truths)])
    c = cal.control_result(fresh[0])
    np.testing.assert_allclose(c.mean, cal.apply(fresh[0]).mean, atol=1e-12)
    lo, hi = c.interval(0.9)
    np.testing.assert_allclose(hi - lo, np.broadcast_to((hi - lo)[0], lo.shape), rtol=1e-9)  # constant in t
    v = control_verdict(entry)
    assert v["beats"] is informative, v
    assert (v["nlpd"]["difference"] < 0) is informative and (v["crps"]["difference"] < 0) is informative


def test_control_survives_save_and_load_and_old_files_have_none(fitted, tmp_path):
    cal, res, _ = fitted
    cal.save(tmp_path)
    back = BandCalibration.load(tmp_path)
    np.testing.assert_array_equal(back.control_var, cal.control_var)
    np.testing.assert_allclose(back.control_result(res[0]).interval(0.9), cal.control_result(res[0]).interval(0.9))
    d = cal.to_dict()
    d.update(version=3, control=None, control_var=None)
    old = BandCalibration.from_dict(d)
    with pytest.raises(ValueError, match="no constant-band control"):
        old.control_result(res[0])


def test_calibrated_warning_records_khat_but_gates_only_on_the_other_checks(fitted):
    """The raw Laplace result warns on k̂ > 0.7; the calibrated one records its k̂ beside the
    largest k̂ of the calibration's held-out syntheses but warns only when another check
    fails or the k̂ is not finite (k̂ was measured not to predict the calibrated coverage:
    BandCalibration.domain), and records the check in its diagnostics."""
    from dataclasses import replace

    from bayes_talk.posterior.diagnostics import sampler_warning

    cal, res, _ = fitted
    cal = replace(cal, info={**cal.info, "held_out_diagnostics": {"khat": [1.2, 2.9, None, 2.1]}})
    assert cal.calibration_khat_max == 2.9

    def raw(k, **extra):
        diag = {"khat": k, **extra}
        return replace(res[0], diagnostics=diag,
                       warnings=["synthesis MAP did not converge: (kept)",
                                 *sampler_warning("laplace", [f"PSIS k̂ {k} > 0.7"])])

    for k in (2.5, 3.4):       # inside and beyond the calibration's own k̂: no k̂ warning
        out = cal.apply(raw(k))
        assert out.warnings == ["synthesis MAP did not converge: (kept)"]
        dom = out.diagnostics["band_calibration"]["domain"]
        assert dom["inside"] and dom["khat"] == k and dom["khat_calibration_max"] == 2.9
    broken = cal.apply(raw(float("inf")))
    assert len(broken.warnings) == 2 and "not finite" in broken.warnings[1]
    assert not broken.diagnostics["band_calibration"]["domain"]["inside"]
    assert "R-hat" in cal.apply(raw(1.0, rhat_max=1.2)).warnings[1]   # other checks stand
    old = replace(cal, info={})                                        # an older file: no held-out k̂
    assert old.calibration_khat_max is None
    assert old.apply(raw(0.9)).warnings == ["synthesis MAP did not converge: (kept)"]


class _PickledPool:
    """A parallel executor stand-in: ``map`` sends every task and result through pickle, as a
    process pool does, but runs it here (worker processes would add ~20 s of start-up; that
    the process engines equal the local one is tests/base/test_executor.py's)."""

    parallel = True
    n_workers = 2

    def __init__(self):
        self.calls, self.submitted = [], []

    @staticmethod
    def _run(fn, x):
        import pickle

        from bayes_talk.base.executor import run_task

        return pickle.loads(pickle.dumps(run_task(*pickle.loads(pickle.dumps((fn, x))))))

    def map(self, fn, items, desc=None, unit="task"):
        items = list(items)
        self.calls.append(len(items))
        return [self._run(fn, x) for x in items]

    def submit(self, fn, item):
        """Queued; computed (through pickle) when its result is first asked for, so in the
        order the caller collects the results, not the order it queued the tasks."""
        self.submitted.append(fn.__name__)
        return _Queued(fn, item)


class _Queued:
    """A task of :class:`_PickledPool`: computed at the first ``result()``."""

    def __init__(self, fn, item):
        self.job, self.done, self.value = (fn, item), False, None

    def result(self):
        if not self.done:
            self.value, self.done = _PickledPool._run(*self.job), True
        return self.value


@pytest.mark.parametrize("holdout, n_workers, n_held", [(0.3, 2, 3), (0.5, 1, 5)])
def test_held_out_syntheses_through_a_parallel_executor_give_the_same_calibration(holdout, n_workers, n_held):
    """Issue 29: with a parallel executor the held-out syntheses go through it in chunks
    balanced by frame count (one utterance each, or 5 utterances in 3 chunks, not in their
    order); the calibration (scale, level map, mean shrinkage, control) equals the serial one."""
    from toydata import make_utterances

    from bayes_talk.calibration.bands import balanced_chunks, fit_band_calibration
    from bayes_talk.estimators.switching import SwitchingSGPDM

    train = make_utterances(10, seed=3, mean_len=30)
    small = {"states": "phone", "latent_dim": 3, "max_iter": 15, "max_frames_per_state": 80, "fallback_frames": 90}
    model, fitted = SwitchingSGPDM(**small), []

    def fit_once(sub, seqs):  # the calibration model is trained once and used by both runs
        if not fitted:
            fitted.append(sub.fit(seqs))
        return fitted[0]

    one = fit_band_calibration(model, train, holdout=holdout, n_draws=16, seed=1, fit=fit_once)
    pool = _PickledPool()
    pool.n_workers = n_workers
    two = fit_band_calibration(model, train, holdout=holdout, n_draws=16, seed=1, executor=pool, fit=fit_once)
    assert pool.submitted == ["_synthesise_chunk"] * 3   # one utterance each, or 5 utterances in 3
    assert one.held_out == two.held_out and len(one.held_out) == n_held
    by_name = {u.name: u for u in train}
    chunks = balanced_chunks([len(by_name[n].mfcc) for n in one.held_out], 3)
    assert (max(map(len, chunks)) > 1) == (n_held > 3)
    if n_held > 3:                      # the results go back to their utterances, not in chunk order
        assert [i for c in chunks for i in c] != list(range(n_held))
    np.testing.assert_array_equal(two.scale, one.scale)
    np.testing.assert_array_equal(two.mean_scale, one.mean_scale)
    np.testing.assert_array_equal(two.level_raw, one.level_raw)
    np.testing.assert_array_equal(two.control_var, one.control_var)
    np.testing.assert_array_equal(two.pool_weight, one.pool_weight)
    assert one.pool_weight is not None


def test_the_refit_scheme_on_workers_gives_the_sequential_model_and_calibration():
    """Issue 29: ``calibrated_fit(..., "refit")`` on an executor with workers queues the
    calibration model's state fits, the shipped model's and the held-out syntheses as one
    queue (refit_beside_calibration; without an executor, the same queue in this process);
    the shipped model (every state's arrays, the views, the entry distributions) and the
    calibration equal the sequential scheme's."""
    from toydata import make_utterances

    from bayes_talk.calibration.bands import calibrated_fit
    from bayes_talk.estimators.switching import SwitchingSGPDM

    train = make_utterances(10, seed=4, mean_len=30)
    small = {"states": "phone", "latent_dim": 3, "max_iter": 15, "max_frames_per_state": 80, "fallback_frames": 90,
             "context_view": 2, "context_mean": True}
    # a fit callable keeps the sequential scheme: fit on all, then fit_band_calibration
    m1, c1 = calibrated_fit(SwitchingSGPDM(**small), train, "refit", holdout=0.3, n_draws=16, seed=1,
                            fit=lambda m, utterances: m.fit(utterances))
    m0, c0 = calibrated_fit(SwitchingSGPDM(**small), train, "refit", holdout=0.3, n_draws=16, seed=1)
    pool = _PickledPool()
    m2, c2 = calibrated_fit(SwitchingSGPDM(**small), train, "refit", holdout=0.3, n_draws=16, seed=1, executor=pool)
    n_sub = pool.submitted.index("_synthesise_chunk")
    assert pool.calls == [] and set(pool.submitted[:n_sub]) == {"fit_state"}
    assert pool.submitted[n_sub:] == ["_synthesise_chunk"] * 3
    assert n_sub > len(m2.models_)          # both models' states went through the queue
    meta1, arr1 = m1.state()
    meta2, arr2 = m2.state()
    assert meta1 == meta2 and arr1.keys() == arr2.keys()
    for k in arr1:
        np.testing.assert_array_equal(arr2[k], arr1[k], err_msg=k)
    assert list(m2.models_) == list(m1.models_)
    for k in m1.entry_:
        np.testing.assert_array_equal(m2.entry_[k][1], m1.entry_[k][1])
    assert c2.held_out == c1.held_out and c1.info["n_fit"] == c2.info["n_fit"] == 7
    for name in ("scale", "mean_scale", "level_raw", "control_var", "pool_weight"):
        np.testing.assert_array_equal(getattr(c2, name), getattr(c1, name), err_msg=name)
        np.testing.assert_array_equal(getattr(c0, name), getattr(c1, name), err_msg=name)
    arr0 = m0.state()[1]        # no executor: the same queue run in this process
    for k in arr1:
        np.testing.assert_array_equal(arr0[k], arr1[k], err_msg=k)


def test_balanced_chunks_partition_the_items_by_longest_processing_time_first():
    """balanced_chunks: every index once, in n non-empty chunks, each sorted, chunks largest
    total first; totals within the largest item of each other (the LPT bound); a worked
    example; the same chunks every time; n outside 1..len is a named error."""
    from bayes_talk.calibration.bands import balanced_chunks

    assert balanced_chunks([5, 4, 3, 3, 3], 2) == [[1, 2, 4], [0, 3]]     # loads 10 and 8
    rng = np.random.default_rng(0)
    for _ in range(200):
        sizes = rng.integers(20, 200, size=int(rng.integers(1, 60))).tolist()
        n = int(rng.integers(1, len(sizes) + 1))
        chunks = balanced_chunks(sizes, n)
        assert chunks == balanced_chunks(sizes, n)
        assert len(chunks) == n and all(chunks) and all(c == sorted(c) for c in chunks)
        assert sorted(i for c in chunks for i in c) == list(range(len(sizes)))
        loads = [sum(sizes[i] for i in c) for c in chunks]
        assert loads == sorted(loads, reverse=True)
        assert loads[0] - loads[-1] <= max(sizes)
    for bad in (0, 6):
        with pytest.raises(ValueError, match="n_chunks must be in 1..5"):
            balanced_chunks([1, 2, 3, 4, 5], bad)


#: a small phone-state switching model for the calibration schemes' tests
SMALL_PHONE = {"states": "phone", "latent_dim": 3, "max_iter": 15, "max_frames_per_state": 80, "fallback_frames": 90}


def _recording_fit():
    """A ``fit(model, utterances)`` for ``calibrated_fit`` that records the utterance names
    of every fit (``seen``) and the fitted models (``fitted``)."""
    seen, fitted = [], []

    def fit(model, seqs):
        seen.append(sorted(s.name for s in seqs))
        fitted.append(model.fit(seqs))
        return fitted[-1]
    return fit, seen, fitted


def test_calibrated_fit_ships_the_holdout_model_or_refits_on_every_utterance():
    """``train --calibrated-model``: "holdout" fits once, on the utterances outside the
    held-out fraction, and ships that model with the calibration fitted for it; "refit"
    fits that model for the calibration, then a second one on every utterance, and ships the
    second with the same calibration. Anything else is refused by name."""
    from toydata import make_utterances

    from bayes_talk.calibration.bands import calibrated_fit
    from bayes_talk.estimators.switching import SwitchingSGPDM

    train = make_utterances(10, seed=3, mean_len=30)
    small = SMALL_PHONE
    fit, seen, fitted = _recording_fit()

    shipped, cal = calibrated_fit(SwitchingSGPDM(**small), train, "holdout", holdout=0.3, n_draws=16, seed=1, fit=fit)
    assert len(seen) == 1 and len(cal.held_out) == 3 and cal.info["n_fit"] == 7
    assert set(seen[0]).isdisjoint(cal.held_out) and len(seen[0]) + 3 == len(train)
    assert shipped is fitted[0]
    seen.clear()
    refit, cal2 = calibrated_fit(SwitchingSGPDM(**small), train, "refit", holdout=0.3, n_draws=16, seed=1, fit=fit)
    assert len(seen) == 2 and seen[0] == sorted(s.name for s in train) and len(seen[1]) == 7
    assert cal2.held_out == cal.held_out and cal2.info["n_fit"] == 7
    np.testing.assert_array_equal(cal2.scale, cal.scale)     # the same calibration model and syntheses
    assert refit is fitted[-2]    # the model on every utterance, fitted first
    with pytest.raises(ValueError, match="calibrated_model: expected one of holdout, refit, cv, found 'both'"):
        calibrated_fit(SwitchingSGPDM(**small), train, "both", fit=fit)


def test_crossfit_calibration_holds_out_every_utterance_once():
    """``--calibrated-model cv``: K = round(1/holdout) seeded folds partition the
    utterances; each fold is synthesised by a model fitted on the others only; the
    calibration is fitted on all the out-of-fold syntheses (its held-out names are every
    utterance, its in-sample coverage is of all of them); the shipped model is fitted on
    every utterance, first. Too few utterances for the folds are refused by name."""
    from toydata import make_utterances

    from bayes_talk.calibration.bands import calibrated_fit, crossfit_folds
    from bayes_talk.estimators.switching import SwitchingSGPDM

    folds = crossfit_folds(11, holdout=0.3, seed=1)
    assert len(folds) == 3 and sorted(i for f in folds for i in f) == list(range(11))
    assert sorted(len(f) for f in folds) == [3, 4, 4] and folds != crossfit_folds(11, holdout=0.3, seed=2)
    train = make_utterances(9, seed=3, mean_len=30)
    small = SMALL_PHONE
    fit, seen, fitted = _recording_fit()

    shipped, cal = calibrated_fit(SwitchingSGPDM(**small), train, "cv", holdout=0.3, n_draws=8, seed=1, fit=fit)
    names = sorted(s.name for s in train)
    assert shipped is fitted[0] and seen[0] == names and len(seen) == 4
    held = [sorted([s.name for i, s in enumerate(train) if i in f]) for f in crossfit_folds(9, 0.3, 1)]
    for fit_names, fold in zip(seen[1:], held):
        assert sorted(fit_names + fold) == names          # each fold's model saw exactly the other folds
    assert sorted(cal.held_out) == names and cal.info["folds"] == 3 and cal.info["n_fit"] == [6, 6, 6]
    assert cal.n_utterances == 9
    with pytest.raises(ValueError, match="3 folds needs at least 4 training utterances"):
        crossfit_folds(3, holdout=0.3)


def _mixed_spread(n, seed, T=30):
    """Gaussian predictives over 2 parameters: on parameter 0 the variance tracks the error
    (an informative shape), on parameter 1 it is noise around a constant error variance."""
    rng = np.random.default_rng(seed)
    res, truths = [], []
    for _ in range(n):
        m = rng.normal(size=(T, 2))
        v = np.exp(rng.uniform(np.log(0.05), np.log(4.0), size=(T, 2)))
        err = np.c_[v[:, 0], np.full(T, 0.8)]
        truths.append(m + np.sqrt(err) * rng.standard_normal((T, 2)))
        res.append(SynthesisResult.gaussian(m, v, method="laplace"))
    return res, truths


def test_pool_weights_go_to_the_constant_band_only_where_the_spread_is_noise():
    """Stage 3: the held-out log score gives the posterior the weight on the parameter whose
    variance tracks its error and the constant band the weight on the other; on fresh data
    the pool's NLPD is at least as good as stage 2's and as the Gaussian's on each."""
    from bayes_talk.calibration.bands import _constant_band

    res, truths = _mixed_spread(80, seed=5)
    cal = BandCalibration.fit(res, truths, method="laplace")
    assert cal.pool_weight[0] < 0.3 and cal.pool_weight[1] > 0.7, cal.pool_weight
    staged = BandCalibration.fit(res, truths, method="laplace", pool=False)
    fresh, fresh_truths = _mixed_spread(60, seed=6)

    def nlpd(make):
        return -np.mean(np.concatenate([make(r).logpdf(z) for r, z in zip(fresh, fresh_truths)]), axis=0)

    pooled = nlpd(cal.apply)
    assert np.all(pooled <= nlpd(staged.apply) + 0.01), (pooled, nlpd(staged.apply))
    gauss = nlpd(lambda r: _constant_band(staged.apply(r), cal.control_var))
    assert np.all(pooled <= gauss + 0.01), (pooled, gauss)
    assert pooled[0] < gauss[0] - 0.05          # the informative shape is kept where it helps


def test_pooled_result_answers_agree(fitted):
    """(4): the CDF is the weighted CDFs, the quantile inverts it, the density is the CDF's
    derivative, draws follow it, w = 0 is the base and the mean is the base's."""
    from bayes_talk.calibration.pooled import PooledResult

    cal, res, _ = fitted
    base = cal.apply(res[0])
    w, v = np.array([0.0, 0.4, 1.0]), np.array([0.5, 2.0, 1.5])
    r = PooledResult.pool(base, w, v)
    y = base.mean + 0.7
    g = scipy.stats.norm.cdf(y, base.mean, np.sqrt(v))
    np.testing.assert_allclose(r.cdf(y), (1 - w) * base.cdf(y) + w * g, atol=1e-12)
    np.testing.assert_allclose(r.cdf(y)[:, 0], base.cdf(y)[:, 0], atol=1e-12)
    np.testing.assert_allclose(r.mean, base.mean)
    for q in (0.05, 0.5, 0.9):
        np.testing.assert_allclose(r.cdf(r.quantile(q)), q, atol=1e-8)
    np.testing.assert_allclose(r.quantile(0.9)[:, 0], base.quantile(0.9)[:, 0], atol=1e-8)
    h = 1e-5
    num = (r.cdf(y + h) - r.cdf(y - h)) / (2 * h)
    np.testing.assert_allclose(np.exp(r.logpdf(y)), num, rtol=1e-4)
    x = r.sample(4000, seed=2)
    lo, hi = r.interval(0.8)
    assert np.mean((x >= lo) & (x <= hi)) == pytest.approx(0.8, abs=0.015)
    np.testing.assert_allclose(np.mean((x - r.mean) ** 2, axis=(0, 1)), r.var.mean(0), rtol=0.08)
    s = r.shift(np.full(r.mean.shape, 0.5))
    np.testing.assert_allclose(s.interval(0.9)[1], r.interval(0.9)[1] + 0.5, atol=1e-7)
    assert r.to_inference_data().posterior_predictive["aam"].shape[-2:] == (r.n_frames, r.n_dims)
    with pytest.raises(ValueError, match=r"weights must lie in \[0, 1\]"):
        PooledResult.pool(base, np.array([0.0, 1.2, 0.5]), v)
    with pytest.raises(ValueError, match=r"var must have one value per AAM parameter \(3,\)"):
        PooledResult.pool(base, w, v[:2])


def test_pool_weights_survive_save_and_load_and_version_4_files_have_none(tmp_path):
    res, truths = _mixed_spread(20, seed=7)
    cal = BandCalibration.fit(res, truths, method="laplace")
    cal.save(tmp_path)
    back = BandCalibration.load(tmp_path)
    np.testing.assert_array_equal(back.pool_weight, cal.pool_weight)
    np.testing.assert_array_equal(back.apply(res[0]).interval(0.9)[0], cal.apply(res[0]).interval(0.9)[0])
    d = cal.to_dict()
    d["version"] = 4
    del d["pool_weight"]
    old = BandCalibration.from_dict(d)
    assert old.pool_weight is None and type(old.apply(res[0])) is RecalibratedResult
    d = cal.to_dict()
    d["pool_weight"] = [0.5, 1.5]
    with pytest.raises(ValueError, match=r"weights must lie in \[0, 1\]"):
        BandCalibration.from_dict(d)


def test_held_out_record_keeps_each_utterances_map_log_density_per_frame(fitted):
    """The calibration's record of its held-out syntheses keeps the MAP log density per frame
    (the reference a domain check on how well the model explains new audio needs)."""
    from dataclasses import replace

    from bayes_talk.calibration.bands import _synthesis_record

    _, res, _ = fitted
    rs = [replace(res[0], diagnostics={"map_converged": True, "khat": 2.0, "map_log_density": -6.0 * res[0].n_frames}),
          replace(res[1], diagnostics={"map_converged": False, "map_log_density": float("nan")}),
          replace(res[2], diagnostics={})]
    rec = _synthesis_record(rs)
    assert rec["map_log_density_per_frame"] == [pytest.approx(-6.0), None, None]
    assert rec["khat"] == [2.0, None, None] and rec["map_converged"] == [True, False, None]


def test_audio_fit_is_the_conformal_rank_of_the_map_log_density_per_frame(fitted):
    """domain() reports ℓ = MAP log density / T and its conformal p-value among the held-out
    ℓ_i: (1 + #{ℓ_i ≤ ℓ}) / (n + 1); None without a reference; never a warning by itself."""
    from dataclasses import replace

    cal, res, _ = fitted
    r = res[0]
    T = r.n_frames
    cal = replace(cal, info={**cal.info, "held_out_diagnostics": {
        "khat": [1.0], "map_log_density_per_frame": [-60.0, -62.0, None, -58.0, -64.0]}})
    for ell, p in ((-70.0, 1 / 5), (-61.0, 3 / 5), (-50.0, 5 / 5), (-62.0, 3 / 5)):
        dom = cal.domain(replace(r, diagnostics={"map_log_density": ell * T}, warnings=[]))
        assert dom["map_log_density_per_frame"] == pytest.approx(ell)
        assert dom["audio_fit_p"] == pytest.approx(p)
        assert dom["inside"] and dom["warning"] == []
    old = replace(cal, info={})
    assert old.domain(replace(r, diagnostics={"map_log_density": -70.0 * T}))["audio_fit_p"] is None
    assert cal.domain(replace(r, diagnostics={}))["map_log_density_per_frame"] is None
