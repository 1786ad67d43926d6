"""A detected box + a depth image + the pose -> the target's world position and its covariance.

Pure JAX and fixed-shape (jit/vmap-able over boxes). Frames: ``C`` camera (x right, y down,
z forward), ``B`` body (IMU), ``W`` world (z up); ``T_BC`` maps camera to body points and
``T_WB`` body to world points (4x4). Boxes are ``(x1, y1, x2, y2)`` in pixel-*edge*
coordinates: pixel column ``j`` spans ``[j, j + 1)``, as the simulator's inclusive-exclusive
labels and detector boxes are; the camera model's pixel *centres* sit at integers
(:mod:`uavcal_jax.geometry.camera`), hence the half-pixel shift in :func:`box_center`.

The depth of a box is a robust statistic, not the centre pixel (box-plus-depth ROS nodes read
holes there and place points behind the object): a fixed grid of samples over the box shrunk
towards its centre; of the valid ones (finite, inside ``[min_depth, max_depth]``, so 0/NaN
holes drop out) a low quantile picks the nearest substantial surface, and the median of the
samples in a band around it is the depth (the band rejects the background behind the target
and specks in front of it). Depth sees the target's front surface, so the point is moved
further along the ray: half a constant depth extent (``extent``), or, for a target modelled as
an upright box, to the centre of the box that would be seen so
(:mod:`uavcal_jax.track.box_model`). Not enough consistent depth gives ``located = False`` and
a NaN point, never a point at the origin.

Covariance: pixel noise on the box centre (``pixel_sigma``) and a z-depth noise that grows with
``z^2`` as stereo depth does, ``sigma_z = z^2 sigma_d / (f b)`` (with a floor), propagated
through the unprojection (its Jacobian, lens distortion included) and the rotation
``R_WC = R_WB R_BC``. The pose itself is taken as exact.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from uavcal_jax.geometry.camera import PinholeRadtan, pixels_to_normalized

__all__ = [
    "LOCATED",
    "NO_CONSISTENT_SURFACE",
    "NO_DEPTH",
    "OUTSIDE_IMAGE",
    "REASONS",
    "BoxDepth",
    "LocateConfig",
    "Located",
    "box_center",
    "box_depth",
    "cut_by_border",
    "depth_sigma",
    "locate_box",
    "locate_from_depth",
    "point_from_depth",
    "robust_depth",
]

#: ``Located.reason`` codes; ``REASONS[code]`` is the words.
LOCATED, OUTSIDE_IMAGE, NO_DEPTH, NO_CONSISTENT_SURFACE = 0, 1, 2, 3
REASONS = ("located", "box outside the image", "no valid depth in the box",
           "no consistent surface in the box")


@dataclasses.dataclass(frozen=True)
class LocateConfig:
    """Settings of the box localisation (every default documented here).

    Attributes:
        shrink: the box is scaled by this about its centre before sampling (0.5: its central
            half in width and height), keeping clear of the background around the target.
        samples: a ``samples x samples`` grid of depth samples over the shrunk box (fixed
            shape whatever the box size; nearest pixel).
        quantile: the low quantile of the valid samples' depth that picks the target's surface
            (0.2: the nearest fifth, robust to a few near specks, short of the background).
        band_min, band_rel: samples within ``max(band_min, band_rel z_q)`` metres of that
            quantile ``z_q`` are the surface; their median is the depth.
        min_valid: the least fraction of samples with valid depth (else ``NO_DEPTH``).
        min_inliers: the least fraction of samples in the band (else
            ``NO_CONSISTENT_SURFACE``).
        min_depth, max_depth: valid depth range, metres (0 and NaN are holes).
        target_extent: default depth extent of the target along the ray, metres (half of it is
            added to the front-surface depth); pass ``extent`` per call for a class's size.
        pixel_sigma: standard deviation of the box centre, pixels (detector jitter).
        disparity_sigma: standard deviation of the stereo disparity, pixels.
        baseline: stereo baseline, metres, of the depth's noise model (0.11 m: EuRoC's
            VI-sensor rig, which the simulator renders).
        depth_sigma_min: floor of the z-depth standard deviation, metres.
    """

    shrink: float = 0.5
    samples: int = 24
    quantile: float = 0.2
    band_min: float = 0.2
    band_rel: float = 0.1
    min_valid: float = 0.1
    min_inliers: float = 0.1
    min_depth: float = 0.1
    max_depth: float = 40.0
    target_extent: float = 0.0
    pixel_sigma: float = 2.0
    disparity_sigma: float = 0.5
    baseline: float = 0.11
    depth_sigma_min: float = 0.02

    def __post_init__(self):
        if not 0.0 < self.shrink <= 1.0:
            raise ValueError(f"shrink must be in (0, 1], got {self.shrink}")
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if not 0.0 <= self.quantile <= 1.0:
            raise ValueError(f"quantile must be in [0, 1], got {self.quantile}")
        if not 0.0 < self.min_depth < self.max_depth:
            raise ValueError("need 0 < min_depth < max_depth")
        if self.baseline <= 0.0:
            raise ValueError(f"baseline must be > 0, got {self.baseline}")


class BoxDepth(NamedTuple):
    """The robust depth of a box: ``depth`` (metres, NaN unless ``reason == LOCATED``),
    ``reason`` (int code), ``valid`` and ``inliers`` (fractions of the samples)."""

    depth: jax.Array
    reason: jax.Array
    valid: jax.Array
    inliers: jax.Array


class Located(NamedTuple):
    """A located target.

    Attributes:
        point: (3,) world position of the target centre, metres (NaN when not located).
        covariance: (3, 3) its covariance in the world frame, m^2 (NaN when not located).
        located: () bool.
        reason: () int, an index into :data:`REASONS`.
        depth: () the front-surface z-depth used, metres (NaN when not located).
    """

    point: jax.Array
    covariance: jax.Array
    located: jax.Array
    reason: jax.Array
    depth: jax.Array


def cut_by_border(box, size, margin: float) -> bool:
    """Whether ``box`` (4,) ``(x1, y1, x2, y2)`` pixels reaches within ``margin`` pixels of the
    border of an image of ``size`` ``(width, height)``; never where ``margin < 0``. Plain
    Python (a per-detection test outside the jitted numerics)."""
    if margin < 0:
        return False
    w, h = size
    x1, y1, x2, y2 = (float(v) for v in box)
    return x1 <= margin or y1 <= margin or x2 >= w - margin or y2 >= h - margin


def box_center(box: jax.Array) -> jax.Array:
    """(2,) the box centre ``(u, v)`` in the camera model's pixel-centre convention."""
    box = jnp.asarray(box)
    return 0.5 * (box[:2] + box[2:4]) - 0.5


