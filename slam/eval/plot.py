"""Figures, drawn with matplotlib's Agg backend (no display): trajectories with their error (as ``evo_ape --plot``)
and precision/recall curves. Each returns an ``(H, W, 3)`` uint8 **BGR** image of exactly ``size = (W, H)`` pixels
(what ``cv2.imwrite`` takes) and writes it as a PNG when given a path.

Example:
    >>> import torch
    >>> from slam.io.trajectory import Trajectory
    >>> t = torch.linspace(0, 6.28, 50, dtype=torch.float64)
    >>> poses = torch.zeros(50, 7, dtype=torch.float64); poses[:, 6] = 1
    >>> poses[:, 0], poses[:, 2] = t.cos(), t.sin()
    >>> img = plot_trajectory(None, Trajectory(t, poses), size=(400, 300))
    >>> img.shape
    (300, 400, 3)
"""
from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.image import imsave

from slam.io.trajectory import Trajectory

__all__ = ["choose_plane", "plot_pr_curves", "plot_trajectory"]

AXIS_NAMES = "xyz"
_DPI = 100
_GT_STYLE = {"color": "0.45", "linestyle": "--", "linewidth": 1.2}  # evo's reference: grey, dashed
_ERROR_MAP = "jet"  # evo's trajectory colour map of the APE


def _figure(size: tuple[int, int]) -> Figure:
    w, h = size
    if not (int(w) > 0 and int(h) > 0):
        raise ValueError(f"size must be (W, H) pixels > 0, got {size!r}")
    fig = Figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI)
    FigureCanvasAgg(fig)
    return fig


def _margins(fig: Figure) -> None:
    """Margins for the tick and axis labels, in pixels (fixed: matplotlib's tight layout measures every text
    first, which costs a second a figure on a busy CPU)."""
    w, h = fig.get_size_inches() * _DPI
    fig.subplots_adjust(left=80 / w, right=1 - 20 / w, bottom=50 / h, top=1 - 35 / h, wspace=0.45)


def _finish(fig: Figure, path: str | os.PathLike | None) -> np.ndarray:
    """Render ``fig``; write it to ``path`` (parent folders created); the BGR pixels."""
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    if path is not None:
        path = os.fspath(path)
        if os.path.dirname(path):
            os.makedirs(os.path.dirname(path), exist_ok=True)
        imsave(path, rgb, format="png")
    return np.ascontiguousarray(rgb[..., ::-1])


def choose_plane(positions: torch.Tensor) -> tuple[int, int]:
    """The two axes (ascending) with the largest spread: the view from along the least-varying axis.

    Args:
        positions: ``(N, 3)``.

    Returns:
        ``(a, b)`` axis indices, e.g. ``(0, 2)`` for the x-z plane.

    Example:
        >>> choose_plane(torch.tensor([[0.0, 0, 0], [1, 0.1, 2], [2, 0, 1]]))
        (0, 2)
    """
    if positions.dim() != 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions must have shape (N, 3), got {tuple(positions.shape)}")
    if positions.shape[0] < 2:
        return (0, 1)
    drop = int(torch.argmin(positions.to(torch.float64).var(dim=0)))
    return tuple(k for k in range(3) if k != drop)


def _nearest_indices(stamps: np.ndarray, queries: np.ndarray) -> np.ndarray:
    k = np.clip(np.searchsorted(stamps, queries), 1, max(len(stamps) - 1, 1))
    left = np.abs(queries - stamps[k - 1]) <= np.abs(stamps[np.minimum(k, len(stamps) - 1)] - queries)
    return np.where(left, k - 1, k).clip(0, len(stamps) - 1)


def _positions(traj: Trajectory) -> torch.Tensor:
    return traj.poses[:, :3].detach().to("cpu", torch.float64)


