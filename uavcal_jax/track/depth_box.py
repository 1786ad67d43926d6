"""A detector's box redrawn around the target the depth image sees inside it.

A small detector's box is loose on a target it sees badly (a black car in a bright room, a
white one burnt out by the auto-exposure: boxes 10-25 px off to one side and a quarter too
tall), and the box model (:mod:`uavcal_jax.track.box_model`) turns every pixel of that error
into a wrong heading and a centre metres off. The depth image knows better where the target
ends: it stands out from what lies behind it by depth, and from the ground it stands on by
height. So the box is grown by ``grow`` on each side and sampled on a fixed
``samples x samples`` grid (nearest pixel); a sample is the target's when

* its depth lies within ``[z - near, z + far]`` of the target's front-surface depth ``z``
  (:func:`~uavcal_jax.track.locate.box_depth` of the detector's box: the background further
  back and the specks in front drop out), and
* its world point lies more than ``clearance`` above the ground under it: a plane through
  the lower envelope of the grid's valid points (least squares on the points within
  ``ground_band`` of the ``ground_quantile`` of their heights, then again on those at most
  ``ground_tolerance`` above the plane, ``ground_fits`` times; then lowered by the
  ``ground_quantile`` of the heights' residuals about it). A plane, not one height: the
  pose's world may be tilted (a VIO's gravity is off by a degree or two until its
  accelerometer bias is known: the demo's 0.22 m/s^2 offset tilted it 1.3-1.6 degrees), and
  then the floor 6 m behind a car rises 0.2 m, stands, and the box grows over it. A plane
  steeper than ``max_ground_slope``, or fit to too few points, gives way to the one height
  (a target that fills the grown box gives its own lowest points, cut by at most
  ``clearance``).

Of those samples the 4-connected region holding most of the detector's box's central half is
the target (a second car at the same depth beside it is another region). Where the target's
size is known (``radius``, its horizontal half-diagonal: a car's 2.3 m), the depth band
gives way to that bound: a sample is the target's when it stands within ``radius`` of the
middle of the region's horizontal extent, pass after pass (``radius_passes``), so a car seen
end-on keeps the far end of its roof, 4 m deeper than its back, and a wall behind it drops
out. The region's extent, widened by half a grid step and by the ``clearance`` it lost at the
foot, is the new box. Too small a region (under ``min_share`` of the detector's box) keeps the
detector's box.

Measured with the shipped detector on the demo's recording (``uavcal run --sequence R``, and
``--set refine.enabled=false`` for the boxes as they come): its car boxes against the
renderer's, median IoU 0.61 -> 0.95 (they were 13 px to the right and 28 % too tall); the
car's filtered median error 0.80 -> 0.50 m. Over the 15 flights of
``experiments/run_flights.py`` (docs/results.md) the median error falls on 13. The
renderer's own boxes, redrawn, keep a median IoU of 0.94 with themselves, yet their car's
error goes 0.28 -> 0.40 m on the demo (the box model's heading moves with a few pixels of the
box's shape): a detector as good as the renderer's labels would want it off.

Frames as in :mod:`uavcal_jax.track.locate` (``T_WC`` camera to world, world z up); boxes in
pixel-edge coordinates. NumPy and OpenCV's connected components around one jitted
unprojection of a fixed-shape grid (compiled once per camera).
"""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.geometry.camera import PinholeRadtan, pixels_to_normalized

__all__ = ["DepthBoxConfig", "refine_box"]


