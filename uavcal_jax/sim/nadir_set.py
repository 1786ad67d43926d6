"""Nadir still frames over street scenes, written as a YOLO detection data set.

Each frame is its own :func:`~uavcal_jax.sim.street_scene.street_scene` (seed ``seed + i``)
seen by a colour camera looking straight down (tilted up to :data:`MAX_TILT_DEG`) from an
altitude uniform in ``altitude`` metres, yawed at random. The scene is sized to the frame's
footprint and textured at its ground sample distance, so the cost per frame hardly depends on
the altitude. The render goes through a little defocus and motion blur (a drone drifting
during the exposure) and the simulator's sensor model (:func:`uavcal_jax.sim.sensor.
sensor_image`: shot and read noise, gain, rounding) with an exposure set by a simple
auto-exposure (the frame's mean near :data:`AE_TARGET`) and jittered per frame.

Labels are the tight boxes of each target's visible pixels
(:func:`~uavcal_jax.sim.target_boxes.target_boxes`): exact, whatever the vehicle's shape.
Targets with fewer than :data:`MIN_PIXELS` visible pixels are left out (a sliver at the
frame's edge).

The folder (ultralytics layout: ``images/NNNNN.png``, ``labels/NNNNN.txt`` with
``class cx cy w h`` normalised, ``classes.txt``) reads with
``uavcal_jax.detect.datasets.load_dataset(out_dir, "yolo")``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from uavcal_jax.geometry import camera as camera_model
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.sim.render import render
from uavcal_jax.sim.scene import CLASS_NAMES
from uavcal_jax.sim.sensor import (
    FULL_SCALE_ELECTRONS,
    SCENE_ELECTRONS_PER_S,
    SensorModel,
    sensor_image,
)
from uavcal_jax.sim.street_scene import street_scene
from uavcal_jax.sim.target_boxes import target_boxes

__all__ = ["MAX_TILT_DEG", "MIN_PIXELS", "nadir_camera", "nadir_frame", "nadir_pose",
           "nadir_street_set"]

#: Largest tilt of the optical axis from straight down, degrees.
MAX_TILT_DEG = 5.0
#: Fewest visible pixels of a labelled target.
MIN_PIXELS = 12
#: Mean image level (a fraction of full scale) the auto-exposure aims at.
AE_TARGET = 0.45


def nadir_camera(resolution=(1280, 720), hfov_deg: float = 70.0) -> camera_model.PinholeRadtan:
    """A distortion-free colour camera of ``resolution`` (width, height) and horizontal
    field of view ``hfov_deg``; the focal length is ``0.5 width / tan(hfov / 2)`` pixels."""
    w, h = (int(v) for v in resolution)
    f = 0.5 * w / np.tan(np.radians(hfov_deg) / 2)
    return camera_model.PinholeRadtan.create(jnp.array([f, f, 0.5 * w - 0.5, 0.5 * h - 0.5]),
                                             jnp.zeros(4), (w, h))


def nadir_pose(xy, altitude: float, yaw: float, tilt=(0.0, 0.0)) -> np.ndarray:
    """(4, 4) ``T_WC`` of a camera at ``(x, y, altitude)`` looking down (world -z), its image
    x axis at ``yaw`` (radians) in the ground plane, then tilted by ``tilt`` (radians about
    the camera's x and y axes)."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])  # columns: x, y, z axes
    ax, ay = tilt
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    T = np.eye(4)
    T[:3, :3] = R @ Rx @ Ry
    T[:3, 3] = [xy[0], xy[1], altitude]
    return T


def _blur(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Defocus (Gaussian, sigma up to 0.7 px) and a straight motion streak (up to 3 px)."""
    sigma = rng.uniform(0.0, 0.7)
    if sigma > 0.2:
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    n = int(rng.integers(1, 4))
    if n > 1:
        k = np.zeros((n, n), np.float32)
        ang = rng.uniform(0, np.pi)
        c = 0.5 * (n - 1)
        for t in np.linspace(-c, c, 4 * n):
            k[int(round(c + t * np.sin(ang))), int(round(c + t * np.cos(ang)))] = 1.0
        img = cv2.filter2D(img, -1, k / k.sum())
    return img


def nadir_frame(seed: int, camera: camera_model.PinholeRadtan, altitude: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame: the street scene of ``seed`` seen from ``altitude`` metres.

    Returns:
        image (H, W, 3) uint8 RGB, boxes (n, 4) float32 ``x0, y0, x1, y1`` pixels and class
        ids (n,) int32 of the targets with at least :data:`MIN_PIXELS` visible pixels.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x7AD1]))
    f = float(camera.fx)
    w, h = camera.width, camera.height
    gsd = altitude / f
    # the footprint's half extents, grown for the tilt and the yaw, plus a margin
    half_diag = 0.5 * np.hypot(w, h) * gsd
    tilt_m = altitude * np.tan(np.radians(MAX_TILT_DEG)) * 1.5
    extent = np.full(2, half_diag + tilt_m + 3.0)
    scene = street_scene(int(rng.integers(1 << 31)), extent, gsd)
    tilt = np.radians(rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG, 2)) / np.sqrt(2)
    T = nadir_pose(rng.uniform(-3.0, 3.0, 2), altitude, rng.uniform(-np.pi, np.pi), tilt)
    out = render(scene, camera, T, 0.0, color="rgb")
    radiance = _blur(np.asarray(out.image, np.float32), rng)
    # auto-exposure: the frame's mean near AE_TARGET of full scale, give or take a quarter
    gain = np.clip(AE_TARGET / max(float(radiance.mean()), 1e-3), 0.7, 3.0)
    exposure = FULL_SCALE_ELECTRONS / SCENE_ELECTRONS_PER_S * gain * rng.uniform(0.8, 1.25)
    image = np.asarray(sensor_image(jnp.asarray(radiance), jax.random.PRNGKey(seed & 0x7FFFFFFF),
                                    SensorModel(exposure_s=exposure)))
    boxes, count = target_boxes(out.object_id, scene.n_targets)
    keep = np.asarray(count) >= MIN_PIXELS
    return (image, np.asarray(boxes)[keep],
            np.asarray(scene.targets.class_id)[keep].astype(np.int32))


def nadir_street_set(out_dir: str | Path, n_frames: int, seed: int = 0, *,
                     altitude=(20.0, 100.0), resolution=(1280, 720), hfov_deg: float = 70.0,
                     progress: bool = True) -> Path:
    """Render ``n_frames`` nadir street frames (module docstring) into a YOLO folder.

    Args:
        out_dir: the folder (created; existing frames of the same names are overwritten).
        n_frames: frames; frame ``i`` is :func:`nadir_frame` of seed ``seed + i``.
        seed: base seed.
        altitude: (min, max) metres, drawn uniformly per frame.
        resolution: (width, height) pixels.  hfov_deg: horizontal field of view.
        progress: show a progress bar.

    Returns:
        ``out_dir``, holding ``images/``, ``labels/``, ``classes.txt`` (the simulator's class
        names: car, person) and ``nadir_set.json`` (the arguments and seconds per frame).
    """
    root = Path(out_dir)
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "labels").mkdir(parents=True, exist_ok=True)
    (root / "classes.txt").write_text("".join(f"{n}\n" for n in CLASS_NAMES))
    cam = nadir_camera(resolution, hfov_deg)
    w, h = cam.width, cam.height
    t0 = time.perf_counter()
    for i in progress_bar(range(int(n_frames)), desc="nadir frames", enabled=progress,
                          unit="frame"):
        alt = np.random.default_rng([int(seed) + i, 0xA17]).uniform(*altitude)
        image, boxes, cls = nadir_frame(int(seed) + i, cam, float(alt))
        name = f"{i:05d}"
        cv2.imwrite(str(root / "images" / f"{name}.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        rows = [f"{c} {(b[0] + b[2]) / 2 / w:.6f} {(b[1] + b[3]) / 2 / h:.6f} "
                f"{(b[2] - b[0]) / w:.6f} {(b[3] - b[1]) / h:.6f}\n"
                for b, c in zip(boxes, cls, strict=True)]
        (root / "labels" / f"{name}.txt").write_text("".join(rows))
    seconds = time.perf_counter() - t0
    (root / "nadir_set.json").write_text(json.dumps(dict(
        n_frames=int(n_frames), seed=int(seed), altitude=list(altitude),
        resolution=[w, h], hfov_deg=hfov_deg,
        seconds_per_frame=round(seconds / max(int(n_frames), 1), 3)), indent=1))
    return root