def _lower_quantile(sorted_values: jax.Array, count: jax.Array, q: float) -> jax.Array:
    """The ``q`` quantile (lower order statistic) of the first ``count`` sorted values."""
    index = jnp.floor(q * jnp.maximum(count - 1, 0)).astype(jnp.int32)
    return sorted_values[index]


@functools.partial(jax.jit, static_argnames="config")
def robust_depth(values: jax.Array, config: LocateConfig = LocateConfig()) -> BoxDepth:
    """The depth of a surface from depth samples ``values`` (N,) metres (0/NaN = hole).

    A low quantile of the valid samples, then the median of the samples within the band
    around it (see the module docstring).
    """
    values = jnp.asarray(values)
    n = values.shape[0]
    valid = jnp.isfinite(values) & (values >= config.min_depth) & (values <= config.max_depth)
    n_valid = jnp.sum(valid)
    z_q = _lower_quantile(jnp.sort(jnp.where(valid, values, jnp.inf)), n_valid, config.quantile)
    band = jnp.maximum(config.band_min, config.band_rel * z_q)
    inlier = valid & (jnp.abs(values - z_q) <= band)
    n_in = jnp.sum(inlier)
    median = _lower_quantile(jnp.sort(jnp.where(inlier, values, jnp.inf)), n_in, 0.5)
    frac_valid, frac_in = n_valid / n, n_in / n
    reason = jnp.where(frac_valid < config.min_valid, NO_DEPTH,
                       jnp.where(frac_in < config.min_inliers, NO_CONSISTENT_SURFACE, LOCATED))
    reason = jnp.where(n_valid == 0, NO_DEPTH, reason)
    depth = jnp.where(reason == LOCATED, median, jnp.nan)
    return BoxDepth(depth, reason.astype(jnp.int32), frac_valid, frac_in)


