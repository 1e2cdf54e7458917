"""Read and write pose graphs in the g2o text format.

Supported lines (one element per line, fields separated by white space):

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw``
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 upper-triangular entries of the 6x6 information
  matrix, row by row, translation first (the ``[rho, phi]`` order used here);
* ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``, lifted to SE(3)
  (z = 0, rotation about z). With the default residual chart ``"se3"`` the residual of a planar edge is
  exactly the SE(2) logarithm that GTSAM's ``BetweenFactor<Pose2>`` uses, so chi2 is 2x GTSAM's error
  on the 2D problem; ``chart_2d="r3so3"`` gives g2o's own ``EDGE_SE2`` error ``(dx, dy, dtheta)``;
* ``FIX id`` (accepted and ignored: the optimiser fixes its own gauge), blank lines and ``#`` comments.

Lifting the 3x3 information ``(x, y, theta)`` to 6x6 ``[x, y, z, roll, pitch, yaw]``: the 3x3 block goes
to rows/columns ``(0, 1, 5)``; the out-of-plane dimensions get ``z: (I11 + I22) / 2`` and
``roll, pitch: I33`` with no cross terms. On a planar graph those residuals and their gradient are
exactly zero, so these weights never change the solution or chi2; they only keep the 6x6 matrix
positive definite with the same scale as the in-plane part.

Anything else (an unknown element, a wrong number of fields, a token that is not a number, a zero
quaternion, a non-positive-definite information matrix, a duplicated vertex id, an edge to an
undefined vertex, a file mixing 2D and 3D elements) raises :class:`G2OFormatError` naming the file,
the 1-based line number and what was expected.

Example:
    >>> import io
    >>> text = '''VERTEX_SE2 0 0 0 0
    ... VERTEX_SE2 1 1 0 0.1
    ... EDGE_SE2 0 1 1 0 0.1 1 0 0 1 0 1
    ... '''
    >>> g = read_g2o(io.StringIO(text))
    >>> g.poses.shape, g.information.shape, g.chart
    (torch.Size([2, 7]), torch.Size([1, 6, 6]), 'se3')
"""
from __future__ import annotations

import math
import os
from typing import IO, Dict, List, Optional, Union

import numpy as np
import torch

from slam.graph.pose_graph import PoseGraph

__all__ = ["G2OFormatError", "read_g2o", "write_g2o"]

PathOrFile = Union[str, "os.PathLike[str]", IO[str]]

# tag -> (number of integer ids, number of floats, human description of the fields)
_LAYOUT = {
    "VERTEX_SE3:QUAT": (1, 7, "id x y z qx qy qz qw"),
    "EDGE_SE3:QUAT": (2, 28, "i j x y z qx qy qz qw + 21 information entries"),
    "VERTEX_SE2": (1, 3, "id x y theta"),
    "EDGE_SE2": (2, 9, "i j dx dy dtheta + 6 information entries"),
    "FIX": (1, 0, "id"),
}
_IU6 = np.triu_indices(6)
_IU3 = np.triu_indices(3)


class G2OFormatError(ValueError):
    """A g2o file could not be read; ``.source`` and ``.line`` (1-based, or None) say where."""

    def __init__(self, source: str, line: Optional[int], message: str):
        self.source, self.line = source, line
        where = f"{source}, line {line}" if line is not None else source
        super().__init__(f"{where}: {message}")


def _open(f: PathOrFile, mode: str):
    if isinstance(f, (str, os.PathLike)):
        return open(f, mode), str(f), True
    return f, getattr(f, "name", "<stream>"), False


