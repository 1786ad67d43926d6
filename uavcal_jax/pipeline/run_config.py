"""The settings of ``uavcal run`` (:func:`uavcal_jax.pipeline.run.run_pipeline`): one frozen
dataclass tree, :class:`RunConfig`, over the stages' own configs.

Every stage keeps its own config class and defaults (the VIO's
:class:`~uavcal_jax.vio.config.VioConfig`, the tracker's ``LocateConfig``, ``FilterConfig``,
``FollowConfig``, ``AssociateConfig``, the stereo matcher's ``StereoConfig``); this tree only
gathers them, adds the detection stage's (:class:`DetectStageConfig`) and the IMU offset
stage's (:class:`OffsetStageConfig`: the estimator and every estimator's options), so that
``--set key=value`` reaches any of them (:func:`uavcal_jax.config.apply_overrides`:
``vio.solver.max_iterations=4``, ``detect.every=2``, ``offset.method=visual-ls``,
``offset.visual_ls.every=2``, ``follow.distance=5``, ``filter.accel_psd=2``, ...).
"""

from __future__ import annotations

import dataclasses

from uavcal_jax.detect.tile import TileConfig
from uavcal_jax.pipeline.auto_offset import AutoOptions, AutoSettings
from uavcal_jax.pipeline.offset_estimators import DEFAULT_METHOD, configure_method, method_names
from uavcal_jax.pipeline.self_calib import SelfCalibOptions
from uavcal_jax.pipeline.transformer_offset import TransformerSettings
from uavcal_jax.pipeline.vio_bias import VioBiasOptions
from uavcal_jax.track.associate import AssociateConfig
from uavcal_jax.track.depth_box import DepthBoxConfig
from uavcal_jax.track.filter import FilterConfig
from uavcal_jax.track.follow import FollowConfig
from uavcal_jax.track.heading import HeadingConfig
from uavcal_jax.track.locate import LocateConfig
from uavcal_jax.track.stereo import StereoConfig
from uavcal_jax.vio.config import VioConfig
from uavcal_jax.vio.visual_gyro import VisualGyroConfig

__all__ = ["CLASS_HALF_SIZE_M", "NO_OFFSET", "RUN_FILTER", "RUN_HEADING", "RUN_LOCATE",
           "DetectStageConfig", "OffsetStageConfig", "RunConfig"]

#: ``RunConfig.offset.method`` that removes no offset from the IMU.
NO_OFFSET = "none"

#: Half sizes, metres (along the heading, across, up), of the upright box that models a target
#: class (by name) when ``DetectStageConfig.extent`` is ``None``: depth sees the box's front
#: surface and :mod:`uavcal_jax.track.box_model` moves the point to its centre for the view
#: and the heading. A mid-size car (4.2 x 1.75 x 1.45 m) and a standing adult
#: (0.5 x 0.34 x 1.72 m): the middle of the simulator's ranges (3.6-4.7 x 1.6-1.9 x 1.3-1.6,
#: 0.4-0.6 x 0.28-0.4 x 1.55-1.9). Other classes: a point target (no offset).
CLASS_HALF_SIZE_M = {"car": (2.1, 0.875, 0.725), "person": (0.25, 0.17, 0.86)}
#: The run's box localisation: the depth quantile at the median of the box's centre (0.5)
#: rather than :class:`~uavcal_jax.track.locate.LocateConfig`'s nearest fifth (0.2): a car
#: filling a quarter of the image shows roof and side at many depths, and the nearest fifth
#: of them sits 1.1-1.5 m before its centre, varying with the view (on the flight above, raw
#: median 0.62 m with 0.2 and the best extent, 0.37 m with 0.5).
RUN_LOCATE = LocateConfig(quantile=0.5)
#: The run's filter: a car that drives, turns and stops (the simulator's accelerates up to 4 m/s^2,
#: turns at up to 1.2 rad/s) needs a larger acceleration density than
#: :class:`~uavcal_jax.track.filter.FilterConfig`'s 1.0 (a walker's): on a simulated V1_02 flight
#: (20 s, the car 6-10 m away) the filtered median error was 0.64 m with 1.0 (48 of 401
#: measurements gated out), 0.47 with 4, 0.42 with 10 (none gated). Faster cars and racing drones'
#: views need more: over 14 simulated flights (the list in README.md) 50 lowered every flight's
#: filtered RMSE or kept it, the mean from 0.63 to 0.54 m (indoor_forward_6 1.02 to 0.56 m, V2_03
#: 0.85 to 0.58 m, indoor_forward_10's median 0.51 to 0.45 m), where 10 gated out good boxes after
#: a turn; 25 gave 0.59 m, 100 0.57 m (indoor_forward_6 back to 1.05 m), 200 0.59 m. Such a
#: velocity is too lively to fly on for long once the car has left the image, the more so as the
#: last boxes before it leaves are cut by the border and their localisations drift by 1-2 m: the
#: prediction moves for 0.25 s, then holds, and a target unseen for 0.6 s is lost (the default 2 s:
#: a car out of view drives up to 6 m/s); the follower holds its last prediction, and the next
#: measurement starts the filter afresh. Over 13 simulated flights (five EuRoC and four UZH-FPV
#: trajectories new to these settings) the mean filtered RMSE was 0.84 m with 0.5 s and 1.0 s, 0.74
#: m with 0.25 s and 0.6 s (V2_03 1.52 to 0.85 m, V1_02 0.98 to 0.91 m, a forward UZH-FPV flight
#: 1.03 to 0.76 m); no median rose by more than 0.02 m. Holding at once (0 s) raised the medians
#: (V1_03 0.27 to 0.41 m). The followed classes (car, person) move on the ground: no vertical
#: velocity, the height a random walk of 1 m^2/s that follows the measured heights
#: (:mod:`uavcal_jax.track.filter`). A cut box's height error no longer becomes a climb that the
#: coasting prediction flies off with: on that V2_02 flight (the car seen from 8 m, shipped
#: detector) the filtered median/RMSE went from 0.29/1.22 m to 0.26/0.80, on the demo from
#: 0.21/0.56 to 0.20/0.55, on a low FLU flight along indoor_45_4 from 0.49/0.65 to 0.48/0.54; a
#: stiff height (PSD 0.1 m^2/s^3 on a vertical velocity) cut the RMSE as much but raised the
#: medians (0.35, 0.27): the measured height's error changes with the view, and a stiff height
#: turns it into a range error along the slanted line of sight. For a flying target: ``--set
#: filter.vertical_accel_psd=none filter.vertical_velocity_sigma=none filter.height_walk_psd=0``.
RUN_FILTER = FilterConfig(accel_psd=50.0, vertical_accel_psd=0.0, vertical_velocity_sigma=0.0,
                          height_walk_psd=1.0, coast_after=0.25, lost_after=0.6)