def plot_trajectory(
    path: str | os.PathLike | None,
    estimate: Trajectory,
    reference: Trajectory | None = None,
    loops: torch.Tensor | None = None,
    plane: str = "auto",
    align: bool | object = True,
    size: tuple[int, int] | None = None,
    title: str | None = None,
    labels: tuple[str, str] = ("ground truth", "estimate"),
) -> np.ndarray:
    """The estimated trajectory (and the ground truth) seen from above, with loop edges; with an ATE, each pose
    coloured by its error and a second panel of the error over time.

    Args:
        path: PNG to write, or None to only return the image.
        estimate: ``N`` estimated camera-to-world poses.
        reference: ground truth, or None.
        loops: ``(M, 2)`` float64 timestamps ``(a, b)`` of accepted loops (``loops.txt``); each is
            drawn as a line between the estimated positions nearest in time to ``a`` and ``b``.
        plane: ``"auto"`` (the two axes with the largest spread of the ground truth, else of the
            estimate; the axis labels say which), or ``"xy"``, ``"xz"``, ``"yz"``.
        align: rigidly align the estimate to the reference first (as the ATE does) so both share a frame;
            or an :class:`~slam.eval.metrics.ATEResult`, whose alignment (rotation, translation, scale) and errors
            are drawn: the figure then shows what that result measured (Sim(3), a time offset, ...). False: the
            estimate as it is, no error colouring.
        size: ``(W, H)`` pixels; default 800 x 700, 1300 x 600 with the error panel.
        title: figure title (default names the plane).
        labels: legend entries of the reference and of the estimate.

    Returns:
        the ``(H, W, 3)`` uint8 BGR image.
    """
    if not isinstance(estimate, Trajectory):
        raise TypeError(f"estimate must be a Trajectory, got {type(estimate).__name__}")
    if len(labels) != 2 or not all(isinstance(s, str) for s in labels):
        raise ValueError(f"labels must be two strings (reference, estimate), got {labels!r}")
    if plane != "auto" and plane not in ("xy", "xz", "yz"):
        raise ValueError(f"plane must be 'auto', 'xy', 'xz' or 'yz', got {plane!r}")
    from slam.eval.metrics import ATEResult, ate  # local: metrics imports this module's siblings

    est_pos, ref_pos, result = _positions(estimate), None, align if isinstance(align, ATEResult) else None
    if reference is not None:
        ref_pos = _positions(reference)
        if result is None and align is not False and len(estimate) > 0 and len(reference) > 0:
            try:
                result = ate(reference, estimate)
            except ValueError as e:
                warnings.warn(f"trajectory plot: estimate not aligned to the reference ({e})", stacklevel=2)
    aligned = result is not None and result.alignment != "none"
    if result is not None:
        R, t = result.rotation.detach().to("cpu", torch.float64), result.translation.detach().to("cpu", torch.float64)
        est_pos = result.scale * est_pos @ R.T + t
    if plane == "auto":
        basis = ref_pos if ref_pos is not None and len(ref_pos) >= 2 else est_pos
        a, b = choose_plane(basis)  # (0, 1) for fewer than two positions
    else:
        a, b = AXIS_NAMES.index(plane[0]), AXIS_NAMES.index(plane[1])
    est2 = est_pos[:, [a, b]].numpy()

    fig = _figure(size or ((1300, 600) if result is not None else (800, 700)))
    if result is not None:
        ax, ax_err = fig.subplots(1, 2, width_ratios=(1.15, 1))
    else:
        ax, ax_err = fig.subplots(), None
    if ref_pos is not None and len(ref_pos):
        ax.plot(*ref_pos[:, [a, b]].numpy().T, label=labels[0], **_GT_STYLE)
    est_label = labels[1] + (" (aligned)" if aligned else "")
    if result is not None and result.num_pairs >= 2:
        # evo's colour map: each segment of the associated poses in the colour of its error
        xy = result.estimate_aligned.poses[:, :3].detach().to("cpu", torch.float64)[:, [a, b]].numpy()
        err = result.errors.detach().to("cpu", torch.float64).numpy()
        lines = LineCollection(np.stack([xy[:-1], xy[1:]], axis=1), cmap=_ERROR_MAP, linewidths=2,
                               label=f"{est_label}, coloured by error")
        lines.set_array((err[:-1] + err[1:]) / 2)
        lines.set_clim(float(err.min()), float(err.max()))
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label="position error [m]", fraction=0.046, pad=0.02)
    elif len(est2):
        ax.plot(*est2.T, color="C0", linewidth=1.6, label=est_label)
    if loops is not None and len(loops) and len(est2):
        loops_np = torch.as_tensor(loops).detach().to("cpu", torch.float64).numpy().reshape(-1, 2)
        stamps = estimate.timestamps.detach().to("cpu", torch.float64).numpy()
        order = np.argsort(stamps, kind="stable")
        ia = order[_nearest_indices(stamps[order], loops_np[:, 0])]
        ib = order[_nearest_indices(stamps[order], loops_np[:, 1])]
        ax.add_collection(LineCollection(np.stack([est2[ia], est2[ib]], axis=1), colors="C3", linewidths=1,
                                         label=f"loop edges ({len(loops_np)})"))
    if len(est2):
        ax.plot(*est2[0], "o", color="C2", markersize=7, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
    ax.grid(True, alpha=0.3)
    ax.set_title(title or f"Trajectory, top view ({AXIS_NAMES[a]}-{AXIS_NAMES[b]} plane, metres)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")
    if ax_err is not None:
        _plot_errors(ax_err, result)
    _margins(fig)
    return _finish(fig, path)


def _plot_errors(ax, result) -> None:
    """The position error over time with its RMSE, mean, median and the mean +- one std band (evo's APE plot)."""
    t = result.timestamps.detach().to("cpu", torch.float64).numpy()
    err = result.errors.detach().to("cpu", torch.float64).numpy()
    t = t - t[0] if len(t) else t
    ax.plot(t, err, color="0.3", linewidth=1, label="position error")
    ax.axhline(result.rmse, color="C0", label=f"rmse {result.rmse:.4f} m")
    ax.axhline(result.median, color="C1", label=f"median {result.median:.4f} m")
    ax.axhline(result.mean, color="C3", label=f"mean {result.mean:.4f} m")
    ax.axhspan(result.mean - result.std, result.mean + result.std, color="C3", alpha=0.15,
               label=f"std {result.std:.4f} m")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [m]")
    ax.set_title(f"Absolute trajectory error ({result.num_pairs} poses, {result.alignment} alignment)")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")


def plot_pr_curves(
    path: str | os.PathLike | None,
    curves: Mapping[str, object] | Sequence[tuple[str, object]],
    title: str = "Loop closure: precision / recall",
    size: tuple[int, int] = (640, 520),
) -> np.ndarray:
    """Precision/recall curves as step lines (recall on x, precision on y), a dot at each one's maximum recall at
    100 % precision; the legend gives it (``R@P100``) with the average precision (``AP``).

    Args:
        path: PNG to write, or None.
        curves: ``{label: PRCurve}`` or ``[(label, PRCurve), ...]``.
        title: figure title.
        size: ``(W, H)`` pixels.

    Returns:
        the ``(H, W, 3)`` uint8 BGR image.
    """
    items = list(curves.items()) if isinstance(curves, Mapping) else list(curves)
    fig = _figure(size)
    ax = fig.subplots()
    for k, (label, c) in enumerate(items):
        colour = f"C{k % 10}"
        ax.plot(c.recall.cpu().numpy(), c.precision.cpu().numpy(), drawstyle="steps-post", color=colour,
                linewidth=1.8, label=f"{label} (R@P100 {c.max_recall_at_full_precision:.2f}, "
                                     f"AP {c.average_precision:.2f})")
        ax.plot([c.max_recall_at_full_precision], [1.0], "o", color=colour, markersize=6)
    if not items:
        ax.text(0.5, 0.5, "no curves", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    if items:
        ax.legend(loc="lower left", fontsize="small")
    _margins(fig)
    return _finish(fig, path)
