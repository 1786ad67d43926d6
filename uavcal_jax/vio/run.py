"""Run the stereo VIO over a whole recorded sequence (EuRoC folder or ROS bag, as read by
:mod:`uavcal_jax.data`), and the run's result: camera-rate trajectory, flags, timings, its
summary (with ATE/RPE against ground truth) and the rows of the per-frame table written
beside the trajectory (:meth:`VioResult.frame_rows`, the format
:mod:`uavcal_jax.data.vio_frames`).

Stereo pairing: a left frame is paired with the right frame of the same timestamp (within
``PAIR_TOLERANCE_NS``); a left frame without one is processed monocularly (no stereo
observations), a right frame without a left one is ignored. A left image that cannot be read
is processed as a dropped frame (no features; the estimator carries on with the IMU) and
counted in ``VioResult.unreadable``.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from uavcal_jax.data.sequence import GroundTruth, ImuData, Sequence
from uavcal_jax.errors import DataError, DataRepairWarning
from uavcal_jax.imu import remove_offset
from uavcal_jax.progress import progress
from uavcal_jax.vio.config import VioConfig, resolve_camera
from uavcal_jax.vio.estimator import StereoVio
from uavcal_jax.vio.frame_estimate import FrameEstimate
from uavcal_jax.vio.stage_timer import TIMING_KEYS
from uavcal_jax.vio.trajectory_metrics import trajectory_errors

__all__ = ["PAIR_TOLERANCE_NS", "VioResult", "estimate_stream", "one_blas_thread", "run_vio",
           "stereo_pairs"]

#: Largest left/right timestamp difference still paired as one stereo frame, ns.
PAIR_TOLERANCE_NS = 1_000_000


@dataclasses.dataclass(frozen=True)
class VioResult:
    """A VIO run: one :class:`~uavcal_jax.vio.frame_estimate.FrameEstimate` per left frame.

    Attributes:
        frames: the per-frame estimates.  resets: failure resets.
        unreadable: left images that could not be read (processed as dropped frames).
        config: the :class:`~uavcal_jax.vio.config.VioConfig` used (resolved against the
            left camera).  imu_offset: (6,) the offset removed.
    """

    frames: list[FrameEstimate]
    resets: int
    unreadable: int
    config: VioConfig
    imu_offset: np.ndarray

    def trajectory(self) -> GroundTruth:
        """The frames with a pose as a trajectory (body = IMU frame, world gravity-aligned),
        in the ground-truth container, ready for :func:`uavcal_jax.data.tum.write_tum`."""
        est = [f for f in self.frames if f.has_pose]
        if not est:
            return GroundTruth(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4)))
        q = Rotation.from_matrix(np.stack([f.rotation for f in est])).as_quat()  # x y z w
        return GroundTruth(np.array([f.t_ns for f in est], np.int64),
                           np.stack([f.position for f in est]), q[:, [3, 0, 1, 2]],
                           velocity=np.stack([f.velocity for f in est]),
                           bias_gyro=np.stack([f.bias_gyro for f in est]),
                           bias_accel=np.stack([f.bias_accel for f in est]))

    def timings(self) -> dict[str, np.ndarray]:
        """Milliseconds per frame of each stage (frames after the first, which compiles);
        ``total`` is the stages' sum, ``wall`` the wall-clock time per frame (less than
        ``total`` when the front end runs concurrently)."""
        keys = (*TIMING_KEYS, "wall")
        rows = [f.timings for f in self.frames[1:] if f.timings]
        return {k: np.array([r.get(k, 0.0) for r in rows]) for k in keys}

    def flags(self) -> dict[str, np.ndarray]:
        """Per-frame ``keyframe``, ``reset`` (bool), ``tracked``, ``stereo``, ``landmarks``
        (int) and ``status`` (str)."""
        return {
            "keyframe": np.array([f.keyframe for f in self.frames]),
            "reset": np.array([f.status == "reset" for f in self.frames]),
            "tracked": np.array([f.tracked for f in self.frames]),
            "stereo": np.array([f.stereo for f in self.frames]),
            "landmarks": np.array([f.landmarks for f in self.frames]),
            "status": np.array([f.status for f in self.frames]),
        }

    def frame_rows(self) -> list[tuple]:
        """The per-frame table's rows (:data:`~uavcal_jax.data.vio_frames.FRAME_COLUMNS`,
        written by :func:`~uavcal_jax.data.vio_frames.write_frames_csv`): each frame's flags,
        its cost and its timings in ms (0 for a stage it did not run)."""
        return [(f.t_ns, f.status, f.reason, f.keyframe, f.tracked, f.stereo, f.landmarks,
                 f.iterations, f.cost, *(f.timings.get(k, 0.0) for k in TIMING_KEYS))
                for f in self.frames]

    def summary(self, ground_truth: GroundTruth | None = None) -> dict:
        """JSON-ready counts, timings and, with ``ground_truth`` (and at least 3 poses),
        ATE/RPE (:func:`~uavcal_jax.vio.trajectory_metrics.trajectory_errors`).

        Keys: ``frames``, ``poses``, ``keyframes``, ``resets``, ``unreadable_frames``,
        ``nan_poses``, ``mean_tracked``, ``ms_per_frame`` (per stage of :meth:`timings`:
        ``mean`` and ``p95``, ``None`` without timed frames), ``imu_offset``; with ground
        truth also ``ate_m``, ``rpe_1m`` and the other keys of ``trajectory_errors``.
        """
        flags = self.flags()
        times = self.timings()
        traj = self.trajectory()
        out = {
            "frames": len(self.frames), "poses": len(traj),
            "keyframes": int(flags["keyframe"].sum()),
            "resets": self.resets, "unreadable_frames": self.unreadable,
            "nan_poses": int(sum(not np.all(np.isfinite(f.position)) for f in self.frames
                                 if f.has_pose)),
            "mean_tracked": float(np.mean(flags["tracked"])) if len(flags["tracked"]) else 0.0,
            "ms_per_frame": {k: {"mean": float(np.mean(v)) if len(v) else None,
                                 "p95": float(np.percentile(v, 95)) if len(v) else None}
                             for k, v in times.items()},
            "imu_offset": self.imu_offset.tolist(),
        }
        if ground_truth is not None and len(traj) >= 3:
            out |= trajectory_errors(traj, ground_truth)
        return out


def stereo_pairs(sequence: Sequence, left: str = "cam0", right: str = "cam1"
                 ) -> list[tuple[int, int, int | None]]:
    """``(t_ns, left index, right index or None)`` for every left frame, in time order."""
    cam0 = sequence.camera(left)
    t_r = sequence.cameras[right].t_ns if right in sequence.cameras else np.zeros(0, np.int64)
    out = []
    for i, t in enumerate(cam0.t_ns):
        j = int(np.searchsorted(t_r, t))
        best = None
        for k in (j - 1, j):
            if 0 <= k < len(t_r) and abs(int(t_r[k]) - int(t)) <= PAIR_TOLERANCE_NS:
                best = k
        out.append((int(t), i, best))
    return out


def _corrected_imu(imu: ImuData, offset: np.ndarray) -> ImuData:
    if not np.any(offset):
        return imu
    gyro, accel = remove_offset(imu.gyro, imu.accel, offset)
    return dataclasses.replace(imu, gyro=np.asarray(gyro, np.float64),
                               accel=np.asarray(accel, np.float64))


def run_vio(sequence: Sequence, config: VioConfig | None = None,
            imu_offset=None, *, show_progress: bool = False, max_frames: int | None = None,
            left: str = "cam0", right: str = "cam1", pipelined: bool = True,
            exclude_boxes: Callable[[int], np.ndarray | None] | None = None,
            window_sink: Callable | None = None) -> VioResult:
    """Stereo VIO over ``sequence``.

    Args:
        sequence: with an IMU stream, its calibration and two cameras.
        config: the estimator's settings (default :class:`~uavcal_jax.vio.config.VioConfig`);
            its camera-dependent values are resolved against the left camera
            (:func:`~uavcal_jax.vio.config.resolve_camera`).
        imu_offset: (6,) constant IMU offset (gyro rad/s, accel m/s^2) subtracted from every
            sample first (the calibrator's output); ``None``: none.
        show_progress: a progress bar on stderr.  max_frames: stop after this many frames.
        pipelined: run the front end one frame ahead in a worker thread
            (:func:`estimate_stream`); the estimates are identical either way.
        exclude_boxes: ``(left frame index) -> (M, 4)`` boxes (``x0, y0, x1, y1``, pixels) of
            moving objects in that left image, or ``None``: no track lies in them (a
            detector's boxes, so that a target filling the view does not move the world).
            Called in the front end's thread, in frame order; it may block until the boxes
            are known.
        window_sink: :attr:`StereoVio.window_sink` (each full window solved on a good frame).

    Raises:
        DataError: no IMU, no IMU calibration, or a camera missing.
    """
    name = sequence.name
    if sequence.imu is None or len(sequence.imu) < 2 or sequence.imu_calibration is None:
        raise DataError(f"{name}: the VIO needs an IMU stream and its calibration")
    for cam in (left, right):
        if cam not in sequence.cameras:
            raise DataError(f"{name}: no camera {cam!r} (the VIO is stereo: "
                            f"{left!r} and {right!r})")
    offset = np.zeros(6) if imu_offset is None else np.asarray(imu_offset, np.float64).reshape(6)
    if not np.all(np.isfinite(offset)):
        raise DataError(f"the IMU offset must be finite, got {offset.tolist()}")
    cam0, cam1 = sequence.camera(left), sequence.camera(right)
    config = resolve_camera(config if config is not None else VioConfig(), cam0.calibration)
    vio = StereoVio(cam0.calibration, cam1.calibration, sequence.imu_calibration,
                    _corrected_imu(sequence.imu, offset), config)
    vio.window_sink = window_sink
    pairs = stereo_pairs(sequence, left, right)
    if max_frames is not None:
        pairs = pairs[:max_frames]
    unreadable = [0]

    def load(t_ns, i, j):
        try:
            img_l = cam0.load(i)
        except (DataError, OSError) as exc:
            unreadable[0] += 1
            warnings.warn(f"{exc}; processed as a dropped frame", DataRepairWarning,
                          stacklevel=2)
            img_l = None
        try:
            img_r = cam1.load(j) if j is not None else None
        except (DataError, OSError):
            img_r = None
        if exclude_boxes is None:
            return t_ns, img_l, img_r
        return t_ns, img_l, img_r, exclude_boxes(i)

    frames = []
    bar = progress(total=len(pairs), desc=f"vio {name}", enabled=show_progress, unit="frame")
    for est in estimate_stream(vio, (lambda p=p: load(*p) for p in pairs), pipelined):
        frames.append(est)
        bar.update(1)
        bar.set_postfix_str(f"{est.status} kf={int(est.keyframe)} lm={est.landmarks}",
                            refresh=False)
    bar.close()
    return VioResult(frames, vio.resets, unreadable[0], vio.config, offset)


def one_blas_thread() -> threadpool_limits:
    """Context manager: every BLAS loaded in the process (the OpenBLAS builds of NumPy, of
    SciPy -- whose LAPACK jaxlib's CPU kernels call for the window's Cholesky and
    eigen-decompositions -- and of OpenCV) limited to one thread, restored on exit.

    The VIO's matrices are small (the 150 x 150 Schur complement at most), too small to gain
    from a second BLAS thread, and OpenBLAS's threads busy-wait for work: on a CPU shared with
    other processes (or with the VIO's own front-end thread) a waiting thread burns the core
    its partner needs. On the 2-core development machine, shared with background jobs, a
    simulated V1_02 flight took 340-380 ms of CPU per frame with OpenBLAS's default two
    threads (single window solves stalling up to 0.7 s) and 38-51 ms with one. The setting is
    process-wide, so it is applied at this edge, around a whole run.
    """
    return threadpool_limits(limits=1, user_api="blas")


def estimate_stream(vio: StereoVio, inputs: Iterable[Callable[[], tuple]],
                    pipelined: bool = True) -> Iterator[FrameEstimate]:
    """:class:`FrameEstimate` of each input, in order, under :func:`one_blas_thread` (held
    until the generator finishes or is closed).

    ``inputs`` yields callables returning ``(t_ns, left, right)`` or ``(t_ns, left, right,
    exclude)`` (so images load lazily, in the front end's thread; ``exclude``: the left
    image's boxes of moving objects, :meth:`StereoVio.track`). ``pipelined``: the front end
    of frame ``k + 1`` (loading, :meth:`StereoVio.track`) runs in a worker thread while the
    back end solves frame ``k`` (:meth:`StereoVio.update`) -- two stages on two cores, as
    VINS-Fusion's threads; each estimate's ``timings["wall"]`` is then the wall-clock time
    since the previous estimate (the throughput a caller sees). Otherwise the stages
    alternate in this thread. Either way the front end of frame ``k + 1`` is seeded with the
    gyro bias and velocity published before ``update(k)`` (:meth:`StereoVio.flow_seed`,
    snapshotted when the task is handed out), so both modes give identical estimates, run
    after run.
    """
    with one_blas_thread():
        yield from _stream(vio, inputs, pipelined)


def _stream(vio: StereoVio, inputs: Iterable[Callable[[], tuple]], pipelined: bool
            ) -> Iterator[FrameEstimate]:
    # The front end of frame k + 1 is seeded with what was published before update(k) runs,
    # in both modes: it is all a pipelined front end can have seen, and snapshotting it
    # when the task is handed out (not reading it while update(k) writes it) makes a run
    # reproducible and the two modes identical.
    def front(load, seed):
        t_ns, left, right, *exclude = load()
        return vio.track(t_ns, left, right, seed, *exclude)

    last = time.perf_counter()
    if not pipelined:
        seed = vio.flow_seed()
        for load in inputs:
            tracked = front(load, seed)
            seed = vio.flow_seed()
            est = vio.update(tracked)
            now = time.perf_counter()
            est.timings["wall"] = 1e3 * (now - last)
            last = now
            yield est
        return
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="vio-frontend") as pool:
        it = iter(inputs)
        first = next(it, None)
        pending = pool.submit(front, first, vio.flow_seed()) if first is not None else None
        while pending is not None:
            tracked = pending.result()
            nxt = next(it, None)
            pending = pool.submit(front, nxt, vio.flow_seed()) if nxt is not None else None
            est = vio.update(tracked)
            now = time.perf_counter()
            est.timings["wall"] = 1e3 * (now - last)
            last = now
            yield est
