"""Motion the model can see (issue 20): frame orientations (oracle slerp, chained visual
rotations), full-rate gyro per frame interval, interval-mean IMU sampling, rotation-residual
tokens and the ``rotation_ls`` closed form, and a training step with them."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uavcal_jax.calib.config import CalibConfig, CalibRunConfig, ModelConfig
from uavcal_jax.calib.data import Windows, gather, load_windows
from uavcal_jax.calib.inject import imu_statistics
from uavcal_jax.calib.loss import tilt_loss
from uavcal_jax.calib.model import Calibrator, rotation_residuals
from uavcal_jax.calib.mounting import isotropic_statistics, random_mountings, remount
from uavcal_jax.calib.predict import predict_sequence
from uavcal_jax.calib.train import create_train_state, eval_step, train_step
from uavcal_jax.config import apply_overrides
from uavcal_jax.data.sequence import (
    CameraCalibration,
    FrameStream,
    GroundTruth,
    ImuData,
    Sequence,
)
from uavcal_jax.data.windows import (
    ALIGNMENT_KEYS,
    WindowConfig,
    chain_orientations,
    interval_mean_imu,
    make_windows,
)
from uavcal_jax.errors import DataError

T0 = 1_400_000_000_000_000_000
RATE_HZ = 20.0
AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
R0 = Rotation.from_rotvec([0.2, 0.1, -0.4])
CONFIG = apply_overrides(CalibConfig(), [
    "model.d_model=16", "model.layers=1", "model.heads=2", "model.use_video=false",
    "model.motion_tokens=true", "model.closed_form=rotation_ls",
    "injection.protocol=physical", "injection.label=injected",
    "loss.sign_term=tanh", "loss.units=standardized",
    "train.batch_size=3", "train.learning_rate=1e-3"])
residuals = jax.jit(rotation_residuals)


def truth(t_s, rate):
    """Body-to-world rotation of a constant-rate turn about ``AXIS``: ``R0 exp(rate t AXIS)``."""
    return R0 * Rotation.from_rotvec(np.outer(np.atleast_1d(t_s) * rate, AXIS))


def make_sequence(rate=0.7, bias=(0.0, 0.0, 0.0), seconds=4.0, drop=(), gt_from_s=0.0,
                  seed=0):
    """A constant-rate turn: 20 Hz camera (tiny frames), 200 Hz IMU on another clock with
    jitter, gyro = the true rate + ``bias``; ground truth at 100 Hz from ``gt_from_s``."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * RATE_HZ))
    keep = np.setdiff1d(np.arange(n), np.asarray(drop, np.int64))
    t_cam = (T0 + keep * 50_000_000).astype(np.int64)
    cal = CameraCalibration(np.array([5.0, 5, 4, 4]), np.zeros(4), (8, 8), RATE_HZ, np.eye(4))
    frames = rng.integers(1, 256, (keep.size, 8, 8), dtype=np.uint8)
    cam = FrameStream("cam0", t_cam, (), cal, lambda i, c: frames[i])
    n_imu = int(seconds * 200) + 20
    t_imu = (T0 - 30_000_000 + np.arange(n_imu) * 5_000_000 + 1_300_000
             + rng.integers(-400_000, 400_000, n_imu)).astype(np.int64)
    gyro = np.broadcast_to(rate * AXIS + np.asarray(bias), (n_imu, 3)).copy()
    accel = rng.normal(size=(n_imu, 3))
    t_gt = (T0 + int(gt_from_s * 1e9) + np.arange(int(seconds * 100) + 10) * 10_000_000)
    q = truth((t_gt - T0) * 1e-9, rate).as_quat()[:, [3, 0, 1, 2]]
    gt = GroundTruth(t_gt.astype(np.int64), np.zeros((t_gt.size, 3)), q)
    seq = Sequence("turn", None, {"cam0": cam}, ImuData(t_imu, gyro, accel), None, gt)
    return seq, frames


def windows(seq, frames, **kw):
    config = WindowConfig(duration=2.0, stride=1.0, size=(8, 8), rotations="oracle", **kw)
    return make_windows(seq, config, frames=frames)


