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
  time, with the median and the true offset (the calibrator's "Figure 2" view).
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

__all__ = ["plot_offsets", "plot_trajectories", "plot_training_curves",
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
