"""Vectorised ray-casting renderer of a :class:`~uavcal_jax.sim.scene.Scene`, in JAX.

Every pixel's ray is the undistorted pixel centre ``(x, y, 1)`` in the camera frame
(:func:`uavcal_jax.geometry.camera.pixel_rays`), so images carry the real lens distortion and
the ray parameter of a hit *is* its z-depth. Rays are rotated into the world by ``T_WC`` and
intersected with every box of the scene at once (slab test in each box's yaw frame: the hall
from inside, obstacles and targets from outside); the nearest hit wins. Its face's texture is
sampled bilinearly from the flat atlas and mixed between the face's two colours, times a
per-face light (ambient + two directional lights, Lambert).

All arithmetic is float32. :func:`render` is pure and jit-able; called with a concrete camera
it reuses cached rays (the undistortion runs once per lens), and with a traced camera it
computes them in the graph (XLA hoists that out of a ``vmap`` over poses). For throughput use
:func:`render_batch`: several frames per call, one compilation per resolution, colour mode and
batch size.

One module, over 450 lines: ray bundles, per-tile culling, slab intersection and shading are
the stages of one jitted function and share its private array layout (tiles of packed rays);
split apart, each piece would export that layout for a single caller.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.data.color import LUMA_WEIGHTS
from uavcal_jax.geometry import camera as camera_model
from uavcal_jax.sim.config import COLORS
from uavcal_jax.sim.scene import Scene, box_arrays
from uavcal_jax.sim.textures import DETAIL_SIZE, DETAIL_TEXEL

__all__ = [
    "RenderOut",
    "DEFAULT_TILE",
    "RayBundle",
    "camera_rays",
    "render",
    "ray_bundle",
    "render_batch",
]

#: Pixels per tile (rows, cols): boxes are culled per tile.
DEFAULT_TILE: tuple[int, int] = (48, 64)
SHADE_CHUNKS = 4
#: The detail texture is at full strength nearer than DETAIL_NEAR_FAR[0] metres (z-depth) and
#: gone beyond DETAIL_NEAR_FAR[1]; DETAIL_GAIN scales its contrast.
DETAIL_NEAR_FAR = (1.5, 3.5)
DETAIL_GAIN = 0.6


class RenderOut(NamedTuple):
    """One rendered frame (or a batch, with a leading dimension).

    Attributes:
        image: (H, W, 3) RGB or (H, W) gray, float32 in [0, 1].
        depth: (H, W) float32 z-depth in the camera frame, metres.
        object_id: (H, W) int32: -1 for the hall and obstacles, ``k`` for target ``k``.
    """

    image: jax.Array
    depth: jax.Array
    object_id: jax.Array


def _is_concrete(tree) -> bool:
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))


@dataclasses.dataclass(frozen=True)
class RayBundle:
    """A camera's pixel rays, laid out for the renderer.

    Attributes:
        rx, ry: (H * W,) float32 undistorted normalised coordinates of every pixel centre
            (the ray is ``(rx, ry, 1)``), row-major.
        tile_x, tile_y: (T, P) the same, tile by tile (edge-padded).
        tile_lo, tile_hi: (T, 2) bounding rectangle of each tile's ``(rx, ry)``.
        height, width, tile_h, tile_w, tiles_y, tiles_x: layout (static).
    """

    rx: jax.Array
    ry: jax.Array
    tile_x: jax.Array
    tile_y: jax.Array
    tile_lo: jax.Array
    tile_hi: jax.Array
    height: int
    width: int
    tile_h: int
    tile_w: int
    tiles_y: int
    tiles_x: int


jax.tree_util.register_dataclass(
    RayBundle,
    data_fields=["rx", "ry", "tile_x", "tile_y", "tile_lo", "tile_hi"],
    meta_fields=["height", "width", "tile_h", "tile_w", "tiles_y", "tiles_x"],
)


def _bundle(xp, rays, tile: tuple[int, int]) -> RayBundle:
    """Lay out (H, W, >=2) rays with numpy (``xp=np``) or jax.numpy."""
    H, W = rays.shape[:2]
    th, tw = min(tile[0], H), min(tile[1], W)
    nty, ntx = -(-H // th), -(-W // tw)
    xy = rays[..., :2].astype(xp.float32)
    padded = xp.pad(xy, [(0, nty * th - H), (0, ntx * tw - W), (0, 0)], mode="edge")
    tiles = padded.reshape(nty, th, ntx, tw, 2).transpose(0, 2, 1, 3, 4).reshape(-1, th * tw, 2)
    return RayBundle(
        rx=xy[..., 0].reshape(-1),
        ry=xy[..., 1].reshape(-1),
        tile_x=tiles[..., 0],
        tile_y=tiles[..., 1],
        tile_lo=tiles.min(axis=1),
        tile_hi=tiles.max(axis=1),
        height=H,
        width=W,
        tile_h=th,
        tile_w=tw,
        tiles_y=nty,
        tiles_x=ntx,
    )


@functools.lru_cache(maxsize=16)
def _cached_rays(key: tuple) -> np.ndarray:
    params, (w, h) = key[:-2], key[-2:]  # see _cam_key
    with jax.enable_x64(True):
        cam64 = camera_model.PinholeRadtan.create(params[:4], params[4:], (w, h), jnp.float64)
        rays = np.asarray(camera_model.pixel_rays(cam64), dtype=np.float32)
    rays.setflags(write=False)
    return rays


@functools.lru_cache(maxsize=16)
def _cached_bundle(key: tuple, tile: tuple[int, int]) -> RayBundle:
    return _bundle(np, _cached_rays(key), tile)


def _cam_key(cam: camera_model.PinholeRadtan) -> tuple:
    params = tuple(float(np.asarray(getattr(cam, n))) for n in camera_model.PARAMETER_NAMES)
    return params + (cam.width, cam.height)


def camera_rays(cam: camera_model.PinholeRadtan) -> jax.Array:
    """(H, W, 3) float32 unit-z rays ``(x, y, 1)`` of every pixel centre.

    A concrete camera's rays are computed once in float64 and cached; a traced camera's are
    computed in the graph (float32 Newton steps, accurate to ~1e-7)."""
    if _is_concrete(cam):
        return jnp.asarray(_cached_rays(_cam_key(cam)))
    return camera_model.pixel_rays(cam.astype(jnp.float32)).astype(jnp.float32)


def ray_bundle(cam_or_rays, tile: tuple[int, int] = DEFAULT_TILE) -> RayBundle:
    """The renderer's ray layout for a camera (cached when concrete) or for (H, W, 3) rays.

    Pass the result to :func:`render` (``rays=``) or into a jitted function as an argument to
    skip the undistortion of every pixel in the graph."""
    tile = (int(tile[0]), int(tile[1]))
    if isinstance(cam_or_rays, camera_model.PinholeRadtan):
        if _is_concrete(cam_or_rays):
            return _cached_bundle(_cam_key(cam_or_rays), tile)
        return _bundle(jnp, camera_rays(cam_or_rays), tile)
    if isinstance(cam_or_rays, RayBundle):
        return cam_or_rays
    rays = cam_or_rays
    if isinstance(rays, np.ndarray):
        return _bundle(np, rays, tile)
    return _bundle(jnp, jnp.asarray(rays), tile)


def _frame_constants(scene: Scene, p_WC, t, color: str):
    """Per-frame scalars: box frames and slab planes (K,), per-face texture/colour (F,)."""
    f32 = jnp.float32
    center, yaw, half = box_arrays(scene, t)
    center, yaw, half = center.astype(f32), yaw.astype(f32), half.astype(f32)
    K = center.shape[0]
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    d = p_WC[None, :] - center
    o = jnp.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)
    # face normals in the world: axis 0 -> (c, s, 0), axis 1 -> (-s, c, 0), axis 2 -> (0, 0, 1)
    z = jnp.zeros_like(c)
    axes = jnp.stack(
        [jnp.stack([c, s, z], -1), jnp.stack([-s, c, z], -1), jnp.stack([z, z, z + 1], -1)], 1
    )  # (K, 3 axes, 3)
    inward = jnp.where(jnp.arange(K) == 0, -1.0, 1.0).astype(f32)  # the hall is seen inside
    normals = axes[:, :, None, :] * jnp.array([-1.0, 1.0], f32)[None, None, :, None]
    normals = normals * inward[:, None, None, None]  # (K, 3, 2, 3)
    lights, lw = scene.lights.astype(f32), scene.light_weight.astype(f32)
    lambert = jnp.maximum(jnp.einsum("kasj,lj->kasl", normals, lights), 0.0)
    shade = (lw[0] + jnp.einsum("kasl,l->kas", lambert, lw[1:])).reshape(-1)  # (F,)
    colors = scene.face_color.astype(f32) * (shade / 255.0)[:, None, None]  # (F, 2, 3)
    if color == "gray":
        colors = colors @ jnp.asarray(LUMA_WEIGHTS, f32)[:, None]  # (F, 2, 1)
    ft = scene.face_tex.astype(f32)
    faces = {
        "off": ft[:, 0].astype(jnp.int32),
        "nu": ft[:, 1].astype(jnp.int32),
        "inv_texel": ft[:, 3],
        # texel coordinate = local * inv_texel + half * inv_texel + 0.5, in [0.5, n - 1.5]
        "hu": ft[:, 4] * ft[:, 3] + 0.5,
        "hv": ft[:, 5] * ft[:, 3] + 0.5,
        "a": [colors[:, 0, i] for i in range(colors.shape[-1])],
        "ab": [colors[:, 1, i] - colors[:, 0, i] for i in range(colors.shape[-1])],
    }
    boxes = {
        "ox": o[:, 0], "oy": o[:, 1], "oz": o[:, 2], "c": c, "s": s,
        "ihx": 1.0 / half[:, 0], "ihy": 1.0 / half[:, 1], "ihz": 1.0 / half[:, 2],
        "lox": -half[:, 0] - o[:, 0], "hix": half[:, 0] - o[:, 0],
        "loy": -half[:, 1] - o[:, 1], "hiy": half[:, 1] - o[:, 1],
        "loz": -half[:, 2] - o[:, 2], "hiz": half[:, 2] - o[:, 2],
    }  # fmt: skip
    return center, yaw, half, boxes, faces


def _box_corners_cam(center, yaw, half, R_WC, p_WC):
    """(K, 8, 3) box corners in the camera frame."""
    signs = jnp.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], jnp.float32
    )
    local = signs[None] * half[:, None, :]
    c, s = jnp.cos(yaw)[:, None], jnp.sin(yaw)[:, None]
    wx = center[:, None, 0] + c * local[..., 0] - s * local[..., 1]
    wy = center[:, None, 1] + s * local[..., 0] + c * local[..., 1]
    wz = center[:, None, 2] + local[..., 2]
    world = jnp.stack([wx, wy, wz], -1)
    return (world - p_WC) @ R_WC  # R_WC^T (p - t), row-vector form


def _visibility(corners_cam, tile_lo, tile_hi):
    """(T, K) whether box k may cover a pixel of tile t (conservative).

    A box entirely in front of the camera covers at most the bounding rectangle of its
    corners' normalised projections; one that straddles the image plane may cover anything;
    one entirely behind covers nothing. Tiles are given by the bounding rectangles of their
    rays' normalised coordinates."""
    zc = corners_cam[..., 2]
    front = jnp.all(zc > 1e-3, axis=1)
    behind = jnp.all(zc <= 0.0, axis=1)
    zs = jnp.where(zc > 1e-3, zc, 1.0)
    nx, ny = corners_cam[..., 0] / zs, corners_cam[..., 1] / zs
    bx0, bx1 = jnp.min(nx, axis=1), jnp.max(nx, axis=1)
    by0, by1 = jnp.min(ny, axis=1), jnp.max(ny, axis=1)
    overlap = (
        (bx0[None] <= tile_hi[:, None, 0])
        & (bx1[None] >= tile_lo[:, None, 0])
        & (by0[None] <= tile_hi[:, None, 1])
        & (by1[None] >= tile_lo[:, None, 1])
    )
    return jnp.where(front[None], overlap, ~behind[None])


