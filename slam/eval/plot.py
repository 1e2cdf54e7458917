"""Figures drawn with OpenCV only (no matplotlib): the top view of a trajectory, and small axes helpers
shared with the precision/recall plot of :mod:`slam.eval.loops`.

Images are returned as ``(H, W, 3)`` uint8 **BGR** (what ``cv2.imwrite`` writes).

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

import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from slam.io.trajectory import Trajectory

__all__ = ["Axes", "choose_plane", "draw_legend", "nice_step", "plot_trajectory", "save_image"]

Color = tuple[int, int, int]
FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK: Color = (0, 0, 0)
GREY: Color = (150, 150, 150)
LIGHT: Color = (232, 232, 232)
# A colour-blind-safe palette (Okabe-Ito), BGR.
PALETTE: list[Color] = [(178, 114, 0), (0, 94, 213), (115, 158, 0), (167, 121, 204), (233, 180, 86), (66, 228, 240)]
AXIS_NAMES = "xyz"


def nice_step(span: float, target: int = 6) -> float:
    """A 1-2-5 x 10^k tick step giving about ``target`` ticks over ``span``.

    Example:
        >>> nice_step(1.0), nice_step(3.0), nice_step(0.12)
        (0.2, 0.5, 0.02)
    """
    if not span > 0:
        return 1.0
    raw = span / max(target, 1)
    base = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if raw <= m * base * (1 + 1e-9):
            return float(f"{m * base:.12g}")
    return 10.0 * base


def _fmt(v: float, step: float) -> str:
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    s = f"{v:.{decimals}f}"
    return "0" if s.strip("-0.") == "" else s


def draw_text(img, s: str, org: tuple[int, int], scale=0.45, color: Color = BLACK, thickness=1, anchor="left"):
    (w, h), _ = cv2.getTextSize(s, FONT, scale, thickness)
    x, y = org
    if anchor == "center":
        x -= w // 2
    elif anchor == "right":
        x -= w
    cv2.putText(img, s, (int(x), int(y)), FONT, scale, color, thickness, cv2.LINE_AA)
    return w, h


def _vertical_text(img, s: str, center: tuple[int, int], scale=0.5, color: Color = BLACK):
    (w, h), base = cv2.getTextSize(s, FONT, scale, 1)
    patch = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
    cv2.putText(patch, s, (2, h + 2), FONT, scale, color, 1, cv2.LINE_AA)
    patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    ph, pw = patch.shape[:2]
    y0, x0 = max(0, center[1] - ph // 2), max(0, center[0] - pw // 2)
    region = img[y0:y0 + ph, x0:x0 + pw]
    np.minimum(region, patch[:region.shape[0], :region.shape[1]], out=region)


@dataclass
class Axes:
    """A data rectangle ``[x0, x1] x [y0, y1]`` mapped into a pixel box of an image (y up)."""

    x0: float
    x1: float
    y0: float
    y1: float
    left: int
    top: int
    right: int
    bottom: int

    @staticmethod
    def fit(size: tuple[int, int], xlim, ylim, margins=(70, 45, 20, 55), equal: bool = False) -> Axes:
        """Axes filling ``size = (W, H)`` minus ``margins = (left, top, right, bottom)``; with ``equal``
        one metre is the same number of pixels on both axes (the limits grow to fit)."""
        W, H = size
        left, top, right, bottom = margins[0], margins[1], W - margins[2], H - margins[3]
        (x0, x1), (y0, y1) = xlim, ylim
        if equal:
            sx, sy = (x1 - x0) / max(right - left, 1), (y1 - y0) / max(bottom - top, 1)
            s = max(sx, sy, 1e-12)
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            x0, x1 = cx - s * (right - left) / 2, cx + s * (right - left) / 2
            y0, y1 = cy - s * (bottom - top) / 2, cy + s * (bottom - top) / 2
        return Axes(x0, x1, y0, y1, left, top, right, bottom)

    @property
    def pixels_per_unit_x(self) -> float:
        return (self.right - self.left) / (self.x1 - self.x0)

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """``(N, 2)`` data coordinates -> ``(N, 2)`` int32 pixel coordinates."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        u = self.left + (xy[:, 0] - self.x0) / (self.x1 - self.x0) * (self.right - self.left)
        v = self.bottom - (xy[:, 1] - self.y0) / (self.y1 - self.y0) * (self.bottom - self.top)
        return np.round(np.stack([u, v], axis=-1)).astype(np.int32)

    def draw_frame(self, img, xlabel: str, ylabel: str, title: str = "", xstep=None, ystep=None, grid=True):
        """Grid, ticks with labels, axis labels, a box and a title."""
        xstep = xstep or nice_step(self.x1 - self.x0)
        ystep = ystep or nice_step(self.y1 - self.y0)
        for v in np.arange(math.ceil(self.x0 / xstep - 1e-9), math.floor(self.x1 / xstep + 1e-9) + 1) * xstep:
            u = int(self.to_px([[v, self.y0]])[0, 0])
            if grid:
                cv2.line(img, (u, self.top), (u, self.bottom), LIGHT, 1)
            cv2.line(img, (u, self.bottom), (u, self.bottom + 5), BLACK, 1)
            draw_text(img, _fmt(v, xstep), (u, self.bottom + 20), 0.4, anchor="center")
        for v in np.arange(math.ceil(self.y0 / ystep - 1e-9), math.floor(self.y1 / ystep + 1e-9) + 1) * ystep:
            y = int(self.to_px([[self.x0, v]])[0, 1])
            if grid:
                cv2.line(img, (self.left, y), (self.right, y), LIGHT, 1)
            cv2.line(img, (self.left - 5, y), (self.left, y), BLACK, 1)
            draw_text(img, _fmt(v, ystep), (self.left - 8, y + 4), 0.4, anchor="right")
        cv2.rectangle(img, (self.left, self.top), (self.right, self.bottom), BLACK, 1)
        draw_text(img, xlabel, ((self.left + self.right) // 2, self.bottom + 42), 0.5, anchor="center")
        _vertical_text(img, ylabel, (14, (self.top + self.bottom) // 2))
        if title:
            draw_text(img, title, ((self.left + self.right) // 2, self.top - 15), 0.55, anchor="center")

    def polyline(self, img, xy: np.ndarray, color: Color, thickness: int = 2):
        if len(xy) >= 2:
            cv2.polylines(img, [self.to_px(xy).reshape(-1, 1, 2)], False, color, thickness, cv2.LINE_AA)


def draw_legend(img, entries: Sequence[tuple[str, Color, str]], corner: str = "top-right", box=None):
    """A legend box; ``entries`` are ``(label, colour, kind)`` with kind ``"line"`` or ``"dot"``.

    ``box = (left, top, right, bottom)`` of the plot area it goes in (default: the whole image).
    """
    if not entries:
        return
    left, top, right, bottom = box if box is not None else (0, 0, img.shape[1], img.shape[0])
    width = max(cv2.getTextSize(label, FONT, 0.45, 1)[0][0] for label, _, _ in entries) + 50
    height = 20 * len(entries) + 10
    x0 = right - width - 8 if "right" in corner else left + 8
    y0 = top + 8 if "top" in corner else bottom - height - 8
    cv2.rectangle(img, (x0, y0), (x0 + width, y0 + height), (255, 255, 255), -1)
    cv2.rectangle(img, (x0, y0), (x0 + width, y0 + height), GREY, 1)
    for k, (label, color, kind) in enumerate(entries):
        y = y0 + 15 + 20 * k
        if kind == "dot":
            cv2.circle(img, (x0 + 20, y), 4, color, -1, cv2.LINE_AA)
        else:
            cv2.line(img, (x0 + 8, y), (x0 + 32, y), color, 2, cv2.LINE_AA)
        draw_text(img, label, (x0 + 40, y + 5), 0.45)


def save_image(path: str | os.PathLike, img: np.ndarray) -> None:
    """Write a PNG (parent folders are created); raises OSError if OpenCV cannot write it."""
    path = os.fspath(path)
    parent = os.path.dirname(path)
    if parent:
        os.makedirs(parent, exist_ok=True)
    if not cv2.imwrite(path, img):
        raise OSError(f"could not write image {path}")


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
    spread = positions.to(torch.float64).var(dim=0)
    drop = int(torch.argmin(spread))
    a, b = [k for k in range(3) if k != drop]
    return (a, b)


def _nearest_indices(stamps: np.ndarray, queries: np.ndarray) -> np.ndarray:
    k = np.clip(np.searchsorted(stamps, queries), 1, max(len(stamps) - 1, 1))
    left = np.abs(queries - stamps[k - 1]) <= np.abs(stamps[np.minimum(k, len(stamps) - 1)] - queries)
    return np.where(left, k - 1, k).clip(0, len(stamps) - 1)


def plot_trajectory(
    path: str | os.PathLike | None,
    estimate: Trajectory,
    reference: Trajectory | None = None,
    loops: torch.Tensor | None = None,
    plane: str = "auto",
    align: bool | object = True,
    size: tuple[int, int] = (800, 700),
    title: str | None = None,
    labels: tuple[str, str] = ("ground truth", "estimate"),
) -> np.ndarray:
    """Draw the estimated trajectory (and the ground truth) seen from above, with loop edges.

    Args:
        path: PNG to write, or None to only return the image.
        estimate: ``N`` estimated camera-to-world poses.
        reference: ground truth, or None.
        loops: ``(M, 2)`` float64 timestamps ``(a, b)`` of accepted loops (``loops.txt``); each is
            drawn as a line between the estimated positions nearest in time to ``a`` and ``b``.
        plane: ``"auto"`` (the two axes with the largest spread of the ground truth, else of the
            estimate; the title says which), or ``"xy"``, ``"xz"``, ``"yz"``.
        align: rigidly align the estimate to the reference first (as the ATE does) so both share a frame;
            or an :class:`~slam.eval.metrics.ATEResult`, whose alignment (rotation, translation, scale) is
            applied: the figure then shows what that result measured (Sim(3), a time offset, ...).
        size: ``(W, H)`` pixels.
        title: figure title (default names the plane).
        labels: legend entries of the reference and of the estimate.

    Returns:
        the ``(H, W, 3)`` uint8 BGR image.
    """
    if not isinstance(estimate, Trajectory):
        raise TypeError(f"estimate must be a Trajectory, got {type(estimate).__name__}")
    if len(labels) != 2 or not all(isinstance(s, str) for s in labels):
        raise ValueError(f"labels must be two strings (reference, estimate), got {labels!r}")
    est_pos = estimate.poses[:, :3].detach().to("cpu", torch.float64)
    from slam.eval.metrics import ATEResult, ate  # local: metrics imports this module's siblings

    given = align if isinstance(align, ATEResult) else None
    aligned = given.alignment != "none" if given is not None else bool(align)
    ref_pos = None
    if reference is not None:
        ref_pos = reference.poses[:, :3].detach().to("cpu", torch.float64)
        if given is not None or (align and len(estimate) > 0 and len(reference) > 0):
            try:
                result = given if given is not None else ate(reference, estimate)
                R, t = result.rotation.detach().to("cpu", torch.float64), result.translation.detach().to("cpu", torch.float64)
                est_pos = result.scale * est_pos @ R.T + t
            except ValueError as e:
                warnings.warn(f"trajectory plot: estimate not aligned to the reference ({e})", stacklevel=2)
    if plane == "auto":
        basis = ref_pos if ref_pos is not None and len(ref_pos) >= 2 else est_pos
        a, b = choose_plane(basis) if len(basis) else (0, 1)
    else:
        if plane not in ("xy", "xz", "yz"):
            raise ValueError(f"plane must be 'auto', 'xy', 'xz' or 'yz', got {plane!r}")
        a, b = AXIS_NAMES.index(plane[0]), AXIS_NAMES.index(plane[1])
    est2 = est_pos[:, [a, b]].numpy()
    ref2 = ref_pos[:, [a, b]].numpy() if ref_pos is not None else np.zeros((0, 2))
    pts = np.concatenate([est2, ref2], axis=0)
    if len(pts) == 0:
        pts = np.zeros((1, 2))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = np.maximum((hi - lo) * 0.06, 0.05)
    ax = Axes.fit(size, (lo[0] - pad[0], hi[0] + pad[0]), (lo[1] - pad[1], hi[1] + pad[1]), equal=True)

    W, H = size
    img = np.full((H, W, 3), 255, np.uint8)
    plane_name = f"{AXIS_NAMES[a]}-{AXIS_NAMES[b]}"
    step = nice_step(max(ax.x1 - ax.x0, ax.y1 - ax.y0))
    ax.draw_frame(img, f"{AXIS_NAMES[a]} [m]", f"{AXIS_NAMES[b]} [m]",
                  title or f"Trajectory, top view ({plane_name} plane, metres)", step, step)

    legend = []
    if len(ref2):
        ax.polyline(img, ref2, GREY, 2)
        legend.append((labels[0], GREY, "line"))
    ax.polyline(img, est2, PALETTE[0], 2)
    legend.append((labels[1] + (" (aligned)" if ref_pos is not None and aligned else ""), PALETTE[0], "line"))
    if loops is not None and len(loops) and len(est2):
        loops_np = torch.as_tensor(loops).detach().to("cpu", torch.float64).numpy().reshape(-1, 2)
        stamps = estimate.timestamps.detach().to("cpu", torch.float64).numpy()
        order = np.argsort(stamps, kind="stable")
        ia = order[_nearest_indices(stamps[order], loops_np[:, 0])]
        ib = order[_nearest_indices(stamps[order], loops_np[:, 1])]
        pa, pb = ax.to_px(est2[ia]), ax.to_px(est2[ib])
        for p, q in zip(pa, pb):
            cv2.line(img, tuple(int(v) for v in p), tuple(int(v) for v in q), PALETTE[1], 1, cv2.LINE_AA)
        legend.append((f"loop edges ({len(loops_np)})", PALETTE[1], "line"))
    if len(est2):
        start = ax.to_px(est2[:1])[0]
        cv2.circle(img, (int(start[0]), int(start[1])), 5, PALETTE[2], -1, cv2.LINE_AA)
        legend.append(("start", PALETTE[2], "dot"))
    draw_legend(img, legend, "top-right", (ax.left, ax.top, ax.right, ax.bottom))

    # Scale bar: one tick step, bottom-left inside the plot.
    bar = round(step * ax.pixels_per_unit_x)
    x0, y0 = ax.left + 12, ax.bottom - 14
    cv2.line(img, (x0, y0), (x0 + bar, y0), BLACK, 2)
    for x in (x0, x0 + bar):
        cv2.line(img, (x, y0 - 4), (x, y0 + 4), BLACK, 2)
    draw_text(img, f"{_fmt(step, step)} m", (x0 + bar // 2, y0 - 8), 0.45, anchor="center")

    if path is not None:
        save_image(path, img)
    return img