#: The run's heading tracker: the detector's boxes are weaker evidence of a car's heading than
#: :class:`~uavcal_jax.track.heading.HeadingConfig`'s defaults assume, its velocity stronger.
#: On unseen simulated flights the shipped detector's box edges sit 5-9 px off the label's
#: (V2_03: the left edge 7 px in, the bottom 6 px up), and the heading that fits the box's
#: shape best was more than 30 degrees off in 72 % of V2_03's frames (V2_02 34 %, the demo
#: 20 %), while the filtered velocity's direction was off by a median 12-19 degrees. With the
#: shape's sigma 0.075 (0.05) and the velocity's concentration 4 (2), over nine simulated
#: flights the worst filtered median fell from 0.48 m to 0.46 m and the worst RMSE from 0.97 m
#: (V2_03, median 0.44 m) to 0.79 m (V2_03: 0.35 m and 0.66 m); the demo's median rose from
#: 0.20 m to 0.23 m and its RMSE fell from 0.55 m to 0.44 m (a forward UZH-FPV racing flight,
#: its car in view a third of the time, stays at 0.98 m either way).
RUN_HEADING = HeadingConfig(shape_sigma=0.075, velocity_kappa=4.0)


@dataclasses.dataclass(frozen=True)
class DetectStageConfig:
    """The detection stage of the run.

    Attributes:
        every: run the detector on every ``every``-th left frame (1: every frame); the filter
            predicts in between.
        score_threshold: only a detection scoring at least this starts a track (ByteTrack's
            track-start score; YOLOv5's 0.25 is for drawing boxes): the shipped weights
            score a mattress on the real EuRoC frames (cam0) at 0.50-0.59.
        continue_score_threshold: a detection scoring at least this, below
            ``score_threshold``, may continue a track (ByteTrack's second round,
            :mod:`uavcal_jax.track.associate`); lower ones are not tracked, located or
            counted. The shipped weights score a car seen from close by, cut by the border
            or seen end-on at 0.3-0.6 (a 155 px tall car on ``bench_run.py``'s flight: median
            0.52; with 0.6 it had a box on 72 of 201 frames, with 0.3 on 141). Over
            ``experiments/run_flights.py``'s 15 flights (docs/results.md) the car was boxed
            on 73 % of the frames with 0.3, 43 % with 0.6, and the filtered error's means
            fell; the demo's median stays 0.39 m, its RMSE rises from 0.61 to 0.75 m (the
            extra frames include a person standing before the car).
        mask_score_threshold: the VIO's mask (``mask_vio``) leaves out every box scoring at
            least this, lower than ``score_threshold``: a doubtful box over a moving target
            still must not give the front end its corners (at 0.6 for both, the demo's ATE
            rose from 0.015 m to 0.058 m). The network detector applies the lower of the two
            as its confidence threshold.
        follow_class: the class name to follow (among the detector's classes); its longest
            track is the target.
        extent: a fixed depth extent of the target along the ray, metres (half of it is added
            to the front-surface depth); ``None``: the class's box model,
            :data:`CLASS_HALF_SIZE_M`, turned by the target's heading.
        border_px: a box within this many pixels of the image border is cut by it (the
            target is partly outside the image); its centre is not the target's, so it is
            not located (see ``locate_cut``). Negative: locate every box.
        locate_cut: locate a cut box too when the class has a box model (the model's box is
            cut at the border as well, and what the border hides joins the covariance). It
            keeps a close target measured as it overflows the image: in the closed loop the
            longest loss is 0.20 s (1.05 s without), the mean follow distance error 0.54 m
            (0.94), following at 4 m and 2 m; the price is a little bias where a target
            drives out of view (demo seed 2: filtered RMSE 0.93 m against 0.69, median 0.35
            either way).
        mask_vio: the VIO's front end tracks nothing inside the frame's detections (every
            class: targets move), so that a target filling the view does not outvote the
            static scene (:meth:`~uavcal_jax.vio.frontend.FeatureTracker.track`'s
            ``exclude``). The VIO then waits for each frame's detections; the detector runs
            ahead of it on the other core.
        tile: sliced inference (:mod:`uavcal_jax.detect.tile`, SAHI): the network runs on
            overlapping windows of the frame at its own resolution, each of the network
            input's size, and on the whole frame, the boxes merged; for small targets in a
            large frame, at several network calls a frame (a 640x480 frame at the shipped
            256x384 input: six windows and the frame, in one batch of eight). Off: the frame
            is letterboxed whole into the input, one call.
        tile_overlap: the least overlap of neighbouring windows, a fraction of a window's side.
    """

    every: int = 1
    score_threshold: float = 0.6
    continue_score_threshold: float = 0.3
    mask_score_threshold: float = 0.25
    follow_class: str = "car"
    extent: float | None = None
    border_px: float = 1.0
    locate_cut: bool = True
    mask_vio: bool = True
    tile: bool = False
    tile_overlap: float = TileConfig.overlap

    def __post_init__(self):
        if not 0.0 <= self.tile_overlap < 1.0:
            raise ValueError(f"detect.tile_overlap must be in [0, 1), got {self.tile_overlap}")
        if self.every < 1:
            raise ValueError(f"detect.every must be >= 1, got {self.every}")
        for name in ("score_threshold", "continue_score_threshold", "mask_score_threshold"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"detect.{name} must be in [0, 1], got "
                                 f"{getattr(self, name)}")
        if self.extent is not None and self.extent < 0.0:
            raise ValueError(f"detect.extent must be >= 0, got {self.extent}")

    def tile_config(self) -> TileConfig | None:
        """The network detector's sliced inference (``None``: off)."""
        return TileConfig(overlap=self.tile_overlap) if self.tile else None

    def tracked_threshold(self) -> float:
        """The lowest score a box the tracker sees may have (one that continues a track)."""
        return min(self.score_threshold, self.continue_score_threshold)

    def detector_threshold(self) -> float:
        """The detector's confidence threshold: the lowest score any use of its boxes keeps."""
        if self.mask_vio:
            return min(self.tracked_threshold(), self.mask_score_threshold)
        return self.tracked_threshold()

    def target_extent(self) -> float:
        """The fixed depth extent of :attr:`follow_class` along the ray, metres (0 when its
        box model is used: the offset is added afterwards)."""
        return 0.0 if self.extent is None else float(self.extent)

    def target_half_size(self) -> tuple[float, float, float] | None:
        """The box model's half sizes of :attr:`follow_class` (metres), or ``None``: a fixed
        :attr:`extent` is set, or the class has no box model."""
        if self.extent is not None:
            return None
        return CLASS_HALF_SIZE_M.get(self.follow_class)