def _directions(R_WC, rx, ry):
    """World directions of unit-z camera rays (parameter along them = z-depth)."""
    dx = R_WC[0, 0] * rx + R_WC[0, 1] * ry + R_WC[0, 2]
    dy = R_WC[1, 0] * rx + R_WC[1, 1] * ry + R_WC[1, 2]
    dz = R_WC[2, 0] * rx + R_WC[2, 1] * ry + R_WC[2, 2]
    return dx, dy, dz


def _slabs(boxes, j, dx, dy, iz):
    """Entry and exit ray parameters of box ``j`` (scalar index) for all rays."""
    cj, sj = boxes["c"][j], boxes["s"][j]
    ix = 1.0 / (cj * dx + sj * dy)
    iy = 1.0 / (-sj * dx + cj * dy)
    tx1, tx2 = boxes["lox"][j] * ix, boxes["hix"][j] * ix
    ty1, ty2 = boxes["loy"][j] * iy, boxes["hiy"][j] * iy
    tz1, tz2 = boxes["loz"][j] * iz, boxes["hiz"][j] * iz
    tnear = jnp.maximum(
        jnp.maximum(jnp.minimum(tx1, tx2), jnp.minimum(ty1, ty2)), jnp.minimum(tz1, tz2)
    )
    tfar = jnp.minimum(
        jnp.minimum(jnp.maximum(tx1, tx2), jnp.maximum(ty1, ty2)), jnp.maximum(tz1, tz2)
    )
    return tnear, tfar