def _numbers(rows: List[List[str]], linenos: List[int], first: int, tag: str, src: str) -> np.ndarray:
    """Tokens ``rows[:, first:]`` as float64; on failure find the first bad token for the message."""
    try:
        out = np.array([r[first:] for r in rows], dtype=np.float64).reshape(len(rows), -1)
    except ValueError:
        for r, ln in zip(rows, linenos):
            for c, tok in enumerate(r[first:], start=first):
                try:
                    float(tok)
                except ValueError:
                    raise G2OFormatError(src, ln, f"{tag} field {c} is {tok!r}, expected a number "
                                                  f"({tag} {_LAYOUT[tag][2]})") from None
        raise  # pragma: no cover - np.array failed for another reason
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        k = int(np.nonzero(bad)[0][0])
        raise G2OFormatError(src, linenos[k], f"{tag} has a non-finite value, expected finite numbers")
    return out


def _ids(rows: List[List[str]], linenos: List[int], n: int, tag: str, src: str) -> np.ndarray:
    out = np.empty((len(rows), n), dtype=np.int64)
    for k, (r, ln) in enumerate(zip(rows, linenos)):
        for c in range(n):
            tok = r[1 + c]
            try:
                out[k, c] = int(tok)
            except ValueError:
                raise G2OFormatError(src, ln, f"{tag} field {c + 1} is {tok!r}, expected an integer "
                                              f"vertex id ({tag} {_LAYOUT[tag][2]})") from None
    return out


