"""A recording estimate's sigma with correlated items, its calibration, and ``auto``'s fusion."""

from __future__ import annotations

import numpy as np
import pytest

from uavcal_jax.pipeline.auto_offset import AutoOptions, configure, fuse
from uavcal_jax.pipeline.offset_estimate import SIX_CHANNELS, OffsetEstimate
from uavcal_jax.pipeline.offset_uncertainty import (
    block_standard_error,
    fit_common_scale,
    fit_scale,
    recording_sigma,
)


def _ar1(rng, n, phi, innovation):
    """``(n,)`` a stationary AR(1) series: correlated over about ``1 / (1 - phi)`` items."""
    x = np.empty(n)
    x[0] = rng.normal(0.0, innovation / np.sqrt(1.0 - phi ** 2))
    for k in range(1, n):
        x[k] = phi * x[k - 1] + rng.normal(0.0, innovation)
    return x


def test_batch_means_cover_a_correlated_series_where_the_naive_error_does_not():
    """Frames at 20 Hz whose errors are correlated over about a second (AR(1), phi 0.9: an
    integrated correlation of 19 items): the median's error over 400 draws has z-scores of RMS
    1.27 with 3 s blocks (ten blocks' Student-t spread is 1.13 of it, the neighbouring blocks'
    correlation the rest: what a method's measured scale absorbs), against 4.8 with the items'
    spread over the root of their count."""
    rng = np.random.default_rng(0)
    t = np.arange(600) / 20.0
    z_block, z_naive = [], []
    for _ in range(400):
        x = _ar1(rng, t.size, 0.9, 1e-3)[:, None]
        error = np.median(x[:, 0])
        z_block.append(error / block_standard_error(x, t, 3.0)[0])
        z_naive.append(error / (x[:, 0].std(ddof=1) / np.sqrt(t.size)))
    rms_block = np.sqrt(np.mean(np.square(z_block)))
    assert 0.8 < rms_block < 1.5
    assert np.sqrt(np.mean(np.square(z_naive))) > 3.0


def test_few_blocks_give_no_credit_for_averaging_and_one_item_is_undetermined():
    x = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 8.0]])
    t = np.array([0.0, 0.1, 0.2])  # one block
    np.testing.assert_allclose(block_standard_error(x, t, 1.0), x.std(axis=0, ddof=1))
    assert np.all(np.isinf(block_standard_error(x[:1], t[:1], 1.0)))
    # the shared part adds in quadrature, the scale multiplies
    sigma = recording_sigma(x, t, 1.0, common=np.array([0.0, 6.0]), scale=2.0)
    np.testing.assert_allclose(sigma, 2.0 * np.hypot(x.std(axis=0, ddof=1), [0.0, 6.0]))
    with pytest.raises(ValueError, match=r"\(N, C\)"):
        block_standard_error(x, t[:2], 1.0)


def test_fitted_scales_make_the_z_scores_rms_one():
    rng = np.random.default_rng(1)
    sigma = rng.uniform(0.5, 2.0, 400)
    errors = 3.0 * sigma * rng.normal(size=400)
    k = fit_scale(errors, sigma)
    assert np.sqrt(np.mean(np.square(errors / (k * sigma)))) == pytest.approx(1.0)
    se = 0.2 * sigma
    k = fit_common_scale(errors, se, sigma)
    z = errors / np.sqrt(se ** 2 + (k * sigma) ** 2)
    assert np.sqrt(np.mean(z ** 2)) == pytest.approx(1.0, abs=1e-6)
    assert fit_common_scale(0.1 * se, se, sigma) == 0.0  # the standard errors cover them


def _estimate(channels, value, sigma):
    at = [SIX_CHANNELS.index(c) for c in channels]
    offset = np.zeros(6)
    offset[at] = value
    return OffsetEstimate(offset=offset, channels=tuple(channels), median=np.asarray(value),
                          per_item=np.asarray(value)[None], item_t_s=np.zeros(1),
                          item="window", span_ns=(0, 1), label="total", settings=None,
                          sigma=np.asarray(sigma, np.float64))


def test_fusion_is_the_inverse_variance_mean_per_channel():
    gyro_only = _estimate(SIX_CHANNELS[:3], [1.0, 2.0, 3.0], [1.0, 1.0, 2.0])
    both = _estimate(SIX_CHANNELS, [3.0, 2.0, 0.0, 4.0, 5.0, 6.0], [1.0, 0.5, np.inf, 2.0,
                                                                      np.inf, 1.0])
    offset, sigma, weights = fuse([gyro_only, both])
    np.testing.assert_allclose(offset[:2], [2.0, 2.0])  # equal weights on gx; 1:4 on gy
    np.testing.assert_allclose(weights[:, 1], [0.2, 0.8])
    np.testing.assert_allclose(sigma[:2], [np.sqrt(0.5), np.sqrt(1.0 / 5.0)])
    # gz: one determined method (the other's sigma inf); ax, az: the one estimating them
    np.testing.assert_allclose(offset[[2, 3, 5]], [3.0, 4.0, 6.0])
    np.testing.assert_allclose(sigma[[2, 3, 5]], [2.0, 2.0, 1.0])
    # ay: no method determined it: not corrected, sigma stays infinite
    assert offset[4] == 0.0 and np.isinf(sigma[4]) and np.all(weights[:, 4] == 0.0)
    np.testing.assert_allclose(weights.sum(axis=0)[[0, 1, 2, 3, 5]], 1.0)