@dataclasses.dataclass(frozen=True)
class DepthBoxConfig:
    """Settings of :func:`refine_box` (module docstring).

    Attributes:
        enabled: redraw the boxes (``False``: the detector's boxes as they are).
        grow: the box is grown by this fraction of its width and height on each side.
        samples: the grid's samples a side.
        near, far: metres before and beyond the front-surface depth that are the target's
            in the first pass (a car seen end-on is 4.7 m deep; the radius passes reach its
            far end where ``far`` would take in the wall behind it too).
        clearance: metres above the ground a sample must be to be the target's.
        ground_quantile: the quantile of the valid samples' heights where the ground's fit
            starts (and the ground's height where no plane fits).
        ground_band, ground_tolerance: metres above that height, then above the plane, of
            the samples each fit takes.
        ground_fits: the plane's fits.
        max_ground_slope: the steepest plane taken for the ground (rise over run).
        min_share: the least size of the target's region, as a share of the samples of the
            detector's box.
        radius_margin: metres added to the target's radius.
        radius_passes: passes of the radius bound after the depth band's.
    """

    enabled: bool = True
    grow: float = 0.25
    samples: int = 64
    near: float = 0.3
    far: float = 2.5
    clearance: float = 0.1
    ground_quantile: float = 0.05
    ground_band: float = 0.5
    ground_tolerance: float = 0.05
    ground_fits: int = 4
    max_ground_slope: float = 0.1
    min_share: float = 0.25
    radius_margin: float = 0.3
    radius_passes: int = 3

    def __post_init__(self):
        if self.grow < 0.0:
            raise ValueError(f"grow must be >= 0, got {self.grow}")
        if self.samples < 4:
            raise ValueError(f"samples must be >= 4, got {self.samples}")
        if self.near < 0.0 or self.far <= 0.0 or self.clearance < 0.0:
            raise ValueError("need near >= 0, far > 0 and clearance >= 0")
        if not 0.0 <= self.ground_quantile <= 1.0 or not 0.0 < self.min_share <= 1.0:
            raise ValueError("need ground_quantile in [0, 1] and min_share in (0, 1]")
        if min(self.ground_band, self.ground_tolerance, self.max_ground_slope) < 0.0 \
                or self.ground_fits < 1:
            raise ValueError("need ground_band, ground_tolerance, max_ground_slope >= 0 and "
                             "ground_fits >= 1")


@jax.jit
def _rays(uv: jax.Array, cam: PinholeRadtan) -> jax.Array:
    """(N, 3) camera-frame rays ``(x, y, 1)`` of pixel centres ``uv`` (N, 2)."""
    xy = pixels_to_normalized(uv, cam)
    return jnp.concatenate([xy, jnp.ones_like(xy[:, :1])], axis=1)


def _grid(box: np.ndarray, grow: float, n: int, size: tuple[int, int]):
    """The grown box's sample columns and rows (edge coordinates of the sample centres, (n,)
    each) and its step (2,), pixels."""
    width, height = size
    lo = box[:2] - grow * (box[2:] - box[:2])
    hi = box[2:] + grow * (box[2:] - box[:2])
    lo, hi = np.maximum(lo, 0.0), np.minimum(hi, [width, height])
    step = (hi - lo) / n
    offsets = np.arange(n) + 0.5
    return lo[0] + offsets * step[0], lo[1] + offsets * step[1], step


def _ground(points: np.ndarray, valid: np.ndarray, config: DepthBoxConfig) -> np.ndarray:
    """(n, n) the ground's height under each sample of ``points`` (n, n, 3) world metres (the
    module docstring; NaN where not ``valid`` (n, n))."""
    z, xy = points[..., 2][valid], points[..., :2][valid]
    level = float(np.quantile(z, config.ground_quantile))
    flat = np.where(valid, level, np.nan)
    centre = xy.mean(axis=0)
    design = np.column_stack([np.ones(len(z)), xy - centre])
    keep = z <= level + config.ground_band
    for _ in range(config.ground_fits):
        if keep.sum() < 16:
            return flat
        coef = np.linalg.lstsq(design[keep], z[keep], rcond=None)[0]
        if np.hypot(coef[1], coef[2]) > config.max_ground_slope:
            return flat
        keep = z - design @ coef <= config.ground_tolerance
    # the fit's slope, at the height of the lower envelope (the same quantile as the level's:
    # a least-squares plane lies in the middle of the floor's noise, and the clearance
    # counts from its bottom)
    offset = coef[0] + np.quantile(z - design @ coef, config.ground_quantile)
    plane = offset + (points[..., :2] - centre) @ coef[1:]
    return np.where(valid, plane, np.nan)


def _region(mask: np.ndarray, core: np.ndarray) -> np.ndarray | None:
    """The 4-connected region of ``mask`` (n, n) bool holding most of ``core``; ``None``:
    none holds any."""
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)
    votes = np.bincount(labels[core & mask], minlength=count)
    votes[0] = 0
    return None if votes.max(initial=0) == 0 else labels == int(np.argmax(votes))