def read_g2o(f: PathOrFile, dtype: torch.dtype = torch.float64, allow_no_edges: bool = False,
             chart_2d: str = "se3") -> PoseGraph:
    """Read a g2o file into a :class:`PoseGraph`.

    Args:
        f: a path or an open text file.
        dtype: floating dtype of the returned tensors.
        allow_no_edges: return a graph without edges instead of raising.
        chart_2d: residual chart of a 2D file: ``"se3"`` (GTSAM's ``Pose2`` error, the default) or
            ``"r3so3"`` (g2o's ``EDGE_SE2`` error).

    Returns:
        The graph; poses are sorted by vertex id (``graph.vertex_ids``), edges are in file order, and the
        poses are the file's VERTEX values (for the benchmark files: the odometry initial guess, i.e. the
        chain of odometry measurements composed from the first pose).

    Raises:
        G2OFormatError: naming the file, the line and what was expected.
    """
    fh, src, close = _open(f, "r")
    try:
        rows: Dict[str, List[List[str]]] = {t: [] for t in _LAYOUT}
        lines: Dict[str, List[int]] = {t: [] for t in _LAYOUT}
        for ln, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            tok = s.split()
            tag = tok[0]
            if tag not in _LAYOUT:
                raise G2OFormatError(src, ln, f"unsupported element {tag!r}; expected one of "
                                              f"{', '.join(_LAYOUT)} (or a '#' comment)")
            nid, nf, desc = _LAYOUT[tag]
            if len(tok) != 1 + nid + nf:
                raise G2OFormatError(src, ln, f"{tag} expects {nid + nf} fields ({desc}), got {len(tok) - 1}")
            rows[tag].append(tok)
            lines[tag].append(ln)
    finally:
        if close:
            fh.close()

    is3 = bool(rows["VERTEX_SE3:QUAT"] or rows["EDGE_SE3:QUAT"])
    is2 = bool(rows["VERTEX_SE2"] or rows["EDGE_SE2"])
    if is3 and is2:
        first2 = min(lines["VERTEX_SE2"][:1] + lines["EDGE_SE2"][:1])
        raise G2OFormatError(src, first2,
                             "2D element in a file with 3D (SE3:QUAT) elements; expected one kind")
    vtag, etag = ("VERTEX_SE2", "EDGE_SE2") if is2 else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    vrows, vlines = rows[vtag], lines[vtag]
    erows, elines = rows[etag], lines[etag]
    if not vrows:
        raise G2OFormatError(src, None, "no vertices: expected VERTEX_SE3:QUAT or VERTEX_SE2 lines")

    vid = _ids(vrows, vlines, 1, vtag, src)[:, 0]
    vval = _numbers(vrows, vlines, 2, vtag, src)
    order = np.argsort(vid, kind="stable")
    vid_sorted = vid[order]
    dup = np.nonzero(vid_sorted[1:] == vid_sorted[:-1])[0]
    if dup.size:
        k = order[dup[0] + 1]
        raise G2OFormatError(src, vlines[k], f"vertex id {vid[k]} is defined twice; expected unique ids")
    vval = vval[order]

    eid = _ids(erows, elines, 2, etag, src) if erows else np.zeros((0, 2), np.int64)
    evals = _numbers(erows, elines, 3, etag, src) if erows else np.zeros((0, 28 if is3 else 9))
    # map vertex ids to rows
    pos = np.searchsorted(vid_sorted, eid)
    pos_c = np.clip(pos, 0, len(vid_sorted) - 1)
    found = vid_sorted[pos_c] == eid
    if not found.all():
        k, c = map(int, np.argwhere(~found)[0])
        raise G2OFormatError(src, elines[k],
                             f"{etag} refers to vertex {eid[k, c]}, which no {vtag} line defines")
    loops = eid[:, 0] == eid[:, 1]
    if loops.any():
        k = int(np.nonzero(loops)[0][0])
        raise G2OFormatError(src, elines[k], f"{etag} connects vertex {eid[k, 0]} to itself; expected i != j")

    if is3:
        poses = vval
        meas = evals[:, :7]
        info = np.zeros((len(erows), 6, 6))
        info[:, _IU6[0], _IU6[1]] = evals[:, 7:]
        info[:, _IU6[1], _IU6[0]] = evals[:, 7:]
        for name, q, lns in (("VERTEX_SE3:QUAT", poses[:, 3:], [vlines[i] for i in order]),
                             ("EDGE_SE3:QUAT", meas[:, 3:], elines)):
            nq = np.linalg.norm(q, axis=1)
            bad = nq < 1e-12
            if bad.any():
                raise G2OFormatError(src, lns[int(np.nonzero(bad)[0][0])],
                                     f"{name} has a zero quaternion; expected a rotation (qx qy qz qw)")
            q /= nq[:, None]
        chart = "se3"
    else:
        poses = _lift_se2(vval)
        meas = _lift_se2(evals[:, :3])
        i3 = np.zeros((len(erows), 3, 3))
        i3[:, _IU3[0], _IU3[1]] = evals[:, 3:]
        i3[:, _IU3[1], _IU3[0]] = evals[:, 3:]
        info = np.zeros((len(erows), 6, 6))
        d = np.array([0, 1, 5])
        info[:, d[:, None], d[None, :]] = i3
        info[:, 2, 2] = 0.5 * (i3[:, 0, 0] + i3[:, 1, 1])
        info[:, 3, 3] = i3[:, 2, 2]
        info[:, 4, 4] = i3[:, 2, 2]
        chart = chart_2d
    if not erows and not allow_no_edges:
        raise G2OFormatError(src, None, f"no edges: expected {etag} lines (a graph without edges "
                                        "cannot be optimised; pass allow_no_edges=True to read it anyway)")
    if len(erows):
        _, chol_info = torch.linalg.cholesky_ex(torch.from_numpy(info))
        bad = np.nonzero(chol_info.numpy() != 0)[0]
        if bad.size:
            k = int(bad[0])
            raise G2OFormatError(src, elines[k], f"{etag} information matrix is not positive definite; "
                                                 f"expected a symmetric positive-definite matrix")
    return PoseGraph(
        poses=torch.from_numpy(poses).to(dtype),
        ii=torch.from_numpy(pos[:, 0].copy()),
        jj=torch.from_numpy(pos[:, 1].copy()),
        measurements=torch.from_numpy(np.ascontiguousarray(meas)).to(dtype),
        information=torch.from_numpy(info).to(dtype),
        chart=chart,
        vertex_ids=torch.from_numpy(vid_sorted.copy()),
    )


