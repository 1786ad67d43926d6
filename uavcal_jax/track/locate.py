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
an upright box, to the centre of the box that would be seen so (:func:`box_centre`): the
offset changes with the view (a car seen from the side is 0.9 m deep, seen end-on from a low
drone 2 m) and the ray through the image box's centre misses the box's centre by up to half a
metre. The box turns with the target's heading: each candidate heading gives a centre and a
fit of the box's shape (:func:`box_centre_candidates`); :mod:`uavcal_jax.track.heading` picks
among them over time. Not enough consistent depth gives ``located = False`` and a NaN point,
never a point at the origin.

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
import numpy as np

from uavcal_jax.geometry.camera import PinholeRadtan, pixels_to_normalized, project_normalized

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
    "CANDIDATE_HEADINGS",
    "box_centre",
    "box_centre_candidates",
    "border_covariance",
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


#: The headings :func:`box_centre_candidates` tries, radians: a box is symmetric, so
#: ``[0, pi)`` in 16 steps of 11.25 degrees.
CANDIDATE_HEADINGS = np.arange(16) * (np.pi / 16)
#: Fixed-point steps of :func:`box_centre` (each moves the centre by the residual; 3 reach a
#: millimetre on a car 5-10 m away).
_CENTRE_STEPS = 6
#: At most this many samples a side model :func:`box_depth`'s grid (a box's faces are planes,
#: so a coarse grid gives their robust depth as the fine one does, at a tenth of the cost).
_MODEL_SAMPLES = 8
#: The largest relative miss (of the front point's range) of a settled :func:`box_centre` fit.
_CENTRE_TOLERANCE = 0.01
#: The corners of a unit box, (8, 3).
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                    dtype=float)


def _slab_entry(origin, direction, half):
    """Ray ``origin + t direction`` (box frame) against the box ``|x_i| <= half_i``: the entry
    ``t`` and whether the ray hits the box (the slab method)."""
    safe = jnp.where(jnp.abs(direction) > 1e-12, direction, 1e-12)
    t1, t2 = (-half - origin) / safe, (half - origin) / safe
    near = jnp.max(jnp.minimum(t1, t2))
    return near, (near <= jnp.min(jnp.maximum(t1, t2))) & (near > 0)


def _yaw_matrix(yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]),
                      jnp.stack([zero, zero, one])])


def _image_radius(cam: PinholeRadtan):
    """The largest normalised (undistorted) radius the image shows: its corners'."""
    w, h = cam.resolution
    corners = jnp.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]],
                        dtype=jnp.result_type(cam.fx))
    return jnp.max(jnp.linalg.norm(pixels_to_normalized(corners, cam), axis=-1))


def _seen_box(centre_C, R_CT, half, cam: PinholeRadtan):
    """The image box ``(lo, hi)`` (2,) each, pixel-edge coordinates, of a box with centre
    ``centre_C`` (camera frame), box-to-camera rotation ``R_CT`` and half sizes ``half``: the
    bounding box of its projected corners (lens distortion included), cut by the image's
    border as a detector's box is. Corners beyond the image's largest radius are drawn in to
    it first: a polynomial lens model folds points far outside its field of view back in."""
    corners = centre_C + (_CORNERS * half) @ R_CT.T
    xy = corners[:, :2] / jnp.maximum(corners[:, 2:], 1e-3)
    radius = jnp.linalg.norm(xy, axis=-1, keepdims=True)
    limit = 1.05 * _image_radius(cam)
    xy = xy * jnp.minimum(1.0, limit / jnp.maximum(radius, 1e-12))
    uv = project_normalized(xy, cam) + 0.5  # pixel centres -> edges
    size = jnp.asarray(cam.resolution, uv.dtype)
    lo = jnp.clip(uv.min(axis=0), 0.0, size)
    return lo, jnp.clip(uv.max(axis=0), lo, size)


