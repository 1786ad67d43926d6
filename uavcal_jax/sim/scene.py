"""The simulator's world: a textured hall, static obstacles and (moving) target objects.

Geometry. Every solid is a box that may be rotated about the world z axis only (a *yaw box*:
centre, yaw, half extents). Box 0 is the hall itself (seen from inside: walls, floor, ceiling),
boxes ``1..n_obstacles`` are static obstacles (pillars from floor to ceiling and crates on the
floor), and the targets follow. The hall contains the trajectory's bounds ``[lo, hi]`` plus a
margin; obstacles and targets keep a clearance from the flight path (sampled path points, or
the whole bounds box when none are given), so the camera never enters a solid. The scene is
built by :func:`uavcal_jax.sim.scene_build.make_scene`.

Targets. ``CLASS_NAMES[c]`` is target class ``c`` ("car": a low wide box, "person": a tall
narrow one). A target is static, moves on a closed ellipse on the floor at constant angular
rate, facing along its velocity, or follows a sampled ground track (position and heading; a
follow target, :mod:`uavcal_jax.sim.follow_targets`); its pose is a pure function of the scene
and the time (:func:`target_poses`). Scene time ``t`` is seconds since the start of the flight
(keep it small: the renderer works in float32, so absolute EuRoC timestamps would lose all
precision).

Appearance. Every face of every box has its own luminance texture, stored in one flat atlas
and mixed between two colours per face (``colour = A + (B - A) * texture``); see
:mod:`uavcal_jax.sim.textures`. Everything is deterministic for a seed.

The :class:`Scene` is a pytree of arrays (class names are static metadata), so it can be passed
into jitted functions; scenes with different numbers of boxes or texels are different shapes.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "CAR",
    "CLASS_NAMES",
    "PERSON",
    "Scene",
    "SceneConfig",
    "Targets",
    "box_arrays",
    "target_class_names",
    "target_poses",
    "target_states",
]

CLASS_NAMES: tuple[str, ...] = ("car", "person")
#: Class ids, indices into :data:`CLASS_NAMES`.
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
        tracked: (n,) bool: the target follows ``track`` instead of its ellipse (a follow
            target, :mod:`uavcal_jax.sim.follow_targets`).
        track: (n, K, 3) ``x, y, yaw`` (world metres; radians, unwrapped) of a tracked target
            at scene times ``track_t0 + k track_dt``, linearly interpolated between them and
            held beyond the ends (``K = 1`` and unused when no target is tracked).
        track_t0: (n,) scene seconds of ``track[:, 0]``.
        track_dt: (n,) seconds between track samples (positive).
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
    tracked: Any
    track: Any
    track_t0: Any
    track_dt: Any

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
            bilinear lookup is one gather (:mod:`uavcal_jax.sim.textures`).
        face_tex: (F, 6) float32 per face ``offset, n_u, n_v, 1/texel, half_u, half_v`` with
            ``F = 6 (S + n_targets)`` and face ``6 k + 2 axis + (1 if the + side)``.
        face_color: (F, 2, 3) float32 RGB colours A (texture 0) and B (texture 1).
        detail: (DETAIL_SIZE ** 2,) uint32 packed quads (as ``texture``) of a fine tiled
            detail texture (``DETAIL_TEXEL`` metres per texel, both constants in
            :mod:`uavcal_jax.sim.textures`) that the renderer blends in
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
    # tracked targets: linear interpolation of their track samples
    K = tg.track.shape[1]
    s = jnp.clip((t - tg.track_t0) / tg.track_dt, 0.0, K - 1.0)
    i0 = jnp.clip(jnp.floor(s).astype(jnp.int32), 0, max(K - 2, 0))
    i1 = jnp.minimum(i0 + 1, K - 1)
    a = jnp.take_along_axis(tg.track, i0[:, None, None], axis=1)[:, 0]
    b = jnp.take_along_axis(tg.track, i1[:, None, None], axis=1)[:, 0]
    q = a + (s - i0.astype(s.dtype))[:, None] * (b - a)
    inside = (t >= tg.track_t0) & (t <= tg.track_t0 + (K - 1) * tg.track_dt) & (i1 > i0)
    tv = jnp.where(inside[:, None], (b - a)[:, :2] / tg.track_dt[:, None], 0.0)
    px, py = jnp.where(tg.tracked, q[:, 0], px), jnp.where(tg.tracked, q[:, 1], py)
    wx, wy = jnp.where(tg.tracked, tv[:, 0], wx), jnp.where(tg.tracked, tv[:, 1], wy)
    yaw = jnp.where(tg.tracked, q[:, 2], yaw)
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