def _lift_se2(xyt: np.ndarray) -> np.ndarray:
    """``(M, 3) (x, y, theta)`` -> ``(M, 7)`` planar SE(3) poses."""
    out = np.zeros((xyt.shape[0], 7))
    out[:, :2] = xyt[:, :2]
    half = 0.5 * xyt[:, 2]
    out[:, 5] = np.sin(half)
    out[:, 6] = np.cos(half)
    out[:, 3:] *= np.where(out[:, 6:] < 0, -1.0, 1.0)
    return out


def _fmt(rows: np.ndarray, digits: int) -> List[str]:
    f = f"%.{digits}g"
    return [" ".join(f % v for v in r) for r in rows]


def write_g2o(f: PathOrFile, graph: PoseGraph, planar: Optional[bool] = None, digits: int = 17) -> None:
    """Write a :class:`PoseGraph` in the g2o format.

    Args:
        f: a path or an open text file.
        graph: the graph; ``graph.vertex_ids`` are written as the vertex ids.
        planar: write ``VERTEX_SE2`` / ``EDGE_SE2``. Default: when that loses nothing, i.e. the graph is
            planar and its out-of-plane information is exactly what :func:`read_g2o` puts there (so a 2D
            file round-trips as 2D); otherwise ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``.
        digits: significant digits (17 round-trips float64 exactly).
    """
    if planar is None:
        planar = _lossless_2d(graph)
    elif planar and not graph.is_planar(tol=1e-6):
        raise ValueError("planar=True but the graph is not planar (z, roll or pitch is non-zero)")
    P = graph.poses.detach().cpu().double().numpy()
    Z = graph.measurements.detach().cpu().double().numpy()
    Om = graph.information.detach().cpu().double().numpy()
    vid = graph.vertex_ids.cpu().numpy()
    ei = vid[graph.ii.cpu().numpy()]
    ej = vid[graph.jj.cpu().numpy()]
    out: List[str] = []
    if planar:
        d = np.array([0, 1, 5])
        for tag, ids, vals in (
            ("VERTEX_SE2", vid[:, None], _planar(P)),
            ("EDGE_SE2", np.stack([ei, ej], 1),
             np.concatenate([_planar(Z), Om[:, d[:, None], d[None, :]][:, _IU3[0], _IU3[1]]], 1)),
        ):
            out += [f"{tag} {' '.join(map(str, i))} {v}" for i, v in zip(ids, _fmt(vals, digits))]
    else:
        out += [f"VERTEX_SE3:QUAT {i} {v}" for i, v in zip(vid, _fmt(P, digits))]
        vals = np.concatenate([Z, Om[:, _IU6[0], _IU6[1]]], 1)
        out += [f"EDGE_SE3:QUAT {i} {j} {v}" for i, j, v in zip(ei, ej, _fmt(vals, digits))]
    fh, _, close = _open(f, "w")
    try:
        fh.write("\n".join(out) + "\n")
    finally:
        if close:
            fh.close()


def _lossless_2d(graph: PoseGraph) -> bool:
    """True when writing the graph as 2D and reading it back gives the same graph."""
    if graph.num_poses == 0 or not graph.is_planar(tol=0.0):
        return False
    Om = graph.information.detach().cpu().double()
    lift = torch.zeros_like(Om)
    d = torch.tensor([0, 1, 5])
    lift[:, d[:, None], d[None, :]] = Om[:, d[:, None], d[None, :]]
    lift[:, 2, 2] = 0.5 * (Om[:, 0, 0] + Om[:, 1, 1])
    lift[:, 3, 3] = Om[:, 5, 5]
    lift[:, 4, 4] = Om[:, 5, 5]
    return bool((lift == Om).all())


def _planar(p: np.ndarray) -> np.ndarray:
    theta = 2.0 * np.arctan2(p[:, 5], p[:, 6])
    theta = (theta + math.pi) % (2.0 * math.pi) - math.pi
    return np.stack([p[:, 0], p[:, 1], theta], 1)