def _unit_z_rays(uv_edges, cam: PinholeRadtan):
    """Pixel-edge coordinates (..., 2) -> undistorted rays (..., 3) with unit z."""
    xy = pixels_to_normalized(uv_edges - 0.5, cam)
    return jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1)


def _seen_front(centre_C, R_CT, half, cam: PinholeRadtan, config: LocateConfig):
    """Where :func:`locate_box` puts a box with centre ``centre_C`` (3,) (camera frame), box-to-
    camera rotation ``R_CT`` and half sizes ``half``: its image box (:func:`_seen_box`) is
    sampled as :func:`box_depth` samples it, each sample's depth is where its ray enters the
    box (a miss is a hole), and the robust depth of those is taken along the ray through the
    image box's centre."""
    lo, hi = _seen_box(centre_C, R_CT, half, cam)
    mid, reach = 0.5 * (lo + hi), 0.5 * config.shrink * (hi - lo)
    s = min(config.samples, _MODEL_SAMPLES)
    offsets = (jnp.arange(s, dtype=lo.dtype) + 0.5) / s * 2.0 - 1.0
    gx, gy = jnp.meshgrid(mid[0] + offsets * reach[0], mid[1] + offsets * reach[1])
    rays = _unit_z_rays(jnp.stack([gx.ravel(), gy.ravel()], axis=-1), cam)
    origin = -R_CT.T @ centre_C
    t, hit = jax.vmap(lambda r: _slab_entry(origin, R_CT.T @ r, half))(rays)
    depth = robust_depth(jnp.where(hit, t, jnp.nan), config).depth  # rays have unit z
    return depth * _unit_z_rays(mid, cam)


def _fit_centre(front_C, R_CT, half, cam: PinholeRadtan, config: LocateConfig):
    """The box centre (camera frame) whose :func:`_seen_front` is ``front_C``: a fixed point,
    started from the front point moved along its ray to where the ray would leave the box's
    far side half-way (the centre of a box that ray passes through the middle of)."""
    ray = front_C / jnp.linalg.norm(front_C)
    start = front_C + jnp.min(half / jnp.maximum(jnp.abs(R_CT.T @ ray), 1e-9)) * ray

    def step(_, centre):
        seen = _seen_front(centre, R_CT, half, cam, config)
        return centre + jnp.where(jnp.all(jnp.isfinite(seen)), front_C - seen, 0.0)

    centre = jax.lax.fori_loop(0, _CENTRE_STEPS, step, start)
    # a fit that did not settle (a view the fixed point cannot follow) keeps the start
    miss = jnp.linalg.norm(_seen_front(centre, R_CT, half, cam, config) - front_C)
    return jnp.where(miss <= _CENTRE_TOLERANCE * jnp.linalg.norm(front_C), centre, start)


