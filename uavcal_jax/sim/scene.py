"""The simulator's world: a textured hall, static obstacles and (moving) target objects.

Geometry. Every solid is a box that may be rotated about the world z axis only (a *yaw box*:
centre, yaw, half extents). Box 0 is the hall itself (seen from inside: walls, floor, ceiling),
boxes ``1..n_obstacles`` are static obstacles (pillars from floor to ceiling and crates on the
floor), and the targets follow. The hall contains the trajectory's bounds ``[lo, hi]`` plus a
margin; obstacles and targets keep a clearance from the flight path (sampled path points, or
the whole bounds box when none are given), so the camera never enters a solid.

Targets. ``CLASS_NAMES[c]`` is target class ``c`` ("car": a low wide box, "person": a tall
narrow one). A target is static or moves on a closed ellipse on the floor at constant angular
rate, facing along its velocity; its pose is a pure function of the scene and the time
(:func:`target_poses`). Scene time ``t`` is seconds since the start of the flight (keep it
small: the renderer works in float32, so absolute EuRoC timestamps would lose all precision).

Appearance. Every face of every box has its own luminance texture (multi-octave value noise,
blobs, checker and stripe patches, posters; a physical texel size of ~2 cm, so corners are
trackable at any distance and views are not self-similar), stored in one flat atlas and mixed
between two colours per face (``colour = A + (B - A) * texture``). Target classes have their
own palettes and patterns (car: body colour, dark window band and wheels; person: shirt over
trousers, skin-coloured head). Everything is deterministic for a seed.

The :class:`Scene` is a pytree of arrays (class names are static metadata), so it can be passed
into jitted functions; scenes with different numbers of boxes or texels are different shapes.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "CLASS_NAMES",
    "Scene",
    "SceneConfig",
    "Targets",
    "box_arrays",
    "make_scene",
    "target_class_names",
    "texture_luminance",
    "target_poses",
    "target_states",
]

CLASS_NAMES: tuple[str, ...] = ("car", "person")
#: Fine detail texture: DETAIL_SIZE x DETAIL_SIZE texels (a power of two), tiled at
#: DETAIL_TEXEL metres per texel on every face.
DETAIL_SIZE = 512
DETAIL_TEXEL = 0.004
CAR, PERSON = 0, 1


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """How a scene is built.

    Attributes:
        margin_xy: hall walls this far beyond the bounds in x and y, metres.
        margin_below: floor this far below the lowest bound, metres.
        margin_above: ceiling this far above the highest bound, metres.
        min_size: smallest hall (x, y, z) extent, metres.
        n_obstacles: obstacles to place (fewer when the hall has no room for them).
        pillar_fraction: share of obstacles that are floor-to-ceiling pillars.
        clearance: minimum distance from the flight path to any obstacle or target, metres.
        n_targets: targets to place, alternating classes starting with ``target_classes[0]``.
        target_classes: class ids cycled through when placing targets.
        moving_fraction: share of targets that move (first ones move).
        target_distance: (min, max) horizontal distance from a path point at which targets
            are placed (beyond the clearance), so the cameras see them.
        texel: texture resolution of the hall and obstacles, metres per texel.
        target_texel: texture resolution of targets, metres per texel.
        max_texels: atlas budget; the hall's texel grows when it would be exceeded.
        ambient: light that every face gets; the rest comes from two directional lights.
    """

    margin_xy: float = 4.0
    margin_below: float = 1.0
    margin_above: float = 1.5
    min_size: tuple[float, float, float] = (6.0, 6.0, 3.0)
    n_obstacles: int = 8
    pillar_fraction: float = 0.4
    clearance: float = 0.8
    n_targets: int = 4
    target_classes: tuple[int, ...] = (CAR, PERSON)
    moving_fraction: float = 0.5
    target_distance: tuple[float, float] = (1.0, 5.0)
    texel: float = 0.02
    target_texel: float = 0.01
    max_texels: int = 8_000_000
    ambient: float = 0.55


@dataclasses.dataclass(frozen=True)
class Targets:
    """Target objects (``n`` of them); all arrays have leading dimension ``n``.

    Attributes:
        class_id: (n,) int32 index into :data:`CLASS_NAMES`.
        half_extents: (n, 3) half length (local x, forward), half width, half height, metres.
        center: (n, 2) world xy of the ellipse centre (the position of a static target).
        radii: (n, 2) ellipse semi-axes, metres (zero for a static target).
        path_yaw: (n,) orientation of the ellipse's first axis, radians.
        omega: (n,) angular rate along the ellipse, rad/s (zero: static).
        phase: (n,) ellipse parameter at ``t = 0``, radians.
        yaw: (n,) heading of a static target, radians.
        z: (n,) world z of the box centre (floor + half height).
    """

    class_id: Any
    half_extents: Any
    center: Any
    radii: Any
    path_yaw: Any
    omega: Any
    phase: Any
    yaw: Any
    z: Any

    @property
    def n(self) -> int:
        return int(self.class_id.shape[0])


jax.tree_util.register_dataclass(
    Targets,
    data_fields=[f.name for f in dataclasses.fields(Targets)],
    meta_fields=[],
)


@dataclasses.dataclass(frozen=True)
class Scene:
    """A renderable world (see the module docstring).

    Attributes:
        box_center: (S, 3) static box centres; box 0 is the hall, 1.. obstacles.
        box_yaw: (S,) rotation about world z, radians.
        box_half: (S, 3) half extents, metres.
        targets: the targets (their boxes follow the static ones, index ``S + k``).
        texture: (N,) uint32 luminance atlas, 8 bits per texel, each entry packing the 2x2
            neighbourhood of one texel (bytes: itself, right, below, below-right) so that a
            bilinear lookup is one gather; see :func:`texture_luminance`.
        face_tex: (F, 6) float32 per face ``offset, n_u, n_v, 1/texel, half_u, half_v`` with
            ``F = 6 (S + n_targets)`` and face ``6 k + 2 axis + (1 if the + side)``.
        face_color: (F, 2, 3) float32 RGB colours A (texture 0) and B (texture 1).
        detail: (DETAIL_SIZE ** 2,) uint32 packed quads (as ``texture``) of a fine tiled
            detail texture (``DETAIL_TEXEL`` metres per texel) that the renderer blends in
            near the camera, where the atlas would be magnified into blur.
        lights: (2, 3) unit directions towards two directional lights (world).
        light_weight: (3,) ambient, light 0, light 1 intensities.
        class_names: target class names (static metadata).
    """

    box_center: Any
    box_yaw: Any
    box_half: Any
    targets: Targets
    texture: Any
    face_tex: Any
    face_color: Any
    detail: Any
    lights: Any
    light_weight: Any
    class_names: tuple[str, ...] = CLASS_NAMES

    @property
    def n_static(self) -> int:
        return int(self.box_center.shape[0])

    @property
    def n_obstacles(self) -> int:
        return self.n_static - 1

    @property
    def n_targets(self) -> int:
        return self.targets.n

    @property
    def room_lo(self) -> np.ndarray:
        return np.asarray(self.box_center[0]) - np.asarray(self.box_half[0])

    @property
    def room_hi(self) -> np.ndarray:
        return np.asarray(self.box_center[0]) + np.asarray(self.box_half[0])


jax.tree_util.register_dataclass(
    Scene,
    data_fields=[
        "box_center",
        "box_yaw",
        "box_half",
        "targets",
        "texture",
        "face_tex",
        "face_color",
        "detail",
        "lights",
        "light_weight",
    ],
    meta_fields=["class_names"],
)


def target_class_names(scene: Scene) -> tuple[str, ...]:
    """Class names, index = ``class_id``."""
    return tuple(scene.class_names)


# --- poses at time t -------------------------------------------------------------------------


def target_states(scene: Scene, t) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Target centres (n, 3), yaws (n,) and velocities (n, 3) at scene time ``t`` (seconds)."""
    tg = scene.targets
    t = jnp.asarray(t, dtype=jnp.result_type(tg.omega))
    ang = tg.omega * t + tg.phase
    ca, sa = jnp.cos(ang), jnp.sin(ang)
    cp, sp = jnp.cos(tg.path_yaw), jnp.sin(tg.path_yaw)
    ex, ey = tg.radii[:, 0] * ca, tg.radii[:, 1] * sa
    vx, vy = -tg.radii[:, 0] * sa * tg.omega, tg.radii[:, 1] * ca * tg.omega
    px = tg.center[:, 0] + cp * ex - sp * ey
    py = tg.center[:, 1] + sp * ex + cp * ey
    wx, wy = cp * vx - sp * vy, sp * vx + cp * vy
    moving = (tg.omega != 0) & (jnp.abs(wx) + jnp.abs(wy) > 0)
    yaw = jnp.where(moving, jnp.arctan2(wy, jnp.where(moving, wx, 1.0)), tg.yaw)
    pos = jnp.stack([px, py, tg.z], axis=-1)
    vel = jnp.stack([wx, wy, jnp.zeros_like(wx)], axis=-1)
    return pos, yaw, vel