def _intersect(bundle: RayBundle, boxes, vis, R_WC):
    """Nearest hit per pixel: z-depth (T, P) and box index (T, P), tile by tile.

    The hall (box 0) is hit from inside everywhere; the other boxes are tested only in the
    tiles they may cover (a ``while_loop`` over each tile's visible boxes)."""
    vis = vis.at[:, 0].set(False)  # the hall is always intersected, separately
    order = jnp.argsort(~vis, axis=1, stable=True).astype(jnp.int32)  # visible first
    count = jnp.sum(vis, axis=1, dtype=jnp.int32)

    def one_tile(args):
        rx, ry, order_t, count_t = args
        dx, dy, dz = _directions(R_WC, rx, ry)
        iz = 1.0 / dz
        _, depth = _slabs(boxes, 0, dx, dy, iz)  # the hall, from inside: where rays leave it
        k = jnp.zeros(depth.shape, jnp.int32)

        def body(state):
            i, depth, k = state
            j = order_t[i]
            tnear, tfar = _slabs(boxes, j, dx, dy, iz)
            hit = (tnear <= tfar) & (tnear > 0.0) & (tnear < depth)
            return i + 1, jnp.where(hit, tnear, depth), jnp.where(hit, j, k)

        _, depth, k = jax.lax.while_loop(lambda s: s[0] < count_t, body, (0, depth, k))
        return depth, k

    return jax.lax.map(one_tile, (bundle.tile_x, bundle.tile_y, order, count))


