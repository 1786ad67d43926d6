"""Fixed-duration training windows over one sequence's frames and IMU samples.

The calibrator (Avola et al. 2023) reads windows of ``duration`` seconds (10 s) taken every
``stride`` seconds (1 s); each frame is paired with the IMU sample *nearest in time*.

Memory layout: the camera's frames are loaded and resized **once per sequence** (default
320x180, ``cv2.INTER_AREA``) into one array ``frames (F, H, W[, 3]) uint8``; a window is a row
of ``frame_index (n_windows, T) int32`` into it, so overlapping windows share frames instead of
copying them (1,000 windows of 200 frames with stride 1 s hold each frame once, not 10 times).
:meth:`WindowSet.window` returns a *view* of ``frames`` when the window is a full run of
consecutive frames; :meth:`WindowSet.batch` gathers copies, ready for a model.

Window rule (all in integer nanoseconds): the usable span is where the camera and the IMU
overlap, ``[t_lo, t_hi]``. Window ``k`` starts at ``s_k = t_lo + k * stride`` and holds the
frames with ``s_k <= t < s_k + duration``; it exists while its last nominal frame time
``s_k + duration - P`` is at most ``t_hi + P/2`` (``P`` the nominal frame period), so a
recording of ``N`` frames (``N * P`` seconds) gives ``floor((N * P - duration) / stride) + 1``
windows (30 s at 20 Hz, 10 s windows, 1 s stride: 21). ``T = frames_per_window`` is
``round(duration * rate_hz)`` (nominal rate from the calibration, else measured), and each
frame goes to its nominal slot ``round((t - s_k) / P)`` (if clock jitter puts two frames in one
slot, the earlier one is kept).

Missing frames (dropped by the camera or by the reader) are **padded**: their slot's
``frame_index`` is ``-1`` and ``frame_mask`` is ``False``, so the other frames keep their
place in time; gathers fill such slots with zero pixels, zero IMU values and ``t_ns = -1``.
Windows with fewer than ``min_valid_fraction * T`` real frames are skipped.

``frame_step = k`` keeps every ``k``-th slot of each window (its frames and their nearest IMU
samples, at ``rate / k``; ``T = ceil(round(duration * rate) / k)``): a cheaper model input
over the same span. Frames no window keeps are not decoded.

Motion inputs (issue 20; off by default, nothing changes then):

- ``WindowConfig.imu_sampling = "interval_mean"``: each used frame gets the mean of the IMU
  samples ``t_f - frame_step * P < t <= t_f`` (since the previous frame slot's nominal time)
  instead of the nearest sample (a frame with no sample there keeps the nearest one).
- ``WindowConfig.rotations``: ``WindowSet.frame_R (F, 3, 3)``, a body (IMU-frame)
  orientation per used frame, world-from-body up to one unknown rotation per *segment*
  (``frame_R_segment (F,)``, ``-1``: no orientation), so that the body rotation from frame
  ``j`` to frame ``i`` of one segment is ``frame_R[i].T @ frame_R[j]``. ``"oracle"``: the
  ground truth's orientation slerped at the frame times (one segment; frames outside the
  ground truth: ``-1``). ``"visual"``: the camera's relative rotations (``make_windows``'
  ``visual_rotations``) chained along the stream; a frame with no valid pair from an earlier
  frame starts a new segment, so intervals across a failed pair are invalid.

One module over 450 lines, one job: cutting a recording into windows and the per-frame
and per-window arrays they index (IMU, rotations, tilt labels, the metric start); the
interval inputs live in :mod:`uavcal_jax.data.window_motion`, the alignment behind the metric
start in :mod:`uavcal_jax.data.window_alignment`.
"""

from __future__ import annotations

import dataclasses
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from uavcal_jax.data.sequence import FrameStream, Sequence
from uavcal_jax.data.timing import measured_rate_hz
from uavcal_jax.data.true_offset import sensor_bias
from uavcal_jax.data.window_alignment import window_accel_starts
from uavcal_jax.data.window_motion import (
    chain_orientations,
    interval_mean_imu,
    interval_motion,
    oracle_orientations,
)
from uavcal_jax.errors import DataError
from uavcal_jax.imu.noise import EUROC_ADIS16448

