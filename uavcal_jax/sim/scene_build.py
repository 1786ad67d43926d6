"""Build a :class:`~uavcal_jax.sim.scene.Scene` around a flight: the hall, obstacles, targets.

:func:`make_scene` sizes the hall to the flight's bounds, places obstacles (pillars and crates)
and targets (cars and people, some moving on ellipses) so that they keep a clearance from the
flight path (and, given the camera's view directions, so that the targets are seen), plans the
follow targets' tracks when asked (:mod:`uavcal_jax.sim.follow_targets`), then
textures every face (:mod:`uavcal_jax.sim.textures`) and picks two directional lights. Cars
are passenger vehicles of :mod:`uavcal_jax.sim.vehicles` (kind, size, paint). Everything is
drawn from two ``numpy`` generators seeded by ``seed`` (the layout and the static textures
from one; the targets' kinds, paints and textures and the lights from the other, so that the
layout does not depend on how targets look): a seed gives the same scene.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from uavcal_jax.sim.follow_targets import FollowRequest, plan_tracks, viewing_floor_z
from uavcal_jax.sim.scene import CAR, CLASS_NAMES, PERSON, Scene, SceneConfig, Targets
from uavcal_jax.sim.textures import detail_quads, face_atlas
from uavcal_jax.sim.vehicles import Vehicle, vehicle_of_size

__all__ = ["make_scene"]

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


def _place_obstacles(rng, cfg, room_lo, room_hi, keep, keep_pad, avoid=None) -> list[_Solid]:
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
            if avoid is not None and np.any(
                    _point_box_distance(avoid[0], center, yaw, half) < avoid[1]):
                continue  # on a follow target's track or line of sight
            disc = (center[:2].copy(), float(np.hypot(half[0], half[1])))
            if any(_discs_overlap(disc, s.footprint, 0.0) for s in solids):
                continue
            solids.append(_Solid(center, yaw, half, disc))
            break
    return solids


#: The tallest target (a person's largest height in :func:`_target_size`), metres.
MAX_TARGET_HEIGHT = 1.9


def _target_size(rng, style, cls: int) -> tuple[np.ndarray, Vehicle | None]:
    """Half extents (3,) of a new target and, for a car, its vehicle: a passenger car of the
    drawn size (:func:`~uavcal_jax.sim.vehicles.vehicle_of_size`, below
    :data:`MAX_TARGET_HEIGHT`), its paint from ``style`` (the hall's layout, drawn from
    ``rng``, stays as it was before cars had kinds)."""
    if cls == CAR:
        half = 0.5 * np.array([rng.uniform(3.6, 4.7), rng.uniform(1.6, 1.9),
                               rng.uniform(1.3, 1.6)])
        return half, vehicle_of_size(style, half)
    return 0.5 * np.array([rng.uniform(0.4, 0.6), rng.uniform(0.28, 0.4),
                           rng.uniform(1.55, 1.9)]), None


def _place_targets(rng, style, cfg, room_lo, room_hi, keep, keep_pad, obstacles,
                   anchors=None, view_yaw=None, avoid=None) -> list[dict]:
    targets: list[dict] = []
    if anchors is None:
        anchors = keep[:, :2]
    floor = room_lo[2]
    n_moving = int(round(cfg.n_targets * cfg.moving_fraction))
    for i in range(cfg.n_targets):
        cls = int(cfg.target_classes[i % len(cfg.target_classes)])
        half, vehicle = _target_size(rng, style, cls)
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
                if avoid is not None:  # off the follow targets' tracks and lines of sight
                    d = (_point_cylinder_distance(avoid[0], xy, reach, floor,
                                                  floor + 2 * half[2]) if mov else
                         _point_box_distance(avoid[0], np.array([xy[0], xy[1], z]), yaw, half))
                    if np.any(d < avoid[1]):
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
                class_id=cls, half=half, vehicle=vehicle, center=xy, reach=reach, radii=radii,
                path_yaw=float(rng.uniform(-np.pi, np.pi)), omega=omega,
                phase=float(rng.uniform(-np.pi, np.pi)), yaw=yaw, z=z,
            )
        )  # fmt: skip
    return targets


def _follow_classes(cfg, n: int) -> list[int]:
    """Class ids of ``n`` follow targets: they cycle through ``cfg.target_classes``."""
    return [int(cfg.target_classes[i % len(cfg.target_classes)]) for i in range(n)]


def _follow_targets(rng, style, cfg, req: FollowRequest, floor: float) -> list[dict]:
    """Follow targets along ``req`` (:mod:`uavcal_jax.sim.follow_targets`): classes cycle
    through ``cfg.target_classes``; target dicts as :func:`_place_targets`' plus the track."""
    classes = _follow_classes(cfg, req.n)
    sized = [_target_size(rng, style, c) for c in classes]
    halves = np.stack([h for h, _ in sized])
    tracks = plan_tracks(req, floor, rng, classes, halves)
    out = []
    for cls, (half, vehicle), track in zip(classes, sized, tracks, strict=True):
        out.append(dict(
            class_id=cls, half=half, vehicle=vehicle, center=track[:, :2].mean(0),
            reach=float(np.hypot(half[0], half[1])), radii=np.zeros(2), path_yaw=0.0,
            omega=0.0, phase=0.0, yaw=float(track[0, 2]), z=floor + half[2], tracked=True,
            track=track, track_t0=float(req.t[0]), track_dt=float(req.t[1] - req.t[0])
            if req.t.shape[0] > 1 else 1.0,
        ))  # fmt: skip
    return out