@pytest.fixture(scope="module")
def turn():
    seq, frames = make_sequence(drop=(23,), gt_from_s=0.12)
    return seq, windows(seq, frames)


def test_oracle_orientations_are_the_ground_truth(turn):
    _, ws = turn
    t = (ws.frame_t_ns - T0) * 1e-9
    inside = t >= 0.12
    assert ws.frame_R_valid.tolist() == inside.tolist()
    np.testing.assert_allclose(ws.frame_R[inside], truth(t[inside], 0.7).as_matrix(),
                               atol=1e-9)
    # any two frames' relative rotation is the truth's
    i, j = np.flatnonzero(inside)[[0, 9]]
    rel = ws.frame_R[i].T @ ws.frame_R[j]
    np.testing.assert_allclose(rel, Rotation.from_rotvec(0.7 * (t[j] - t[i]) * AXIS)
                               .as_matrix(), atol=1e-9)


def test_interval_batches_hold_exactly_the_samples_of_each_interval(turn):
    _, ws = turn
    out = ws.motion(np.arange(len(ws)))
    S = ws.interval_cap
    assert out["gyro_seq"].shape == (len(ws), ws.frames_per_window, S, 3)
    imu_t = ws.imu_t_ns
    for w in range(len(ws)):
        idx, mask = ws.frame_index[w], ws.frame_mask[w]
        assert not out["rot_mask"][w, 0] and not out["dt_seq"][w, 0].any()
        for k in range(1, idx.size):
            ok = (mask[k] and mask[k - 1] and ws.frame_R_valid[idx[k]]
                  and ws.frame_R_valid[idx[k - 1]])
            assert out["rot_mask"][w, k] == ok
            if not ok:
                assert not out["dt_seq"][w, k].any()
                np.testing.assert_array_equal(out["rot_cam"][w, k], np.eye(3))
                continue
            a, b = ws.frame_t_ns[idx[k - 1]], ws.frame_t_ns[idx[k]]
            # brute force: samples whose hold [t_i, t_{i+1}) overlaps [a, b)
            nxt = np.append(imu_t[1:], np.iinfo(np.int64).max)
            hit = np.flatnonzero((imu_t < b) & (nxt > a))
            overlap = (np.minimum(nxt[hit], b) - np.maximum(imu_t[hit], a)) * 1e-9
            m = hit.size
            np.testing.assert_array_equal(out["gyro_seq"][w, k, :m],
                                          ws.gyro[hit].astype(np.float32))
            np.testing.assert_allclose(out["dt_seq"][w, k, :m], overlap, rtol=1e-6)
            assert not out["dt_seq"][w, k, m:].any() and not out["gyro_seq"][w, k, m:].any()
            np.testing.assert_allclose(out["dt_seq"][w, k].sum(), (b - a) * 1e-9, rtol=1e-6)
            np.testing.assert_allclose(out["rot_cam"][w, k],
                                       ws.frame_R[idx[k - 1]].T @ ws.frame_R[idx[k]],
                                       atol=1e-7)
    # the dropped frame (stream index 23) masks both intervals that touch its slot
    assert (~out["rot_mask"][:, 1:]).sum() >= 2


def test_visual_chain_breaks_at_a_failed_pair():
    t = np.arange(6) * 10
    rel = Rotation.from_rotvec(np.outer(np.arange(1, 6), [0.01, 0.02, -0.03])).as_matrix()
    valid = np.array([True, True, False, True, True])
    vis = type("V", (), {"t0_ns": t[:-1], "t1_ns": t[1:], "R": rel, "valid": valid})
    R, seg = chain_orientations(t, vis)
    assert seg.tolist() == [0, 0, 0, 1, 1, 1]
    np.testing.assert_allclose(R[0].T @ R[2], rel[0] @ rel[1], atol=1e-12)
    np.testing.assert_allclose(R[3].T @ R[5], rel[3] @ rel[4], atol=1e-12)