#: ``WindowConfig.rotations``, ``WindowConfig.imu_sampling`` and ``WindowConfig.accel_start``
#: values.
ROTATION_SOURCES = ("none", "oracle", "visual")
IMU_SAMPLINGS = ("nearest", "interval_mean")
ACCEL_STARTS = ("none", "alignment")
#: The window-level arrays of ``accel_start="alignment"`` (:meth:`WindowSet.motion` adds them).
ALIGNMENT_KEYS = ("accel_start", "accel_response", "accel_start_std")


@dataclass(frozen=True)
class WindowConfig:
    """How to cut a sequence into windows.

    Attributes:
        duration: window length, seconds (paper: 10).
        stride: offset between window starts, seconds (paper: 1).
        size: output frame size ``(width, height)`` (default 320x180).
        camera: which camera stream.
        color: ``"gray"`` (F, H, W) or ``"rgb"`` (F, H, W, 3).
        interpolation: OpenCV resize interpolation (``cv2.INTER_AREA``).
        min_valid_fraction: skip windows with fewer real frames than this fraction of ``T``.
        frame_step: keep every ``frame_step``-th frame slot (1: every frame).
        workers: threads used to decode frames (``None``: all CPUs).
        rotations: body orientations per frame (module docstring): ``"none"``, ``"oracle"``
            (ground truth) or ``"visual"`` (the camera's relative rotations, given to
            :func:`make_windows`).
        imu_sampling: ``"nearest"`` (the paper: the IMU sample nearest each frame) or
            ``"interval_mean"`` (the mean of the samples since the previous frame slot).
        accel_start: ``"none"`` or ``"alignment"``: each window's accelerometer bias from a
            visual-inertial alignment of the recording's VIO trajectory around it
            (:mod:`uavcal_jax.data.window_alignment`; :func:`make_windows`' ``vio_poses``).
        alignment_span: seconds of that alignment, centred on the window (``None``: the
            window's own ``duration``).
    """

    duration: float = 10.0
    stride: float = 1.0
    size: tuple[int, int] = (320, 180)
    camera: str = "cam0"
    color: str = "gray"
    interpolation: int = cv2.INTER_AREA
    min_valid_fraction: float = 0.5
    frame_step: int = 1
    workers: int | None = None
    rotations: str = "none"
    imu_sampling: str = "nearest"
    accel_start: str = "none"
    alignment_span: float | None = None

    def __post_init__(self) -> None:
        if self.alignment_span is not None and not self.alignment_span > 0:
            raise ValueError(f"alignment_span must be > 0 s, got {self.alignment_span}")
        if self.accel_start not in ACCEL_STARTS:
            raise ValueError(f"accel_start must be one of {ACCEL_STARTS}, "
                             f"got {self.accel_start!r}")
        if self.rotations not in ROTATION_SOURCES:
            raise ValueError(f"rotations must be one of {ROTATION_SOURCES}, "
                             f"got {self.rotations!r}")
        if self.imu_sampling not in IMU_SAMPLINGS:
            raise ValueError(f"imu_sampling must be one of {IMU_SAMPLINGS}, "
                             f"got {self.imu_sampling!r}")
        if self.duration <= 0 or self.stride <= 0:
            raise ValueError("duration and stride must be positive")
        if self.frame_step < 1:
            raise ValueError(f"frame_step must be >= 1, got {self.frame_step}")
        if self.color not in ("gray", "rgb"):
            raise ValueError(f"color must be 'gray' or 'rgb', got {self.color!r}")
        if len(self.size) != 2 or min(self.size) <= 0:
            raise ValueError(f"size must be (width, height), got {self.size}")


