"""A box-shaped target's centre from the front surface :func:`~uavcal_jax.track.locate.locate_box`
found: the view-dependent half of RPEOD's "locate the target in 3D".

Depth sees a target's front surface, and the offset to its centre changes with the view (a car
seen from the side is 0.9 m deep, seen end-on from a low drone 2 m); the ray through the image
box's centre also misses the box's centre by up to half a metre. For each candidate heading
the centre is the one whose image would give the measured front point (the box projected
through the lens, cut by the image's border as a detector's box is, sampled and reduced as
:func:`~uavcal_jax.track.locate.box_depth` does), with a score of how well the box's shape fits
the detection; :mod:`uavcal_jax.track.heading` picks among the headings over time.

Frames as in :mod:`uavcal_jax.track.locate`; boxes in pixel-edge coordinates. Jitted JAX,
fixed-shape, vmap-able over boxes.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.geometry.camera import PinholeRadtan, pixels_to_normalized, project_normalized
from uavcal_jax.track.locate import LocateConfig, robust_depth

__all__ = ["CANDIDATE_HEADINGS", "DEFAULT_LOCATE", "border_covariance", "box_centre_candidates"]


#: The headings :func:`box_centre_candidates` tries, radians: a box is symmetric, so
#: ``[0, pi)`` in 16 steps of 11.25 degrees.
CANDIDATE_HEADINGS = np.arange(16) * (np.pi / 16)
#: Fixed-point steps of :func:`_fit_centre` (each moves the centre by the residual; 3 reach a
#: millimetre on a car 5-10 m away).
_CENTRE_STEPS = 6
#: At most this many samples a side model :func:`box_depth`'s grid (a box's faces are planes,
#: so a coarse grid gives their robust depth as the fine one does, at a tenth of the cost).
_MODEL_SAMPLES = 8
#: The largest relative miss (of the front point's range) of a settled :func:`_fit_centre` fit.
_CENTRE_TOLERANCE = 0.01
#: How far past the image's largest normalised radius a box corner may lie before it is drawn
#: in (:func:`_seen_box`).
_RADIUS_MARGIN = 1.05
#: :class:`LocateConfig`'s defaults.
DEFAULT_LOCATE = LocateConfig()
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


def _seen_box(centre_C, R_CT, half, cam: PinholeRadtan, limit):
    """The image box ``(lo, hi)`` (2,) each, pixel-edge coordinates, of a box with centre
    ``centre_C`` (camera frame), box-to-camera rotation ``R_CT`` and half sizes ``half``: the
    bounding box of its projected corners (lens distortion included), cut by the image's
    border as a detector's box is. Corners beyond ``limit`` (a normalised radius a little past
    the image's, :func:`_image_radius`) are drawn in to it first: a polynomial lens model folds
    points far outside its field of view back in."""
    corners = centre_C + (_CORNERS * half) @ R_CT.T
    xy = corners[:, :2] / jnp.maximum(corners[:, 2:], 1e-3)
    radius = jnp.linalg.norm(xy, axis=-1, keepdims=True)
    xy = xy * jnp.minimum(1.0, limit / jnp.maximum(radius, 1e-12))
    uv = project_normalized(xy, cam) + 0.5  # pixel centres -> edges
    size = jnp.asarray(cam.resolution, uv.dtype)
    lo = jnp.clip(uv.min(axis=0), 0.0, size)
    return lo, jnp.clip(uv.max(axis=0), lo, size)


def _unit_z_rays(uv_edges, cam: PinholeRadtan):
    """Pixel-edge coordinates (..., 2) -> undistorted rays (..., 3) with unit z."""
    xy = pixels_to_normalized(uv_edges - 0.5, cam)
    return jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1)


def _seen_front(centre_C, R_CT, half, cam: PinholeRadtan, limit, config: LocateConfig):
    """Where :func:`locate_box` puts a box with centre ``centre_C`` (3,) (camera frame), box-to-
    camera rotation ``R_CT`` and half sizes ``half``: its image box (:func:`_seen_box`) is
    sampled as :func:`box_depth` samples it, each sample's depth is where its ray enters the
    box (a miss is a hole), and the robust depth of those is taken along the ray through the
    image box's centre."""
    lo, hi = _seen_box(centre_C, R_CT, half, cam, limit)
    mid, reach = 0.5 * (lo + hi), 0.5 * config.shrink * (hi - lo)
    s = min(config.samples, _MODEL_SAMPLES)
    offsets = (jnp.arange(s, dtype=lo.dtype) + 0.5) / s * 2.0 - 1.0
    gx, gy = jnp.meshgrid(mid[0] + offsets * reach[0], mid[1] + offsets * reach[1])
    rays = _unit_z_rays(jnp.stack([gx.ravel(), gy.ravel()], axis=-1), cam)
    origin = -R_CT.T @ centre_C
    t, hit = jax.vmap(lambda r: _slab_entry(origin, R_CT.T @ r, half))(rays)
    depth = robust_depth(jnp.where(hit, t, jnp.nan), config).depth  # rays have unit z
    return depth * _unit_z_rays(mid, cam)


def _fit_centre(front_C, R_CT, half, cam: PinholeRadtan, limit, config: LocateConfig):
    """The box centre (camera frame) whose :func:`_seen_front` is ``front_C``: a fixed point,
    started from the front point moved along its ray to where the ray would leave the box's
    far side half-way (the centre of a box that ray passes through the middle of)."""
    ray = front_C / jnp.linalg.norm(front_C)
    start = front_C + jnp.min(half / jnp.maximum(jnp.abs(R_CT.T @ ray), 1e-9)) * ray

    def step(_, centre):
        seen = _seen_front(centre, R_CT, half, cam, limit, config)
        return centre + jnp.where(jnp.all(jnp.isfinite(seen)), front_C - seen, 0.0)

    centre = jax.lax.fori_loop(0, _CENTRE_STEPS, step, start)
    # a fit that did not settle (a view the fixed point cannot follow) keeps the start
    miss = jnp.linalg.norm(_seen_front(centre, R_CT, half, cam, limit, config) - front_C)
    return jnp.where(miss <= _CENTRE_TOLERANCE * jnp.linalg.norm(front_C), centre, start)


@functools.partial(jax.jit, static_argnames="config")
def box_centre_candidates(front: jax.Array, T_WC: jax.Array, half_size: jax.Array,
                          box: jax.Array, cam: PinholeRadtan,
                          config: LocateConfig = DEFAULT_LOCATE
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
    limit = _RADIUS_MARGIN * _image_radius(cam)
    centres = jax.vmap(lambda R: _fit_centre(front_C, R, half, cam, limit, config))(rotations)
    lo, hi = jax.vmap(lambda c, R: _seen_box(c, R, half, cam, limit))(centres, rotations)
    size = jnp.tile(jnp.asarray(cam.resolution, front_C.dtype), 2)
    box = jnp.clip(jnp.asarray(box, front_C.dtype), 0.0, size)  # cut as the model's is
    diagonal = jnp.sum((box[2:] - box[:2]) ** 2)
    mismatch = jnp.sum((lo - box[:2]) ** 2 + (hi - box[2:]) ** 2, axis=-1) / diagonal
    return centres @ R_WC.T + p_WC, mismatch


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
