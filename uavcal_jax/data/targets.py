"""Per-frame target labels (2D boxes + 3D positions), as the simulator writes them.

On disk: ``mav0/target0/data.csv`` with the header ::

    #timestamp [ns],camera,track_id,class_id,x_min,y_min,x_max,y_max,visible_pixels,
    p_W_x [m],p_W_y [m],p_W_z [m]

(one line in the file),
one row per target visible in one camera's frame (boxes in pixels, inclusive-exclusive,
tight around the target's visible pixels), and ``mav0/target0/classes.txt`` with one class
name per line (line i is class id i).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uavcal_jax.data.euroc_format import DATA_CSV
from uavcal_jax.errors import DataError, DataRepairWarning

#: One class name per line (line i is class id i).
CLASSES_TXT = "classes.txt"
HEADER = (
    "#timestamp [ns],camera,track_id,class_id,x_min,y_min,x_max,y_max,visible_pixels,"
    "p_W_x [m],p_W_y [m],p_W_z [m]"
)


@dataclass(frozen=True)
class TargetLabels:
    """Target boxes, one row per (frame, camera, target).

    Attributes:
        t_ns: (M,) int64 frame timestamps.
        camera: (M,) camera names (``"cam0"`` ...).
        track_id: (M,) int, the target's identity across frames.
        class_id: (M,) int, index into ``class_names``.
        box: (M, 4) float ``x_min, y_min, x_max, y_max`` in pixels.
        visible_pixels: (M,) int.
        position: (M, 3) target centre in the world frame, metres.
        class_names: class names by id.
    """

    t_ns: np.ndarray
    camera: np.ndarray
    track_id: np.ndarray
    class_id: np.ndarray
    box: np.ndarray
    visible_pixels: np.ndarray
    position: np.ndarray
    class_names: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def for_frame(self, t_ns: int, camera: str = "cam0") -> TargetLabels:
        """The rows of one camera frame."""
        keep = (self.t_ns == t_ns) & (self.camera == camera)
        return TargetLabels(
            self.t_ns[keep], self.camera[keep], self.track_id[keep], self.class_id[keep],
            self.box[keep], self.visible_pixels[keep], self.position[keep], self.class_names,
        )


def write_target_labels(folder: str | Path, labels: TargetLabels) -> None:
    """Write ``data.csv`` and ``classes.txt`` into ``folder`` (created if needed)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / CLASSES_TXT).write_text("".join(f"{name}\n" for name in labels.class_names))
    lines = [HEADER]
    for i in range(len(labels)):
        x0, y0, x1, y1 = labels.box[i]
        px, py, pz = labels.position[i]
        lines.append(
            f"{int(labels.t_ns[i])},{labels.camera[i]},{int(labels.track_id[i])},"
            f"{int(labels.class_id[i])},{x0:.2f},{y0:.2f},{x1:.2f},{y1:.2f},"
            f"{int(labels.visible_pixels[i])},{px:.6f},{py:.6f},{pz:.6f}"
        )
    (folder / DATA_CSV).write_text("\n".join(lines) + "\n")


def read_target_labels(folder: str | Path) -> TargetLabels:
    """Read a ``target0`` folder. Malformed rows are dropped with one warning listing them."""
    folder = Path(folder)
    csv_path, classes_path = folder / DATA_CSV, folder / CLASSES_TXT
    for path in (csv_path, classes_path):
        if not path.is_file():
            raise DataError("missing target-label file", path)
    class_names = tuple(
        line.strip() for line in classes_path.read_text().splitlines() if line.strip()
    )
    rows, bad = [], []
    for lineno, line in enumerate(csv_path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        fields = line.split(",")
        try:
            if len(fields) != 12:
                raise ValueError(f"{len(fields)} fields, expected 12")
            row = (int(fields[0]), fields[1].strip(), int(fields[2]), int(fields[3]),
                   *map(float, fields[4:8]), int(fields[8]), *map(float, fields[9:12]))
            if not 0 <= row[3] < len(class_names):
                raise ValueError(f"class id {row[3]} not in classes.txt")
            if not np.all(np.isfinite(row[4:8] + row[9:12])):
                raise ValueError("non-finite value")
        except ValueError as err:
            bad.append(f"line {lineno} ({err})")
            continue
        rows.append(row)
    if bad:
        warnings.warn(f"{csv_path}: dropped {len(bad)} malformed rows: {', '.join(bad[:20])}",
                      DataRepairWarning, stacklevel=2)
    cols = list(zip(*rows, strict=True)) if rows else [()] * 12
    return TargetLabels(
        t_ns=np.asarray(cols[0], dtype=np.int64),
        camera=np.asarray(cols[1], dtype=str),
        track_id=np.asarray(cols[2], dtype=np.int64),
        class_id=np.asarray(cols[3], dtype=np.int64),
        box=np.asarray(cols[4:8], dtype=np.float64).T.reshape(-1, 4),
        visible_pixels=np.asarray(cols[8], dtype=np.int64),
        position=np.asarray(cols[9:12], dtype=np.float64).T.reshape(-1, 3),
        class_names=class_names,
    )
