"""Procedural textures of the simulator's scene, packed into one flat atlas.

Every face of every box has its own luminance texture (multi-octave value noise, blobs,
checker and stripe patches, posters; a physical texel size of ~2 cm, so corners are trackable
at any distance and views are not self-similar), mixed between two colours per face
(``colour = A + (B - A) * texture``). Target classes have their own palettes and patterns
(car: a :class:`~uavcal_jax.sim.vehicles.Vehicle`'s paint, with glass, roof, cargo box and
wheels where its kind has them; person: shirt over trousers, skin-coloured head). A fine
tiled detail texture (:data:`DETAIL_SIZE` squared texels of :data:`DETAIL_TEXEL` metres) is
blended in by the renderer near the camera.

Texels are stored 8 bits each, every uint32 entry packing a texel's 2x2 neighbourhood, so
that a bilinear lookup is one gather. Everything is drawn from the caller's
``numpy.random.Generator`` in a fixed order, so a seed gives the same atlas.
"""

from __future__ import annotations

import cv2
import numpy as np

from uavcal_jax.sim.scene import CAR
from uavcal_jax.sim.vehicles import Vehicle

__all__ = ["DETAIL_SIZE", "DETAIL_TEXEL", "detail_quads", "face_atlas", "normalise", "pack_quads",
           "target_faces", "value_noise"]

#: Fine detail texture: DETAIL_SIZE x DETAIL_SIZE texels (a power of two), tiled at
#: DETAIL_TEXEL metres per texel on every face.
DETAIL_SIZE = 512
DETAIL_TEXEL = 0.004

#: Palette (RGB in [0, 1]) a person's shirt is drawn from (car paints:
#: :data:`uavcal_jax.sim.vehicles.PAINTS`).
_SHIRT_COLOURS = np.array(
    [
        [0.85, 0.15, 0.45], [0.1, 0.6, 0.85], [0.95, 0.85, 0.2], [0.2, 0.75, 0.3],
        [0.95, 0.5, 0.1], [0.55, 0.2, 0.75], [0.9, 0.9, 0.9], [0.8, 0.1, 0.1],
    ]
)  # fmt: skip


def value_noise(rng, h, w, texel, periods_m, beta) -> np.ndarray:
    """(h, w) float32 value noise: one octave per period in ``periods_m`` (metres, at
    ``texel`` metres per texel), weighted ``period ** beta``; zero mean, unnormalised."""
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