def target_poses(scene: Scene, t) -> jax.Array:
    """(n, 4, 4) target-to-world transforms ``T_WT`` at scene time ``t`` (seconds since the
    flight's start). The target frame is the box centre, x forward, z up."""
    pos, yaw, _ = target_states(scene, t)
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    R = jnp.stack(
        [jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2
    )
    top = jnp.concatenate([R, pos[:, :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], dtype=R.dtype), (c.shape[0], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def box_arrays(scene: Scene, t) -> tuple[jax.Array, jax.Array, jax.Array]:
    """All boxes at time ``t``: centres (K, 3), yaws (K,), half extents (K, 3);
    ``K = n_static + n_targets``."""
    pos, yaw, _ = target_states(scene, t)
    center = jnp.concatenate([scene.box_center, pos.astype(scene.box_center.dtype)], axis=0)
    yaws = jnp.concatenate([scene.box_yaw, yaw.astype(scene.box_yaw.dtype)], axis=0)
    half = jnp.concatenate([scene.box_half, scene.targets.half_extents], axis=0)
    return center, yaws, half


# --- construction (numpy side) ---------------------------------------------------------------


def _point_box_distance(points: np.ndarray, center, yaw, half) -> np.ndarray:
    """Distance from points (M, 3) to a solid yaw box (0 inside)."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = points - np.asarray(center)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)
    q = np.maximum(np.abs(local) - np.asarray(half), 0.0)
    return np.linalg.norm(q, axis=-1)


def _point_cylinder_distance(points: np.ndarray, center_xy, radius, z0, z1) -> np.ndarray:
    dxy = np.maximum(np.linalg.norm(points[:, :2] - np.asarray(center_xy), axis=-1) - radius, 0)
    dz = np.maximum(np.maximum(points[:, 2] - z1, z0 - points[:, 2]), 0.0)
    return np.hypot(dxy, dz)


def _keepout_points(lo, hi, path_points, spacing=0.25):
    """Points the solids must keep clear of: the path, or a grid filling ``[lo, hi]``."""
    if path_points is not None:
        pts = np.asarray(path_points, dtype=np.float64).reshape(-1, 3)
        return pts, 0.0
    n = np.maximum(np.ceil((hi - lo) / spacing).astype(int) + 1, 2)
    n = np.minimum(n, 60)
    axes = [np.linspace(lo[i], hi[i], n[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    step = (hi - lo) / (n - 1)
    return grid, 0.5 * float(np.linalg.norm(step))


@dataclasses.dataclass
class _Solid:
    center: np.ndarray
    yaw: float
    half: np.ndarray
    footprint: tuple[np.ndarray, float]  # xy disc covering the solid (or its sweep)


def _discs_overlap(a: tuple[np.ndarray, float], b: tuple[np.ndarray, float], gap=0.2) -> bool:
    return float(np.linalg.norm(a[0] - b[0])) < a[1] + b[1] + gap


def _place_obstacles(rng, cfg, room_lo, room_hi, keep, keep_pad) -> list[_Solid]:
    solids: list[_Solid] = []
    floor, ceil = room_lo[2], room_hi[2]
    n_pillars = int(round(cfg.n_obstacles * cfg.pillar_fraction))
    for i in range(cfg.n_obstacles):
        for _ in range(200):
            yaw = float(rng.uniform(-np.pi, np.pi))
            if i < n_pillars:
                hxy = rng.uniform(0.2, 0.5, 2)
                if rng.random() < 0.5:
                    hxy[1] = hxy[0]
                half = np.array([hxy[0], hxy[1], 0.5 * (ceil - floor)])
            else:
                half = np.array([*rng.uniform(0.25, 1.0, 2), 0.5 * rng.uniform(0.4, 2.5)])
            xy = rng.uniform(room_lo[:2] + 0.2, room_hi[:2] - 0.2)
            center = np.array([xy[0], xy[1], floor + half[2]])
            d = _point_box_distance(keep, center, yaw, half)
            if d.min() < cfg.clearance + keep_pad:
                continue
            disc = (center[:2].copy(), float(np.hypot(half[0], half[1])))
            if any(_discs_overlap(disc, s.footprint, 0.0) for s in solids):
                continue
            solids.append(_Solid(center, yaw, half, disc))
            break
    return solids


_CAR_COLOURS = np.array(
    [
        [0.75, 0.08, 0.07], [0.08, 0.2, 0.7], [0.92, 0.92, 0.9], [0.62, 0.64, 0.66],
        [0.95, 0.75, 0.05], [0.05, 0.45, 0.15], [0.85, 0.35, 0.05], [0.12, 0.12, 0.14],
    ]
)  # fmt: skip
_SHIRT_COLOURS = np.array(
    [
        [0.85, 0.15, 0.45], [0.1, 0.6, 0.85], [0.95, 0.85, 0.2], [0.2, 0.75, 0.3],
        [0.95, 0.5, 0.1], [0.55, 0.2, 0.75], [0.9, 0.9, 0.9], [0.8, 0.1, 0.1],
    ]
)  # fmt: skip


def _target_size(rng, cls: int) -> np.ndarray:
    if cls == CAR:
        return 0.5 * np.array([rng.uniform(3.6, 4.7), rng.uniform(1.6, 1.9), rng.uniform(1.3, 1.6)])
    return 0.5 * np.array([rng.uniform(0.4, 0.6), rng.uniform(0.28, 0.4), rng.uniform(1.55, 1.9)])


def _place_targets(rng, cfg, room_lo, room_hi, keep, keep_pad, obstacles,
                   anchors=None, view_yaw=None) -> list[dict]:
    targets: list[dict] = []
    if anchors is None:
        anchors = keep[:, :2]
    floor = room_lo[2]
    n_moving = int(round(cfg.n_targets * cfg.moving_fraction))
    for i in range(cfg.n_targets):
        cls = int(cfg.target_classes[i % len(cfg.target_classes)])
        half = _target_size(rng, cls)
        moving = i < n_moving
        # moving targets try shrinking ellipses, then settle for standing still
        tries = [(1.0, moving), (0.6, moving), (0.35, moving), (0.0, False)] if moving else [
            (0.0, False)
        ]
        placed = None
        speed = 0.0
        for scale, mov in tries:
            for attempt in range(150):
                if mov:
                    speed = rng.uniform(0.8, 1.5) if cls == PERSON else rng.uniform(1.0, 2.5)
                    radii = scale * rng.uniform(0.8, 2.5, 2) * (1.0 if cls == PERSON else 1.3)
                    reach = float(radii.max() + np.hypot(half[0], half[1]))
                else:
                    radii = np.zeros(2)
                    reach = float(np.hypot(half[0], half[1]))
                if attempt < 110:  # near the path, so the cameras see it
                    k = rng.integers(len(anchors))
                    anchor = anchors[k]
                    if view_yaw is None:
                        ang = rng.uniform(-np.pi, np.pi)
                    else:  # inside the horizontal field of view, so the target is seen
                        ang = view_yaw[k] + rng.uniform(-0.5, 0.5)
                    dist = reach + cfg.clearance + rng.uniform(*cfg.target_distance)
                    xy = anchor + dist * np.array([np.cos(ang), np.sin(ang)])
                else:
                    xy = rng.uniform(room_lo[:2], room_hi[:2])
                yaw = float(rng.uniform(-np.pi, np.pi))
                if mov:
                    ext = np.array([reach, reach])
                else:  # the rotated footprint's half extents in x and y
                    c, s_ = abs(np.cos(yaw)), abs(np.sin(yaw))
                    ext = np.array([c * half[0] + s_ * half[1], s_ * half[0] + c * half[1]])
                if np.any(xy - ext < room_lo[:2] + 0.1) or np.any(xy + ext > room_hi[:2] - 0.1):
                    continue
                z = floor + half[2]
                if mov:
                    d = _point_cylinder_distance(keep, xy, reach, floor, floor + 2 * half[2])
                else:
                    d = _point_box_distance(keep, np.array([xy[0], xy[1], z]), yaw, half)
                if d.min() < cfg.clearance + keep_pad:
                    continue
                disc = (xy.copy(), reach)
                if any(_discs_overlap(disc, s.footprint) for s in obstacles):
                    continue
                if any(_discs_overlap(disc, (t["center"], t["reach"])) for t in targets):
                    continue
                placed = (mov, speed if mov else 0.0, radii, reach, xy, yaw, z)
                break
            if placed is not None:
                break
        if placed is None:
            continue
        moving, speed, radii, reach, xy, yaw, z = placed
        omega = 0.0
        if moving:
            omega = float(speed / radii.mean()) * (1.0 if rng.random() < 0.5 else -1.0)
        targets.append(
            dict(
                class_id=cls, half=half, center=xy, reach=reach, radii=radii,
                path_yaw=float(rng.uniform(-np.pi, np.pi)), omega=omega,
                phase=float(rng.uniform(-np.pi, np.pi)), yaw=yaw, z=z,
            )
        )  # fmt: skip
    return targets


# --- textures --------------------------------------------------------------------------------


def _value_noise(rng, h, w, texel, periods_m, beta) -> np.ndarray:
    img = np.zeros((h, w), np.float32)
    for p_m in periods_m:
        p = max(p_m / texel, 1.5)
        gh, gw = int(np.ceil(h / p)) + 3, int(np.ceil(w / p)) + 3
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        up = cv2.resize(grid, (int(gw * p), int(gh * p)), interpolation=cv2.INTER_CUBIC)
        oy, ox = rng.integers(0, int(p) + 1, 2)
        img += np.float32(p_m**beta) * up[oy : oy + h, ox : ox + w]
    return img


def _decorate(rng, img, texel, area_density=1.0) -> None:
    """Blobs and speckles, checker and stripe patches and flat posters, drawn in place."""
    h, w = img.shape
    area = h * w * texel * texel
    std = float(img.std()) + 1e-6
    # blob radii log-uniform in [1.5 cm, 30 cm]: many small ones, a few large
    n_blobs = rng.poisson(area * 6.0 * area_density)
    radii = np.exp(rng.uniform(np.log(0.015), np.log(0.3), n_blobs)) / texel
    for r in radii:
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        axes = (max(1, int(r)), max(1, int(r * rng.uniform(0.3, 1.0))))
        val = float(rng.normal(0.0, 2.5 * std))
        cv2.ellipse(img, (int(cx), int(cy)), axes, float(rng.uniform(0, 180)), 0, 360, val, -1)
    n_patches = rng.poisson(area * 0.3 * area_density)
    for _ in range(n_patches):
        pw, ph = (rng.uniform(0.1, 0.7, 2) / texel).astype(int) + 2
        x0, y0 = int(rng.integers(0, max(1, w - 2))), int(rng.integers(0, max(1, h - 2)))
        sub = img[y0 : y0 + ph, x0 : x0 + pw]
        if sub.size == 0:
            continue
        yy, xx = np.mgrid[0 : sub.shape[0], 0 : sub.shape[1]]
        kind = rng.integers(3)
        sq = max(2.0, rng.uniform(0.02, 0.1) / texel)
        if kind == 0:  # checker
            pat = ((xx // sq + yy // sq) % 2).astype(np.float32)
        elif kind == 1:  # stripes at an angle
            ang = rng.uniform(0, np.pi)
            pat = ((np.cos(ang) * xx + np.sin(ang) * yy) // sq % 2).astype(np.float32)
        else:  # poster: flat with a frame and noise
            pat = np.full(sub.shape, rng.uniform(0, 1), np.float32)
            pat += 0.3 * rng.standard_normal(sub.shape).astype(np.float32)
            pat[: max(1, sub.shape[0] // 8)] = 1 - pat[0, 0]
        lo, hi = np.sort(rng.normal(0.0, 2.0 * std, 2))
        sub[...] = lo + (hi - lo + std) * pat


def _normalise(img: np.ndarray, lo_q=1.0, hi_q=99.0) -> np.ndarray:
    lo, hi = np.percentile(img[:: max(1, img.shape[0] // 256), :: max(1, img.shape[1] // 256)],
                           [lo_q, hi_q])  # fmt: skip
    out = (img - lo) / max(hi - lo, 1e-6)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _surface_texture(rng, h, w, texel) -> np.ndarray:
    """Rich, non-repeating luminance texture for a hall or obstacle face."""
    periods = [0.04, 0.08, 0.16, 0.32, 0.64, 1.28, 2.56]
    img = _value_noise(rng, h, w, texel, periods, beta=rng.uniform(0.05, 0.4))
    _decorate(rng, img, texel, area_density=rng.uniform(0.6, 1.5))
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return _normalise(img)


def _detail_texture(rng) -> np.ndarray:
    """Seamless fine grain (DETAIL_SIZE^2 texels of DETAIL_TEXEL m): periodic value noise at
    2-16 texels plus speckles; mean 0.5."""
    n = DETAIL_SIZE
    img = np.zeros((n, n), np.float32)
    for period in (2, 4, 8, 16):
        g = rng.standard_normal((n // period, n // period)).astype(np.float32)
        tiled = np.tile(g, (3, 3))  # wrap-around so the upsampled texture tiles seamlessly
        up = cv2.resize(tiled, (3 * n, 3 * n), interpolation=cv2.INTER_CUBIC)[n : 2 * n, n : 2 * n]
        img += np.float32(period**0.3) * up
    speck = rng.random((n, n)) < 0.01
    img[speck] += np.float32(3.0 * img.std()) * rng.choice([-1.0, 1.0], int(speck.sum()))
    return _normalise(img, 0.5, 99.5)


def _target_texture(rng, cls, h, w, texel, z_rows, face_axis, side) -> np.ndarray:
    """Class pattern in texture space. ``z_rows`` (h, w) is the height of every texel above
    the box's bottom, normalised to [0, 1] (all equal on top/bottom faces)."""
    raw = _value_noise(rng, h, w, texel, [0.02, 0.05, 0.12, 0.3], 0.3)
    _decorate(rng, raw, texel, area_density=0.5)  # dirt, stickers, decals
    noise = _normalise(raw)
    if cls == CAR:
        lum = 0.3 + 0.7 * noise  # body colour (B) dominates
        if face_axis != 2:
            band = (z_rows > 0.58) & (z_rows < 0.92)
            lum = np.where(band, 0.08 + 0.15 * noise, lum)  # dark windows
            lum = np.where(np.abs(z_rows - 0.4) < 0.015, 0.2, lum)  # trim line
        elif side == 0:
            lum = 0.1 * noise
        return lum.astype(np.float32)
    # person: shirt (B, high) above the waist, trousers (A, low) below, head at the top
    lum = np.where(z_rows > 0.5, 0.6 + 0.4 * noise, 0.05 + 0.35 * noise)
    lum = np.where(z_rows > 0.87, 0.55 + 0.1 * noise, lum)
    return lum.astype(np.float32)


def _pack_quads(tex: np.ndarray, wrap: bool = False) -> np.ndarray:
    """(h, w) float texture in [0, 1] -> (h * w,) uint32 packed 2x2 neighbourhoods (edges
    repeated, or wrapped around for a tiling texture)."""
    t8 = np.clip(np.round(tex * 255.0), 0, 255).astype(np.uint32)
    if wrap:
        right = np.roll(t8, -1, axis=1)
        below = np.roll(t8, -1, axis=0)
        diag = np.roll(right, -1, axis=0)
    else:
        right = np.concatenate([t8[:, 1:], t8[:, -1:]], axis=1)
        below = np.concatenate([t8[1:], t8[-1:]], axis=0)
        diag = np.concatenate([right[1:], right[-1:]], axis=0)
    return (t8 | (right << 8) | (below << 16) | (diag << 24)).ravel()


def texture_luminance(scene: Scene) -> np.ndarray:
    """(N,) float32 luminance in [0, 1] of every atlas texel (the low byte of each quad)."""
    return (np.asarray(scene.texture) & 255).astype(np.float32) / 255.0


def _face_axes(axis: int) -> tuple[int, int]:
    """Local axes along the texture's columns (u) and rows (v) on a face normal to ``axis``."""
    return (axis + 1) % 3, (axis + 2) % 3


def _hsv_tint(rng, value, saturation) -> np.ndarray:
    hue = rng.uniform(0, 1)
    rgb = cv2.cvtColor(
        np.array([[[hue * 180.0, saturation * 255.0, 255.0]]], np.float32).astype(np.uint8),
        cv2.COLOR_HSV2RGB,
    )[0, 0].astype(np.float64) / 255.0
    return np.clip(value * rgb, 0.0, 1.0)


def make_scene(
    lo,
    hi,
    seed: int = 0,
    config: SceneConfig | None = None,
    *,
    path_points=None,
    view_directions=None,
) -> Scene:
    """Build a scene around the axis-aligned bounds ``[lo, hi]`` of a flight.

    Args:
        lo, hi: (3,) world bounds of the flight path (e.g. ``Trajectory.bounds()``).
        seed: everything random (placement, textures, colours) follows from it.
        config: sizes, counts and appearance (:class:`SceneConfig`).
        path_points: (M, 3) sampled path positions; obstacles and targets keep
            ``config.clearance`` from them. Without them the whole ``[lo, hi]`` box is kept
            clear (fewer places for solids, but always safe).
        view_directions: (M, 3) world-frame optical axes of a camera at ``path_points``;
            when given, targets are placed in front of that camera (within about +-30 degrees
            of its heading) instead of in any direction around the path.

    Returns:
        The scene (arrays float32; textures in one flat atlas).
    """
    cfg = config or SceneConfig()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x5CE7E]))
    lo = np.asarray(lo, dtype=np.float64).reshape(3)
    hi = np.asarray(hi, dtype=np.float64).reshape(3)
    if np.any(hi < lo):
        raise ValueError(f"bounds must satisfy lo <= hi, got lo={lo}, hi={hi}")
    room_lo = lo - np.array([cfg.margin_xy, cfg.margin_xy, cfg.margin_below])
    room_hi = hi + np.array([cfg.margin_xy, cfg.margin_xy, cfg.margin_above])
    short = np.maximum(np.asarray(cfg.min_size) - (room_hi - room_lo), 0.0)
    room_lo[:2] -= 0.5 * short[:2]
    room_hi[:2] += 0.5 * short[:2]
    room_hi[2] += short[2]
    keep, keep_pad = _keepout_points(lo, hi, path_points)

    obstacles = _place_obstacles(rng, cfg, room_lo, room_hi, keep, keep_pad)
    anchors = view_yaw = None
    if view_directions is not None and path_points is not None:
        anchors = np.asarray(path_points, dtype=np.float64).reshape(-1, 3)[:, :2]
        view = np.asarray(view_directions, dtype=np.float64).reshape(-1, 3)
        if view.shape[0] != anchors.shape[0]:
            raise ValueError(f"view_directions has {view.shape[0]} rows, path_points "
                             f"{anchors.shape[0]}")
        view_yaw = np.arctan2(view[:, 1], view[:, 0])
    targets = _place_targets(rng, cfg, room_lo, room_hi, keep, keep_pad, obstacles,
                             anchors, view_yaw)

    room_c, room_h = 0.5 * (room_lo + room_hi), 0.5 * (room_hi - room_lo)
    static = [(room_c, 0.0, room_h)] + [(o.center, o.yaw, o.half) for o in obstacles]

    # textures: one per face, hall faces first
    hall_area = 2 * (
        (room_h[0] * room_h[1]) + (room_h[1] * room_h[2]) + (room_h[0] * room_h[2])
    ) * 4.0 + sum(8.0 * (h[0] * h[1] + h[1] * h[2] + h[0] * h[2]) for _, _, h in static[1:])
    texel = max(cfg.texel, float(np.sqrt(hall_area / (0.85 * cfg.max_texels))))
    chunks: list[np.ndarray] = []
    face_tex, face_color = [], []
    offset = 0

    def add_face(tex: np.ndarray, texel_: float, hu: float, hv: float, a_rgb, b_rgb):
        nonlocal offset
        chunks.append(_pack_quads(tex))
        face_tex.append([offset, tex.shape[1], tex.shape[0], 1.0 / texel_, hu, hv])
        face_color.append([a_rgb, b_rgb])
        offset += tex.size

    for k, (_, _, half) in enumerate(static):
        is_room = k == 0
        base = _hsv_tint(rng, 1.0, rng.uniform(0.05, 0.3) if is_room else rng.uniform(0.2, 0.7))
        for axis in range(3):
            iu, iv = _face_axes(axis)
            for _side in range(2):
                nu = int(np.ceil(2 * half[iu] / texel)) + 2
                nv = int(np.ceil(2 * half[iv] / texel)) + 2
                tex = _surface_texture(rng, nv, nu, texel)
                dark = rng.uniform(0.03, 0.25)
                light = rng.uniform(0.65, 1.0)
                tint = base * rng.uniform(0.85, 1.0, 3)
                add_face(tex, texel, half[iu], half[iv], dark * tint, light * tint)

    for tg in targets:
        cls, half = tg["class_id"], tg["half"]
        if cls == CAR:
            body = _CAR_COLOURS[rng.integers(len(_CAR_COLOURS))] * rng.uniform(0.85, 1.0)
            a_rgb, b_rgb = np.array([0.03, 0.03, 0.04]), body
        else:
            a_rgb = np.array([0.1, 0.12, 0.3]) * rng.uniform(0.6, 1.2)  # trousers
            b_rgb = _SHIRT_COLOURS[rng.integers(len(_SHIRT_COLOURS))]
        for axis in range(3):
            iu, iv = _face_axes(axis)
            for side in range(2):
                nu = int(np.ceil(2 * half[iu] / cfg.target_texel)) + 2
                nv = int(np.ceil(2 * half[iv] / cfg.target_texel)) + 2
                # height of every texel above the box bottom, in [0, 1]
                if axis == 0:  # rows are z
                    z = np.repeat(np.linspace(0, 1, nv)[:, None], nu, axis=1)
                elif axis == 1:  # columns are z
                    z = np.repeat(np.linspace(0, 1, nu)[None, :], nv, axis=0)
                else:
                    z = np.full((nv, nu), float(side))
                tex = _target_texture(rng, cls, nv, nu, cfg.target_texel, z, axis, side)
                if cls == PERSON and axis == 2 and side == 1:
                    a_face, b_face = a_rgb, np.array([0.35, 0.22, 0.12])  # hair
                    tex = np.full_like(tex, 0.8)
                else:
                    a_face, b_face = a_rgb, b_rgb
                add_face(tex, cfg.target_texel, half[iu], half[iv], a_face, b_face)

    sun = np.array([0.35, 0.55, 0.75]) + rng.uniform(-0.15, 0.15, 3)
    fill = np.array([-0.6, -0.3, -0.45]) + rng.uniform(-0.15, 0.15, 3)
    lights = np.stack([sun / np.linalg.norm(sun), fill / np.linalg.norm(fill)])
    light_weight = np.array([cfg.ambient, 0.8 * (1 - cfg.ambient), 0.5 * (1 - cfg.ambient)])

    f32 = np.float32
    n_t = len(targets)

    def tcol(key, shape, dtype=f32):
        if n_t == 0:
            return jnp.zeros(shape, dtype)
        return jnp.asarray(np.array([tg[key] for tg in targets], dtype=dtype).reshape(shape))

    target_arrays = Targets(
        class_id=tcol("class_id", (n_t,), np.int32),
        half_extents=tcol("half", (n_t, 3)),
        center=tcol("center", (n_t, 2)),
        radii=tcol("radii", (n_t, 2)),
        path_yaw=tcol("path_yaw", (n_t,)),
        omega=tcol("omega", (n_t,)),
        phase=tcol("phase", (n_t,)),
        yaw=tcol("yaw", (n_t,)),
        z=tcol("z", (n_t,)),
    )
    return Scene(
        box_center=jnp.asarray(np.array([s[0] for s in static], f32)),
        box_yaw=jnp.asarray(np.array([s[1] for s in static], f32)),
        box_half=jnp.asarray(np.array([s[2] for s in static], f32)),
        targets=target_arrays,
        texture=jnp.asarray(np.concatenate(chunks)),
        face_tex=jnp.asarray(np.array(face_tex, f32)),
        face_color=jnp.asarray(np.clip(np.array(face_color, f32), 0.0, 1.0)),
        detail=jnp.asarray(_pack_quads(_detail_texture(rng), wrap=True)),
        lights=jnp.asarray(lights.astype(f32)),
        light_weight=jnp.asarray(light_weight.astype(f32)),
        class_names=CLASS_NAMES,
    )
