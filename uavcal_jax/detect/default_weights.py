"""The small detector weights shipped in the package (``uavcal run`` without ``--detector``).

They are a run folder like any ``uavcal detect train`` output, cut down to ``config.json``,
``metrics.json``, ``eval.json`` (the held-out flight's mAP) and the best checkpoint
(:func:`uavcal_jax.detect.run.export_run`), under ``uavcal_jax/detect/weights/default/``;
:func:`uavcal_jax.detect.run.load_run` restores them, as ``uavcal detect predict
--checkpoint`` does. ``experiments/detector_default_weights.py`` makes them (its docstring
holds the command, the flights and the figures reached): the simulator's two target classes
(car, person) on frames rendered at EuRoC's 752x480 along procedural flights and real EuRoC
and UZH-FPV trajectories, with targets placed in view (``SimConfig.follow_targets``), trained
with the :data:`SHIPPED` preset.

The preset is YZNet-YOLO-tiny (RPEOD Table 3's small model, about 1.24 M parameters; 2.6 MB
stored, the parameters as float16) at a 256x384 (H x W) input: a 752x480 frame letterboxes
into it at 0.51 scale (384x245 plus 11 rows of padding), where the simulator's cars (about
130x60 px there) and people (about 30x65 px) stay well within the anchors' reach, and a frame
costs about a quarter of the paper's 640x480 input. Training is YOLOv5's SGD recipe
(:meth:`TrainConfig.yolov5`), batch 8, validation on a tenth of the frames every few epochs.

What they are worth, measured (``python experiments/detector_default_weights.py``, the
defaults: 26 flights -- 8 procedural, 8 procedural with the rig pitched 45 degrees down (targets
seen steeply from above, as from a low flight), the EuRoC trajectories MH_01/V1_02/MH_03/V2_01/
V1_03/MH_05, the UZH-FPV indoor_forward_3 and indoor_forward_7 (rig at 30 degrees) and
indoor_45_2 and indoor_45_13 (at 45) -- 20 s at 2 Hz, 1066 frames and 3025 boxes; all 20
epochs, the best the last, 29 min of training on 2 cores): on the held-out MH_04_difficult
flight (41 frames, 119 boxes, a seed no training flight uses) mAP@0.5 0.84 and mAP@0.5:0.95
0.52; on the validation frames 0.86 and 0.54. The weights before, without the steep flights
(16 flights), reached 0.80 and 0.50 on MH_04 but boxed a car seen steeply from above badly:
on unseen 45-degree FLU flights along indoor_45_4 and indoor_45_12 their best box's median
IoU with the car's label was 0.41 and 0.36, these weights' 0.83 and 0.83.

They are a demonstration on the simulator's targets, not a detector for real footage: train
one on labelled frames of your own targets (``uavcal detect train``).
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
        epochs=30, batch_size=8, val_fraction=0.1, eval_every=3, autoanchor=False,
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
