"""A detector run scored on each source it must work on: the held-out rendered flight, the
real aerial photos' held-out split (whole and sliced), and the real EuRoC frames (false
positives per frame at ``uavcal run``'s threshold: they show no target).

The sources and how each is scored are ``detector_default_weights.py``'s (the recipe of the
shipped weights, which writes the same rows into their ``eval.json``):
:func:`uavcal_jax.pipeline.detector_sources.score_sources`.

Usage::

    python experiments/detect_sources.py                  # the shipped weights
    python experiments/detect_sources.py --run runs/mine --write-docs mine

The table is printed; the last line is the rows as one JSON object.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from _docs import add_write_docs, cpu_name, write_docs  # the script's folder is on sys.path
from detector_default_weights import (
    AERIAL,
    SOURCES_COMMAND,
    aerial_split,
    held_out,
    micro_frames,
)

from uavcal_jax.argtypes import print_json
from uavcal_jax.data.results_doc import markdown_table
from uavcal_jax.detect.default_weights import DEFAULT_DETECTOR_RUN
from uavcal_jax.detect.run import load_run
from uavcal_jax.pipeline.detector_sources import score_sources
from uavcal_jax.sim.cache import cached_simulation

ROOT = Path(__file__).resolve().parents[1]

#: Rows of the table: (source key, what it is).
SOURCES = (
    ("rendered", "rendered held-out flight"),
    ("aerial", "real aerial photos, held-out split, whole"),
    ("aerial_tiled", "the same, sliced (--tile)"),
    ("micro", "real EuRoC frames (no target): detections per frame"),
)


def table(rows: dict) -> str:
    """The sources' figures as a markdown table."""
    out = []
    for key, label in SOURCES:
        row = rows.get(key)
        if row is None:
            continue
        if key == "micro":
            out.append([label, "", "", f"{row['per_frame']:.3f} ({row['frames_with_any']} of "
                                       f"{row['frames']} frames; top score {row['top_score']})"])
        else:
            out.append([label, f"{row['map50']:.3f}", f"{row['map50_95']:.3f}",
                        f"{row['num_images']} images, {row['num_boxes']} boxes"])
    return markdown_table(["source", "mAP@0.5", "mAP@0.5:0.95", "size"], out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, default=DEFAULT_DETECTOR_RUN,
                    help="a detector run folder [default: the shipped weights]")
    ap.add_argument("--aerial", type=Path, default=AERIAL,
                    help="the real aerial photos (YOLO) [default: %(default)s]")
    ap.add_argument("--cache", type=Path, default=ROOT / "experiments" / "out" / "detect_sources",
                    help="the rendered flight and the evaluations [default: %(default)s]")
    add_write_docs(ap)
    args = ap.parse_args()
    classes = load_run(args.run).data["class_names"]
    name, cfg = held_out()
    folder = cached_simulation(cfg, args.cache / "held_out", name)
    aerial = aerial_split(args.aerial, classes)[1] if args.aerial.is_dir() else None
    rows = score_sources(args.run, (name, cfg, folder), aerial, micro_frames(),
                         args.cache / "eval", SOURCES_COMMAND)
    text = table(rows)
    print(f"{args.run} ({cpu_name()})\n\n{text}")
    write_docs(args, "detect_sources", text,
               anchor="RPEOD reports no real-image figure; the issue asks mAP@0.5 >= 0.5 on "
                      "real vehicles")
    print_json(rows)


if __name__ == "__main__":
    main()
