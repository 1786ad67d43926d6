"""Loss (eq. 15-18) against NumPy, its zero-gradient sign term and the smooth surrogate;
metrics (eq. 19-23) against an independent NumPy count of TP/FP/FN and NumPy RMSEs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from uavcal_jax.calib.config import LossConfig
from uavcal_jax.calib.loss import calibration_loss, gaussian_nll
from uavcal_jax.calib.metrics import calibration_metrics, metric_sums, metrics_from_sums


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(0)
    target = rng.normal(0, 1, (37, 6)).astype(np.float32)
    pred = (target + rng.normal(0, 0.8, target.shape)).astype(np.float32)
    pred[0, 0] = 0.0  # a zero prediction: sign 0, counted as "not positive"
    return pred, target


def test_loss_is_the_sum_of_three_mses(pair):
    pred, target = pair
    loss, terms = calibration_loss(jnp.asarray(pred), jnp.asarray(target))
    o = np.mean((pred - target) ** 2)
    s = np.mean((np.sign(pred) - np.sign(target)) ** 2)
    m = np.mean((np.abs(pred) - np.abs(target)) ** 2)
    np.testing.assert_allclose([terms["offset"], terms["sign"], terms["magnitude"]], [o, s, m],
                               rtol=1e-5)
    np.testing.assert_allclose(float(loss), o + s + m, rtol=1e-5)


def test_standardized_units_divide_each_channel_by_its_scale(pair):
    pred, target = pair
    scale = np.asarray([0.1, 0.2, 0.3, 1.0, 2.0, 4.0], np.float32)
    cfg = LossConfig(units="standardized")
    _, terms = calibration_loss(jnp.asarray(pred), jnp.asarray(target), cfg,
                                scale=jnp.asarray(scale))
    np.testing.assert_allclose(float(terms["offset"]), np.mean(((pred - target) / scale) ** 2),
                               rtol=1e-5)
    np.testing.assert_allclose(float(terms["magnitude"]),
                               np.mean(((np.abs(pred) - np.abs(target)) / scale) ** 2),
                               rtol=1e-5)
    # the sign term is unit-free; SI units ignore the scale
    assert float(terms["sign"]) == float(calibration_loss(jnp.asarray(pred),
                                                          jnp.asarray(target))[1]["sign"])
    si = calibration_loss(jnp.asarray(pred), jnp.asarray(target), scale=jnp.asarray(scale))
    np.testing.assert_allclose(float(si[1]["offset"]), np.mean((pred - target) ** 2), rtol=1e-5)


def test_window_weights_leave_padding_out(pair):
    pred, target = pair
    w = np.ones(37, np.float32)
    w[30:] = 0
    loss, _ = calibration_loss(jnp.asarray(pred), jnp.asarray(target), weight=jnp.asarray(w))
    want, _ = calibration_loss(jnp.asarray(pred[:30]), jnp.asarray(target[:30]))
    np.testing.assert_allclose(float(loss), float(want), rtol=1e-6)


def test_sign_term_has_no_gradient_and_the_surrogate_has(pair):
    pred, target = pair

    def term(p, cfg):
        return calibration_loss(p, jnp.asarray(target), cfg)[1]["sign"]

    g_exact = jax.grad(term)(jnp.asarray(pred), LossConfig())
    assert float(jnp.abs(g_exact).max()) == 0.0
    cfg = LossConfig(sign_term="tanh", tau=0.5)
    g = jax.grad(term)(jnp.asarray(pred), cfg)
    want = (2 / pred.size) * (np.tanh(pred / 0.5) - np.sign(target)) * (
        1 - np.tanh(pred / 0.5) ** 2) / 0.5
    np.testing.assert_allclose(np.asarray(g), want, rtol=1e-4, atol=1e-7)
    # the surrogate is reported beside the exact term
    terms = calibration_loss(jnp.asarray(pred), jnp.asarray(target), cfg)[1]
    np.testing.assert_allclose(float(terms["sign_exact"]),
                               np.mean((np.sign(pred) - np.sign(target)) ** 2), rtol=1e-6)


def _numpy_f1(pred, target):
    """Direct count: positive class is a positive offset."""
    tp = fp = fn = 0
    for p, t in zip(pred.ravel(), target.ravel(), strict=True):
        if p > 0 and t > 0:
            tp += 1
        elif p > 0:
            fp += 1
        elif t > 0:
            fn += 1
    precision, recall = tp / (tp + fp), tp / (tp + fn)
    return 2 * precision * recall / (precision + recall), precision, recall


def test_metrics_match_numpy(pair):
    pred, target = pair
    m = calibration_metrics(jnp.asarray(pred), jnp.asarray(target))
    f1, precision, recall = _numpy_f1(pred, target)
    np.testing.assert_allclose([m["sign_f1"], m["sign_precision"], m["sign_recall"]],
                               [f1, precision, recall], rtol=1e-6)
    for c in range(6):
        np.testing.assert_allclose(float(m["sign_f1_per_channel"][c]),
                                   _numpy_f1(pred[:, c], target[:, c])[0], rtol=1e-6)
    np.testing.assert_allclose(float(m["offset_rmse"]), np.sqrt(np.mean((pred - target) ** 2)),
                               rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(m["magnitude_rmse_per_channel"]),
        np.sqrt(np.mean((np.abs(pred) - np.abs(target)) ** 2, axis=0)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(m["offset_rmse_per_channel"]),
                               np.sqrt(np.mean((pred - target) ** 2, axis=0)), rtol=1e-6)


def test_sums_accumulate_over_batches(pair):
    pred, target = pair
    a = metric_sums(jnp.asarray(pred[:20]), jnp.asarray(target[:20]))
    b = metric_sums(jnp.asarray(pred[20:]), jnp.asarray(target[20:]))
    acc = metrics_from_sums(jax.tree.map(lambda x, y: x + y, a, b))
    whole = calibration_metrics(jnp.asarray(pred), jnp.asarray(target))
    for k in whole:
        np.testing.assert_allclose(np.asarray(acc[k]), np.asarray(whole[k]), rtol=1e-6)


def test_no_positives_gives_zero_f1_not_nan():
    m = calibration_metrics(-jnp.ones((3, 6)), -jnp.ones((3, 6)))
    assert float(m["sign_f1"]) == 0.0 and float(m["offset_rmse"]) == 0.0


def test_gaussian_nll_is_scipys_less_its_constant_and_teaches_only_sigma(pair):
    from scipy.stats import norm

    pred, target = pair
    log_sigma = jnp.asarray(np.random.default_rng(3).normal(-1.0, 0.5, pred.shape), jnp.float32)
    want = -norm.logpdf(np.asarray(target), np.asarray(pred), np.exp(np.asarray(log_sigma)))
    got = gaussian_nll(pred, log_sigma, target)
    np.testing.assert_allclose(float(got), want.mean() - 0.5 * np.log(2 * np.pi), rtol=1e-5)
    weight = jnp.asarray([1.0] + [0.0] * (pred.shape[0] - 1))
    np.testing.assert_allclose(float(gaussian_nll(pred, log_sigma, target, weight)),
                               want[0].mean() - 0.5 * np.log(2 * np.pi), rtol=1e-5)
    g_pred, g_sigma = jax.grad(gaussian_nll, argnums=(0, 1))(pred, log_sigma, target)
    assert float(jnp.abs(g_pred).max()) == 0.0  # the estimate's gradient is stopped
    # sigma = |error| is the minimum of each term: zero gradient there
    at_error = jnp.log(jnp.abs(target - pred))
    np.testing.assert_allclose(jax.grad(gaussian_nll, argnums=1)(pred, at_error, target), 0.0,
                               atol=1e-6)
    assert float(jnp.abs(g_sigma).max()) > 0


def test_sign_f1_without_a_channel_pools_the_others_counts():
    """Under the paper protocol ax (gravity's reaction) is always positive and always predicted
    so: it lifts the pooled F1. Left out, the F1 is the other channels' micro average."""
    from uavcal_jax.calib.metrics import sign_f1_without

    rng = np.random.default_rng(0)
    target = rng.normal(size=(50, 6))
    pred = target + rng.normal(scale=1.0, size=(50, 6))
    target[:, 3], pred[:, 3] = 9.8, 9.7  # ax
    metrics = jax.tree.map(lambda x: np.asarray(x).tolist(), calibration_metrics(
        jnp.asarray(pred), jnp.asarray(target)))
    channels = ("gx", "gy", "gz", "ax", "ay", "az")
    keep = [0, 1, 2, 4, 5]
    p, t = pred[:, keep] > 0, target[:, keep] > 0
    tp, fp, fn = np.sum(p & t), np.sum(p & ~t), np.sum(~p & t)
    assert sign_f1_without(metrics, channels, ("ax",)) == pytest.approx(2 * tp / (2 * tp + fp + fn))
    assert sign_f1_without(metrics, channels, ()) == pytest.approx(metrics["sign_f1"])
    assert metrics["sign_f1"] > sign_f1_without(metrics, channels, ("ax",))