def _untile(a, b: RayBundle):
    """(T, P, ...) tile layout -> (H, W, ...)."""
    rest = a.shape[2:]
    a = a.reshape(b.tiles_y, b.tiles_x, b.tile_h, b.tile_w, *rest)
    a = jnp.moveaxis(a, 2, 1)
    return a.reshape(b.tiles_y * b.tile_h, b.tiles_x * b.tile_w, *rest)[: b.height, : b.width]


def _bilinear_packed(q, fu, fv):
    """Bilinear blend at fractions ``(fu, fv)`` of the 2x2 texels packed in ``q`` (uint32,
    bytes t00, t01, t10, t11 from the lowest up); float32 in 0..255."""
    t00 = (q & 255).astype(jnp.float32)
    t01 = ((q >> 8) & 255).astype(jnp.float32)
    t10 = ((q >> 16) & 255).astype(jnp.float32)
    t11 = (q >> 24).astype(jnp.float32)
    top = t00 + fu * (t01 - t00)
    return top + fv * ((t10 + fu * (t11 - t10)) - top)


def _shade(texture, detail, dx, dy, dz, depth, k, boxes, faces, color: str):
    """Texture (bilinear, from packed 2x2 texel quads) x face colours x light, per hit.

    Returns (...) gray or a tuple of three (...) planes R, G, B."""
    ck, sk = boxes["c"][k], boxes["s"][k]
    px = boxes["ox"][k] + depth * (dx * ck + dy * sk)
    py = boxes["oy"][k] + depth * (-dx * sk + dy * ck)
    pz = boxes["oz"][k] + depth * dz
    ax = jnp.abs(px) * boxes["ihx"][k]
    ay = jnp.abs(py) * boxes["ihy"][k]
    az = jnp.abs(pz) * boxes["ihz"][k]
    axis = jnp.where((ax >= ay) & (ax >= az), 0, jnp.where(ay >= az, 1, 2))
    pa = jnp.where(axis == 0, px, jnp.where(axis == 1, py, pz))
    u = jnp.where(axis == 0, py, jnp.where(axis == 1, pz, px))
    v = jnp.where(axis == 0, pz, jnp.where(axis == 1, px, py))
    face = 6 * k + 2 * axis + (pa > 0).astype(jnp.int32)
    barrier = jax.lax.optimization_barrier
    face, u, v = barrier((face, u, v))
    inv_texel = faces["inv_texel"][face]
    tu = jnp.maximum(u * inv_texel + faces["hu"][face], 0.0)
    tv = jnp.maximum(v * inv_texel + faces["hv"][face], 0.0)
    u0, v0 = jnp.floor(tu), jnp.floor(tv)
    fu, fv = tu - u0, tv - v0
    base = faces["off"][face] + v0.astype(jnp.int32) * faces["nu"][face] + u0.astype(jnp.int32)
    base, fu, fv = barrier((base, fu, fv))
    lum = _bilinear_packed(barrier(texture[base]), fu, fv)  # 0..255; colours carry the 1/255
    # fine tiled detail near the camera (the atlas is blurry there), faded out with distance
    # before it would alias; each face reads the detail tile at its own offset
    w_detail = jnp.clip(DETAIL_NEAR_FAR[1] - depth, 0.0, DETAIL_NEAR_FAR[1] - DETAIL_NEAR_FAR[0])
    w_detail = w_detail * (DETAIL_GAIN / (DETAIL_NEAR_FAR[1] - DETAIL_NEAR_FAR[0]))
    n_det = DETAIL_SIZE
    du = u * (1.0 / DETAIL_TEXEL) + ((face * 211) % n_det).astype(jnp.float32)
    dv = v * (1.0 / DETAIL_TEXEL) + ((face * 157) % n_det).astype(jnp.float32)
    du0, dv0 = jnp.floor(du), jnp.floor(dv)
    dfu, dfv = du - du0, dv - dv0
    dbase = (dv0.astype(jnp.int32) & (n_det - 1)) * n_det + (du0.astype(jnp.int32) & (n_det - 1))
    dbase, dfu, dfv, w_detail = barrier((dbase, dfu, dfv, w_detail))
    dlum = _bilinear_packed(barrier(detail[dbase]), dfu, dfv)
    lum = jnp.clip(lum + w_detail * (dlum - 127.5), 0.0, 255.0)
    if color == "gray":
        return jnp.clip(faces["a"][0][face] + faces["ab"][0][face] * lum, 0.0, 1.0)
    # RGB: materialise (lum, face) once rather than let XLA recompute the lookup per channel
    lum, face = barrier((lum, face))
    chans = [
        jnp.clip(a[face] + ab[face] * lum, 0.0, 1.0)
        for a, ab in zip(faces["a"], faces["ab"], strict=True)
    ]
    return barrier(tuple(chans))


