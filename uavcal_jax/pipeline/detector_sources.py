"""A detector run scored on each kind of image it meets: a held-out rendered flight, a real
photo set (whole and sliced), and real frames without targets (false positives at
``uavcal run``'s threshold). The rows are those of the shipped weights' ``eval.json`` and of
``experiments/detect_sources.py``'s table.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from uavcal_jax.detect.evaluate import evaluate_run
from uavcal_jax.detect.tile import TileConfig
from uavcal_jax.pipeline.detectors import load_network_detector
from uavcal_jax.pipeline.run_config import DetectStageConfig

__all__ = ["false_positives", "score_sources"]

#: The evaluation figures a row keeps.
_KEYS = ("map50", "map50_95", "per_class", "num_images", "num_boxes", "checkpoint_epoch")


def score_sources(run: Path, flight, aerial, empty_frames: list[Path], out: Path,
                  command: str) -> dict:
    """A detector run scored on each source:

    - ``rendered``: the held-out flight ``flight = (name, SimConfig, folder)``: COCO mAP;
    - ``aerial`` and ``aerial_tiled``: a real photo set (a loaded data set, or ``None`` to
      skip), the images letterboxed whole and sliced (SAHI, :class:`TileConfig`): COCO mAP;
    - ``micro``: ``empty_frames``, real grey frames that show no target (none: skipped):
      detections per frame at ``uavcal run``'s threshold (:func:`false_positives`).

    ``out`` receives the evaluations; each row carries the command that reproduces it
    (``command`` for the photo rows)."""
    name, cfg, folder = flight
    rows = {"rendered": {**{k: v for k, v in evaluate_run(run, folder, "sim",
                                                            out_dir=out / "rendered").items()
                            if k in _KEYS},
                         "flight": {"name": name, **cfg.to_dict()},
                         "command": f"uavcal detect eval RUN --data {folder} --format sim"}}
    if aerial is not None:
        for key, tile in (("aerial", None), ("aerial_tiled", TileConfig())):
            result = evaluate_run(run, aerial, tile=tile, out_dir=out / key)
            rows[key] = {**{k: v for k, v in result.items() if k in _KEYS},
                         "images": sorted(aerial.image_ids), "command": command}
    if empty_frames:
        rows["micro"] = {**false_positives(run, empty_frames),
                         "command": "uavcal run --sequence FRAMES --json (the target: none)"}
    return rows


def false_positives(run: Path, frames: list[Path]) -> dict:
    """Detections at the run's threshold (``uavcal run``'s ``detect.score_threshold``) on real
    grey frames that show no car and no person: per frame, the frames with any, the top
    score."""
    detector = load_network_detector(run, DetectStageConfig().score_threshold)
    counts, top = [], 0.0
    for start in range(0, len(frames), 8):
        images = [cv2.cvtColor(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2RGB)
                  for f in frames[start:start + 8]]
        for det in detector(images, None):
            counts.append(len(det.scores))
            top = max([top, *det.scores])
    return {"frames": len(counts), "per_frame": round(float(np.mean(counts)), 4),
            "frames_with_any": int(np.count_nonzero(counts)), "top_score": round(top, 3)}