def test_interval_mean_sampling_equals_a_brute_force_mean():
    seq, frames = make_sequence(rate=0.0)
    seq.imu.gyro[:] = np.random.default_rng(3).normal(size=seq.imu.gyro.shape)
    config = WindowConfig(duration=2.0, stride=1.0, size=(8, 8), imu_sampling="interval_mean",
                          frame_step=2)
    ws = make_windows(seq, config, frames=frames)
    b = ws.batch(np.arange(len(ws)))
    t_imu, span = seq.imu.t_ns, 2 * 50_000_000
    for w in range(len(ws)):
        for k, f in enumerate(ws.frame_index[w]):
            tf = ws.frame_t_ns[f]
            sel = (t_imu > tf - span) & (t_imu <= tf)
            np.testing.assert_allclose(b["gyro"][w, k], seq.imu.gyro[sel].mean(axis=0),
                                       atol=1e-12)
            np.testing.assert_allclose(b["accel"][w, k], seq.imu.accel[sel].mean(axis=0),
                                       atol=1e-12)
    with pytest.raises(ValueError, match="imu_sampling"):
        WindowConfig(imu_sampling="mean")
    # the check of interval_mean_imu's fallback: a frame with no sample keeps its nearest
    out = interval_mean_imu(np.array([100]), 10, np.array([0, 200]), np.eye(2), np.array([1]))
    np.testing.assert_array_equal(out, [[0.0, 1.0]])


@pytest.fixture(scope="module")
def parallel():
    """The turn with a gyro error along its axis (everything commutes: exact residuals)."""
    seq, frames = make_sequence(rate=0.5, bias=0.03 * AXIS)
    ws = windows(seq, frames)
    parts = [Windows(ws, np.arange(len(ws)), "turn")]
    return parts, gather(parts, np.arange(len(ws)), CONFIG.model, "gyro")


def test_rotation_residual_is_minus_the_gyro_error(parallel):
    _, batch = parallel
    offset = 0.05 * AXIS
    gyro_seq = batch["gyro_seq"] + offset.astype(np.float32)
    r, dt = residuals(gyro_seq, batch["dt_seq"], batch["rot_cam"], batch["rot_mask"])
    valid = batch["rot_mask"]
    assert valid.sum() > 0.9 * valid[:, 1:].size
    np.testing.assert_allclose(np.asarray(r)[valid], np.broadcast_to(-(0.03 + 0.05) * AXIS,
                               (valid.sum(), 3)), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(r)[~valid], 0.0)
    # a general (non-commuting) error: the float64 residual, and -error to first order
    err = np.array([0.02, -0.03, 0.01])
    seq, frames = make_sequence(rate=0.5, bias=err)
    ws = windows(seq, frames)
    m = ws.motion(np.arange(len(ws)))
    r, dt = residuals(m["gyro_seq"], m["dt_seq"], m["rot_cam"], m["rot_mask"])
    r, dt = np.asarray(r)[m["rot_mask"]], np.asarray(dt)[m["rot_mask"]]
    d = dt[:, None]
    ref = (Rotation.from_rotvec(-(0.5 * AXIS + err) * d)
           * Rotation.from_rotvec(0.5 * AXIS * d)).as_rotvec() / d
    np.testing.assert_allclose(r, ref, atol=1e-5)
    first_order = 0.5 * 0.05 * np.linalg.norm(np.cross(err, 0.5 * AXIS))  # BCH term
    assert np.abs(r + err).max() < first_order + 1e-5


@pytest.fixture(scope="module")
def state(parallel):
    return create_train_state(CONFIG, jax.random.key(0), parallel[1])