@functools.partial(jax.jit, static_argnames="config")
def box_depth(depth_image: jax.Array, box: jax.Array,
              config: LocateConfig = LocateConfig()) -> BoxDepth:
    """The robust depth of ``box`` (4,) in ``depth_image`` (H, W) metres (0/NaN = hole).

    Samples a ``samples x samples`` grid over the box shrunk by ``shrink`` about its centre
    (nearest pixel); samples off the image count as holes. A box without area, or wholly off
    the image, is ``OUTSIDE_IMAGE``.
    """
    depth_image = jnp.asarray(depth_image)
    box = jnp.asarray(box, depth_image.dtype)
    height, width = depth_image.shape
    centre = 0.5 * (box[:2] + box[2:4])  # edge coordinates
    half = 0.5 * config.shrink * (box[2:4] - box[:2])
    s = config.samples
    offsets = (jnp.arange(s, dtype=box.dtype) + 0.5) / s * 2.0 - 1.0  # (s,) in (-1, 1)
    cols = jnp.floor(centre[0] + offsets * half[0]).astype(jnp.int32)
    rows = jnp.floor(centre[1] + offsets * half[1]).astype(jnp.int32)
    rr, cc = jnp.meshgrid(rows, cols, indexing="ij")
    inside = (rr >= 0) & (rr < height) & (cc >= 0) & (cc < width)
    values = depth_image[jnp.clip(rr, 0, height - 1), jnp.clip(cc, 0, width - 1)]
    values = jnp.where(inside, values, jnp.nan).reshape(-1)
    out = robust_depth(values, config)
    empty = (box[2] <= box[0]) | (box[3] <= box[1]) | ~jnp.any(inside)
    reason = jnp.where(empty, OUTSIDE_IMAGE, out.reason).astype(jnp.int32)
    return out._replace(depth=jnp.where(empty, jnp.nan, out.depth), reason=reason)


def depth_sigma(z: jax.Array, focal: jax.Array, config: LocateConfig = LocateConfig()):
    """Standard deviation of a stereo z-depth ``z`` (metres) at focal length ``focal`` (px):
    ``sqrt((z^2 sigma_d / (f b))^2 + sigma_min^2)``."""
    stereo = z * z * config.disparity_sigma / (focal * config.baseline)
    return jnp.sqrt(stereo * stereo + config.depth_sigma_min ** 2)


def point_from_depth(uv: jax.Array, z: jax.Array, cam: PinholeRadtan, extent: jax.Array,
                     config: LocateConfig = LocateConfig()) -> tuple[jax.Array, jax.Array]:
    """Camera-frame target centre (3,) and its covariance (3, 3) from the pixel ``uv`` (2,)
    (pixel-centre convention, distorted) and the front-surface z-depth ``z`` (metres).

    The centre is the front-surface point ``z (x, y, 1)`` moved ``extent / 2`` further along
    the unit ray. The covariance is ``J diag(s_px^2, s_px^2, s_z^2) J^T`` with ``J`` the
    Jacobian of that map in ``(u, v, z)`` (lens distortion included).
    """

    def centre(args):
        u, v, depth = args[0], args[1], args[2]
        xy = pixels_to_normalized(jnp.stack([u, v]), cam)
        ray = jnp.concatenate([xy, jnp.ones_like(xy[:1])])
        return depth * ray + 0.5 * extent * ray / jnp.linalg.norm(ray)

    args = jnp.stack([uv[0], uv[1], z])
    point = centre(args)
    jac = jax.jacfwd(centre)(args)
    sz = depth_sigma(z, cam.fx, config)
    noise = jnp.stack([config.pixel_sigma ** 2, config.pixel_sigma ** 2, sz * sz])
    return point, (jac * noise) @ jac.T