def _follow_keepout(follow: list[dict], req: FollowRequest, stride: int = 4
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Points (M, 3) and radii (M,) that other solids must keep clear of: the follow targets'
    swept boxes (every ``stride``-th track sample, radius reach + 0.3 m) and their lines of
    sight from the left camera (radius 0.25 m), so that nothing stands on or hides them."""
    pts, rad = [], []
    cam = req.T_WC[::stride, :3, 3]
    for tg in follow:
        centre = np.concatenate([tg["track"][::stride, :2],
                                 np.full((cam.shape[0], 1), tg["z"])], -1)
        for h in (-0.7, 0.0, 0.7):  # the box's bottom, middle and top
            pts.append(centre + np.array([0.0, 0.0, h * tg["half"][2]]))
            rad.append(np.full(centre.shape[0], tg["reach"] + 0.3))
        for f in np.linspace(0.1, 0.9, 9):
            pts.append(cam + f * (centre - cam))
            rad.append(np.full(centre.shape[0], 0.25))
    return np.concatenate(pts), np.concatenate(rad)


def _track_arrays(targets: list[dict]) -> dict[str, jnp.ndarray]:
    """:class:`Targets`' ``tracked``, ``track``, ``track_t0``, ``track_dt`` (float32; all
    tracks share one length, K = 1 zeros when none is tracked)."""
    n = len(targets)
    K = max([tg["track"].shape[0] for tg in targets if tg.get("tracked")] + [1])
    track = np.zeros((n, K, 3), np.float32)
    t0, dt = np.zeros(n, np.float32), np.ones(n, np.float32)
    for i, tg in enumerate(targets):
        if tg.get("tracked"):
            track[i] = tg["track"]
            t0[i], dt[i] = tg["track_t0"], tg["track_dt"]
    tracked = np.array([bool(tg.get("tracked")) for tg in targets], dtype=bool)
    return dict(tracked=jnp.asarray(tracked), track=jnp.asarray(track),
                track_t0=jnp.asarray(t0), track_dt=jnp.asarray(dt))


def make_scene(
    lo,
    hi,
    seed: int = 0,
    config: SceneConfig | None = None,
    *,
    path_points=None,
    view_directions=None,
    follow: FollowRequest | None = None,
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
        follow: ``follow.n`` follow targets to plan along the left camera's view
            (:mod:`uavcal_jax.sim.follow_targets`); they are targets ``0 .. n-1``, the
            ordinary ones follow. The floor is then at least the tallest target plus the
            clearance below the flight (no target can touch the drone), and deep enough for
            the camera to see them whole (:func:`~uavcal_jax.sim.follow_targets.viewing_floor_z`),
            the hall grows to
            hold their tracks, and obstacles and the other targets keep off their tracks and
            their lines of sight from the camera.

    Returns:
        The scene (arrays float32; textures in one flat atlas).
    """
    cfg = config or SceneConfig()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x5CE7E]))
    # targets' kinds, paints and textures and the lights: a stream of their own
    style = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x5CE7E, 1]))
    lo = np.asarray(lo, dtype=np.float64).reshape(3)
    hi = np.asarray(hi, dtype=np.float64).reshape(3)
    if np.any(hi < lo):
        raise ValueError(f"bounds must satisfy lo <= hi, got lo={lo}, hi={hi}")
    below = cfg.margin_below
    if follow is not None:
        below = max(below, MAX_TARGET_HEIGHT + cfg.clearance)
    room_lo = lo - np.array([cfg.margin_xy, cfg.margin_xy, below])
    room_hi = hi + np.array([cfg.margin_xy, cfg.margin_xy, cfg.margin_above])
    followers: list[dict] = []
    avoid = None
    if follow is not None:
        room_lo[2] = min(room_lo[2], viewing_floor_z(follow, _follow_classes(cfg, follow.n)))
        followers = _follow_targets(rng, style, cfg, follow, float(room_lo[2]))
        for tg in followers:  # the hall holds the tracks, with a metre to spare
            room_lo[:2] = np.minimum(room_lo[:2], tg["track"][:, :2].min(0) - tg["reach"] - 1)
            room_hi[:2] = np.maximum(room_hi[:2], tg["track"][:, :2].max(0) + tg["reach"] + 1)
        avoid = _follow_keepout(followers, follow)
    short = np.maximum(np.asarray(cfg.min_size) - (room_hi - room_lo), 0.0)
    room_lo[:2] -= 0.5 * short[:2]
    room_hi[:2] += 0.5 * short[:2]
    room_hi[2] += short[2]
    keep, keep_pad = _keepout_points(lo, hi, path_points)

    obstacles = _place_obstacles(rng, cfg, room_lo, room_hi, keep, keep_pad, avoid)
    anchors = view_yaw = None
    if view_directions is not None and path_points is not None:
        anchors = np.asarray(path_points, dtype=np.float64).reshape(-1, 3)[:, :2]
        view = np.asarray(view_directions, dtype=np.float64).reshape(-1, 3)
        if view.shape[0] != anchors.shape[0]:
            raise ValueError(f"view_directions has {view.shape[0]} rows, path_points "
                             f"{anchors.shape[0]}")
        view_yaw = np.arctan2(view[:, 1], view[:, 0])
    targets = followers + _place_targets(rng, style, cfg, room_lo, room_hi, keep, keep_pad,
                                         obstacles, anchors, view_yaw, avoid)

    room_c, room_h = 0.5 * (room_lo + room_hi), 0.5 * (room_hi - room_lo)
    static = [(room_c, 0.0, room_h)] + [(o.center, o.yaw, o.half) for o in obstacles]

    # textures: one per face, hall faces first; the hall's texel grows to fit the atlas budget
    hall_area = 2 * (
        (room_h[0] * room_h[1]) + (room_h[1] * room_h[2]) + (room_h[0] * room_h[2])
    ) * 4.0 + sum(8.0 * (h[0] * h[1] + h[1] * h[2] + h[0] * h[2]) for _, _, h in static[1:])
    texel = max(cfg.texel, float(np.sqrt(hall_area / (0.85 * cfg.max_texels))))
    texture, face_tex, face_color = face_atlas(
        rng, [h for _, _, h in static], texel,
        [(tg["class_id"], tg["half"], tg["vehicle"]) for tg in targets],
        cfg.target_texel, style)

    # two lights in fixed directions, jittered per scene (the halls' photometry and VIO
    # figures are tuned to them; street scenes vary the sun far more)
    sun = np.array([0.35, 0.55, 0.75]) + style.uniform(-0.15, 0.15, 3)
    fill = np.array([-0.6, -0.3, -0.45]) + style.uniform(-0.15, 0.15, 3)
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
        **_track_arrays(targets),
    )
    return Scene(
        box_center=jnp.asarray(np.array([s[0] for s in static], f32)),
        box_yaw=jnp.asarray(np.array([s[1] for s in static], f32)),
        box_half=jnp.asarray(np.array([s[2] for s in static], f32)),
        targets=target_arrays,
        texture=jnp.asarray(texture),
        face_tex=jnp.asarray(face_tex),
        face_color=jnp.asarray(face_color),
        detail=jnp.asarray(detail_quads(rng)),
        lights=jnp.asarray(lights.astype(f32)),
        light_weight=jnp.asarray(light_weight.astype(f32)),
        class_names=CLASS_NAMES,
    )
