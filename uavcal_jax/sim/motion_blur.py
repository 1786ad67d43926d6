"""Motion blur from the camera's motion during the exposure.

A global-shutter pixel integrates the light of every pose the camera passes through in
``[t - exposure/2, t + exposure/2]``. The exposure is split into ``S`` equal parts and the
image is the mean of the images seen at their midpoints (:func:`exposure_times`), the
camera's poses there coming from the trajectory itself.

Rather than ray-cast ``S`` extra frames (``S`` times the renderer's cost), each sub-image is
warped from the one frame rendered at mid-exposure, using its depth (:func:`blur_image`): the
ray of pixel ``u`` at sub-pose ``s`` is taken to hit the scene at the mid-exposure depth of
``u``, that point is projected (with the lens distortion) into the mid-exposure camera, and
the rendered image is sampled there bilinearly. For rotation this is exact whatever the depth;
for translation it assumes the depth under a pixel changes little over the exposure's few
pixels of motion, which fails only along depth edges. The scene's moving targets are blurred
by the camera's motion, not by their own. Samples falling outside the image take the nearest
edge pixel. ``tests/test_sim_camera.py`` compares the result with the mean of ``S`` ray-cast
renders.

Rolling shutter. A rolling-shutter sensor exposes row ``r`` ``line_delay`` seconds after row
``r - 1``, so each row sees the scene from its own pose. The same warp gives it: row ``r``'s
sub-exposure poses are taken at its own times (:func:`row_times`; the frame's timestamp is
the middle row's, where the depth and the labels are rendered) and each pixel is warped with
its row's pose (``T_CmCs`` per row in :func:`blur_image`): one render per frame whatever the
delay, the same approximation as the blur (exact for rotation), and per-row rather than
per-band poses, so no band seams.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.geometry import camera as camera_model

__all__ = ["blur_image", "exposure_times", "relative_poses", "row_times"]


def exposure_times(t_ns: np.ndarray, exposure_s: float | np.ndarray, samples: int,
                   t_min_ns: int | None = None, t_max_ns: int | None = None) -> np.ndarray:
    """(N, S) int64 ns: midpoints of ``S`` equal parts of ``[t - exposure/2, t + exposure/2]``
    for each frame time ``t`` (N,) and exposure (seconds, one or (N,)), clamped to
    ``[t_min_ns, t_max_ns]`` when given (the trajectory's span: the first and last frames'
    exposures may reach past it)."""
    offsets = (np.arange(samples) + 0.5) / samples - 0.5  # in units of the exposure
    t = np.asarray(t_ns, dtype=np.int64)[:, None] + np.round(
        offsets[None, :] * np.reshape(exposure_s, (-1, 1)) * 1e9).astype(np.int64)
    lo = np.iinfo(np.int64).min if t_min_ns is None else int(t_min_ns)
    hi = np.iinfo(np.int64).max if t_max_ns is None else int(t_max_ns)
    return np.clip(t, lo, hi)


def row_times(t_ns: np.ndarray, rows: int, line_delay_s: float,
              t_min_ns: int | None = None, t_max_ns: int | None = None) -> np.ndarray:
    """(..., rows) int64 ns: the times (...) shifted to each row of a rolling shutter, row
    ``r`` by ``(r - (rows - 1) / 2) * line_delay_s`` (the middle row keeps the time), clamped
    to ``[t_min_ns, t_max_ns]`` when given."""
    shift = np.round((np.arange(rows) - 0.5 * (rows - 1)) * line_delay_s * 1e9).astype(np.int64)
    t = np.asarray(t_ns, dtype=np.int64)[..., None] + shift
    lo = np.iinfo(np.int64).min if t_min_ns is None else int(t_min_ns)
    hi = np.iinfo(np.int64).max if t_max_ns is None else int(t_max_ns)
    return np.clip(t, lo, hi)


def relative_poses(T_WC_mid: np.ndarray, T_WC_sub: np.ndarray) -> np.ndarray:
    """(N, S, 4, 4) ``T_CmCs = T_WCm^-1 T_WCs``: the sub-exposure cameras in the
    mid-exposure camera's frame, from (N, 4, 4) and (N, S, 4, 4) camera-to-world poses."""
    R = np.swapaxes(T_WC_mid[:, :3, :3], -1, -2)
    T_CmW = np.zeros_like(T_WC_mid)
    T_CmW[:, :3, :3] = R
    T_CmW[:, :3, 3] = -np.einsum("nij,nj->ni", R, T_WC_mid[:, :3, 3])
    T_CmW[:, 3, 3] = 1.0
    return np.einsum("nij,nsjk->nsik", T_CmW, T_WC_sub)