def _render_bundle(scene: Scene, bundle: RayBundle, T_WC, t, color: str) -> RenderOut:
    """Core: one frame along a ray bundle."""
    if color not in COLORS:
        raise ValueError(f"color must be one of {COLORS}, got {color!r}")
    f32 = jnp.float32
    T_WC = jnp.asarray(T_WC, f32)
    R_WC, p_WC = T_WC[:3, :3], T_WC[:3, 3]
    center, yaw, half, boxes, faces = _frame_constants(scene, p_WC, t, color)
    tile_lo, tile_hi = jnp.asarray(bundle.tile_lo), jnp.asarray(bundle.tile_hi)
    vis = _visibility(_box_corners_cam(center, yaw, half, R_WC, p_WC), tile_lo, tile_hi)
    depth, k = _intersect(bundle, boxes, vis, R_WC)  # (T, P)

    # Shading in a few chunks of tiles (a loop): the loop's outputs are materialised, so XLA
    # cannot fuse the texture lookup into the RGB interleave (recomputing it per channel).
    n_tiles = depth.shape[0]
    chunks = next(c for c in (SHADE_CHUNKS, 4, 3, 2, 1) if n_tiles % c == 0)

    def shade_chunk(args):
        rx, ry, d, kk = args
        dx, dy, dz = _directions(R_WC, rx, ry)
        return _shade(scene.texture, scene.detail, dx, dy, dz, d, kk, boxes, faces, color)

    split = lambda a: a.reshape(chunks, n_tiles // chunks, *a.shape[1:])  # noqa: E731
    img = jax.lax.map(
        shade_chunk, (split(bundle.tile_x), split(bundle.tile_y), split(depth), split(k))
    )
    img = jax.tree_util.tree_map(lambda a: a.reshape(n_tiles, *a.shape[2:]), img)
    n_static = scene.n_static
    obj = jnp.where(k >= n_static, k - n_static, -1).astype(jnp.int32)
    if color == "rgb":  # planes -> interleaved at the end
        image = jnp.stack([_untile(c, bundle) for c in img], axis=-1)
    else:
        image = _untile(img, bundle)
    return RenderOut(image=image, depth=_untile(depth, bundle), object_id=_untile(obj, bundle))


# jitted entry points (inlined when called inside another jit; compiled once per shape/colour)
_render_bundle_jit = jax.jit(_render_bundle, static_argnames=("color",))


def render(
    scene: Scene,
    cam: camera_model.PinholeRadtan,
    T_WC,
    t=0.0,
    *,
    color: str = "rgb",
    rays: RayBundle | jax.Array | None = None,
) -> RenderOut:
    """Render one frame.

    Args:
        scene: the world.
        cam: the lens and image size.
        T_WC: (4, 4) camera-to-world pose (maps camera-frame points into the world).
        t: scene time, seconds since the flight's start (moves the targets).
        color: ``"rgb"`` -> image (H, W, 3), ``"gray"`` -> (H, W) (luma of the RGB colours).
        rays: a :func:`ray_bundle` (or (H, W, 3) :func:`camera_rays`) of ``cam``: optional,
            saves undistorting every pixel in the graph when ``cam`` is traced.

    Returns:
        :class:`RenderOut` (image, z-depth, object ids).
    """
    bundle = ray_bundle(cam if rays is None else rays)
    return _render_bundle_jit(scene, bundle, T_WC, t, color)


def render_batch(
    scene: Scene,
    cam: camera_model.PinholeRadtan,
    T_WC,
    t,
    *,
    color: str = "rgb",
    rays: RayBundle | jax.Array | None = None,
) -> RenderOut:
    """Render ``B`` frames: ``T_WC`` (B, 4, 4), ``t`` (B,) -> RenderOut with leading ``B``.

    Frames are rendered one after the other (``lax.map``), not ``vmap``-ed: the per-tile
    culling loops and gathers are faster unbatched."""
    bundle = ray_bundle(cam if rays is None else rays)
    return _render_frames_jit(scene, bundle, jnp.asarray(T_WC), jnp.asarray(t), color)


def _render_frames(scene, bundle, T_WC, t, color):
    t = jnp.broadcast_to(jnp.asarray(t), T_WC.shape[:1])
    return jax.lax.map(lambda a: _render_bundle(scene, bundle, a[0], a[1], color), (T_WC, t))


_render_frames_jit = jax.jit(_render_frames, static_argnames=("color",))