def normalise(img: np.ndarray, lo_q=1.0, hi_q=99.0) -> np.ndarray:
    """``img`` mapped so that its ``lo_q`` and ``hi_q`` percentiles become 0 and 1, clipped."""
    lo, hi = np.percentile(img[:: max(1, img.shape[0] // 256), :: max(1, img.shape[1] // 256)],
                           [lo_q, hi_q])  # fmt: skip
    out = (img - lo) / max(hi - lo, 1e-6)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _surface_texture(rng, h, w, texel) -> np.ndarray:
    """Rich, non-repeating luminance texture for a hall or obstacle face."""
    periods = [0.04, 0.08, 0.16, 0.32, 0.64, 1.28, 2.56]
    img = value_noise(rng, h, w, texel, periods, beta=rng.uniform(0.05, 0.4))
    _decorate(rng, img, texel, area_density=rng.uniform(0.6, 1.5))
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    return normalise(img)


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
    return normalise(img, 0.5, 99.5)


def _vehicle_texture(rng, vehicle: Vehicle, h, w, texel, axis, side) -> np.ndarray:
    """A vehicle face's luminance (body colour B high, glass and tyres near A = 0): glass,
    roof and cargo box where the vehicle's kind puts them, dark wheels on the long sides, a
    darker rim where the body curves away from the light. Texel coordinates map to the box's
    local ``x`` (0 rear .. 1 front), ``y``, ``z`` (0 bottom .. 1 top)."""
    iu, iv = _face_axes(axis)
    coord = [None, None, None]
    coord[iu] = np.broadcast_to(np.linspace(0.0, 1.0, w)[None, :], (h, w))
    coord[iv] = np.broadcast_to(np.linspace(0.0, 1.0, h)[:, None], (h, w))
    coord[axis] = np.full((h, w), float(side))
    x, y, z = coord
    L, W, H = 2.0 * vehicle.half
    g0, g1, g2, g3 = vehicle.kind.glass
    if axis == 2 and side == 0:
        return np.full((h, w), 0.03, np.float32)  # underside
    raw = value_noise(rng, h, w, texel, [0.06, 0.25], 0.3)
    noise = np.clip(0.5 + raw / (4.0 * float(raw.std()) + 1e-6), 0.0, 1.0)  # ~[0, 1]
    lum = 0.82 + 0.18 * noise  # paint: near uniform, a little mottled
    glass = 0.1 + 0.12 * noise
    cargo = x < vehicle.kind.cargo
    if vehicle.kind.cargo > 0:
        lum = np.where(cargo, np.minimum(lum + 0.1, 1.0), 0.6 * lum)  # cab darker than box
    belt = float(np.clip(1.0 / H, 0.45, 0.7))  # window sill about 1 m up
    if axis == 2:  # roof: rear window and windshield across the inner width
        inner = np.abs(y - 0.5) < 0.5 - 0.12 / W
        panes = ((x >= g0) & (x < g1)) | ((x >= g2) & (x < g3))
        lum = np.where(inner & panes, glass, lum)
        rim = np.minimum(np.minimum(x, 1 - x) * L, np.minimum(y, 1 - y) * W) < 0.1
        lum = np.where(rim & ~(inner & panes), 0.7 * lum, lum)
    elif axis == 1:  # long sides: windows above the sill, wheels below
        lum = np.where((x >= g0) & (x < g3) & (z > belt) & (z < 0.94), glass, lum)
        r = 0.5 if L > 6.0 else 0.32
        for xc in (min(0.9 + r, 0.3 * L), max(L - 0.9 - r, 0.7 * L)):
            tyre = (x * L - xc) ** 2 + (z * H - r) ** 2 < r * r
            lum = np.where(tyre, 0.04 + 0.05 * noise, lum)
    else:  # front (side 1) and back: windshield / rear window above the sill
        has = (g3 < 0.995) if side == 1 else (g0 < g1 and vehicle.kind.cargo == 0)
        if has:
            inner = np.abs(y - 0.5) < 0.5 - 0.1 / W
            lum = np.where(inner & (z > belt) & (z < 0.94), glass, lum)
        lum = np.where(z < 0.12 / H, 0.15 * noise, lum)  # bumper shadow, tyres
    return lum.astype(np.float32)


def _person_texture(rng, h, w, texel, z_rows) -> np.ndarray:
    """A person's pattern in texture space. ``z_rows`` (h, w) is the height of every texel
    above the box's bottom, normalised to [0, 1] (all equal on top/bottom faces)."""
    raw = value_noise(rng, h, w, texel, [0.02, 0.05, 0.12, 0.3], 0.3)
    _decorate(rng, raw, texel, area_density=0.5)  # dirt, stickers, decals
    noise = normalise(raw)
    # shirt (B, high) above the waist, trousers (A, low) below, head at the top
    lum = np.where(z_rows > 0.5, 0.6 + 0.4 * noise, 0.05 + 0.35 * noise)
    lum = np.where(z_rows > 0.87, 0.55 + 0.1 * noise, lum)
    return lum.astype(np.float32)


def pack_quads(tex: np.ndarray, wrap: bool = False) -> np.ndarray:
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


def target_faces(rng: np.random.Generator, cls: int, half, vehicle: Vehicle | None,
                 texel: float) -> list[tuple[np.ndarray, float, float, np.ndarray, np.ndarray]]:
    """A target's six faces in the atlas' face order (``2 axis + side``): ``(texture (nv, nu)
    in [0, 1], half_u, half_v, colour A, colour B)`` each, ``texel`` metres per texel; a car
    is painted as its ``vehicle``, a person (``vehicle=None``) as shirt over trousers."""
    if cls == CAR:
        a_rgb, b_rgb = np.array([0.03, 0.03, 0.04]), vehicle.color
    else:
        a_rgb = np.array([0.1, 0.12, 0.3]) * rng.uniform(0.6, 1.2)  # trousers
        b_rgb = _SHIRT_COLOURS[rng.integers(len(_SHIRT_COLOURS))]
    out = []
    for axis in range(3):
        iu, iv = _face_axes(axis)
        for side in range(2):
            nu = int(np.ceil(2 * half[iu] / texel)) + 2
            nv = int(np.ceil(2 * half[iv] / texel)) + 2
            a_face, b_face = a_rgb, b_rgb
            if cls == CAR:
                tex = _vehicle_texture(rng, vehicle, nv, nu, texel, axis, side)
            elif axis == 2 and side == 1:
                a_face, b_face = a_rgb, np.array([0.35, 0.22, 0.12])  # hair
                tex = np.full((nv, nu), 0.8, np.float32)
            else:
                # height of every texel above the box bottom, in [0, 1]
                if axis == 0:  # rows are z
                    z = np.repeat(np.linspace(0, 1, nv)[:, None], nu, axis=1)
                elif axis == 1:  # columns are z
                    z = np.repeat(np.linspace(0, 1, nu)[None, :], nv, axis=0)
                else:
                    z = np.full((nv, nu), float(side))
                tex = _person_texture(rng, nv, nu, texel, z)
            out.append((tex, float(half[iu]), float(half[iv]), a_face, b_face))
    return out


def face_atlas(rng: np.random.Generator, static_half, texel: float, targets,
               target_texel: float, target_rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Textures and colours of every face: the static boxes' (hall first), then the targets'.

    Faces are ordered ``6 k + 2 axis + (1 if the + side)`` for box ``k`` (the targets follow
    the static boxes), the layout :class:`~uavcal_jax.sim.scene.Scene` documents.

    Args:
        rng: draws every static box's texture and colour, boxes in order.
        static_half: (3,) half extents of each static box, metres; box 0 is the hall (tinted
            paler than the obstacles).
        texel: metres per texel on the static boxes.
        targets: ``(class_id, (3,) half extents, vehicle)`` per target; ``vehicle`` a
            :class:`~uavcal_jax.sim.vehicles.Vehicle` for a car (its ``half`` is the
            target's), ``None`` for a person.
        target_texel: metres per texel on the targets.
        target_rng: draws the targets' textures and colours.

    Returns:
        ``texture (N,) uint32`` packed quads, ``face_tex (F, 6) float32`` (offset, n_u, n_v,
        1/texel, half_u, half_v) and ``face_color (F, 2, 3) float32`` colours A and B in [0, 1].
    """
    chunks: list[np.ndarray] = []
    face_tex, face_color = [], []
    offset = 0

    def add_face(tex: np.ndarray, texel_: float, hu: float, hv: float, a_rgb, b_rgb):
        nonlocal offset
        chunks.append(pack_quads(tex))
        face_tex.append([offset, tex.shape[1], tex.shape[0], 1.0 / texel_, hu, hv])
        face_color.append([a_rgb, b_rgb])
        offset += tex.size

    for k, half in enumerate(static_half):
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

    for cls, half, vehicle in targets:
        for tex, hu, hv, a_face, b_face in target_faces(target_rng, cls, half, vehicle,
                                                        target_texel):
            add_face(tex, target_texel, hu, hv, a_face, b_face)
    return (np.concatenate(chunks), np.array(face_tex, np.float32),
            np.clip(np.array(face_color, np.float32), 0.0, 1.0))


def detail_quads(rng: np.random.Generator) -> np.ndarray:
    """(DETAIL_SIZE ** 2,) uint32 packed quads of the seamless detail texture (wrapped)."""
    return pack_quads(_detail_texture(rng), wrap=True)
