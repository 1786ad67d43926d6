"""The small detector weights shipped in the package (``uavcal run`` without ``--detector``).

They are a run folder like any ``uavcal detect train`` output, cut down to ``config.json``,
``metrics.json``, ``eval.json`` (their scores on each source, below) and the best checkpoint
(:func:`uavcal_jax.detect.run.export_run`), under ``uavcal_jax/detect/weights/default/``;
:func:`uavcal_jax.detect.run.load_run` restores them, as ``uavcal detect predict
--checkpoint`` does. ``experiments/detector_default_weights.py`` makes them (its docstring
holds the command): the two classes car and person, learnt from real aerial photos
(``aerial_cars_kit``'s fixed 80 % split; trucks, buses and minibuses are cars), real photos
with neither, frames rendered at EuRoC's 752x480 along procedural flights and real EuRoC and
UZH-FPV trajectories with targets placed in view, and rendered nadir street frames: trained
with the :data:`SHIPPED` preset (the script's defaults), then fine-tuned from those weights
on the same sources with four times the rendered frames (2 a second), for the rendered
follow view the demo flies (``--init``; the second command in the script's docstring), and
fine-tuned once more on flights rendered with the simulator's realistic defaults (EuRoC's
auto-exposure and vignetting), at 752x480 and at the demo's 376x240 (``--rate 1.5
--low-res --epochs 6``): the previous weights found the car on 22 % of the frames of
``experiments/run_flights.py``'s flights, these on 43 %.

``eval.json`` holds, per source, the figures and the command that reproduces them
(``python experiments/detect_sources.py`` scores any run the same way): COCO mAP on a
held-out rendered flight and on the real aerial photos' 13 held-out photos (letterboxed
whole, and sliced as ``--tile auto`` slices them), and the detections per frame at
``uavcal run``'s threshold on the real EuRoC frames, a room with no target.
"""

from __future__ import annotations

from pathlib import Path

from uavcal_jax.detect.augment import AugmentConfig
from uavcal_jax.detect.config import DetectConfig, DetectorConfig, TrainConfig
from uavcal_jax.errors import DataError

__all__ = ["DEFAULT_DETECTOR_RUN", "SHIPPED", "default_detector_run"]

#: The shipped run folder.
DEFAULT_DETECTOR_RUN = Path(__file__).resolve().parent / "weights" / "default"

#: The shipped detector's preset: YZNet-YOLO-tiny predicting at 480x640 (H x W, the paper's
#: 640x480), trained with YOLOv5's SGD recipe on 320x320 crops at 0.35-2.5 times each image's
#: stored resolution (a quarter of them turned by a quarter turn, 30 % grey), YOLOv5's anchors
#: (autoanchor would fit them to letterboxed sizes, not the crops').
#: ``experiments/detector_default_weights.py`` trains it (``--epochs``, ``--set`` change it).
SHIPPED = DetectConfig(
    detector=DetectorConfig(model="yznet-yolo-tiny", img_size=(480, 640)),
    train=TrainConfig.yolov5(
        epochs=14, batch_size=8, val_fraction=0.1, eval_every=3, autoanchor=False,
        augment=AugmentConfig(crop_scale=(0.35, 2.5), crop_size=(320, 320), degrees=5.0,
                              rot90=0.25, gray=0.3)),
)


def default_detector_run() -> Path:
    """:data:`DEFAULT_DETECTOR_RUN`, checked to hold a run's ``config.json`` and its best
    checkpoint; a :class:`~uavcal_jax.errors.DataError` naming the folder otherwise."""
    if not (DEFAULT_DETECTOR_RUN / "config.json").is_file() or not (
            DEFAULT_DETECTOR_RUN / "checkpoints" / "best").is_dir():
        raise DataError("the shipped detector weights are missing from this installation "
                        "(reinstall the package, or give --detector RUN: a `uavcal detect "
                        "train` run folder)", DEFAULT_DETECTOR_RUN)
    return DEFAULT_DETECTOR_RUN
