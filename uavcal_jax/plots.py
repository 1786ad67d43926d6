"""Every figure the project draws, as PNG files (matplotlib, Agg canvas, no display).

The edge of the package: only the CLI's commands and the experiment scripts import this module
(the import-linter layers in ``pyproject.toml``); the task packages compute, and never draw.
Each function builds a :class:`matplotlib.figure.Figure` on its own Agg canvas (no pyplot
global state, so drawing from a worker thread is safe), writes ``path`` (creating its folder)
and returns it.

- :func:`plot_trajectories`: a VIO estimate, aligned, against the ground truth (top view and
  height over time);
- :func:`plot_training_curves`: the detector's training loss and validation mAP per epoch
  (:func:`training_curves_writer`: redrawn after every epoch of a training run);
- :func:`plot_offsets`: per IMU channel, per-window offset estimates against window start
  time, with the median and the true offset (the calibrator's "Figure 2" view);
- :func:`plot_run`: a ``uavcal run``'s top view, frames with boxes and localisation error.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from uavcal_jax.vio.trajectory_metrics import (
    ALIGNMENTS,
    DEFAULT_MAX_TIME_DIFF_S,
    as_trajectory,
    ate,
)

__all__ = ["plot_drift_curves", "plot_offsets", "plot_trajectories", "plot_training_curves",
           "training_curves_writer"]


def _figure(figsize: tuple[float, float], dpi: int) -> Figure:
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def plot_trajectories(estimate: Any, ground_truth: Any, path: str | Path, *,
                      alignment: str = ALIGNMENTS[0],
                      max_diff_s: float = DEFAULT_MAX_TIME_DIFF_S,
                      title: str | None = None) -> Path:
    """Write a PNG of the aligned estimate against the truth: top view (x-y) and height (z).

    The estimate is associated and aligned as in
    :func:`~uavcal_jax.vio.trajectory_metrics.ate` (whose RMSE goes in the title); the ground
    truth is drawn over the estimate's time span (a short run on a long recording would
    otherwise be lost in it). Positions in metres, world frame. Returns ``path``.
    """
    gt_full = as_trajectory(ground_truth, "ground truth")
    result = ate(estimate, gt_full, alignment=alignment, max_diff_s=max_diff_s)
    est = result.aligned
    span = (gt_full.t_ns >= est.t_ns[0]) & (gt_full.t_ns <= est.t_ns[-1])
    if span.sum() < 2:
        span = np.ones(len(gt_full.t_ns), bool)
    gt_t, gt_p = gt_full.t_ns[span], gt_full.position[span]
    fig = _figure((11, 4.8), 100)
    top, height = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1, 1.4]})
    top.plot(gt_p[:, 0], gt_p[:, 1], "k-", lw=1.2, label="ground truth")
    top.plot(est.position[:, 0], est.position[:, 1], "r-", lw=1.0, label="estimate (aligned)")
    top.plot(*gt_p[0, :2], "ko", ms=4)
    top.set(xlabel="x [m]", ylabel="y [m]", title="top view")
    top.set_aspect("equal", adjustable="datalim")
    top.legend(loc="best", fontsize=8)
    t0 = gt_t[0]
    height.plot((gt_t - t0) * 1e-9, gt_p[:, 2], "k-", lw=1.2,
                label="ground truth")
    height.plot((est.t_ns - t0) * 1e-9, est.position[:, 2], "r-", lw=1.0,
                label="estimate (aligned)")
    height.set(xlabel="time [s]", ylabel="z [m]", title="height")
    height.grid(alpha=0.3)
    rmse = result.translation.rmse
    fig.suptitle((title + "  " if title else "")
                 + f"ATE RMSE {rmse:.4f} m ({alignment}, {result.translation.count} poses)")
    fig.tight_layout()
    return _save(fig, path)


def plot_training_curves(path: str | Path, rows: Sequence[Mapping[str, Any]],
                         title: str = "") -> Path:
    """Training loss (``loss``, ``box``, ``obj``, ``cls``; log scale) and validation mAP
    (``map50``, ``map50_95``, where evaluated) per epoch.

    Args:
        rows: one dict per epoch with ``epoch`` and any of the keys above (the detector's
            ``metrics.json`` history).
    """
    epochs = [r["epoch"] for r in rows]
    fig = _figure((10, 3.6), 100)
    ax1, ax2 = fig.subplots(1, 2)
    for key in ("loss", "box", "obj", "cls"):
        if any(key in r for r in rows):
            ax1.plot(epochs, [r.get(key, np.nan) for r in rows], label=key)
    ax1.set_xlabel("epoch")
    ax1.set_ylabel("train loss")
    ax1.set_yscale("log")
    ax1.legend()
    for key in ("map50", "map50_95"):
        xs = [r["epoch"] for r in rows if r.get(key) is not None]
        ax2.plot(xs, [r[key] for r in rows if r.get(key) is not None], "o-", label=key)
    ax2.set_xlabel("epoch")
    ax2.set_ylabel("validation mAP")
    ax2.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


def training_curves_writer(path: str | Path) -> Callable[[Sequence[Mapping[str, Any]], Any],
                                                        None]:
    """A per-epoch callback for the detector's training
    (:func:`uavcal_jax.detect.train.train`'s ``on_epoch``): redraws :func:`plot_training_curves`
    at ``path`` after every epoch, titled with the model's name. A plot must never stop
    training: a failed one writes its error to ``path`` with the suffix ``.txt`` instead."""
    path = Path(path)

    def on_epoch(history: Sequence[Mapping[str, Any]], det_cfg: Any) -> None:
        try:
            plot_training_curves(path, history, title=det_cfg.model)
        except Exception as err:  # noqa: BLE001 - a plot must never stop training
            path.with_suffix(".txt").write_text(f"plot failed: {err}\n")

    return on_epoch


def plot_offsets(path: str | Path, start_s: np.ndarray, channels: Sequence[str],
                 series: Mapping[str, np.ndarray], *, true: np.ndarray | None = None,
                 true_label: str = "true", median: np.ndarray | None = None,
                 styles: Mapping[str, Mapping[str, Any]] | None = None,
                 title: str | None = None) -> Path:
    """Per channel (a grid of three columns), each series' per-window offset estimate against
    the window's start time, the median estimate and the true offset as horizontal lines.

    Args:
        start_s: ``(W,)`` window start times, seconds.
        channels: the ``C`` channel names (a multiple of 3; names starting with ``g`` are gyro
            channels in rad/s, the others accel in m/s^2).
        series: label -> ``(W, C)`` estimates (e.g. one per method).
        true: ``(C,)`` the true offset, or ``None`` when unknown.
        median: ``(C,)`` the sequence's estimate (the median over windows), or ``None``.
        styles: label -> matplotlib line keywords (default: dots).
        title: the figure's title.
    """
    styles = styles or {}
    c = len(channels)
    rows = max(1, c // 3)
    fig = _figure((12, 3.3 * rows), 110)
    axes = np.atleast_2d(fig.subplots(rows, 3, sharex=True, squeeze=False))
    for j, (ax, name) in enumerate(zip(axes.flat, channels, strict=True)):
        for label, values in series.items():
            style = styles.get(label, {"marker": ".", "ls": "none", "ms": 4})
            ax.plot(start_s, np.asarray(values)[:, j], label=label, **style)
        if median is not None:
            ax.axhline(median[j], color="C0", lw=1.5, label="median")
        if true is not None:
            ax.axhline(true[j], color="k", ls="--", lw=1.3, label=true_label)
        ax.set_title(name + (" (rad/s)" if name.startswith("g") else " (m/s^2)"))
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("window start (s)")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    return _save(fig, path)


def plot_drift_curves(path: str | Path,
                      panels: Sequence[tuple[str, Mapping[str, tuple[np.ndarray, np.ndarray]]]],
                      *, columns: int = 2, title: str | None = None) -> Path:
    """Position error against distance travelled, one line per correction, one panel per
    (flight, estimator) pair (the drift study, :mod:`uavcal_jax.pipeline.drift`).

    Args:
        panels: ``(panel title, {line label: (distance_m (M,), error_m (M,))})`` in reading
            order, ``columns`` to a row (e.g. dead reckoning then VIO for each flight).
        columns: panels per row.
        title: the figure's title.

    The error axis is logarithmic: dead reckoning on a raw IMU and the VIO on a corrected one
    differ by orders of magnitude.
    """
    rows = max(1, -(-len(panels) // columns))
    fig = _figure((6.0 * columns, 3.8 * rows), 110)
    axes = np.atleast_2d(fig.subplots(rows, columns, squeeze=False))
    labels: list[str] = []
    for ax, (name, lines) in zip(axes.flat, panels, strict=False):
        for label, (distance, error) in lines.items():
            if label not in labels:
                labels.append(label)
            ax.plot(distance, np.maximum(error, 1e-3), lw=1.3, label=label,
                    color=f"C{labels.index(label)}")
        ax.set_yscale("log")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("distance travelled (m)")
        ax.set_ylabel("position error (m)")
        ax.grid(alpha=0.3, which="both")
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    handles = [h for ax in axes.flat for h in ax.get_legend_handles_labels()[0]]
    by_label = dict(zip([h.get_label() for h in handles], handles, strict=True))
    fig.legend(list(by_label.values()), list(by_label), loc="lower center",
               ncol=len(by_label), fontsize=9)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return _save(fig, path)


# ----------------------------------------------------------------------------- uavcal run


def plot_run(result: Any) -> dict[str, Path]:
    """The figures of a ``uavcal run`` (a :class:`uavcal_jax.pipeline.run.RunResult`), in its
    output folder under :data:`uavcal_jax.pipeline.run_outputs.FIGURE_FILES`' names: the top
    view, a strip of frames with boxes, and the localisation error over time. Returns the
    paths by role."""
    from uavcal_jax.pipeline.run_outputs import FIGURE_FILES

    out = {k: Path(result.out_dir) / v for k, v in FIGURE_FILES.items()}
    _run_top_view(result, out["top_view"])
    _run_frames(result, out["frames"])
    _run_localisation_error(result, out["localisation_error"])
    return out


def _run_top_view(result: Any, path: Path) -> Path:
    """Top view (x-y, metres): the estimated trajectory (aligned to the truth when there is
    one) and the true one, the target's raw and filtered estimates and its true track, and
    the position set-points."""
    ev, seq = result.evaluation, result.sequence
    traj = result.vio.trajectory()
    est = traj.position
    if ev.alignment is not None:
        a = ev.alignment
        est = a.scale * est @ a.rotation.T + a.translation
    fig = _figure((7.5, 6.5), 110)
    ax = fig.subplots()
    gt = seq.ground_truth
    if gt is not None and ev.alignment is not None:
        span = (gt.t_ns >= traj.t_ns[0]) & (gt.t_ns <= traj.t_ns[-1])
        ax.plot(gt.position[span, 0], gt.position[span, 1], "k-", lw=1.2, label="true trajectory")
    ax.plot(est[:, 0], est[:, 1], "C0-", lw=1.0, label="VIO trajectory")
    if ev.truth is not None:
        ax.plot(ev.truth[:, 0], ev.truth[:, 1], "k--", lw=1.2, label="true target")
    if len(ev.raw_points):
        ax.plot(ev.raw_points[:, 0], ev.raw_points[:, 1], ".", color="C1", ms=3,
                label="target (raw)")
    ax.plot(ev.filtered[:, 0], ev.filtered[:, 1], "-", color="C3", lw=1.3,
            label="target (filtered)")
    ax.plot(ev.setpoints[:, 0], ev.setpoints[:, 1], "-", color="C2", lw=1.0, label="set-points")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    frame = "ground-truth world (aligned)" if ev.alignment is not None else "VIO world"
    ax.set_title(f"{seq.name}: top view, {frame}", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def _run_frames(result: Any, path: Path, count: int = 6) -> Path:
    """``count`` left frames evenly spread over the detected ones, with every detection's
    box (the followed target's thick, red)."""
    cam0 = result.sequence.camera("cam0")
    ran = [k for k, d in enumerate(result.detections) if d is not None]
    picks = [ran[int(i)] for i in np.linspace(0, len(ran) - 1, min(count, len(ran)))] if ran \
        else []
    fig = _figure((3.2 * max(len(picks), 1), 2.8), 110)
    axes = np.atleast_1d(fig.subplots(1, max(len(picks), 1), squeeze=False)[0])
    for ax, k in zip(axes, picks, strict=False):
        ax.imshow(cam0.load(k, "rgb"))
        det = result.detections[k]
        followed = result.target.boxes[k]
        for box, cls in zip(det.boxes, det.classes, strict=True):
            ax.add_patch(_box_patch(box, "C1", 0.8))
            name = result.class_names[int(cls)] if 0 <= int(cls) < len(result.class_names) \
                else str(int(cls))
            ax.text(box[0], box[1] - 2, name, color="C1", fontsize=6)
        if np.all(np.isfinite(followed)):
            ax.add_patch(_box_patch(followed, "red", 2.0))
        ax.set_title(f"frame {k}, t={(cam0.t_ns[k] - cam0.t_ns[0]) * 1e-9:.2f} s", fontsize=8)
        ax.axis("off")
    if not picks:
        axes[0].text(0.5, 0.5, "no frame was run through the detector", ha="center")
        axes[0].axis("off")
    fig.tight_layout()
    return _save(fig, path)


def _box_patch(box, color, width):
    from matplotlib.patches import Rectangle

    x1, y1, x2, y2 = (float(v) for v in box)
    return Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, ec=color, lw=width)


def _run_localisation_error(result: Any, path: Path) -> Path:
    """The target's localisation error against the truth over time (raw and filtered,
    metres); without a truth, the filter's position standard deviation instead."""
    ev, target = result.evaluation, result.target
    t_ns = result.sequence.camera("cam0").t_ns
    t = (t_ns - t_ns[0]) * 1e-9
    fig = _figure((8, 3.5), 110)
    ax = fig.subplots()
    if ev.truth is not None:
        ax.plot(t[target.raw_frames], ev.raw_errors, ".", color="C1", ms=3, label="raw")
        ax.plot(t, ev.filtered_errors, "-", color="C3", lw=1.2, label="filtered")
        ax.set_ylabel("error (m)")
        ax.set_title("target localisation error against the truth (aligned)", fontsize=10)
    else:
        cov = target.filtered.covariance[:, :3, :3]
        sigma = np.sqrt(np.trace(cov, axis1=1, axis2=2))
        sigma = np.where(np.isfinite(target.filtered.position[:, 0]), sigma, np.nan)
        ax.plot(t, sigma, "-", color="C3", lw=1.2, label="filter position std")
        ax.set_ylabel("std (m)")
        reason = ev.omitted.get("target_error_m", "no truth")
        ax.set_title(f"no localisation error: {reason}", fontsize=9)
    ax.set_xlabel("time (s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)