def locate_from_depth(uv: jax.Array, measured: BoxDepth, cam: PinholeRadtan, T_WC: jax.Array,
                      extent=None, config: LocateConfig = LocateConfig()) -> Located:
    """:class:`Located` from a pixel, its robust depth and the camera pose ``T_WC`` (4, 4).

    Shared by the depth-image path (:func:`locate_box`) and the stereo path
    (:func:`uavcal_jax.track.stereo.locate_box_stereo`).
    """
    extent = config.target_extent if extent is None else extent
    return _locate_from_depth(jnp.asarray(uv), measured, cam, jnp.asarray(T_WC),
                              jnp.asarray(extent, jnp.result_type(float)), config)


@functools.partial(jax.jit, static_argnames="config")
def _locate_from_depth(uv, measured: BoxDepth, cam: PinholeRadtan, T_WC, extent,
                       config: LocateConfig) -> Located:
    ok = measured.reason == LOCATED
    z = jnp.where(ok, measured.depth, 1.0)  # a finite stand-in keeps the Jacobian finite
    p_C, cov_C = point_from_depth(uv, z, cam, extent.astype(z.dtype), config)
    R_WC = T_WC[:3, :3]
    point = R_WC @ p_C + T_WC[:3, 3]
    cov = R_WC @ cov_C @ R_WC.T
    return Located(
        point=jnp.where(ok, point, jnp.nan),
        covariance=jnp.where(ok, 0.5 * (cov + cov.T), jnp.nan),
        located=ok,
        reason=measured.reason,
        depth=measured.depth,
    )


def locate_box(box: jax.Array, depth_image: jax.Array, cam: PinholeRadtan, T_BC: jax.Array,
               T_WB: jax.Array, extent=None, config: LocateConfig = LocateConfig()) -> Located:
    """The world position of the target in ``box`` (4,) (left-image pixel edges).

    Args:
        box: ``(x1, y1, x2, y2)`` pixels, edge coordinates (see the module docstring).
        depth_image: (H, W) z-depth in the camera frame, metres; 0 or NaN = no depth (the
            simulator's uint16 millimetre PNG as :func:`uavcal_jax.data.euroc.load_depth`
            reads it).
        cam: the camera model (its ``fx`` is also the depth noise's focal length).
        T_BC: (4, 4) camera-to-body; T_WB: (4, 4) body-to-world (the body pose).
        extent: the target's depth extent along the ray, metres (default
            ``config.target_extent``); half of it is added to the front-surface depth.
        config: :class:`LocateConfig`.

    Returns:
        :class:`Located` (world point, 3x3 world covariance, flag, reason, depth).
    """
    extent = config.target_extent if extent is None else extent
    return _locate_box(jnp.asarray(box), jnp.asarray(depth_image), cam, jnp.asarray(T_BC),
                       jnp.asarray(T_WB), jnp.asarray(extent, jnp.result_type(float)), config)


@functools.partial(jax.jit, static_argnames="config")
def _locate_box(box, depth_image, cam, T_BC, T_WB, extent, config: LocateConfig) -> Located:
    measured = box_depth(depth_image, box, config)
    uv = box_center(box.astype(measured.depth.dtype))
    return _locate_from_depth(uv, measured, cam, T_WB @ T_BC, extent, config)