def refine_box(box, depth_image: np.ndarray, front_depth: float, cam: PinholeRadtan,
               T_WC: np.ndarray, config: DepthBoxConfig = DepthBoxConfig(),
               radius: float | None = None) -> np.ndarray:
    """The box (4,) redrawn around the target the depth image shows in ``box`` (4,).

    Args:
        box: ``(x1, y1, x2, y2)`` pixels, edge coordinates.
        depth_image: (H, W) z-depth, metres (0 or NaN: no depth).
        front_depth: the target's front-surface z-depth, metres
            (:func:`~uavcal_jax.track.locate.box_depth` of ``box``); NaN: ``box`` unchanged.
        cam: the camera model; T_WC: (4, 4) camera to world (world z up).
        config: :class:`DepthBoxConfig`.
        radius: the target's largest horizontal half-extent, metres (a car's half diagonal);
            ``None``: unknown, the depth band alone bounds it.

    Returns:
        (4,) float64 the new box, or ``box`` itself where the depth says too little.
    """
    box = np.asarray(box, np.float64)
    if not np.isfinite(front_depth) or box[2] <= box[0] or box[3] <= box[1]:
        return box
    height, width = depth_image.shape
    n = config.samples
    cols, rows, step = _grid(box, config.grow, n, (width, height))
    if np.any(step <= 0.0):
        return box
    cc, rr = np.meshgrid(np.floor(cols).astype(int), np.floor(rows).astype(int))
    # sampled first, then widened (not the whole image)
    depth = np.asarray(depth_image)[np.clip(rr, 0, height - 1),
                                    np.clip(cc, 0, width - 1)].astype(np.float64)
    valid = np.isfinite(depth) & (depth > 0.0)
    if valid.sum() < 4:
        return box
    uv = np.stack(np.meshgrid(cols - 0.5, rows - 0.5), axis=-1).reshape(-1, 2)  # pixel centres
    rays = np.asarray(_rays(jnp.asarray(uv, jnp.float32), cam), np.float64).reshape(n, n, 3)
    T_WC = np.asarray(T_WC, np.float64)
    points = np.where(valid[..., None], depth[..., None] * rays @ T_WC[:3, :3].T + T_WC[:3, 3],
                      np.nan)  # (n, n, 3) world
    with np.errstate(invalid="ignore"):  # NaN heights (no depth) do not stand
        standing = valid & (depth >= front_depth - config.near) \
            & (points[..., 2] > _ground(points, valid, config) + config.clearance)
    inside = ((cc + 0.5 >= box[0]) & (cc + 0.5 <= box[2]) & (rr + 0.5 >= box[1])
              & (rr + 0.5 <= box[3]))
    core = (np.abs(cols[None, :] - 0.5 * (box[0] + box[2])) <= 0.25 * (box[2] - box[0])) \
        & (np.abs(rows[:, None] - 0.5 * (box[1] + box[3])) <= 0.25 * (box[3] - box[1]))
    region = _region(standing & (depth <= front_depth + config.far), core)
    for _ in range(config.radius_passes if radius is not None else 0):
        if region is None:
            break
        # the target is bounded: what stands within its radius of the middle of the region's
        # extent (which moves out to a long target's far end in a pass or two; the median
        # would stay on the face that fills the image)
        middle = np.mean(np.quantile(points[region][:, :2], [0.02, 0.98], axis=0), axis=0)
        near_middle = np.linalg.norm(np.nan_to_num(points[..., :2] - middle, nan=np.inf),
                                     axis=-1) <= radius + config.radius_margin
        region = _region(standing & near_middle, core)
    if region is None or region.sum() < config.min_share * max(int(inside.sum()), 1):
        return box
    ys, xs = np.nonzero(region)
    x1, x2 = cols[xs.min()] - 0.5 * step[0], cols[xs.max()] + 0.5 * step[0]
    y1, y2 = rows[ys.min()] - 0.5 * step[1], rows[ys.max()] + 0.5 * step[1]
    # the foot lost to the clearance: its height seen at the target's depth
    y2 = min(y2 + float(cam.fy) * config.clearance / front_depth, float(height))
    return np.array([x1, y1, x2, y2])