@dataclasses.dataclass(frozen=True)
class OffsetStageConfig:
    """The IMU offset stage of the run: which estimator, and each estimator's options (those
    of ``uavcal calib predict --method NAME --set ...``, here under ``offset.<name>.*``, the
    name's ``-`` written ``_``).

    The VIO's settings are the run's one ``vio`` (the run's own VIO pass and a method's VIO
    alike): a method's own ``vio`` subtree is not set here (refused).

    Attributes:
        method: a name of :data:`~uavcal_jax.pipeline.offset_estimators.METHODS` (default the
            registry's default, ``vio-bias``, read from the run's own VIO pass) or ``"none"``
            to remove nothing.
        vio_bias: :class:`~uavcal_jax.pipeline.vio_bias.VioBiasOptions`.
        visual_ls: :class:`~uavcal_jax.vio.visual_gyro.VisualGyroConfig`.
        self_calib: :class:`~uavcal_jax.pipeline.self_calib.SelfCalibOptions`.
        transformer: :class:`~uavcal_jax.pipeline.transformer_offset.TransformerSettings`
            (the calibrator's run folder, checkpoint kind, frame encoder dtype).
        auto: :class:`~uavcal_jax.pipeline.auto_offset.AutoSettings` (the methods fused; each
            with its options above).
        prior: with an offset removed before the VIO (a method other than ``vio-bias``),
            its sigma also becomes the VIO's prior on the biases
            (:func:`uavcal_jax.pipeline.bias_prior.prior_from_estimate`): what carries the
            VIO through a visual dropout.
    """

    method: str = DEFAULT_METHOD
    vio_bias: VioBiasOptions = VioBiasOptions()
    visual_ls: VisualGyroConfig = VisualGyroConfig()
    self_calib: SelfCalibOptions = SelfCalibOptions()
    transformer: TransformerSettings = TransformerSettings()
    auto: AutoSettings = AutoSettings()
    prior: bool = False

    def __post_init__(self):
        if self.method not in (*method_names(), NO_OFFSET):
            raise ValueError(f"offset.method must be one of {', '.join(method_names())} or "
                             f"{NO_OFFSET}, got {self.method!r}")
        for name in ("vio_bias", "self_calib"):
            if getattr(self, name).vio != VioConfig():
                raise ValueError(f"offset.{name}.vio.* is the run's vio.* (one VIO setting "
                                 "for the run and its offset method): set vio.* instead")

    def options(self, vio: VioConfig):
        """The options of :attr:`method` (not ``"none"``) as its ``estimate`` takes them,
        with the run's ``vio`` settings where the method runs a VIO.

        Raises:
            DataError: the transformer's run folder is not one (its ``configure``).
        """
        if self.method == "auto":
            return AutoOptions(methods=self.auto.methods,
                               vio_bias=dataclasses.replace(self.vio_bias, vio=vio),
                               visual_ls=self.visual_ls,
                               self_calib=dataclasses.replace(self.self_calib, vio=vio),
                               transformer=self.transformer)
        settings = getattr(self, self.method.replace("-", "_"))
        if isinstance(settings, TransformerSettings):  # a run folder to read, at run time
            return configure_method(self.method, **dataclasses.asdict(settings))
        if any(f.name == "vio" for f in dataclasses.fields(settings)):
            return dataclasses.replace(settings, vio=vio)
        return settings


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything ``uavcal run`` computes with (``--set`` keys are the dotted fields).

    Attributes:
        offset: :class:`OffsetStageConfig`: the IMU offset estimator and its options. An
            offsets file given to the run overrides it.
        vio: the VIO's settings (camera-dependent values resolved against the left camera),
            the run's and its offset method's.
        detect: :class:`DetectStageConfig`.
        associate: frame-to-frame association of the detections into tracks.
        locate: the box localisation from depth (or stereo disparity) (:data:`RUN_LOCATE`).
        refine: each box redrawn around the target its depth image shows before it is
            located (:mod:`uavcal_jax.track.depth_box`; recordings with a depth image).
        stereo: the stereo matcher, for recordings with a right camera and no depth.
        filter: the constant-velocity Kalman filter on the target (:data:`RUN_FILTER`).
        heading: the target's heading over time, which turns its box model
            (:data:`RUN_HEADING`).
        follow: the follow set-points.
        warmup_frames: frames at the start of each stage left out of the steady-state
            timings (1 s at EuRoC's 20 Hz: the VIO compiles its solve and its marginalisation
            while the first window fills; the first calls' extra time is reported apart).
    """

    offset: OffsetStageConfig = OffsetStageConfig()
    vio: VioConfig = VioConfig()
    detect: DetectStageConfig = DetectStageConfig()
    associate: AssociateConfig = AssociateConfig()
    locate: LocateConfig = RUN_LOCATE
    refine: DepthBoxConfig = DepthBoxConfig()
    stereo: StereoConfig = StereoConfig()
    filter: FilterConfig = RUN_FILTER
    heading: HeadingConfig = RUN_HEADING
    follow: FollowConfig = FollowConfig()
    warmup_frames: int = 20

    def __post_init__(self):
        if self.warmup_frames < 0:
            raise ValueError(f"warmup_frames must be >= 0, got {self.warmup_frames}")