def test_untrained_rotation_ls_model_predicts_the_gyro_error(parallel, state):
    _, batch = parallel
    offset = np.concatenate([-0.04 * AXIS, [0.1, -0.1, 0.05]]).astype(np.float32)
    # eval_step injects the offset into imu and into every gyro sample of gyro_seq
    pred = np.asarray(eval_step(state, {**batch, "offset": np.tile(offset, (3, 1))})["pred"])
    np.testing.assert_allclose(pred[:, :3], np.broadcast_to((0.03 - 0.04) * AXIS,
                                                            pred[:, :3].shape), atol=1e-4)
    # accel channels: the mean offset of the protocol (0 under physical)
    np.testing.assert_allclose(pred[:, 3:], 0.0, atol=1e-6)
    # the model itself, outside the steps: the same prediction
    motion = {k: batch[k] for k in ("gyro_seq", "dt_seq", "rot_cam", "rot_mask")}
    motion["gyro_seq"] = motion["gyro_seq"] + offset[:3]
    direct = jax.jit(Calibrator(CONFIG.model).apply)(
        state.variables(), None, batch["imu"] + offset, batch["mask"], motion)
    np.testing.assert_allclose(np.asarray(direct), pred, atol=1e-6)
    # and calib predict's path over the sequence (frame tokens reused, motion per window)
    parts, _ = parallel
    seq_pred = predict_sequence(state, parts[0].windows, inject_offset=offset)
    np.testing.assert_allclose(seq_pred.per_window, pred, atol=1e-5)


def test_train_step_with_motion_tokens_lowers_the_loss(parallel, state):
    _, batch = parallel
    key = jax.random.key(7)  # one key: the same offsets every step
    losses = []
    for _ in range(25):
        state, m = train_step(state, batch, key)
        losses.append(float(m["loss"]))
    assert np.isfinite(losses).all()
    assert losses[-1] < 0.8 * losses[0], losses


def test_bad_motion_settings_are_refused(turn):
    _, ws = turn
    with pytest.raises(ValueError, match="motion_tokens"):
        ModelConfig(closed_form="rotation_ls")
    with pytest.raises(ValueError, match="rotations"):
        WindowConfig(rotations="gps")
    plain = Windows(ws.__class__(**{**ws.__dict__, "frame_R": None, "frame_R_segment": None}),
                    np.arange(1), "turn")
    with pytest.raises(DataError, match="rotations"):
        gather([plain], np.arange(1), CONFIG.model, "gyro")
    with pytest.raises(DataError, match="rotation_source"):
        load_windows(["/nonexistent"], WindowConfig(rotations="visual"))


def test_correction_scale_shrinks_the_learned_correction_on_the_closed_form_channels(
        parallel, state):
    """The head's output adds ``correction_scale * offset_std * y`` on the gyro channels
    that ``rotation_ls`` estimates and ``offset_std * y`` on the accelerometer's."""
    _, batch = parallel
    motion = {k: batch[k] for k in ("gyro_seq", "dt_seq", "rot_cam", "rot_mask")}
    variables = state.variables()
    zero = np.asarray(jax.jit(Calibrator(CONFIG.model).apply)(
        variables, None, batch["imu"], batch["mask"], motion))
    params = jax.tree_util.tree_map_with_path(
        lambda path, v: jnp.ones_like(v) if "head" in jax.tree_util.keystr(path)
        and "bias" in jax.tree_util.keystr(path) else v, variables["params"])
    shifted = {**variables, "params": params}
    std = np.asarray(variables["normalization"]["offset_std"])
    for scale in (1.0, 0.05):
        model = Calibrator(dataclasses.replace(CONFIG.model, correction_scale=scale))
        pred = np.asarray(jax.jit(model.apply)(shifted, None, batch["imu"], batch["mask"],
                                               motion))
        np.testing.assert_allclose(pred - zero, np.broadcast_to(
            std * np.array([scale] * 3 + [1.0] * 3), pred.shape), rtol=1e-4, atol=1e-7)
    with pytest.raises(ValueError, match="correction_scale"):
        ModelConfig(correction_scale=0.0)