@functools.partial(jax.jit, static_argnames="config")
def box_centre_candidates(front: jax.Array, T_WC: jax.Array, half_size: jax.Array,
                          box: jax.Array, cam: PinholeRadtan,
                          config: LocateConfig = LocateConfig()
                          ) -> tuple[jax.Array, jax.Array]:
    """The box centre for each of :data:`CANDIDATE_HEADINGS`, and how well each explains the
    detected box's shape.

    :func:`locate_box` (with no extent) returns where the ray through the centre of the box's
    image enters the target; for a box seen from above and aside that ray misses the box's
    centre by up to half a metre. For a heading, the centre is the one whose image would give
    that same front point (a fixed point of "render the box's image box, sample its depth as
    :func:`box_depth` does, cast its centre ray"), exact for a box-shaped target.

    Args:
        front: (3,) world front-surface point, metres.
        T_WC: (4, 4) camera-to-world pose it was seen from.
        half_size: (3,) half sizes, metres: along the heading, across it, up (world z).
        box: (4,) the detected box ``(x1, y1, x2, y2)``, pixel-edge coordinates (the module
            docstring).
        cam: the camera model (its lens distortion and image size: a model box beyond the
            image is cut by its border as the detector's is, so a target cut by the border is
            located too).
        config: the :class:`LocateConfig` ``front`` was located with.

    Returns:
        ``(centres, mismatch)``: (H, 3) world centres, metres, and (H,) the squared distance of
        each centre's image box corners from the detected ones, over the detected box's
        squared diagonal (0: the box's shape fits exactly).

    The model box is the bounding box of the projected corners and is sampled on a coarser
    grid than :func:`box_depth`'s; both are exact for a box seen near the image's centre and
    approximate where the lens distortion bends its edges.
    """
    R_WC, p_WC = T_WC[:3, :3], T_WC[:3, 3]
    front_C = R_WC.T @ (front - p_WC)
    half = jnp.asarray(half_size, front_C.dtype)
    headings = jnp.asarray(CANDIDATE_HEADINGS, front_C.dtype)
    rotations = jax.vmap(lambda h: R_WC.T @ _yaw_matrix(h))(headings)
    centres = jax.vmap(lambda R: _fit_centre(front_C, R, half, cam, config))(rotations)
    lo, hi = jax.vmap(lambda c, R: _seen_box(c, R, half, cam))(centres, rotations)
    size = jnp.tile(jnp.asarray(cam.resolution, front_C.dtype), 2)
    box = jnp.clip(jnp.asarray(box, front_C.dtype), 0.0, size)  # cut as the model's is
    diagonal = jnp.sum((box[2:] - box[:2]) ** 2)
    mismatch = jnp.sum((lo - box[:2]) ** 2 + (hi - box[2:]) ** 2, axis=-1) / diagonal
    return centres @ R_WC.T + p_WC, mismatch


@functools.partial(jax.jit, static_argnames="config")
def box_centre(front: jax.Array, T_WC: jax.Array, half_size: jax.Array, yaw: jax.Array,
               box: jax.Array, cam: PinholeRadtan,
               config: LocateConfig = LocateConfig()) -> jax.Array:
    """The centre (3,) world metres of an upright box seen with heading ``yaw`` () radians, or,
    with ``yaw`` NaN, of the candidate heading that best fits the box's shape (arguments as
    :func:`box_centre_candidates`)."""
    centres, mismatch = box_centre_candidates(front, T_WC, half_size, box, cam, config)
    R_WC, p_WC = T_WC[:3, :3], T_WC[:3, 3]
    front_C = R_WC.T @ (front - p_WC)
    known = jnp.isfinite(yaw)
    rotation = R_WC.T @ _yaw_matrix(jnp.where(known, yaw, 0.0).astype(front_C.dtype))
    centre = R_WC @ _fit_centre(front_C, rotation, jnp.asarray(half_size, front_C.dtype),
                                cam, config) + p_WC
    return jnp.where(known, centre, centres[jnp.argmin(mismatch)])


def border_covariance(box, resolution, R_WC, half_size, margin: float = 1.0) -> np.ndarray:
    """(3, 3) m^2: what a box cut by the image's border hides of where the target's centre is.

    A box model fitted to a cut box (:func:`box_centre_candidates`) could be moved along the
    cut image axis by up to the target's largest half size without changing what the image
    shows; that variance is added along the camera's axis (world frame) for each image axis
    the box is cut on.

    Args:
        box: (4,) the box, pixel edges; resolution: ``(width, height)``.
        R_WC: (3, 3) camera-to-world rotation.
        half_size: (3,) the target's half sizes, metres.
        margin: pixels from the border within which a box edge counts as cut.
    """
    x1, y1, x2, y2 = (float(v) for v in box)
    w, h = resolution
    R_WC = np.asarray(R_WC, np.float64)
    variance = float(np.max(half_size)) ** 2
    cov = np.zeros((3, 3))
    cut = (x1 <= margin or x2 >= w - margin, y1 <= margin or y2 >= h - margin)
    for axis in (0, 1):
        if cut[axis]:
            cov += variance * np.outer(R_WC[:, axis], R_WC[:, axis])
    return cov
