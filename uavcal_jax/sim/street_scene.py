"""A street seen from above: asphalt, lane and bay markings, parked and driving vehicles,
sidewalks, grass, trees, buildings and containers, with the sun's shadows on the ground.

The road runs along world x through ``y = 0``; across it (y) the street repeats outwards:
lanes (vehicles driving in both directions), a parking strip on either side (parallel or
perpendicular bays, most taken), a sidewalk (a raised paving tile, a person now and then),
then a block (a grass tile with trees, a parking lot of back-to-back bays, or a building),
then the next road. Vehicles are targets (class ``car``, any kind of
:mod:`uavcal_jax.sim.vehicles`); everything else is a static box that is *not* a car (a
detector must learn that a container or a roof is not one). Shadows of every box are baked
into the ground and the tiles under the scene's sun (flat surfaces only: a shadow falls on
the ground, not on another car), darkened by the sun's share of the light.

Scenes have fixed slot counts (:data:`MAX_STATIC`, :data:`MAX_TARGETS`; unused slots are
tiny boxes below the floor, never seen) and an atlas padded to a multiple of
:data:`ATLAS_BUCKET` texels, so that the renderer compiles once for many scenes. Floor at
``z = 0``; everything is drawn from one generator seeded by ``seed``.
"""

from __future__ import annotations

import cv2
import jax.numpy as jnp
import numpy as np

from uavcal_jax.sim.scene import CAR, CLASS_NAMES, PERSON, Scene, Targets
from uavcal_jax.sim.textures import detail_quads, normalise, pack_quads, target_faces, value_noise
from uavcal_jax.sim.vehicles import draw_vehicle

__all__ = ["ATLAS_BUCKET", "MAX_STATIC", "MAX_TARGETS", "street_scene", "sun_lights"]

#: Static boxes (the hall first) and targets of every street scene (unused slots hidden).
MAX_STATIC = 72
MAX_TARGETS = 160
#: The texture atlas is padded to a multiple of this many texels.
ATLAS_BUCKET = 1 << 21
LANE_M = 3.3
#: Ambient share of the light outdoors (the rest: the sun and its bounce), and the sun's
#: elevation range, degrees (morning to noon).
AMBIENT = 0.42
SUN_ELEVATION_DEG = (20.0, 70.0)
_ASPHALT = (np.array([0.02, 0.02, 0.02]), np.array([0.86, 0.86, 0.84]))
_PAVING = (np.array([0.25, 0.24, 0.22]), np.array([0.80, 0.78, 0.74]))
_GRASS = (np.array([0.05, 0.12, 0.03]), np.array([0.35, 0.55, 0.22]))
_TREE = (np.array([0.02, 0.07, 0.02]), np.array([0.22, 0.42, 0.14]))
_ROOFS = ((0.60, 0.28, 0.20), (0.45, 0.45, 0.46), (0.25, 0.25, 0.27), (0.72, 0.70, 0.64),
          (0.55, 0.50, 0.42))
_CONTAINERS = ((0.65, 0.12, 0.08), (0.12, 0.25, 0.55), (0.15, 0.40, 0.20), (0.85, 0.45, 0.10),
               (0.55, 0.56, 0.58), (0.90, 0.90, 0.88))