def test_rotation_window_mean_takes_the_gyro_from_rotations_and_the_rest_from_the_mean(
        parallel, state):
    """``rotation_window_mean``: the gyro as ``rotation_ls``, the accelerometer as each
    window's mean sample minus the training mean (the ``window_mean`` closed form); the
    head's unit is ``correction_scale`` on every channel."""
    _, batch = parallel
    offset = np.concatenate([-0.04 * AXIS, [0.3, -0.2, 0.5]]).astype(np.float32)
    motion = {k: batch[k] for k in ("gyro_seq", "dt_seq", "rot_cam", "rot_mask")}
    motion["gyro_seq"] = motion["gyro_seq"] + offset[:3]
    imu = batch["imu"] + offset
    variables = state.variables()
    forms = {}
    for form in ("rotation_ls", "rotation_window_mean", "window_mean"):
        model = Calibrator(dataclasses.replace(CONFIG.model, closed_form=form))
        forms[form] = np.asarray(jax.jit(model.apply)(variables, None, imu, batch["mask"],
                                                      motion))
    np.testing.assert_allclose(forms["rotation_window_mean"][:, :3],
                               forms["rotation_ls"][:, :3], atol=1e-6)
    np.testing.assert_allclose(forms["rotation_window_mean"][:, :3],
                               np.broadcast_to((0.03 - 0.04) * AXIS, (3, 3)), atol=1e-4)
    mask = batch["mask"][..., None]
    mean = (imu * mask).sum(axis=1) / mask.sum(axis=1)
    expected = mean - np.asarray(variables["normalization"]["imu_mean"])
    np.testing.assert_allclose(forms["rotation_window_mean"][:, 3:], expected[:, 3:],
                               rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(forms["window_mean"], expected, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="motion_tokens"):
        ModelConfig(closed_form="rotation_window_mean")


def test_mounting_angle_is_zero_as_trained_and_a_quarter_turn_for_another_mounting():
    """``mounting_angle_deg``: a recording's mean specific force against the training mean
    (EuRoC's IMU: gravity on x); the transformer method warns past 30 degrees."""
    from uavcal_jax.calib.predict import mounting_angle_deg
    from uavcal_jax.pipeline.transformer_offset import MOUNTING_TOLERANCE_DEG

    rng = np.random.default_rng(0)
    trained = np.array([9.7, 0.3, -1.2])
    accel = trained + rng.normal(0.0, 2.0, (4000, 3))  # flight accelerations average out
    assert mounting_angle_deg(accel, trained) < 5.0
    turned = accel @ Rotation.from_rotvec([0.0, -np.pi / 2, 0.0]).as_matrix()
    assert 80.0 < mounting_angle_deg(turned, trained) < 100.0
    assert MOUNTING_TOLERANCE_DEG < 80.0
    np.testing.assert_allclose(mounting_angle_deg(-accel, trained), 180.0, atol=5.0)


# ----------------------------------------------------------------------------- any mounting


def test_remounted_windows_read_every_vector_in_the_turned_imu_frame(parallel, state):
    """``train.mounting=random``: a window read through a mounting ``R`` has its rotation
    residuals turned by ``R`` (``R^T r``), and the untrained ``rotation_ls`` model's gyro
    estimate with them."""
    _, batch = parallel
    R = np.asarray(random_mountings(jax.random.key(3), batch["imu"].shape[0]))
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-6)
    turned = remount(batch, R)
    r, _ = residuals(batch["gyro_seq"], batch["dt_seq"], batch["rot_cam"], batch["rot_mask"])
    r_t, _ = residuals(turned["gyro_seq"], turned["dt_seq"], turned["rot_cam"],
                       turned["rot_mask"])
    np.testing.assert_allclose(np.asarray(r_t), np.einsum("bti,bij->btj", np.asarray(r), R),
                               atol=1e-5)
    for b in range(R.shape[0]):  # the IMU samples, both sensors
        for c in (0, 3):
            np.testing.assert_allclose(np.asarray(turned["imu"])[b, :, c:c + 3],
                                       batch["imu"][b, :, c:c + 3] @ R[b], atol=1e-5)
    offset = np.tile(np.float32([0.02, -0.01, 0.03, 0, 0, 0]), (3, 1))
    pred = np.asarray(eval_step(state, {**batch, "offset": offset})["pred"])[:, :3]
    offset_t = np.concatenate([np.einsum("bi,bij->bj", offset[:, :3], R), offset[:, 3:]], 1)
    pred_t = np.asarray(eval_step(state, {**turned, "offset": offset_t})["pred"])[:, :3]
    np.testing.assert_allclose(pred_t, np.einsum("bi,bij->bj", pred, R), atol=1e-4)