def nearest_index(t_query: np.ndarray, t_ref: np.ndarray) -> np.ndarray:
    """For each query time, the index of the nearest reference time (ties: the earlier).

    Both arrays int64 (or float); ``t_ref`` sorted ascending and non-empty.
    """
    t_query = np.asarray(t_query)
    t_ref = np.asarray(t_ref)
    if t_ref.shape[0] == 0:
        raise ValueError("no reference times")
    j = np.searchsorted(t_ref, t_query, side="left")
    j = np.clip(j, 1, max(t_ref.shape[0] - 1, 1))
    if t_ref.shape[0] == 1:
        return np.zeros(t_query.shape, dtype=np.int64)
    before, after = t_ref[j - 1], t_ref[j]
    pick_before = np.abs(t_query - before) <= np.abs(after - t_query)
    return np.where(pick_before, j - 1, j).astype(np.int64)


def load_frames(stream: FrameStream, indices: np.ndarray | None = None, *,
                size: tuple[int, int] | None = (320, 180), color: str = "gray",
                interpolation: int = cv2.INTER_AREA, workers: int | None = None) -> np.ndarray:
    """Load (and resize) frames of ``stream`` into one uint8 array, decoding in threads.

    Returns (N, H, W) for gray, (N, H, W, 3) for RGB; ``size`` is ``(width, height)`` or
    ``None`` to keep the stream's own size.
    """
    idx = np.arange(len(stream)) if indices is None else np.asarray(indices, dtype=np.int64)

    def one(i: int) -> np.ndarray:
        img = stream.load(int(i), color)
        if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
            img = cv2.resize(img, tuple(size), interpolation=interpolation)
        return img

    if idx.size == 0:
        w, h = size if size is not None else stream.calibration.resolution
        return np.zeros((0, h, w) + ((3,) if color == "rgb" else ()), np.uint8)
    first = one(int(idx[0]))
    out = np.empty((idx.size, *first.shape), dtype=np.uint8)
    out[0] = first

    def fill(k: int) -> None:
        img = one(int(idx[k]))
        if img.shape != first.shape:
            raise DataError(f"frame {int(idx[k])} has shape {img.shape}, frame {int(idx[0])} "
                            f"has {first.shape}", stream.paths[idx[k]] if stream.paths else None)
        out[k] = img

    n_workers = workers or min(16, os.cpu_count() or 1)
    if n_workers <= 1 or idx.size < 8:
        for k in range(1, idx.size):
            fill(k)
    else:
        with ThreadPoolExecutor(n_workers) as pool:
            list(pool.map(fill, range(1, idx.size)))
    return out