def test_auto_options_refuse_an_unknown_method_and_take_the_transformers_checkpoint():
    with pytest.raises(ValueError, match="distinct names"):
        AutoOptions(methods=("vio-bias", "nope"))
    options = configure(["methods=vio-bias,visual-ls"], checkpoint="/runs/x", kind="last")
    assert options.methods == ("vio-bias", "visual-ls")
    assert options.transformer.checkpoint == "/runs/x" and options.transformer.kind == "last"


def test_uavcal_run_takes_auto_with_the_other_methods_options():
    """``uavcal run --set offset.method=auto``: the fused methods are ``offset.auto.methods``,
    each with its own ``offset.<method>.*`` options and the run's one VIO setting."""
    from uavcal_jax.config import apply_overrides
    from uavcal_jax.pipeline.run_config import RunConfig
    from uavcal_jax.vio.config import VioConfig

    config = apply_overrides(RunConfig(), ["offset.method=auto",
                                           "offset.auto.methods=vio-bias,visual-ls",
                                           "offset.vio_bias.tail_fraction=0.5"])
    vio = VioConfig(keyframes=7)
    options = config.offset.options(vio)
    assert isinstance(options, AutoOptions)
    assert options.methods == ("vio-bias", "visual-ls")
    assert options.vio_bias.tail_fraction == 0.5 and options.vio_bias.vio == vio


def test_an_estimates_sigma_becomes_the_vios_bias_prior_within_bounds():
    from uavcal_jax.pipeline.bias_prior import MIN_SIGMA, prior_from_estimate
    from uavcal_jax.vio.config import InitialPrior

    est = _estimate(SIX_CHANNELS, np.zeros(6), [1e-3, 2e-3, 2e-3, 0.02, 0.02, 5.0])
    prior = prior_from_estimate(est)
    assert prior.bias_gyro == pytest.approx(np.sqrt((1e-6 + 4e-6 + 4e-6) / 3))
    assert prior.bias_accel == InitialPrior().bias_accel  # never looser than the default
    tight = prior_from_estimate(_estimate(SIX_CHANNELS, np.zeros(6), [1e-9] * 6))
    assert (tight.bias_gyro, tight.bias_accel) == MIN_SIGMA
    gyro_only = prior_from_estimate(_estimate(SIX_CHANNELS[:3], np.zeros(3), [1e-3] * 3))
    assert gyro_only.bias_accel == InitialPrior().bias_accel and gyro_only.bias_gyro == 1e-3
    with pytest.raises(ValueError, match="sigma"):
        prior_from_estimate(OffsetEstimate(
            offset=np.zeros(6), channels=SIX_CHANNELS, median=np.zeros(6),
            per_item=np.zeros((1, 6)), item_t_s=np.zeros(1), item="window", span_ns=(0, 1),
            label="total", settings=None))


def test_frame_dropout_blinds_the_span_only_and_drops_the_folder():
    from uavcal_jax.data.frame_dropout import with_frame_dropout
    from uavcal_jax.data.sequence import CameraCalibration, FrameStream, ImuData, Sequence

    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (20, 48, 64), dtype=np.uint8)
    t = (np.arange(20) * 50_000_000).astype(np.int64)
    cal = CameraCalibration(np.array([50.0, 50, 32, 24]), np.zeros(4), (64, 48), 20.0,
                            np.eye(4))
    streams = {c: FrameStream(c, t, (), cal, lambda i, color: images[i]) for c in ("cam0", "cam1")}
    seq = Sequence("s", None, streams, ImuData(t, np.zeros((20, 3)), np.zeros((20, 3))), None,
                   None)
    black = with_frame_dropout(seq, 0.2, 0.25)  # frames 4-8
    blinded = [k for k in range(20) if not black.camera("cam1").load(k).any()]
    assert blinded == [4, 5, 6, 7, 8] and black.root is None
    np.testing.assert_array_equal(black.camera("cam0").load(9), images[9])
    blur = with_frame_dropout(seq, 0.2, 0.25, "blur").camera("cam0").load(5)
    assert np.abs(np.diff(blur.astype(float), axis=1)).mean() < 0.1 * np.abs(
        np.diff(images[5].astype(float), axis=1)).mean()
    with pytest.raises(ValueError, match="kind"):
        with_frame_dropout(seq, 0.0, 1.0, "smoke")