def test_isotropic_statistics_are_those_of_the_imu_over_random_mountings():
    rng = np.random.default_rng(0)
    samples = np.concatenate([rng.normal([0.1, -0.2, 0.05], [0.3, 0.2, 0.5], (4000, 3)),
                              rng.normal([9.5, 0.3, -2.0], [0.4, 0.3, 0.6], (4000, 3))], 1)
    stats = isotropic_statistics(imu_statistics(samples))
    R = np.asarray(random_mountings(jax.random.key(0), 4000))
    turned = np.concatenate([np.einsum("ni,nij->nj", samples[:, c:c + 3], R)
                             for c in (0, 3)], 1)
    np.testing.assert_allclose(stats.mean, 0.0)
    np.testing.assert_allclose(stats.std, np.sqrt(np.mean(turned ** 2, axis=0)), rtol=0.05)
    # exactly: E[(R^T v)_i^2] = |v|^2 / 3 for a uniform R
    accel_rms = np.sqrt(np.mean(np.sum(samples[:, 3:] ** 2, axis=1)) / 3)
    np.testing.assert_allclose(stats.std[3:], accel_rms, rtol=1e-4)


@pytest.mark.heavy  # CI budget: an option, 20+ s
def test_random_mounting_trains_on_turned_windows_and_refuses_the_paper_protocol(parallel):
    _, batch = parallel
    config = apply_overrides(CONFIG, ["train.mounting=random"])
    s = create_train_state(config, jax.random.key(0), batch)
    np.testing.assert_array_equal(np.asarray(s.imu_stats.mean), 0.0)
    fixed = create_train_state(CONFIG, jax.random.key(0), batch)
    key = jax.random.key(7)
    _, m = train_step(s, batch, key)
    _, m_fixed = train_step(fixed, batch, key)
    assert np.isfinite(float(m["loss"]))
    assert float(m["offset_rmse"]) != float(m_fixed["offset_rmse"])
    with pytest.raises(ValueError, match="paper"):
        apply_overrides(CalibConfig(), ["train.mounting=random"])
    with pytest.raises(ValueError, match="mounting"):
        apply_overrides(CalibConfig(), ["train.mounting=sideways"])


TILT = apply_overrides(CONFIG, ["model.tilt_head=true"])


def test_frame_up_is_the_ground_truth_up_in_the_body_frame(turn):
    _, ws = turn
    t = (ws.frame_t_ns - T0) * 1e-9
    inside = t >= 0.12
    up = truth(t[inside], 0.7).inv().apply([0.0, 0.0, 1.0])  # R^T e_z
    np.testing.assert_allclose(ws.frame_up[inside], up, atol=1e-6)
    np.testing.assert_array_equal(ws.frame_up[~inside], 0.0)
    labels = ws.up(np.arange(len(ws)))
    assert labels.shape == (len(ws), ws.frames_per_window, 3)
    np.testing.assert_array_equal(labels[~ws.frame_mask], 0.0)  # the dropped frame's slot
    norms = np.linalg.norm(labels[ws.frame_mask], axis=-1)
    assert set(np.round(norms, 5)) <= {0.0, 1.0}


def test_tilt_loss_is_the_squared_distance_and_the_angle_over_labelled_frames():
    up = np.zeros((1, 3, 3), np.float32)
    up[0, 0] = [0, 0, 1]
    up[0, 1] = [1, 0, 0]  # frame 2: no ground truth (zero)
    pred = np.float32([[[0, 2, 0], [1, 0, 0], [5, 5, 5]]])
    loss, angle = tilt_loss(pred, up, np.ones((1, 3), bool))
    np.testing.assert_allclose(float(loss), (5.0 + 0.0) / 2, rtol=1e-6)
    np.testing.assert_allclose(float(angle), 45.0, rtol=1e-5)