@dataclass(frozen=True)
class WindowSet:
    """Windows of one sequence as index arrays into shared per-sequence arrays.

    Attributes:
        config: the :class:`WindowConfig` used.
        name: the sequence name.
        frames: (F, H, W[, 3]) uint8, every used frame once, resized.
        frame_t_ns: (F,) int64 frame timestamps.
        imu_index: (F,) int32, nearest IMU sample of each frame.
        imu_t_ns, gyro, accel: the sequence's IMU arrays, (N,), (N, 3), (N, 3).
        start_ns: (n_windows,) int64 window start times.
        frame_index: (n_windows, T) int32 into ``frames``; ``-1`` marks a padded slot.
        frame_mask: (n_windows, T) bool, ``False`` on padded slots.
        imu_range: (n_windows, 2) int64 ``[first, stop)`` of all IMU samples inside the window
            (for consumers that want every sample, e.g. preintegration).
        sensor_bias: (n_windows, 6) float64, the ground truth's mean IMU bias over each window
            (gyro rad/s xyz, accel m/s^2 xyz; :func:`uavcal_jax.data.true_offset.sensor_bias`),
            the sensor's own share of the ``total`` label; ``None`` when the recording's ground
            truth has no bias columns.
        frame_imu: (F, 6) float64 gyro and accel of each used frame under ``interval_mean``
            sampling (``None``: the nearest sample, ``imu_index``).
        frame_R: (F, 3, 3) float64 body orientation per used frame (module docstring), or
            ``None`` when ``config.rotations`` is ``"none"``.
        frame_R_segment: (F,) int64 segment of each ``frame_R`` (``-1``: none).
        frame_up: (F, 3) float32 unit vector of gravity's reaction ("up", world +z) in the
            body frame at each used frame, from the ground truth's orientation (zero for a
            frame outside its span); ``None`` without ground truth. The label of the
            calibrator's tilt head (``ModelConfig.tilt_head``).
        accel_start, accel_response, accel_start_std: ``(n_windows, 3)``, ``(n_windows, 3,
            3)``, ``(n_windows, 3)`` float64, each window's metric accelerometer start
            (:class:`~uavcal_jax.data.window_alignment.WindowAlignment`) under
            ``config.accel_start="alignment"``; ``None`` otherwise.
    """

    config: WindowConfig
    name: str
    frames: np.ndarray
    frame_t_ns: np.ndarray
    imu_index: np.ndarray
    imu_t_ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    start_ns: np.ndarray
    frame_index: np.ndarray
    frame_mask: np.ndarray
    imu_range: np.ndarray
    sensor_bias: np.ndarray | None = None
    meta: dict = field(default_factory=dict, compare=False)
    frame_imu: np.ndarray | None = None
    frame_R: np.ndarray | None = None
    frame_R_segment: np.ndarray | None = None
    frame_up: np.ndarray | None = None
    accel_start: np.ndarray | None = None
    accel_response: np.ndarray | None = None
    accel_start_std: np.ndarray | None = None

    @property
    def frame_R_valid(self) -> np.ndarray | None:
        """(F,) bool, the frame has an orientation (``None`` without ``frame_R``)."""
        return None if self.frame_R_segment is None else self.frame_R_segment >= 0

    def __len__(self) -> int:
        return int(self.frame_index.shape[0])

    @property
    def frames_per_window(self) -> int:
        return int(self.frame_index.shape[1])

    def window(self, i: int) -> dict[str, np.ndarray]:
        """Arrays of window ``i``: ``frames (T, H, W[, 3])`` uint8 (a view of ``frames`` when
        the window is a full consecutive run), ``mask (T,)``, ``t_ns (T,)``, ``gyro (T, 3)``,
        ``accel (T, 3)``, ``imu_t_ns (T,)`` of the nearest IMU samples."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"window {i} out of range [0, {len(self)})")
        idx, mask = self.frame_index[i], self.frame_mask[i]
        if mask.all() and np.all(np.diff(idx) == 1):
            frames = self.frames[idx[0]: idx[-1] + 1]
        else:
            frames = np.where(_expand(mask, self.frames.ndim), self.frames[np.maximum(idx, 0)],
                              np.uint8(0))
        return {"frames": frames, **self._side(idx[None], mask[None], squeeze=True)}

    def batch(self, indices) -> dict[str, np.ndarray]:
        """Gathered copies for windows ``indices``: ``frames (B, T, H, W[, 3])`` uint8,
        ``mask (B, T)``, ``t_ns (B, T)``, ``gyro (B, T, 3)``, ``accel (B, T, 3)``,
        ``imu_t_ns (B, T)``, ``window (B,)``, and ``sensor_bias (B, 6)`` when the windows have
        it."""
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        idx, mask = self.frame_index[indices], self.frame_mask[indices]
        frames = self.frames[np.maximum(idx, 0)]
        frames[~mask] = 0
        return {"frames": frames, **self._side(idx, mask), "window": indices,
                **self._bias(indices)}

    def samples(self, indices=None) -> dict[str, np.ndarray]:
        """:meth:`batch` without the frames (cheap for every window of a long sequence,
        whose frames a consumer reads through ``frame_index`` instead); ``indices``
        ``None``: all windows."""
        indices = (np.arange(len(self)) if indices is None
                   else np.asarray(indices, dtype=np.int64).reshape(-1))
        return {**self._side(self.frame_index[indices], self.frame_mask[indices]),
                "window": indices, **self._bias(indices)}

    def subset(self, indices) -> WindowSet:
        """The windows ``indices`` (any integer array, in its order) as a WindowSet of their
        own; ``frames`` and the IMU arrays are shared, not copied."""
        idx = np.asarray(indices, np.int64)

        def rows(a):
            return None if a is None else a[idx]

        return dataclasses.replace(self, start_ns=self.start_ns[idx],
                                   frame_index=self.frame_index[idx],
                                   frame_mask=self.frame_mask[idx], imu_range=self.imu_range[idx],
                                   sensor_bias=rows(self.sensor_bias),
                                   **{k: rows(getattr(self, k)) for k in ALIGNMENT_KEYS})

    @property
    def interval_cap(self) -> int:
        """Static bound ``S`` on the IMU samples of one frame interval in :meth:`motion`:
        the frame interval over the median IMU period, plus 2 (the sample running at the
        interval's start, and jitter)."""
        period_ns = 1e9 / float(self.meta["rate_hz"]) * int(self.meta.get("frame_step", 1))
        imu_dt = float(np.median(np.diff(self.imu_t_ns))) if self.imu_t_ns.size > 1 else 1.0
        return int(np.ceil(period_ns / max(imu_dt, 1.0))) + 2

    def motion(self, indices, cap: int | None = None) -> dict[str, np.ndarray]:
        """Per frame interval inputs of windows ``indices`` (needs ``frame_R``). Interval
        ``k`` of a window is ``[t_{k-1}, t_k)`` between its slots ``k - 1`` and ``k``
        (slot 0 has none: all zero, invalid).

        Returns:
            ``gyro_seq (B, T, S, 3)`` float32, rad/s: the gyro samples that run during the
            interval (zero-order hold: sample ``i`` holds over ``[t_i, t_{i+1})``, from the
            one running at ``t_{k-1}`` to the last one starting before ``t_k``), zero-padded
            to ``S = cap`` (default :attr:`interval_cap`); ``dt_seq (B, T, S)`` float32,
            seconds: each sample's time inside the interval (they sum to ``t_k - t_{k-1}``;
            0 on padding); ``rot_cam (B, T, 3, 3)`` float32, the body rotation of the
            interval (body frame at ``t_{k-1}`` from ``t_k``: ``frame_R[i].T @
            frame_R[j]``; identity where invalid); ``rot_mask (B, T)`` bool, both slots real,
            both orientations of one segment and at most ``S`` samples. With
            ``accel_start="alignment"`` also :data:`ALIGNMENT_KEYS` (float32, per window).
        """
        out = interval_motion(self, indices, cap)
        if self.accel_start is not None:
            indices = np.asarray(indices, dtype=np.int64).reshape(-1)
            out.update({k: getattr(self, k)[indices].astype(np.float32)
                        for k in ALIGNMENT_KEYS})
        return out

    def up(self, indices) -> np.ndarray:
        """``(B, T, 3)`` float32 :attr:`frame_up` at the slots of windows ``indices``, zero
        on padded slots and frames without ground truth (a zero vector marks "no label").

        Raises:
            ValueError: the windows have no ground-truth orientation (``frame_up`` None).
        """
        if self.frame_up is None:
            raise ValueError(f"{self.name}: no ground-truth orientation (frame_up)")
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        idx, mask = self.frame_index[indices], self.frame_mask[indices]
        return np.where(mask[..., None], self.frame_up[np.maximum(idx, 0)], np.float32(0.0))

    def _bias(self, indices: np.ndarray) -> dict:
        return {} if self.sensor_bias is None else {"sensor_bias": self.sensor_bias[indices]}

    def _side(self, idx: np.ndarray, mask: np.ndarray, squeeze: bool = False) -> dict:
        safe = np.maximum(idx, 0)
        imu = self.imu_index[safe]
        if self.frame_imu is None:
            gyro, accel = self.gyro[imu], self.accel[imu]
        else:
            gyro, accel = self.frame_imu[safe, :3], self.frame_imu[safe, 3:]
        out = {
            "mask": mask.copy(),
            "t_ns": np.where(mask, self.frame_t_ns[safe], -1),
            "gyro": np.where(mask[..., None], gyro, 0.0),
            "accel": np.where(mask[..., None], accel, 0.0),
            "imu_t_ns": np.where(mask, self.imu_t_ns[imu], -1),
        }
        if squeeze:
            out = {k: v[0] for k, v in out.items()}
        return out


def _expand(mask: np.ndarray, ndim: int) -> np.ndarray:
    return mask.reshape(mask.shape + (1,) * (ndim - 1))


def window_starts(t_lo: int, t_hi: int, duration_ns: int, stride_ns: int,
                  period_ns: int) -> np.ndarray:
    """Window start times (see the module docstring's rule)."""
    span = t_hi + period_ns // 2 - t_lo - (duration_ns - period_ns)
    if span < 0:
        return np.zeros(0, np.int64)
    return t_lo + np.arange(span // stride_ns + 1, dtype=np.int64) * stride_ns


def make_windows(sequence: Sequence, config: WindowConfig = WindowConfig(), *,
                 frames: np.ndarray | None = None, visual_rotations=None,
                 vio_poses=None) -> WindowSet:
    """Cut ``sequence`` into windows (see the module docstring).

    Args:
        frames: optional pre-loaded frames of the whole camera stream (one per frame, already
            at ``config.size``); by default they are loaded from the stream.
        visual_rotations: under ``config.rotations == "visual"``, the camera's relative body
            rotations (a ``VisualRotations``-like tuple with ``t0_ns``, ``t1_ns`` (K,),
            ``R`` (K, 3, 3) body frame at ``t0`` from ``t1``, ``valid`` (K,)).
        vio_poses: under ``config.accel_start == "alignment"``, the recording's VIO
            trajectory (a :class:`~uavcal_jax.vio.pose_cache.VioPoses`-like tuple).

    Raises:
        DataError: no IMU, no such camera, or the sequence is shorter than one window.
    """
    where = sequence.root if sequence.root is not None else sequence.name
    if sequence.imu is None or len(sequence.imu) == 0:
        raise DataError("sequence has no IMU samples; windows need them", where)
    stream = sequence.camera(config.camera)
    if len(stream) == 0:
        raise DataError(f"camera {config.camera!r} has no frames", where)
    imu = sequence.imu
    t_cam = np.asarray(stream.t_ns, np.int64)
    rate = stream.calibration.rate_hz
    if not (rate and np.isfinite(rate) and rate > 0):
        rate = measured_rate_hz(t_cam)
    if not rate:
        raise DataError(f"camera {config.camera!r}: cannot tell its frame rate", where)
    period_ns = int(round(1e9 / rate))
    duration_ns = int(round(config.duration * 1e9))
    stride_ns = int(round(config.stride * 1e9))
    T = int(round(config.duration * rate))

    t_lo = max(int(t_cam[0]), int(imu.t_ns[0]))
    t_hi = min(int(t_cam[-1]), int(imu.t_ns[-1]))
    starts = window_starts(t_lo, t_hi, duration_ns, stride_ns, period_ns)
    if starts.size == 0:
        raise DataError(
            f"sequence too short for one {config.duration:g} s window: camera and IMU overlap "
            f"for {(t_hi - t_lo) * 1e-9:.3f} s", where)

    # Frames of each window, [s, s + duration), each in its nominal slot round((t - s) / P).
    first = np.searchsorted(t_cam, starts, side="left")
    stop = np.searchsorted(t_cam, starts + duration_ns, side="left")
    cam_index = np.full((starts.size, T), -1, dtype=np.int64)
    for w in range(starts.size):
        idx = np.arange(first[w], stop[w])
        slots = np.clip(np.rint((t_cam[idx] - starts[w]) / period_ns).astype(np.int64), 0, T - 1)
        slots, pos = np.unique(slots, return_index=True)  # jitter collisions: first frame wins
        cam_index[w, slots] = idx[pos]
    cam_index = cam_index[:, ::config.frame_step]
    T = cam_index.shape[1]
    mask = cam_index >= 0
    keep = mask.sum(axis=1) >= max(1, int(np.ceil(config.min_valid_fraction * T)))
    starts, cam_index, mask = starts[keep], cam_index[keep], mask[keep]
    if starts.size == 0:
        raise DataError(f"no window has at least {config.min_valid_fraction:.0%} of its "
                        f"{T} frames", where)

    # Frames actually used, loaded once; window rows index into them.
    used = np.unique(cam_index[mask])
    if frames is None:
        frame_arr = load_frames(stream, used, size=config.size, color=config.color,
                                interpolation=config.interpolation, workers=config.workers)
    else:
        if frames.shape[0] != len(stream):
            raise ValueError(f"frames has {frames.shape[0]} entries, stream has {len(stream)}")
        frame_arr = np.ascontiguousarray(frames[used])
    remap = np.full(len(stream), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    frame_index = np.where(mask, remap[np.maximum(cam_index, 0)], -1)

    frame_t = t_cam[used]
    imu_index = nearest_index(frame_t, imu.t_ns).astype(np.int32)
    imu_range = np.stack([np.searchsorted(imu.t_ns, starts, side="left"),
                          np.searchsorted(imu.t_ns, starts + duration_ns, side="left")], axis=1)
    bias = [sensor_bias(sequence.ground_truth, s, s + duration_ns - 1) for s in starts]
    frame_imu = None
    if config.imu_sampling == "interval_mean":
        frame_imu = interval_mean_imu(frame_t, config.frame_step * period_ns, imu.t_ns,
                                      np.concatenate([imu.gyro, imu.accel], axis=1), imu_index)
    frame_R = frame_seg = frame_up = None
    if sequence.ground_truth is not None:
        true_R, true_seg = oracle_orientations(sequence.ground_truth, frame_t)
        # R is world-from-body: up (world +z) in the body frame is R^T e_z, R's third row
        frame_up = np.where((true_seg >= 0)[:, None], true_R[:, 2, :], 0.0).astype(np.float32)
    if config.rotations == "oracle":
        if sequence.ground_truth is None:
            raise DataError("rotations='oracle' needs the recording's ground truth", where)
        frame_R, frame_seg = true_R, true_seg
    elif config.rotations == "visual":
        if visual_rotations is None:
            raise DataError("rotations='visual' needs the camera's relative rotations "
                            "(make_windows' visual_rotations)", where)
        # Chain along every frame of the stream (a used frame's predecessor may be unused).
        all_R, all_seg = chain_orientations(t_cam, visual_rotations)
        frame_R, frame_seg = all_R[used], all_seg[used]
    alignment = {}
    if config.accel_start == "alignment":
        if vio_poses is None:
            raise DataError("accel_start='alignment' needs the recording's VIO trajectory "
                            "(make_windows' vio_poses)", where)
        noise = (sequence.imu_calibration.noise if sequence.imu_calibration is not None
                 else EUROC_ADIS16448)
        span_ns = (None if config.alignment_span is None
                   else int(round(config.alignment_span * 1e9)))
        found = window_accel_starts(vio_poses, imu.t_ns, imu.gyro, imu.accel, starts,
                                    duration_ns, span_ns, noise)
        alignment = dict(zip(ALIGNMENT_KEYS, found, strict=True))
    return WindowSet(
        config=config, name=sequence.name, frames=frame_arr, frame_t_ns=frame_t,
        imu_index=imu_index, imu_t_ns=imu.t_ns, gyro=imu.gyro, accel=imu.accel,
        start_ns=starts, frame_index=frame_index.astype(np.int32), frame_mask=mask,
        imu_range=imu_range.astype(np.int64),
        sensor_bias=None if any(b is None for b in bias) else np.stack(bias),
        meta={"camera": config.camera, "rate_hz": rate, "frames_per_window": T,
              "frame_step": config.frame_step},
        frame_imu=frame_imu, frame_R=frame_R, frame_R_segment=frame_seg, frame_up=frame_up,
        **alignment,
    )
