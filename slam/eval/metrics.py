"""Absolute trajectory error (ATE) and relative pose error (RPE), equal to evo's ``evo_ape`` / ``evo_rpe``.

Trajectories are associated by timestamp first (:mod:`slam.io.associate`: evo's rule by default, TUM's with
``association="tum"``). The ATE aligns the estimate's positions by Umeyama and measures camera-centre distances;
the RPE compares ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` (``Q`` reference, ``P`` estimate) over pairs ``delta`` apart.

Example:
    >>> import torch
    >>> from slam.io.trajectory import Trajectory
    >>> t = torch.arange(5, dtype=torch.float64)
    >>> poses = torch.zeros(5, 7, dtype=torch.float64); poses[:, 6] = 1; poses[:, 0] = t; poses[:, 1] = t ** 2
    >>> ref = Trajectory(t, poses)
    >>> round(ate(ref, ref).rmse, 9), ate(ref, ref).num_pairs
    (0.0, 5)
    >>> rpe(ref, ref, delta=1).translation.num
    4
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from typing import Union

import numpy as np
import torch

from slam.eval.align import transform_poses, umeyama_alignment
from slam.io.associate import TUM_MAX_DIFFERENCE, association_indices
from slam.input_checks import MAX_COORDINATE, timestamp_unit, unit_quaternions
from slam.io.trajectory import Trajectory, read_tum_trajectory
from slam.lie import quat_angle, se3_between

__all__ = ["ATEResult", "ErrorStats", "RPEResult", "as_trajectory", "ate", "rpe"]

TrajectoryLike = Union[str, "os.PathLike[str]", Trajectory]
_ALIGNMENTS = ("se3", "sim3", "none")


def as_trajectory(x: TrajectoryLike, what: str = "trajectory") -> Trajectory:
    """A checked :class:`Trajectory` in float64 from a trajectory or the path of a TUM file.

    Raises:
        ValueError: naming ``what``, the pose and its timestamp: a non-finite timestamp or pose, a
            translation beyond :data:`~slam.input_checks.MAX_COORDINATE`, a zero quaternion (so no error
            figure is ever ``inf`` or NaN); :class:`~slam.io.trajectory.TrajectoryFormatError` for a file.
    """
    if isinstance(x, Trajectory):
        traj = x
    elif isinstance(x, (str, os.PathLike)):
        traj = read_tum_trajectory(x)
    else:
        raise TypeError(f"{what} must be a Trajectory or the path of a TUM trajectory file, got {type(x).__name__}")
    stamps, poses = traj.timestamps.to(torch.float64), traj.poses.to(torch.float64)
    bad = ~torch.isfinite(stamps)
    if bool(bad.any()):
        k = int(bad.nonzero()[0, 0])
        raise ValueError(f"{what}: timestamp {k} is {float(stamps[k])}; expected finite seconds")
    P = poses.detach().cpu().numpy()

    def refuse(mask, why):
        if mask.any():
            k = int(mask.nonzero()[0][0])
            raise ValueError(f"{what}: pose {k} (t = {float(stamps[k]):.6f} s) {why(k)}")

    refuse(~np.isfinite(P).all(axis=1), lambda k: f"has a non-finite value {P[k].tolist()}")
    refuse(np.abs(P[:, :3]).max(axis=1, initial=0.0) > MAX_COORDINATE,
           lambda k: f"has a translation {P[k, :3].tolist()} beyond {MAX_COORDINATE:.0e} m")
    # unit quaternions, as evo (its SE(3) matrices come from normalised quaternions), without overflow
    q, zero = unit_quaternions(P[:, 3:])
    refuse(zero, lambda k: f"has a zero quaternion {P[k, 3:].tolist()}")
    poses = torch.cat([poses[:, :3], torch.from_numpy(q).to(poses.device)], dim=-1)
    return Trajectory(stamps, poses)


@dataclass
class ErrorStats:
    """Statistics of a set of non-negative errors, named as evo names them.

    Attributes:
        rmse, mean, median, std, min, max: floats (``std`` is the population std, ``median`` the
            average of the two middle values for an even count, as numpy).
        sse: sum of squared errors.
        num: number of errors.
    """

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    num: int

    @staticmethod
    def from_errors(errors: torch.Tensor) -> ErrorStats:
        """Statistics of ``errors (M,)``, ``M >= 1``."""
        if errors.dim() != 1 or errors.numel() == 0:
            raise ValueError(f"errors must have shape (M,) with M >= 1, got {tuple(errors.shape)}")
        e = errors.detach().to(torch.float64)
        sse = float((e * e).sum())
        return ErrorStats(
            rmse=math.sqrt(sse / e.numel()),
            mean=float(e.mean()),
            median=float(torch.quantile(e, 0.5)) if e.numel() <= 16_000_000 else float(e.median()),
            std=float(e.std(unbiased=False)) if e.numel() > 1 else 0.0,
            min=float(e.min()),
            max=float(e.max()),
            sse=sse,
            num=int(e.numel()),
        )

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass
class ATEResult:
    """Absolute trajectory error after alignment (translation part, metres).

    Attributes:
        rmse, mean, median, std, min, max, sse: statistics of ``errors`` (see :class:`ErrorStats`).
        num_pairs: number of associated pose pairs.
        alignment: ``"se3"``, ``"sim3"`` or ``"none"``.
        scale: the Sim(3) scale (1.0 otherwise).
        rotation: ``(3, 3)`` and translation ``(3,)``: the alignment applied to the estimate.
        errors: ``(K,)`` per-pair position errors.
        timestamps: ``(K,)`` reference stamps of the pairs.
        reference: the associated reference poses ``(K, 7)`` as a trajectory.
        estimate_aligned: the associated estimate poses after alignment, as a trajectory.
    """

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    num_pairs: int
    alignment: str
    scale: float
    rotation: torch.Tensor = field(repr=False)
    translation: torch.Tensor = field(repr=False)
    errors: torch.Tensor = field(repr=False)
    timestamps: torch.Tensor = field(repr=False)
    reference: Trajectory = field(repr=False)
    estimate_aligned: Trajectory = field(repr=False)

    def to_dict(self) -> dict[str, object]:
        """The scalar results (JSON-serialisable)."""
        return {"rmse": self.rmse, "mean": self.mean, "median": self.median, "std": self.std, "min": self.min,
                "max": self.max, "sse": self.sse, "num_pairs": self.num_pairs, "alignment": self.alignment,
                "scale": self.scale}


@dataclass
class RPEResult:
    """Relative pose error.

    Attributes:
        translation: statistics of the translation errors (metres).
        rotation: statistics of the rotation errors (degrees).
        delta: the pair distance, in ``delta_unit`` (``"frames"`` or ``"seconds"``).
        all_pairs: every start index was used (otherwise consecutive, non-overlapping pairs).
        pairs: ``(M, 2)`` int64 indices ``(i, j)`` into the associated poses.
        timestamps: ``(M, 2)`` the estimate's stamps of each pair.
        trans_errors: ``(M,)`` metres; rot_errors: ``(M,)`` degrees.
    """

    translation: ErrorStats
    rotation: ErrorStats
    delta: float
    delta_unit: str
    all_pairs: bool
    pairs: torch.Tensor = field(repr=False)
    timestamps: torch.Tensor = field(repr=False)
    trans_errors: torch.Tensor = field(repr=False)
    rot_errors: torch.Tensor = field(repr=False)

    @property
    def rmse(self) -> float:
        """Translation RMSE in metres (the number usually quoted)."""
        return self.translation.rmse

    @property
    def num_pairs(self) -> int:
        return int(self.pairs.shape[0])

    def to_dict(self) -> dict[str, object]:
        return {"translation_m": self.translation.to_dict(), "rotation_deg": self.rotation.to_dict(),
                "delta": self.delta, "delta_unit": self.delta_unit, "all_pairs": self.all_pairs,
                "num_pairs": self.num_pairs}


def _no_pairs_hint(ref_t: torch.Tensor, est_t: torch.Tensor, offset: float) -> str:
    """What to try when no stamps pair: other units, a clock offset (--t-offset), or a larger tolerance."""
    units = [timestamp_unit(t.detach().cpu().numpy())[0] for t in (ref_t, est_t)]
    if units[0] != units[1]:
        return (f"; the reference's stamps look like {units[0]} and the estimate's like {units[1]}: write both in "
                "seconds")
    r0, r1 = float(ref_t.min()), float(ref_t.max())
    e0, e1 = float(est_t.min()) + offset, float(est_t.max()) + offset
    if e1 < r0 or e0 > r1:  # disjoint spans: clocks with different origins
        shift = r0 - (e0 - offset)
        return (f"; the two do not overlap in time: if their clocks differ, give the offset that makes them "
                f"overlap (--t-offset {shift:.6f} in attnloop-eval, offset={shift:.6f} in Python, lines up the "
                f"first poses)")
    return "; they overlap in time but are sampled apart: try a larger tolerance (--t-max-diff, max_difference)"


def _associated(reference: TrajectoryLike, estimate: TrajectoryLike, max_difference: float, offset: float,
                association: str):
    ref = as_trajectory(reference, "reference")
    est = as_trajectory(estimate, "estimate")
    if len(ref) == 0 or len(est) == 0:
        empty = [f"{what} {os.fspath(x) if isinstance(x, (str, os.PathLike)) else ''}".strip()
                 for what, x, t in (("reference", reference, ref), ("estimate", estimate, est)) if len(t) == 0]
        raise ValueError(f"cannot evaluate an empty trajectory ({len(ref)} reference, {len(est)} estimated poses): "
                         f"{' and '.join(empty)} holds no pose")
    i, j = association_indices(ref.timestamps, est.timestamps, max_difference, offset, association)
    if i.numel() == 0:
        raise ValueError(
            f"no timestamps of the estimate ({len(est)} poses, {float(est.timestamps[0]):.3f}..."
            f"{float(est.timestamps[-1]):.3f} s) are within {max_difference} s of the reference "
            f"({len(ref)} poses, {float(ref.timestamps[0]):.3f}...{float(ref.timestamps[-1]):.3f} s)"
            + _no_pairs_hint(ref.timestamps, est.timestamps, offset)
        )
    return ref.subset(i.to(ref.poses.device)), est.subset(j.to(est.poses.device))


def _align(ref: Trajectory, est: Trajectory, alignment: str):
    if alignment not in _ALIGNMENTS:
        raise ValueError(f"alignment must be one of {_ALIGNMENTS}, got {alignment!r}")
    dtype, device = est.poses.dtype, est.poses.device
    if alignment == "none":
        R, t, s = torch.eye(3, dtype=dtype, device=device), torch.zeros(3, dtype=dtype, device=device), 1.0
        return R, t, s, est
    R, t, s = umeyama_alignment(est.positions, ref.positions, with_scale=alignment == "sim3")
    return R, t, float(s), Trajectory(est.timestamps, transform_poses(est.poses, R, t, s))


def ate(
    reference: TrajectoryLike,
    estimate: TrajectoryLike,
    alignment: str = "se3",
    max_difference: float = TUM_MAX_DIFFERENCE,
    offset: float = 0.0,
    association: str = "evo",
) -> ATEResult:
    """Absolute trajectory error of ``estimate`` against ``reference``.

    Args:
        reference: ground truth: a :class:`Trajectory` or a TUM file path.
        estimate: the estimated trajectory: a :class:`Trajectory` or a TUM file path.
        alignment: ``"se3"`` (rigid, default, evo ``-a``), ``"sim3"`` (rigid + scale, evo ``-as``) or ``"none"``.
        max_difference: association tolerance in seconds.
        offset: seconds added to the estimate's stamps before association.
        association: ``"evo"`` (default, ``|dt| <= max_difference``) or ``"tum"`` (``|dt| < max_difference``).

    Returns:
        an :class:`ATEResult` (``.rmse`` in metres).

    Raises:
        ValueError: empty trajectories, no associated pairs, an unknown ``association``, or fewer than 3
            pairs / collinear positions when aligning.
    """
    ref, est = _associated(reference, estimate, max_difference, offset, association)
    R, t, s, est_aligned = _align(ref, est, alignment)
    errors = (est_aligned.positions - ref.positions).norm(dim=-1)
    st = ErrorStats.from_errors(errors)
    return ATEResult(
        rmse=st.rmse, mean=st.mean, median=st.median, std=st.std, min=st.min, max=st.max, sse=st.sse,
        num_pairs=st.num, alignment=alignment, scale=s, rotation=R, translation=t, errors=errors,
        timestamps=ref.timestamps, reference=ref, estimate_aligned=est_aligned,
    )


def _pairs_frames(n: int, delta: int, all_pairs: bool) -> torch.Tensor:
    # evo's filters.filter_pairs_by_index
    if all_pairs:
        i = torch.arange(max(n - delta, 0))
        return torch.stack([i, i + delta], dim=-1)
    ids = torch.arange(0, n, delta)
    return torch.stack([ids[:-1], ids[1:]], dim=-1)


def _pairs_seconds(stamps: torch.Tensor, delta: float, all_pairs: bool) -> torch.Tensor:
    # half a frame: close enough for the nearest stamp of a gap-free stream, not for one past a gap. The
    # associated stamps need not be sorted: pairs are found in time order and mapped back.
    t_in = stamps.detach().to("cpu", torch.float64)
    n = t_in.numel()
    if n < 2:
        return torch.zeros(0, 2, dtype=torch.long)
    order = torch.argsort(t_in, stable=True)
    t = t_in[order]
    tol = 0.5 * float(torch.median(t[1:] - t[:-1]))
    target = t + delta
    k = torch.searchsorted(t, target).clamp(1, n - 1)
    closer_left = (target - t[k - 1]).abs() <= (t[k] - target).abs()
    j = torch.where(closer_left, k - 1, k)
    ok = (j > torch.arange(n)) & ((t[j] - target).abs() <= tol)
    if all_pairs:
        i = torch.nonzero(ok).flatten()
        return order[torch.stack([i, j[i]], dim=-1)]
    out, i = [], 0
    j_list, ok_list = j.tolist(), ok.tolist()
    while i < n:
        jj = j_list[i]
        if jj <= i:
            i += 1  # no later partner: resume at the next pose (after a gap) or stop at the end
            continue
        if ok_list[i]:
            out.append((i, jj))
        i = jj
    return order[torch.tensor(out, dtype=torch.long).reshape(-1, 2)]


def rpe(
    reference: TrajectoryLike,
    estimate: TrajectoryLike,
    delta: float = 1,
    delta_unit: str = "frames",
    all_pairs: bool = False,
    alignment: str = "none",
    max_difference: float = TUM_MAX_DIFFERENCE,
    offset: float = 0.0,
    association: str = "evo",
) -> RPEResult:
    """Relative pose error (drift per ``delta``) of ``estimate`` against ``reference``.

    Args:
        reference: ground truth: a :class:`Trajectory` or a TUM file path.
        estimate: a :class:`Trajectory` or a TUM file path.
        delta: pair distance: an integer number of associated poses (``"frames"``) or seconds.
        delta_unit: ``"frames"`` (evo's pairs ``(0, d), (d, 2d), ...``) or ``"seconds"`` (each start with the
            stamp nearest ``t_i + delta`` when within half a frame of it, as TUM's ``evaluate_rpe.py
            --fixed_delta``; a start without a later partner hands over to the next pose).
        all_pairs: use every start pose; otherwise consecutive non-overlapping pairs (evo's default).
        alignment: ``"none"`` (default; a rigid alignment does not change the RPE), ``"se3"`` or ``"sim3"``.
        max_difference: association tolerance in seconds.
        offset: seconds added to the estimate's stamps before association.
        association: ``"evo"`` (default) or ``"tum"``, as for :func:`ate`.

    Returns:
        an :class:`RPEResult`: translation errors ``|t(E)|`` in metres (``.rmse``), rotation errors (the angle of
        ``E``) in degrees.

    Raises:
        ValueError: bad ``delta``/``delta_unit``, no associated pairs, or no pose pair ``delta`` apart.
    """
    if delta_unit not in ("frames", "seconds"):
        raise ValueError(f"delta_unit must be 'frames' or 'seconds', got {delta_unit!r}")
    if delta_unit == "frames" and (delta < 1 or float(delta) != int(delta)):
        raise ValueError(f"delta in frames must be a positive integer, got {delta}")
    if delta_unit == "seconds" and not delta > 0:
        raise ValueError(f"delta in seconds must be positive, got {delta}")
    ref, est = _associated(reference, estimate, max_difference, offset, association)
    est = _align(ref, est, alignment)[3]
    if delta_unit == "frames":
        pairs = _pairs_frames(len(est), int(delta), all_pairs)
    else:
        pairs = _pairs_seconds(est.timestamps, float(delta), all_pairs)
    if pairs.shape[0] == 0:
        raise ValueError(
            f"no pose pairs {delta} {delta_unit} apart among the {len(est)} associated poses; use a smaller delta"
        )
    pairs = pairs.to(est.poses.device)
    Q, P = ref.poses, est.poses
    E = se3_between(se3_between(Q[pairs[:, 0]], Q[pairs[:, 1]]), se3_between(P[pairs[:, 0]], P[pairs[:, 1]]))
    trans = E[:, :3].norm(dim=-1)
    rot = torch.rad2deg(quat_angle(E[:, 3:]))
    return RPEResult(
        translation=ErrorStats.from_errors(trans), rotation=ErrorStats.from_errors(rot), delta=delta,
        delta_unit=delta_unit, all_pairs=all_pairs, pairs=pairs, timestamps=est.timestamps[pairs],
        trans_errors=trans, rot_errors=rot,
    )