@pytest.mark.heavy  # CI budget: an option, 30 s
def test_tilt_head_learns_gravity_without_changing_the_untrained_offsets(parallel):
    parts, batch = parallel
    tilt_batch = gather(parts, np.arange(batch["imu"].shape[0]), TILT.model, "gyro")
    np.testing.assert_allclose(np.linalg.norm(tilt_batch["up"], axis=-1)[tilt_batch["mask"]],
                               1.0, atol=1e-5)
    plain = create_train_state(CONFIG, jax.random.key(0), batch)
    state = create_train_state(TILT, jax.random.key(0), tilt_batch)
    offset = np.tile(np.float32([0.02, -0.01, 0.03, 0.1, 0, 0]), (3, 1))
    np.testing.assert_allclose(
        np.asarray(eval_step(state, {**tilt_batch, "offset": offset})["pred"]),
        np.asarray(eval_step(plain, {**batch, "offset": offset})["pred"]), atol=1e-6)
    key = jax.random.key(7)
    tilts = []
    for _ in range(40):
        state, m = train_step(state, tilt_batch, key)
        tilts.append(float(m["tilt"]))
    assert tilts[-1] < 0.5 * tilts[0], tilts
    assert np.isfinite(float(m["tilt_deg"]))
    # a remounted window's label is read in the turned IMU frame too
    R = np.asarray(random_mountings(jax.random.key(3), 3))
    turned = remount(tilt_batch, R)
    np.testing.assert_allclose(np.asarray(turned["up"]),
                               np.einsum("bti,bij->btj", tilt_batch["up"], R), atol=1e-6)


def test_tilt_head_needs_ground_truth(turn):
    _, ws = turn
    blind = dataclasses.replace(ws, frame_up=None)
    with pytest.raises(DataError, match="ground truth"):
        gather([Windows(blind, np.arange(len(ws)), "turn")], np.arange(1), TILT.model, "gyro")


def test_rotation_alignment_starts_the_accelerometer_at_the_windows_metric_start(parallel):
    """``closed_form=rotation_alignment``: the untrained model's gyro is the rotation least
    squares, its accelerometer each window's metric start moved by the injected offset
    through the window's response (what the alignment of the injected IMU gives), in the
    training steps and in ``calib predict``'s path alike."""
    parts, batch = parallel
    ws = parts[0].windows
    rng = np.random.default_rng(3)
    n = len(ws)
    fields = {"accel_start": rng.normal(0.0, 0.1, (n, 3)),
              "accel_response": np.stack([np.diag(rng.uniform(0.2, 1.0, 3)) for _ in range(n)]),
              "accel_start_std": rng.uniform(0.01, 0.1, (n, 3))}
    aligned = dataclasses.replace(ws, **fields)
    config = apply_overrides(CONFIG, ["model.closed_form=rotation_alignment"])
    parts = [Windows(aligned, np.arange(n), "turn")]
    batch = gather(parts, np.arange(n), config.model, "gyro")
    assert set(ALIGNMENT_KEYS) <= set(batch)
    state = create_train_state(config, jax.random.key(0), batch)
    offset = np.concatenate([-0.04 * AXIS, [0.1, -0.1, 0.05]]).astype(np.float32)
    pred = np.asarray(eval_step(state, {**batch, "offset": np.tile(offset, (n, 1))})["pred"])
    np.testing.assert_allclose(pred[:, :3], np.broadcast_to((0.03 - 0.04) * AXIS, (n, 3)),
                               atol=1e-4)
    want = fields["accel_start"] + fields["accel_response"] @ offset[3:]
    np.testing.assert_allclose(pred[:, 3:], want, atol=1e-5)
    seq_pred = predict_sequence(state, aligned, inject_offset=offset)
    np.testing.assert_allclose(seq_pred.per_window, pred, atol=1e-5)
    with pytest.raises(ValueError, match="accel_start=alignment"):
        CalibRunConfig(model=config.model)
