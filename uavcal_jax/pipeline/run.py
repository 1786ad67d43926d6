"""``uavcal run``: calibrate the IMU, fly on the VIO, find, locate, filter and follow the target,
over one recording (:func:`run_pipeline`).

Steps (RPEOD section 6.3 on a calibrated IMU), over the recording read once:

1. the IMU covers the frames (:func:`~uavcal_jax.data.imu_coverage.check_imu_covers`, before
   any work); the IMU offset to remove first: ``offset.method``'s estimate
   (:func:`~uavcal_jax.pipeline.predict_offset.predict_offset`, which never shows the method
   the ground truth), or a given offset, or none (``offset.method=none``); the default
   method, :data:`IN_PASS_METHOD`, removes none and is read from step 2's own VIO (2b), so
   that the default run makes one VIO pass;
2. the stereo VIO (:func:`uavcal_jax.vio.run.run_vio`) on the IMU minus that offset; (2b) the
   default offset estimate from its bias states (:func:`uavcal_jax.pipeline.vio_bias.from_vio`,
   in a worker thread beside steps 4-5), reported, not removed: the VIO has estimated the
   biases itself;
3. *concurrently* with the detector on every ``detect.every``-th left frame, in a worker
   thread (as the VIO pipelines its own front end; XLA and OpenCV release the GIL);
4. the target and the follow set-points: the online tracker over the frames
   (:mod:`uavcal_jax.pipeline.targets`): the chosen class's track seen longest so far, each
   box located (depth, or stereo disparity), filtered, and followed from the VIO's pose.

The files written in ``out_dir`` (:mod:`uavcal_jax.pipeline.run_outputs`) are named by
:data:`~uavcal_jax.pipeline.run_outputs.OUTPUT_FILES`; the figures are drawn by
:func:`uavcal_jax.plots.plot_run` (the plots sit above this package).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from uavcal_jax.data.imu_coverage import check_imu_covers
from uavcal_jax.data.read import read_sequence
from uavcal_jax.data.sequence import Sequence
from uavcal_jax.data.sim_config import recorded_imu_offset
from uavcal_jax.detect.predict import ImageDetections
from uavcal_jax.errors import DataError
from uavcal_jax.pipeline import vio_bias
from uavcal_jax.pipeline.bias_prior import prior_from_estimate
from uavcal_jax.pipeline.detectors import Detector, load_network_detector
from uavcal_jax.pipeline.offset_estimate import SIX_CHANNELS, OffsetEstimate
from uavcal_jax.pipeline.predict_offset import predict_offset, score, without_ground_truth
from uavcal_jax.pipeline.run_config import NO_OFFSET, RunConfig
from uavcal_jax.pipeline.run_metrics import Evaluation, evaluate, follow_metrics, stage_timings
from uavcal_jax.pipeline.run_outputs import build_metrics, write_outputs
from uavcal_jax.pipeline.targets import TargetResult, build_localizer, track_target
from uavcal_jax.progress import progress as progress_bar
from uavcal_jax.track import Setpoint
from uavcal_jax.vio.run import VioResult, run_vio

__all__ = ["IN_PASS_METHOD", "DetectionBoard", "RunResult", "run_pipeline"]


@dataclasses.dataclass(frozen=True)
class RunResult:
    """A finished run (everything :func:`uavcal_jax.plots.plot_run` draws from).

    Attributes:
        out_dir: where the files are.  paths: ``{name: path}`` of the files written.
        sequence: the recording.  config: the settings, the VIO's resolved.
        offset: ``estimate`` (6,), ``true`` (6,) or ``None``, ``method``.
        vio: the VIO run.  detections: per left frame (``None``: not run).
        class_names: the detector's classes.  target: the followed target.
        setpoints: :class:`~uavcal_jax.track.Setpoint`, ``position`` (T, 3), ``yaw`` (T,).
        evaluation: against the truth.  metrics: ``metrics.json``'s content.
        notes: warnings for the user (localisation off, no detection, ...).
    """

    out_dir: Path
    paths: dict[str, Path]
    sequence: Sequence
    config: RunConfig
    offset: dict
    vio: VioResult
    detections: list[ImageDetections | None]
    class_names: tuple[str, ...]
    target: TargetResult
    setpoints: Setpoint
    evaluation: Evaluation
    metrics: dict
    notes: list[str]


#: The offset method read from the run's own VIO pass: the VIO runs on the recorded IMU and
#: its bias states are the estimate (:func:`uavcal_jax.pipeline.vio_bias.from_vio`), so the
#: default run is one VIO pass. The VIO estimates the biases itself: on the drift study's
#: flights removing the estimate first changed its final error by at most 4 %.
IN_PASS_METHOD = vio_bias.METHOD.name


def _given(offset) -> OffsetEstimate:
    """An offset given rather than estimated (``--offsets``, or none), over the recording's
    whole span, for :func:`~uavcal_jax.pipeline.predict_offset.score`."""
    offset = np.asarray(offset, np.float64).reshape(6)
    return OffsetEstimate(offset=offset, channels=SIX_CHANNELS, median=offset,
                          per_item=offset[None], item_t_s=np.zeros(1), item="given",
                          span_ns=(None, None), label="total", settings=None)


def _offset_before_vio(sequence: Sequence, config: RunConfig, offsets, offsets_from: str,
                       progress: bool) -> dict | None:
    """Step 1 where the offset is removed before the VIO: ``{"estimate": OffsetEstimate,
    "method", "removed": True, "seconds"}``; ``None`` for :data:`IN_PASS_METHOD` (step 2b)."""
    t0 = time.perf_counter()
    method = config.offset.method
    if offsets is not None:
        estimate, method = _given(offsets), offsets_from
    elif method == NO_OFFSET:
        estimate = _given(np.zeros(6))
    elif method == IN_PASS_METHOD:
        return None
    else:
        _, estimate = predict_offset(sequence, method, config.offset.options(config.vio),
                                     progress=progress)
    return {"estimate": estimate, "method": method, "removed": True,
            "seconds": time.perf_counter() - t0}


def _offset_from_vio(sequence: Sequence, vio: VioResult, config: RunConfig) -> dict:
    """Step 2b: the :data:`IN_PASS_METHOD` estimate read from the run's VIO (on the recorded
    IMU), reported, not removed."""
    t0 = time.perf_counter()
    estimate = vio_bias.from_vio(without_ground_truth(sequence), vio,
                                 config.offset.options(vio.config))
    return {"estimate": estimate, "method": IN_PASS_METHOD, "removed": False,
            "seconds": time.perf_counter() - t0}


def _in_thread(function, *args) -> Future:
    """``function(*args)`` started in a worker thread of its own (its result or exception
    comes back through the future)."""
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="offset")
    future = pool.submit(function, *args)
    pool.shutdown(wait=False)  # the thread ends with the job
    return future


def _scored(offset: dict, recording: Path, sequence: Sequence) -> dict:
    """``metrics.json``'s offset: ``estimate`` (6,), ``true`` (6,) or ``None`` (the truth
    under the estimate's label, :func:`~uavcal_jax.pipeline.predict_offset.score`),
    ``method``, ``label``, ``removed``, ``seconds``."""
    estimate = offset["estimate"]
    recorded = recorded_imu_offset(recording) if recording.is_dir() else None
    true = score(estimate, recorded, sequence.ground_truth, all_channels=True)["true"]
    return {**offset, "estimate": np.asarray(estimate.offset, np.float64),
            "true": None if true is None else np.asarray(true, np.float64),
            "label": estimate.label}


class DetectionBoard:
    """The detector's per-frame results as the worker thread publishes them, for the VIO's
    front end to wait on (:meth:`boxes`)."""

    def __init__(self, n_frames: int, every: int):
        self.frames: list[ImageDetections | None] = [None] * n_frames
        self.every = every
        self._done_upto = -1  # frames below this index are published
        self._finished = False
        self._cond = threading.Condition()

    def publish(self, k: int, found: ImageDetections) -> None:
        with self._cond:
            self.frames[k] = found
            self._done_upto = k + 1
            self._cond.notify_all()

    def finish(self) -> None:
        with self._cond:
            self._finished = True
            self._cond.notify_all()

    def boxes(self, k: int) -> np.ndarray | None:
        """``(M, 4)`` every box of the last detected frame at or before ``k``, once the
        detector has reached it; ``None`` when the detector stopped before it."""
        last = (k // self.every) * self.every
        with self._cond:
            self._cond.wait_for(lambda: self._done_upto > last or self._finished)
            found = self.frames[last] if self._done_upto > last else None
        return None if found is None else found.boxes


def _detect_frames(sequence: Sequence, frames: list[int], detector: Detector, threshold: float,
                   show: bool, stop: threading.Event, board: DetectionBoard):
    """Step 3, in the worker thread: per left frame the detections above ``threshold``
    (``None`` where not run), published to ``board`` as they come, and each detected frame's
    milliseconds (load + network)."""
    cam0 = sequence.camera("cam0")
    ms = []
    bar = progress_bar(total=len(frames), desc="detect", enabled=show, unit="frame")
    try:
        for k in frames:
            if stop.is_set():
                break
            t0 = time.perf_counter()
            image = cam0.load(k, "rgb") if detector.needs_images else None
            board.publish(k, detector([image], [int(cam0.t_ns[k])])[0].above(threshold))
            ms.append(1e3 * (time.perf_counter() - t0))
            bar.update(1)
    finally:
        board.finish()  # a waiting VIO front end must not wait for ever
        bar.close()
    return board.frames, np.asarray(ms)


def _vio_and_detect(sequence: Sequence, config: RunConfig, offset: np.ndarray,
                    detector: Detector, show: bool):
    """Steps 2 and 3 at once: the detector in a worker thread beside the VIO (whose front end
    waits for each frame's boxes under ``detect.mask_vio``). The detections returned are those
    the tracker sees (:meth:`~uavcal_jax.pipeline.run_config.DetectStageConfig.
    tracked_threshold`); the mask took the lower ``detect.mask_score_threshold`` too."""
    n_frames = len(sequence.camera("cam0"))
    frames = list(range(0, n_frames, config.detect.every))
    board = DetectionBoard(n_frames, config.detect.every)
    stop = threading.Event()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="detector") as pool:
        job = pool.submit(_detect_frames, sequence, frames, detector,
                          config.detect.detector_threshold(), show, stop, board)
        try:
            vio = run_vio(sequence, config.vio, offset, show_progress=show,
                          exclude_boxes=board.boxes if config.detect.mask_vio else None)
        except BaseException:
            stop.set()
            raise
        detections, detect_ms = job.result()
    # the mask's doubtful boxes are not targets
    detections = [None if d is None else d.above(config.detect.tracked_threshold())
                  for d in detections]
    return vio, detections, detect_ms, len(frames)


def _poses(vio: VioResult) -> list[np.ndarray | None]:
    out = []
    for f in vio.frames:
        if not f.has_pose or not np.all(np.isfinite(f.position)):
            out.append(None)
            continue
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = f.rotation, f.position
        out.append(T)
    return out


def _checked(recording: Path, read: tuple[Sequence, str] | None) -> tuple[Sequence, str]:
    """``(sequence, format)`` of ``recording`` (or the caller's ``read`` of it), with left
    camera frames and an IMU that covers them, before any work."""
    sequence, fmt = read_sequence(recording) if read is None else read
    if "cam0" not in sequence.cameras or len(sequence.camera("cam0")) == 0:
        raise DataError("the recording has no left camera frames (cam0)", recording)
    check_imu_covers(sequence)
    return sequence, fmt


def _checked_detector(detector: Detector | None, config: RunConfig) -> Detector:
    """``detector`` (``None``: the shipped weights), which knows the class to follow."""
    if detector is None:
        detector = load_network_detector(None, config.detect.detector_threshold(),
                                         config.detect.tile_config())
    if config.detect.follow_class not in detector.class_names:
        raise DataError(f"detect.follow_class={config.detect.follow_class!r} is not a class "
                        f"of the detector (its classes: {', '.join(detector.class_names)})")
    return detector


def run_pipeline(recording: str | Path, out_dir: str | Path, config: RunConfig | None = None,
                 *, read: tuple[Sequence, str] | None = None, offsets=None,
                 offsets_from: str = "given", detector: Detector | None = None,
                 progress: bool = True, inputs: dict | None = None) -> RunResult:
    """Run the whole pipeline over ``recording`` and write its files into ``out_dir``.

    Args:
        recording: an EuRoC/ASL folder (real or simulated) or a ROS bag, with an IMU and a
            stereo pair (the VIO's needs).
        out_dir: the output folder (created).
        config: :class:`~uavcal_jax.pipeline.run_config.RunConfig` (``None``: defaults).
        read: ``(sequence, format)``, :func:`~uavcal_jax.data.read.read_sequence` of
            ``recording`` when the caller has read it (the recording is read once); ``None``:
            read here.
        offsets: (6,) an IMU offset to remove instead of estimating one, or ``None``.
        offsets_from: what ``offsets`` is, for ``metrics.json``'s ``offset.method`` (e.g.
            the name of the estimator that made it).
        detector: a :class:`~uavcal_jax.pipeline.detectors.Detector`; ``None``: the weights
            shipped in the package.
        progress: a progress bar per stage on stderr.
        inputs: extra entries for ``config.json``'s ``inputs`` (the command line).

    Raises:
        DataError: not a recording, an IMU that does not cover the frames (before any work,
            :func:`~uavcal_jax.data.imu_coverage.check_imu_covers`), no shipped weights
            (with ``detector=None``), a class to follow the detector does not know, a VIO
            that never initialises, ...
    """
    t_start = time.perf_counter()
    config = RunConfig() if config is None else config
    recording, out_dir = Path(recording), Path(out_dir)
    sequence, fmt = _checked(recording, read)
    detector = _checked_detector(detector, config)
    localizer = build_localizer(sequence, config)
    offset = _offset_before_vio(sequence, config, offsets, offsets_from, progress)
    if offset is not None and config.offset.prior and offset["estimate"].sigma is not None:
        prior = prior_from_estimate(offset["estimate"], config.vio.prior)
        config = dataclasses.replace(config, vio=dataclasses.replace(config.vio, prior=prior))
    t0 = time.perf_counter()
    vio, detections, detect_ms, detected_frames = _vio_and_detect(
        sequence, config, None if offset is None else offset["estimate"].offset, detector,
        progress)
    vio_detect_s = time.perf_counter() - t0
    trajectory = vio.trajectory()
    if len(trajectory) == 0:
        raise DataError(f"the VIO never initialised (no frame had "
                        f"{vio.config.min_init_landmarks} stereo corners)", recording)
    # 2b beside steps 4-5 (the alignment's solve and compilation on the other core)
    pending = None if offset is not None else _in_thread(_offset_from_vio, sequence, vio, config)
    config = dataclasses.replace(config, vio=vio.config)
    poses = _poses(vio)
    t0 = time.perf_counter()
    target = track_target(sequence, detections, detector.class_names, poses, config, localizer)
    cam0 = sequence.camera("cam0")
    times_s = (cam0.t_ns - cam0.t_ns[0]).astype(np.float64) * 1e-9
    setpoints = target.setpoints
    track_s = time.perf_counter() - t0
    offset = _scored(offset if pending is None else pending.result(), recording, sequence)
    evaluation = evaluate(sequence, trajectory, target, setpoints.position)
    ms, compile_s = stage_timings([f.timings for f in vio.frames], detect_ms, target,
                                  len(cam0), config.detect.every, config.warmup_frames)
    follow = follow_metrics(times_s, setpoints.position, setpoints.yaw, target, evaluation,
                            config, detected_frames)
    notes = _notes(target, detections, detector)
    metrics = build_metrics(
        recording=recording, fmt=fmt, vio=vio, offset=offset, detections=detections,
        detected_frames=detected_frames, class_names=detector.class_names, target=target,
        evaluation=evaluation, follow=follow, ms_per_frame=ms, compile_s=compile_s,
        seconds={"offset": offset["seconds"], "vio_and_detect": vio_detect_s,
                 "track_and_follow": track_s}, notes=notes)
    paths = write_outputs(out_dir, trajectory=trajectory, times_ns=cam0.t_ns, target=target,
                          evaluation=evaluation, setpoints=setpoints, metrics=metrics,
                          config=config, inputs={"sequence": str(recording),
                                                 "out": str(out_dir),
                                                 "detector": str(getattr(detector, "source",
                                                                         type(detector).__name__)),
                                                 **(inputs or {})},
                          t_start=t_start)
    return RunResult(out_dir, paths, sequence, config, offset, vio, detections,
                     tuple(detector.class_names), target, setpoints, evaluation, metrics, notes)


def _notes(target: TargetResult, detections, detector: Detector) -> list[str]:
    """What the user should know: localisation off, nothing detected, boxes not located."""
    notes = []
    if target.localisation["mode"] == "off":
        notes.append(target.localisation["reason"])
    boxes = sum(len(d.boxes) for d in detections if d is not None)
    if boxes == 0:
        notes.append("the detector found no target in any frame")
    elif target.track_id is None:
        notes.append(f"no {target.class_name} detected (classes: "
                     f"{', '.join(detector.class_names)})")
    for reason, count in sorted(target.not_located.items()):
        if target.localisation["mode"] != "off":
            notes.append(f"{count} of the followed target's boxes not located: {reason}")
    return notes
