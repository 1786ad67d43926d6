"""Per-frame target labels (2D boxes + 3D positions), as the simulator writes them.

On disk: ``mav0/target0/data.csv`` with the header ::

    #timestamp [ns],camera,track_id,class_id,x_min,y_min,x_max,y_max,visible_pixels,
    p_W_x [m],p_W_y [m],p_W_z [m]

(one line in the file),
one row per target visible in one camera's frame (boxes in pixels, inclusive-exclusive,
tight around the target's visible pixels), and ``mav0/target0/classes.txt`` with one class
name per line (line i is class id i).

The targets' true world tracks, at every frame whether seen or not, are in
``mav0/target0/track.csv`` (optional: older recordings lack it) with the header ::

    #timestamp [ns],track_id,class_id,p_W_x [m],p_W_y [m],p_W_z [m],yaw [rad],
    v_W_x [m/s],v_W_y [m/s],v_W_z [m/s]

(one line in the file), one row per frame and target, frames in time order (the targets'
box centres, their heading about world z, and their velocity).
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
#: The tracks' file, beside ``data.csv``.
TRACK_CSV = "track.csv"
TRACK_HEADER = (
    "#timestamp [ns],track_id,class_id,p_W_x [m],p_W_y [m],p_W_z [m],yaw [rad],"
    "v_W_x [m/s],v_W_y [m/s],v_W_z [m/s]"
)


@dataclass(frozen=True)
class TargetTracks:
    """Every target's true state at every frame time (seen or not).

    Attributes:
        t_ns: (N,) int64 increasing frame timestamps.
        track_id: (n,) int, the targets' identities (as in :class:`TargetLabels`).
        class_id: (n,) int, their classes.
        position: (N, n, 3) box centres in the world frame, metres.
        yaw: (N, n) headings about world z, radians (continuous in time where the simulator
            made them so).
        velocity: (N, n, 3) world velocities, m/s.
    """

    t_ns: np.ndarray
    track_id: np.ndarray
    class_id: np.ndarray
    position: np.ndarray
    yaw: np.ndarray
    velocity: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


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
        tracks: every target's world track at every frame (``track.csv``), or ``None``
            (a recording without it).
    """

    t_ns: np.ndarray
    camera: np.ndarray
    track_id: np.ndarray
    class_id: np.ndarray
    box: np.ndarray
    visible_pixels: np.ndarray
    position: np.ndarray
    class_names: tuple[str, ...]
    tracks: TargetTracks | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def for_frame(self, t_ns: int, camera: str = "cam0") -> TargetLabels:
        """The rows of one camera frame."""
        keep = (self.t_ns == t_ns) & (self.camera == camera)
        return TargetLabels(
            self.t_ns[keep], self.camera[keep], self.track_id[keep], self.class_id[keep],
            self.box[keep], self.visible_pixels[keep], self.position[keep], self.class_names,
            self.tracks,
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
    if labels.tracks is not None:
        _write_tracks(folder / TRACK_CSV, labels.tracks)


def _write_tracks(path: Path, tracks: TargetTracks) -> None:
    lines = [TRACK_HEADER]
    for k in range(len(tracks)):
        for j in range(tracks.track_id.shape[0]):
            px, py, pz = tracks.position[k, j]
            vx, vy, vz = tracks.velocity[k, j]
            lines.append(f"{int(tracks.t_ns[k])},{int(tracks.track_id[j])},"
                         f"{int(tracks.class_id[j])},{px:.6f},{py:.6f},{pz:.6f},"
                         f"{tracks.yaw[k, j]:.6f},{vx:.6f},{vy:.6f},{vz:.6f}")
    path.write_text("\n".join(lines) + "\n")


def read_target_tracks(path: str | Path) -> TargetTracks:
    """Read a ``track.csv`` (the module docstring's layout).

    Raises:
        DataError: a malformed row (named by its line) or rows that are not every target at
            every timestamp.
    """
    path = Path(path)
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        fields = line.split(",")
        try:
            if len(fields) != 10:
                raise ValueError(f"{len(fields)} fields, expected 10")
            row = (int(fields[0]), int(fields[1]), int(fields[2]), *map(float, fields[3:]))
            if not np.all(np.isfinite(row[3:])):
                raise ValueError("non-finite value")
        except ValueError as err:
            raise DataError(f"line {lineno}: {err}", path) from None
        rows.append(row)
    if not rows:
        z = np.zeros(0)
        return TargetTracks(z.astype(np.int64), z.astype(np.int64), z.astype(np.int64),
                            z.reshape(0, 0, 3), z.reshape(0, 0), z.reshape(0, 0, 3))
    a = np.array(rows, dtype=np.float64)
    t_ns = np.unique(np.array([r[0] for r in rows], dtype=np.int64))
    ids = np.unique(a[:, 1].astype(np.int64))
    N, n = t_ns.shape[0], ids.shape[0]
    if a.shape[0] != N * n:
        raise DataError(f"{a.shape[0]} rows are not {n} targets at each of {N} timestamps",
                        path)
    order = np.lexsort((a[:, 1], np.array([r[0] for r in rows], dtype=np.int64)))
    a = a[order].reshape(N, n, 10)
    if not np.all(a[:, :, 1].astype(np.int64) == ids):
        raise DataError("rows are not every target at every timestamp", path)
    class_id = a[0, :, 2].astype(np.int64)
    return TargetTracks(t_ns=t_ns, track_id=ids, class_id=class_id,
                        position=a[:, :, 3:6].copy(), yaw=a[:, :, 6].copy(),
                        velocity=a[:, :, 7:10].copy())


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
        tracks=(read_target_tracks(folder / TRACK_CSV) if (folder / TRACK_CSV).is_file()
                else None),
    )