def sun_lights(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A street's lights: ``(2, 3)`` unit directions towards the sun (azimuth uniform,
    elevation uniform in :data:`SUN_ELEVATION_DEG`) and a fill light from the opposite side
    and below (the surroundings' bounce), and ``(3,)`` weights ``ambient, sun, fill``: the
    ambient share is :data:`AMBIENT` +- 25 % (haze, overcast), the sun and fill share the
    rest."""
    az = rng.uniform(-np.pi, np.pi)
    el = np.radians(rng.uniform(*SUN_ELEVATION_DEG))
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    fill = np.array([-sun[0], -sun[1], -0.45]) + rng.uniform(-0.15, 0.15, 3)
    amb = AMBIENT * rng.uniform(0.75, 1.25)
    lights = np.stack([sun, fill / np.linalg.norm(fill)])
    return lights, np.array([amb, 0.8 * (1 - amb), 0.5 * (1 - amb)])


class _Layout:
    """Boxes and targets of a street being laid out (world frame, yaw boxes)."""

    def __init__(self):
        self.tiles: list[tuple] = []  # (center, half, kind): flat ground tiles
        self.solids: list[tuple] = []  # (center, yaw, half, kind, colour)
        self.targets: list[tuple] = []  # (center xy, yaw, class, vehicle or None, half, z0)


def _lay_vehicles_along(rng, lay, x0, x1, y, yaw_choices, gap, fill=1.0, kinds=None):
    """Vehicles nose to tail along x in ``[x0, x1]`` at ``y``, gaps from ``gap`` (m, range)."""
    x = x0 + rng.uniform(0, 3.0)
    while True:
        v = draw_vehicle(rng, kinds)
        L = 2 * v.half[0]
        if x + L > x1:
            return
        if rng.random() < fill:
            yaw = float(rng.choice(yaw_choices)) + rng.normal(0.0, 0.01)
            lay.targets.append((np.array([x + 0.5 * L, y + rng.normal(0, 0.1)]), yaw, CAR, v,
                                v.half, 0.0))
        x += L + rng.uniform(*gap)


def _lay_bays(rng, lay, x0, x1, y_row, facing, lines, texel, origin, fill):
    """Perpendicular bays (2.5 m wide, 5 m deep) along x, their rear at ``y_row``, opening
    towards ``facing`` (+1: +y); painted lines into ``lines`` (the floor's marking mask)."""
    n = int((x1 - x0) // 2.5)
    for i in range(n + 1):
        xl = x0 + 2.5 * i
        p0 = ((np.array([xl, y_row]) - origin) / texel).astype(int)
        p1 = ((np.array([xl, y_row + facing * 5.0]) - origin) / texel).astype(int)
        cv2.line(lines, tuple(int(v) for v in p0), tuple(int(v) for v in p1), 1.0,
                 max(1, int(round(0.12 / texel))))
        if i == n or rng.random() > fill:
            continue
        v = draw_vehicle(rng, ("sedan", "hatchback", "suv", "van"))
        depth = 2 * v.half[0]
        yc = y_row + facing * (0.2 + 0.5 * depth + rng.uniform(0, 0.3))
        yaw = float(np.pi / 2 * facing * rng.choice([1, -1])) + rng.normal(0.0, 0.04)
        lay.targets.append((np.array([xl + 1.25 + rng.normal(0, 0.12), yc]), yaw, CAR, v,
                            v.half, 0.0))


def _layout(rng, ext, max_height, floor_lum, texel, origin):
    """Fill ``[-ext, ext]`` (2,) metres with the street (module docstring); markings and
    blemishes are painted into ``floor_lum`` (rows y, columns x from ``origin``)."""
    lay = _Layout()
    lines = np.zeros_like(floor_lum)
    px = lambda p: tuple(int(v) for v in ((np.asarray(p) - origin) / texel))  # noqa: E731
    width_px = lambda m: max(1, int(round(m / texel)))  # noqa: E731
    xr = (-ext[0], ext[0])
    for side in (1, -1):
        y = 0.0
        first = True
        while y < ext[1]:
            lanes = int(rng.integers(1, 3))  # per direction
            road = lanes * LANE_M
            lo = y  # the centre road straddles y = 0: each side holds its own lanes
            road_hi = lo + road
            for j in range(lanes):  # lanes on this side; traffic keeps right of y = 0
                yl = side * (lo + (j + 0.5) * LANE_M)
                _lay_vehicles_along(rng, lay, *xr, yl, [0.0 if side < 0 else np.pi],
                                    (3.0, 25.0), fill=0.8)
                if j > 0:  # dashed lane line
                    yy = side * (lo + j * LANE_M)
                    for xd in np.arange(xr[0], xr[1], 9.0):
                        cv2.line(lines, px((xd, yy)), px((xd + 3.0, yy)), 1.0, width_px(0.12))
            if first:
                cv2.line(lines, px((xr[0], 0.0)), px((xr[1], 0.0)), 1.0, width_px(0.15))
            yy = side * (road_hi - 0.3)
            cv2.line(lines, px((xr[0], yy)), px((xr[1], yy)), 1.0, width_px(0.12))
            y = road_hi
            kind = rng.choice(["parallel", "bays", "none"], p=[0.45, 0.4, 0.15])
            if kind == "parallel":
                _lay_vehicles_along(rng, lay, *xr, side * (y + 1.15), [0.0, np.pi], (0.5, 3.0),
                                    fill=0.8, kinds=("sedan", "hatchback", "suv", "van"))
                y += 2.3
            elif kind == "bays":
                _lay_bays(rng, lay, xr[0] + rng.uniform(0, 2.5), xr[1], side * (y + 5.0),
                          -side, lines, texel, origin, fill=rng.uniform(0.5, 0.95))
                y += 5.0
            walk = rng.uniform(2.0, 4.0)
            lay.tiles.append((np.array([0.0, side * (y + 0.5 * walk), 0.06]),
                              np.array([ext[0], 0.5 * walk, 0.06]), "paving"))
            for _ in range(rng.poisson(1.0)):  # people on the sidewalk
                half = 0.5 * np.array([rng.uniform(0.4, 0.6), rng.uniform(0.28, 0.4),
                                       rng.uniform(1.55, 1.9)])
                lay.targets.append((np.array([rng.uniform(*xr), side * (y + rng.uniform(
                    0.5, walk - 0.5))]), float(rng.uniform(-np.pi, np.pi)), PERSON, None, half,
                    0.12))
            for _ in range(rng.poisson(0.8)):  # bins, kiosks, boxes: not cars
                half = np.array([rng.uniform(0.4, 1.5), rng.uniform(0.4, 1.0),
                                 rng.uniform(0.5, 1.3)])
                lay.solids.append((np.array([rng.uniform(*xr), side * (y + 0.5 * walk),
                                             0.12 + half[2]]), float(rng.choice([0, np.pi / 2])),
                                   half, "box", _CONTAINERS[rng.integers(len(_CONTAINERS))]))
            y += walk
            block = float(rng.uniform(12.0, 35.0))
            what = rng.choice(["grass", "lot", "building"], p=[0.4, 0.3, 0.3])
            yb = side * (y + 0.5 * block)
            if what == "grass":
                lay.tiles.append((np.array([0.0, yb, 0.03]), np.array([ext[0], 0.5 * block,
                                                                      0.03]), "grass"))
                for _ in range(rng.poisson(0.06 * block * ext[0] / 10.0)):
                    r = rng.uniform(1.5, 3.5)
                    h = min(rng.uniform(4.0, 10.0), max_height)
                    lay.solids.append((np.array([rng.uniform(*xr), yb + rng.uniform(
                        -0.5, 0.5) * (block - 2 * r), 0.06 + 0.5 * h]), float(rng.uniform(
                            -np.pi, np.pi)), np.array([r, r * rng.uniform(0.7, 1.0), 0.5 * h]),
                        "tree", None))
            elif what == "lot":
                n_rows = max(1, int(block // 12.0))
                for r_i in range(n_rows):
                    yrow = side * (y + 1.0 + 12.0 * r_i + 5.0)
                    for facing in (-1, 1):
                        _lay_bays(rng, lay, xr[0] + rng.uniform(0, 2.5), xr[1], yrow, facing,
                                  lines, texel, origin, fill=rng.uniform(0.3, 0.95))
                for _ in range(rng.poisson(1.0)):  # containers in the lot
                    long = rng.choice([6.06, 12.19])
                    half = 0.5 * np.array([long, 2.44, 2.59])
                    lay.solids.append((np.array([rng.uniform(*xr), yb, half[2]]),
                                       float(rng.choice([0.0, np.pi / 2])) + rng.normal(0, 0.05),
                                       half, "container",
                                       _CONTAINERS[rng.integers(len(_CONTAINERS))]))
            else:
                h = min(rng.uniform(4.0, 20.0), max_height)
                bx = rng.uniform(10.0, 40.0)
                for xb in np.arange(xr[0] + rng.uniform(0, 10), xr[1], bx + rng.uniform(3, 10)):
                    half = np.array([0.5 * bx, 0.5 * (block - 2.0), 0.5 * h])
                    lay.solids.append((np.array([xb + half[0], yb, half[2]]), 0.0, half,
                                       "building", _ROOFS[rng.integers(len(_ROOFS))]))
            y += block
            first = False
    # blemishes: patches, oil stains, manhole covers
    for _ in range(rng.poisson(0.02 * ext[0] * ext[1])):
        c = px(rng.uniform(-ext, ext))
        ax = (width_px(rng.uniform(0.3, 2.5)), width_px(rng.uniform(0.3, 1.5)))
        cv2.ellipse(floor_lum, c, ax, float(rng.uniform(0, 180)), 0, 360,
                    float(rng.uniform(0.25, 0.5)), -1)
    floor_lum[:] = np.maximum(floor_lum, 0.92 * lines)
    return lay


def _inside(target, tiles) -> bool:
    """Whether a vehicle's centre stands on a raised tile or a solid (it would float)."""
    c = target[0]
    return any(np.all(np.abs(c - t[0][:2]) < t[1][:2]) for t in tiles)


def _bake_shadow(lum, surface_z, origin, texel, boxes, sun, factor):
    """Darken ``lum`` (rows y, columns x from ``origin``, ``texel`` m) by ``factor`` where a
    box (centre, yaw, half) shades the plane ``z = surface_z`` from the ``sun`` (unit, up)."""
    mask = np.zeros(lum.shape, np.float32)
    shift = sun[:2] / sun[2]
    signs = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)])
    for center, yaw, half in boxes:
        top = center[2] + half[2]
        if top <= surface_z + 1e-3:
            continue
        c, s = np.cos(yaw), np.sin(yaw)
        loc = signs * half[:2]
        xy = center[:2] + np.stack([c * loc[:, 0] - s * loc[:, 1],
                                    s * loc[:, 0] + c * loc[:, 1]], -1)
        bottom = max(center[2] - half[2], surface_z)
        pts = np.concatenate([xy - (bottom - surface_z) * shift, xy - (top - surface_z) * shift])
        pix = ((pts - origin) / texel).astype(np.int32)
        cv2.fillConvexPoly(mask, cv2.convexHull(pix), 1.0)
    mask = cv2.GaussianBlur(mask, (0, 0), 0.8)
    lum *= 1.0 - (1.0 - factor) * mask


class _Atlas:
    """Faces in the scene's order, textures packed into one flat atlas."""

    def __init__(self):
        self.chunks, self.face_tex, self.face_color, self.offset = [], [], [], 0
        self.blank = self.add(np.full((2, 2), 0.5, np.float32))

    def add(self, tex):
        """Append a texture; returns (offset, n_u, n_v) for :meth:`face`."""
        ref = (self.offset, tex.shape[1], tex.shape[0])
        self.chunks.append(pack_quads(tex))
        self.offset += tex.size
        return ref

    def face(self, ref, texel, hu, hv, a, b):
        self.face_tex.append([ref[0], ref[1], ref[2], 1.0 / texel, hu, hv])
        self.face_color.append([a, b])

    def plain(self, hu, hv, a, b):
        """A face that shows its colours' mean (walls, undersides, hidden slots)."""
        self.face(self.blank, max(hu, hv, 1e-3), hu, hv, a, b)

    def textured(self, tex, texel, hu, hv, a, b):
        self.face(self.add(tex), texel, hu, hv, a, b)


def _box_faces(atlas, rng, half, texel, top, a, b, kind):
    """Six faces of a static box: its top textured (``top`` (nv, nu) or a noise texture of
    ``kind``), its sides a coarse noise, its bottom plain."""
    for axis in range(3):
        iu, iv = (axis + 1) % 3, (axis + 2) % 3
        for side in range(2):
            hu, hv = float(half[iu]), float(half[iv])
            if axis == 2 and side == 0:
                atlas.plain(hu, hv, a, b)
                continue
            t = texel if axis == 2 else max(texel, 0.1)
            nu, nv = int(np.ceil(2 * hu / t)) + 2, int(np.ceil(2 * hv / t)) + 2
            if axis == 2 and top is not None:
                tex = top
            else:
                periods = [0.3, 1.0, 3.0] if kind in ("tree", "grass") else [0.2, 0.8]
                tex = normalise(value_noise(rng, nv, nu, t, periods, 0.5))
                if kind == "container" and axis == 2:  # corrugation across the roof
                    tex = 0.6 * tex + 0.4 * (np.arange(nu)[None, :] * t / 0.3 % 1.0 < 0.5)
                if axis != 2:
                    tex = 0.55 * tex + 0.2  # walls darker than the roof
                elif kind == "tree":  # a crown: bright in the middle, dark at the rim
                    yy, xx = np.mgrid[-1:1:nv * 1j, -1:1:nu * 1j]
                    tex = tex * np.clip(1.2 - np.hypot(xx, yy), 0.05, 1.0)
                else:
                    tex = 0.35 + 0.65 * tex
            atlas.textured(tex.astype(np.float32), t, hu, hv, a, b)


def street_scene(seed: int, extent, gsd: float) -> Scene:
    """A street scene (module docstring) covering ``[-extent, extent]`` (2,) metres in x and
    y, textured at about ``gsd`` metres per texel (the camera's ground sample distance), for
    a camera no higher than ``max(extent)`` metres (buildings stay below a fifth of that).

    Returns:
        The scene: hall (box 0) floor at ``z = 0`` and ceiling above ``2 max(extent)``,
        :data:`MAX_STATIC` static boxes, :data:`MAX_TARGETS` targets (classes car, person;
        slots beyond the laid-out ones hidden below the floor), atlas padded to
        :data:`ATLAS_BUCKET`.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x57EE7]))
    ext = np.asarray(extent, np.float64).reshape(2)
    texel = float(gsd)
    lights, light_weight = sun_lights(rng)
    sun = lights[0]
    # a horizontal surface in shadow keeps the ambient light only
    factor = light_weight[0] / (light_weight[0] + light_weight[1] * sun[2])

    nx, ny = int(np.ceil(2 * ext[0] / texel)) + 2, int(np.ceil(2 * ext[1] / texel)) + 2
    origin = -ext - texel  # world xy of texel (0, 0)'s corner, so that column = (x - o) / t
    floor = 0.42 + 0.06 * normalise(value_noise(rng, ny, nx, texel, [0.5, 2.0, 8.0], 0.4))
    floor += 0.05 * (rng.random((ny, nx)) - 0.5)  # grain
    lay = _layout(rng, ext, 0.2 * float(ext.max()), floor, texel, origin)
    raised = [t for t in lay.tiles] + [(s[0], s[2], s[3]) for s in lay.solids]
    lay.targets = [t for t in lay.targets if t[2] == PERSON or not _inside(t, raised)]
    if len(lay.solids) + len(lay.tiles) > MAX_STATIC - 1:
        lay.solids = lay.solids[: MAX_STATIC - 1 - len(lay.tiles)]
    order = rng.permutation(len(lay.targets))[:MAX_TARGETS]
    targets = [lay.targets[i] for i in sorted(order)]

    casters = [(np.array([*t[0], t[5] + t[4][2]]), t[1], t[4]) for t in targets]
    casters += [(s[0], s[1], s[2]) for s in lay.solids]
    _bake_shadow(floor, 0.0, origin, texel, casters, sun, factor)

    atlas = _Atlas()
    pad = int(np.ceil(5.0 / texel))  # texels of asphalt beyond the street on every side
    hall_half = np.array([ext[0] + pad * texel, ext[1] + pad * texel, float(ext.max()) + 5.0])
    hall_c = np.array([0.0, 0.0, hall_half[2]])
    # the hall: its floor (axis 2, side 0) is the street; walls and ceiling plain sky-grey
    sky = (np.array([0.55, 0.6, 0.65]), np.array([0.75, 0.8, 0.85]))
    for axis in range(3):
        iu, iv = (axis + 1) % 3, (axis + 2) % 3
        for side in range(2):
            if axis == 2 and side == 0:
                ground = np.pad(floor, ((pad, pad), (pad, pad)), mode="edge")
                atlas.textured(np.clip(ground, 0, 1).astype(np.float32), texel, hall_half[0],
                               hall_half[1], *_ASPHALT)
            else:
                atlas.plain(hall_half[iu], hall_half[iv], *sky)
    static = [(hall_c, 0.0, hall_half)]
    for center, half, kind in lay.tiles:
        a, b = _PAVING if kind == "paving" else _GRASS
        nu, nv = int(np.ceil(2 * half[0] / texel)) + 2, int(np.ceil(2 * half[1] / texel)) + 2
        top = normalise(value_noise(rng, nv, nu, texel, [0.3, 1.5, 6.0], 0.4))
        top = 0.55 + 0.3 * top if kind == "paving" else 0.35 + 0.5 * top
        if kind == "paving":  # slabs: a grid of joints
            jj = max(1, int(round(0.6 / texel)))
            top[::jj] *= 0.8
            top[:, ::jj] *= 0.8
        top_origin = center[:2] - half[:2] - texel
        _bake_shadow(top, 2 * half[2], top_origin, texel, casters, sun, factor)
        _box_faces(atlas, rng, half, texel, top.astype(np.float32), a, b, kind)
        static.append((center, 0.0, half))
    for center, yaw, half, kind, colour in lay.solids:
        if kind == "tree":
            a, b = _TREE
        else:
            b = np.array(colour) * rng.uniform(0.9, 1.05)
            a = 0.15 * b
        _box_faces(atlas, rng, half, texel, None, a, b, kind)
        static.append((center, yaw, half))
    hidden = (np.array([0.0, 0.0, -1000.0]), 0.0, np.full(3, 0.01))
    while len(static) < MAX_STATIC:
        static.append(hidden)
        for _ in range(6):
            atlas.plain(0.01, 0.01, *_PAVING)

    tex_texel = max(0.7 * texel, 0.02)
    for _, _, cls, vehicle, half, _ in targets:
        for tex, hu, hv, a, b in target_faces(rng, cls, half, vehicle, tex_texel):
            atlas.textured(tex, tex_texel, hu, hv, a, b)
    n_t = len(targets)
    for _ in range(MAX_TARGETS - n_t):
        for _ in range(6):
            atlas.plain(0.01, 0.01, *_PAVING)

    texture = np.concatenate(atlas.chunks)
    texture = np.pad(texture, (0, -texture.size % ATLAS_BUCKET))
    f32 = np.float32
    cls = np.array([t[2] for t in targets] + [CAR] * (MAX_TARGETS - n_t), np.int32)
    half = np.array([t[4] for t in targets] + [np.full(3, 0.01)] * (MAX_TARGETS - n_t), f32)
    center = np.array([t[0] for t in targets] + [np.zeros(2)] * (MAX_TARGETS - n_t), f32)
    z = np.array([t[5] + t[4][2] for t in targets] + [-1000.0] * (MAX_TARGETS - n_t), f32)
    yaw = np.array([t[1] for t in targets] + [0.0] * (MAX_TARGETS - n_t), f32)
    zeros = np.zeros(MAX_TARGETS, f32)
    tg = Targets(class_id=jnp.asarray(cls), half_extents=jnp.asarray(half),
                 center=jnp.asarray(center), radii=jnp.zeros((MAX_TARGETS, 2), jnp.float32),
                 path_yaw=jnp.asarray(zeros), omega=jnp.asarray(zeros),
                 phase=jnp.asarray(zeros), yaw=jnp.asarray(yaw), z=jnp.asarray(z),
                 tracked=jnp.zeros(MAX_TARGETS, bool),
                 track=jnp.zeros((MAX_TARGETS, 1, 3), jnp.float32),
                 track_t0=jnp.asarray(zeros), track_dt=jnp.ones(MAX_TARGETS, jnp.float32))
    return Scene(
        box_center=jnp.asarray(np.array([s[0] for s in static], f32)),
        box_yaw=jnp.asarray(np.array([s[1] for s in static], f32)),
        box_half=jnp.asarray(np.array([s[2] for s in static], f32)),
        targets=tg,
        texture=jnp.asarray(texture),
        face_tex=jnp.asarray(np.array(atlas.face_tex, f32)),
        face_color=jnp.asarray(np.clip(np.array(atlas.face_color, f32), 0.0, 1.0)),
        detail=jnp.asarray(detail_quads(rng)),
        lights=jnp.asarray(lights.astype(f32)),
        light_weight=jnp.asarray(light_weight.astype(f32)),
        class_names=CLASS_NAMES,
    )