def _bilinear(image: jax.Array, u: jax.Array, v: jax.Array) -> jax.Array:
    """Sample (H, W[, C]) at pixel coordinates ``u`` (column), ``v`` (row) (P,), edge-clamped;
    returns (P[, C])."""
    H, W = image.shape[:2]
    u = jnp.clip(u, 0.0, W - 1.0)
    v = jnp.clip(v, 0.0, H - 1.0)
    u0 = jnp.minimum(jnp.floor(u), W - 2.0)
    v0 = jnp.minimum(jnp.floor(v), H - 2.0)
    fu, fv = u - u0, v - v0
    flat = image.reshape(H * W, *image.shape[2:])
    i00 = v0.astype(jnp.int32) * W + u0.astype(jnp.int32)
    if image.ndim == 3:
        fu, fv = fu[:, None], fv[:, None]
    top = flat[i00] * (1.0 - fu) + flat[i00 + 1] * fu
    bottom = flat[i00 + W] * (1.0 - fu) + flat[i00 + W + 1] * fu
    return top * (1.0 - fv) + bottom * fv


def blur_image(image: jax.Array, depth: jax.Array, rx: jax.Array, ry: jax.Array,
               T_CmCs: jax.Array, cam: camera_model.PinholeRadtan) -> jax.Array:
    """The exposure's mean image, warped from the mid-exposure render.

    Args:
        image: (H, W) or (H, W, 3) float radiance rendered at mid-exposure.
        depth: (H, W) its z-depth, metres.
        rx, ry: (H * W,) undistorted normalised coordinates of every pixel centre, row-major
            (the ray ``(rx, ry, 1)``; :class:`~uavcal_jax.sim.render.RayBundle`'s).
        T_CmCs: (S, 4, 4) each sub-exposure camera in the mid-exposure camera's frame
            (:func:`relative_poses`), or (S, H, 4, 4) one per image row (rolling shutter).
        cam: the lens (projects into the mid-exposure image with its distortion).

    Returns:
        The mean over the ``S`` sub-exposures, shaped like ``image``.
    """
    f32 = jnp.float32
    image = image.astype(f32)
    d = depth.reshape(-1).astype(f32)
    X, Y, Z = rx * d, ry * d, d  # (P,) points at the mid-exposure depth
    cam = cam.astype(f32)
    T_CmCs = jnp.asarray(T_CmCs, f32)
    if T_CmCs.ndim == 4:  # one pose per row: (H, W) points against (H, 1) coefficients
        X, Y, Z = (a.reshape(image.shape[:2]) for a in (X, Y, Z))
        T_CmCs = T_CmCs[:, :, None]

    def add_sample(total, T):
        # scalar-times-array products fuse; a (P, 3) @ (3, 3) product ran 6x slower on CPU
        px = T[..., 0, 0] * X + T[..., 0, 1] * Y + T[..., 0, 2] * Z + T[..., 0, 3]
        py = T[..., 1, 0] * X + T[..., 1, 1] * Y + T[..., 1, 2] * Z + T[..., 1, 3]
        pz = jnp.maximum(T[..., 2, 0] * X + T[..., 2, 1] * Y + T[..., 2, 2] * Z + T[..., 2, 3],
                         1e-6)
        xy = jnp.stack([px / pz, py / pz], axis=-1).reshape(-1, 2)
        uv = camera_model.project_normalized(xy, cam)
        return total + _bilinear(image, uv[:, 0], uv[:, 1]), None

    zero = jnp.zeros((d.shape[0], *image.shape[2:]), f32)
    total, _ = jax.lax.scan(add_sample, zero, T_CmCs)
    return (total * (1.0 / T_CmCs.shape[0])).reshape(image.shape)
