"""Read and write pose graphs in the g2o text format.

Supported lines (one element per line, fields separated by white space):

* ``VERTEX_SE3:QUAT id x y z qx qy qz qw``
* ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + the 21 upper-triangular entries of the 6x6 information
  matrix, row by row, translation first (the ``[rho, phi]`` order used here);
* ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33``, lifted to SE(3)
  (z = 0, rotation about z; chart ``"se3"``: GTSAM's ``Pose2`` error, ``chart_2d="r3so3"``: g2o's). The 3x3
  information goes to rows/columns ``(0, 1, 5)``, with ``z: (I11 + I22) / 2`` and ``roll, pitch: I33``
  (zero residuals on a planar graph: they only keep the 6x6 matrix positive definite);
* ``FIX id [id ...]``: those vertices are held constant by :func:`~slam.graph.optimize` (``graph.fixed``);
* blank lines and ``#`` comments, also after the fields of a line.

Files from the wild: a file with edges only gets its poses composed along a spanning tree of the edges; an
information matrix that is not positive definite is replaced by the nearest one with eigenvalues at least
``1e-6`` times its largest; a repeated edge is kept (its information counts twice) and a vertex line repeated
exactly is read once. Each repair gives a :class:`G2OWarning` (``strict=True``: a :class:`G2OFormatError`).
Anything else malformed raises :class:`G2OFormatError` naming the file, the 1-based line and what was expected.

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

import logging
import math
import os
import warnings
from typing import IO, Dict, List, Optional, Tuple, Union

import numpy as np
import torch

from slam.graph.pose_graph import PoseGraph
from slam.input_checks import MAX_COORDINATE, TextDecodeError, read_text_lines, unit_quaternions

__all__ = ["G2OFormatError", "G2OWarning", "read_g2o", "write_g2o"]

logger = logging.getLogger(__name__)

PathOrFile = Union[str, "os.PathLike[str]", IO[str], IO[bytes]]

# tag -> (number of integer ids, number of floats, human description of the fields)
_LAYOUT = {
    "VERTEX_SE3:QUAT": (1, 7, "id x y z qx qy qz qw"),
    "EDGE_SE3:QUAT": (2, 28, "i j x y z qx qy qz qw + 21 information entries"),
    "VERTEX_SE2": (1, 3, "id x y theta"),
    "EDGE_SE2": (2, 9, "i j dx dy dtheta + 6 information entries"),
    "FIX": (1, 0, "id [id ...]"),
}
_IU6 = np.triu_indices(6)
_IU3 = np.triu_indices(3)
_PLANAR = np.array([0, 1, 5])  # x, y, yaw in [x, y, z, roll, pitch, yaw]
# an information matrix that is not positive definite gets its eigenvalues clipped to at least this
# fraction of its largest
_PD_FLOOR = 1e-6


class G2OFormatError(ValueError):
    """A g2o file could not be read; ``.source`` and ``.line`` (1-based, or None) say where."""

    def __init__(self, source: str, line: Optional[int], message: str):
        self.source, self.line = source, line
        where = f"{source}, line {line}" if line is not None else source
        super().__init__(f"{where}: {message}")


class G2OWarning(UserWarning):
    """Something in a g2o file was repaired or is suspicious; ``read_g2o(..., strict=True)`` raises instead."""


def _report(notes: List[str], src: str, lines: List[int], problem: str, action: str, strict: bool) -> None:
    """Note the warning ``problem; action`` about ``lines`` for :func:`read_g2o` to give, or (``strict``)
    raise a :class:`G2OFormatError` at the first line."""
    if strict:
        raise G2OFormatError(src, lines[0], f"{problem} (refused with strict=True; otherwise {action})")
    shown = ", ".join(map(str, lines[:5])) + (f" and {len(lines) - 5} more" if len(lines) > 5 else "")
    notes.append(f"{src}, line{'s' if len(lines) > 1 else ''} {shown}: {problem}; {action}")


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


def _ids(tokens: List[str], linenos: List[int], tag: str, src: str, field: List[int]) -> np.ndarray:
    """``(M,)`` int64 vertex ids from their tokens (``field``: each token's field number, for messages)."""
    out = np.empty(len(tokens), dtype=np.int64)
    for k, (tok, ln) in enumerate(zip(tokens, linenos)):
        try:
            out[k] = int(tok)
        except ValueError:
            raise G2OFormatError(src, ln, f"{tag} field {field[k]} is {tok!r}, expected an integer vertex id "
                                          f"({tag} {_LAYOUT[tag][2]})") from None
        except OverflowError:
            raise G2OFormatError(src, ln, f"{tag} vertex id {tok} is out of range; expected a 64-bit integer "
                                          "(|id| < 2^63)") from None
    return out


def _row_ids(rows: List[List[str]], linenos: List[int], n: int, tag: str, src: str) -> np.ndarray:
    """``(M, n)`` the ids in fields ``1 .. n`` of each row."""
    toks = [r[1 + c] for r in rows for c in range(n)]
    lns = [ln for ln in linenos for _ in range(n)]
    return _ids(toks, lns, tag, src, [1 + c for _ in rows for c in range(n)]).reshape(len(rows), n)


def _check_translations(t: np.ndarray, lines: List[int], tag: str, src: str) -> None:
    bad = np.abs(t).max(axis=1) > MAX_COORDINATE
    if bad.any():
        k = int(np.nonzero(bad)[0][0])
        raise G2OFormatError(src, lines[k], f"{tag} has a translation of {np.abs(t[k]).max():.3g}, beyond "
                                            f"{MAX_COORDINATE:.0e}; expected the coordinates of a real map")


def _unit(q: np.ndarray, lines: List[int], tag: str, src: str) -> np.ndarray:
    unit, zero = unit_quaternions(q)
    if zero.any():
        raise G2OFormatError(src, lines[int(np.nonzero(zero)[0][0])],
                             f"{tag} has a zero quaternion; expected a rotation (qx qy qz qw)")
    return unit


def _positive_definite(info: np.ndarray, lines: List[int], tag: str, src: str, strict: bool,
                       notes: List[str]) -> np.ndarray:
    """``info (E, d, d)`` (symmetric) with each matrix that is not positive definite projected onto the
    nearest one with eigenvalues >= ``_PD_FLOOR`` x its largest, and reported."""
    if not info.shape[0]:
        return info
    _, fail = torch.linalg.cholesky_ex(torch.from_numpy(info))
    bad = np.nonzero(fail.numpy() != 0)[0]
    if not bad.size:
        return info
    w, V = np.linalg.eigh(info[bad])
    top = w[:, -1]
    if (top <= 0).any():
        k = int(bad[np.nonzero(top <= 0)[0][0]])
        raise G2OFormatError(src, lines[k], f"{tag} information matrix has no positive eigenvalue (the edge "
                                            "carries no information); expected a positive-definite matrix")
    _report(notes, src, [lines[k] for k in bad],
            f"{tag} information matrix is not positive definite (eigenvalues {w[0, 0]:.3g} .. {top[0]:.3g}"
            f"{' on the first' if bad.size > 1 else ''})", "replaced by the nearest positive-definite matrix "
            f"(eigenvalues clipped to >= {_PD_FLOOR:g} x the largest, eigenvectors kept)", strict)
    # A + sum over the clipped eigenvalues of (floor - w) v v^T (= V max(w, floor) V^T, the rest of A exact)
    lift = np.maximum(_PD_FLOOR * top[:, None] - w, 0.0)
    out = info.copy()
    corr = (V * lift[:, None, :]) @ V.transpose(0, 2, 1)
    out[bad] += 0.5 * (corr + corr.transpose(0, 2, 1))
    return out


def _repeated(ids: np.ndarray, values: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """``(k, first)``: the rows of ``ids (M, a)`` int64 and ``values (M, b)`` float64 that repeat an earlier
    row exactly (bit for bit), and that earlier row."""
    m = ids.shape[0]
    if not m:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    raw = np.concatenate([np.ascontiguousarray(ids, dtype=np.int64).view(np.uint8).reshape(m, -1),
                          np.ascontiguousarray(values, dtype=np.float64).view(np.uint8).reshape(m, -1)], 1)
    rows = np.ascontiguousarray(raw).view(np.dtype((np.void, raw.shape[1]))).reshape(m)
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    k = np.nonzero(first[inverse] != np.arange(m))[0]
    return k, first[inverse[k]]


def _lookup(sorted_ids: np.ndarray, ids: np.ndarray):
    """Positions of ``ids`` in ``sorted_ids`` and whether each was found."""
    pos = np.searchsorted(sorted_ids, ids)
    if not sorted_ids.size:
        return pos, np.zeros(ids.shape, dtype=bool)
    return pos, sorted_ids[np.clip(pos, 0, sorted_ids.size - 1)] == ids


def read_g2o(f: PathOrFile, allow_no_edges: bool = False, chart_2d: str = "se3", strict: bool = False) -> PoseGraph:
    """Read a g2o file into a :class:`PoseGraph`.

    Args:
        f: a path or an open file (text or binary).
        allow_no_edges: return a graph without edges instead of raising.
        chart_2d: residual chart of a 2D file: ``"se3"`` (GTSAM's ``Pose2`` error, the default) or
            ``"r3so3"`` (g2o's ``EDGE_SE2`` error).
        strict: raise :class:`G2OFormatError` where the default repairs the file with a
            :class:`G2OWarning` (an information matrix that is not positive definite, a repeated line).

    Returns:
        The float64 graph; poses ``(N, 7)`` sorted by vertex id (``graph.vertex_ids``), edges in file order,
        ``graph.fixed`` the ``FIX`` vertices.

    Raises:
        G2OFormatError: naming the file, the line and what was expected.
        FileNotFoundError: (or another ``OSError``) the file cannot be opened.
    """
    if chart_2d not in ("se3", "r3so3"):
        raise ValueError(f"chart_2d must be 'se3' or 'r3so3', got {chart_2d!r}")
    try:
        src, text = read_text_lines(f)
    except TextDecodeError as e:
        raise G2OFormatError(e.path, e.line, e.reason) from None
    rows: Dict[str, List[List[str]]] = {t: [] for t in _LAYOUT}
    lines: Dict[str, List[int]] = {t: [] for t in _LAYOUT}
    notes: List[str] = []  # the warnings, given once the whole file has been read
    for ln, line in enumerate(text, start=1):
        tok = line.split("#", 1)[0].split()
        if not tok:
            continue
        tag = tok[0]
        if tag not in _LAYOUT:
            raise G2OFormatError(src, ln, f"unsupported element {tag!r}; expected one of "
                                          f"{', '.join(_LAYOUT)} (or a '#' comment)")
        nid, nf, desc = _LAYOUT[tag]
        if tag == "FIX" and len(tok) < 2 or tag != "FIX" and len(tok) != 1 + nid + nf:
            raise G2OFormatError(src, ln, f"{tag} expects {'at least ' if tag == 'FIX' else ''}{nid + nf} "
                                          f"field{'s' if nid + nf > 1 else ''} ({desc}), got {len(tok) - 1}")
        rows[tag].append(tok)
        lines[tag].append(ln)

    is3 = bool(rows["VERTEX_SE3:QUAT"] or rows["EDGE_SE3:QUAT"])
    is2 = bool(rows["VERTEX_SE2"] or rows["EDGE_SE2"])
    if is3 and is2:
        first2 = min(lines["VERTEX_SE2"][:1] + lines["EDGE_SE2"][:1])
        raise G2OFormatError(src, first2,
                             "2D element in a file with 3D (SE3:QUAT) elements; expected one kind")
    vtag, etag = ("VERTEX_SE2", "EDGE_SE2") if is2 else ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT")
    vrows, vlines = rows[vtag], lines[vtag]
    erows, elines = rows[etag], lines[etag]
    if not vrows and not erows:
        raise G2OFormatError(src, None, "no vertices: expected VERTEX_SE3:QUAT or VERTEX_SE2 lines (or edges "
                                        "to compose them from)")
    dim = 2 if is2 else 3  # translation fields

    eid = _row_ids(erows, elines, 2, etag, src) if erows else np.zeros((0, 2), np.int64)
    evals = _numbers(erows, elines, 3, etag, src) if erows else np.zeros((0, 28 if is3 else 9))
    loops = eid[:, 0] == eid[:, 1]
    if loops.any():
        k = int(np.nonzero(loops)[0][0])
        raise G2OFormatError(src, elines[k], f"{etag} connects vertex {eid[k, 0]} to itself; expected i != j")
    _check_translations(evals[:, :dim], elines, etag, src)

    edges_only = not vrows
    if edges_only:  # the vertices are the ids the edges name; their poses come from a spanning tree below
        vid_sorted, vval = np.unique(eid), None
    else:
        vid = _row_ids(vrows, vlines, 1, vtag, src)[:, 0]
        vval = _numbers(vrows, vlines, 2, vtag, src)
        same, first = _repeated(vid[:, None], vval)
        if same.size:  # an exact copy of a vertex line: read once
            _report(notes, src, [vlines[k] for k in same], f"{vtag} repeats the line {vlines[first[0]]}"
                    f"{' (and others repeat theirs)' if same.size > 1 else ''}", "read once", strict)
            keep = np.ones(len(vid), dtype=bool)
            keep[same] = False
            vid, vval, vlines = vid[keep], vval[keep], [ln for ln, k in zip(vlines, keep) if k]
        order = np.argsort(vid, kind="stable")
        vid_sorted = vid[order]
        dup = np.nonzero(vid_sorted[1:] == vid_sorted[:-1])[0]
        if dup.size:
            k = order[dup[0] + 1]
            raise G2OFormatError(src, vlines[k], f"vertex id {vid[k]} is defined twice, with other values on "
                                                 f"line {vlines[order[dup[0]]]}; expected unique ids")
        vval, vlines = vval[order], [vlines[k] for k in order]
        _check_translations(vval[:, :dim], vlines, vtag, src)

    pos, found = _lookup(vid_sorted, eid)
    if not found.all():
        k, c = map(int, np.argwhere(~found)[0])
        raise G2OFormatError(src, elines[k],
                             f"{etag} refers to vertex {eid[k, c]}, which no {vtag} line defines")
    same, first = _repeated(eid, evals)
    if same.size:
        _report(notes, src, [elines[k] for k in same], f"{etag} repeats the line {elines[first[0]]}"
                f"{' (and others repeat theirs)' if same.size > 1 else ''}", "kept, so its information counts "
                "twice (as in g2o and GTSAM): delete the line if it is a copy", strict)

    fix_tok = [t for r in rows["FIX"] for t in r[1:]]
    fix_ln = [ln for r, ln in zip(rows["FIX"], lines["FIX"]) for _ in r[1:]]
    fix_ids = _ids(fix_tok, fix_ln, "FIX", src, [k + 1 for r in rows["FIX"] for k in range(len(r) - 1)])
    fixed, ok = _lookup(vid_sorted, fix_ids)
    if not ok.all():
        k = int(np.nonzero(~ok)[0][0])
        what = f"{etag} line names" if edges_only else f"{vtag} line defines"
        raise G2OFormatError(src, fix_ln[k], f"FIX of vertex {fix_ids[k]}, which no {what}; expected the id "
                                             "of a vertex")

    if is3:
        meas = evals[:, :7].copy()
        meas[:, 3:] = _unit(meas[:, 3:], elines, etag, src)
        info = np.zeros((len(erows), 6, 6))
        info[:, _IU6[0], _IU6[1]] = evals[:, 7:]
        info[:, _IU6[1], _IU6[0]] = evals[:, 7:]
        info = _positive_definite(info, elines, etag, src, strict, notes)
        if vval is not None:
            poses = vval.copy()
            poses[:, 3:] = _unit(poses[:, 3:], vlines, vtag, src)
        chart = "se3"
    else:
        meas = _lift_se2(evals[:, :3])
        i3 = np.zeros((len(erows), 3, 3))
        i3[:, _IU3[0], _IU3[1]] = evals[:, 3:]
        i3[:, _IU3[1], _IU3[0]] = evals[:, 3:]
        info = _lift_information(_positive_definite(i3, elines, etag, src, strict, notes))
        if vval is not None:
            poses = _lift_se2(vval)
        chart = chart_2d
    if not erows and not allow_no_edges:
        raise G2OFormatError(src, None, f"no edges: expected {etag} lines (a graph without edges "
                                        "cannot be optimised; pass allow_no_edges=True to read it anyway)")
    if vval is None:
        poses = np.zeros((len(vid_sorted), 7))
        poses[:, 6] = 1.0
    graph = PoseGraph(
        poses=torch.from_numpy(poses),
        ii=torch.from_numpy(pos[:, 0].copy()),
        jj=torch.from_numpy(pos[:, 1].copy()),
        measurements=torch.from_numpy(np.ascontiguousarray(meas)),
        information=torch.from_numpy(info),
        chart=chart,
        vertex_ids=torch.from_numpy(vid_sorted.copy()),
        fixed=torch.from_numpy(fixed),
    )
    if edges_only:
        from slam.graph.initialization import spanning_tree_poses  # (it imports this package)

        logger.info("%s has no %s lines: the poses of its %d vertices are composed along a spanning tree of "
                    "the edges", src, vtag, len(vid_sorted))
        graph = graph.with_poses(spanning_tree_poses(graph))
    for note in notes:
        warnings.warn(note, G2OWarning, stacklevel=2)
    return graph


def _lift_information(i3: np.ndarray) -> np.ndarray:
    """``(M, 3, 3)`` information of ``(x, y, theta)`` -> ``(M, 6, 6)`` (see the module docstring)."""
    info = np.zeros((i3.shape[0], 6, 6))
    info[:, _PLANAR[:, None], _PLANAR] = i3
    info[:, 2, 2] = 0.5 * (i3[:, 0, 0] + i3[:, 1, 1])
    info[:, 3, 3] = i3[:, 2, 2]
    info[:, 4, 4] = i3[:, 2, 2]
    return info


def _lift_se2(xyt: np.ndarray) -> np.ndarray:
    """``(M, 3) (x, y, theta)`` -> ``(M, 7)`` planar SE(3) poses."""
    out = np.zeros((xyt.shape[0], 7))
    out[:, :2] = xyt[:, :2]
    half = 0.5 * xyt[:, 2]
    out[:, 5] = np.sin(half)
    out[:, 6] = np.cos(half)
    out[:, 3:] *= np.where(out[:, 6:] < 0, -1.0, 1.0)
    return out


def _fmt(rows: np.ndarray) -> List[str]:
    return [" ".join("%.17g" % v for v in r) for r in rows]  # 17 digits round-trip float64


def write_g2o(f: PathOrFile, graph: PoseGraph, planar: Optional[bool] = None) -> None:
    """Write a :class:`PoseGraph` in the g2o format.

    Args:
        f: a path or an open text file.
        graph: the graph; ``graph.vertex_ids`` are written as the vertex ids, ``graph.fixed`` as a ``FIX``
            line after the vertices.
        planar: write ``VERTEX_SE2`` / ``EDGE_SE2``. Default: when that loses nothing, i.e. the graph is
            planar and its out-of-plane information is exactly what :func:`read_g2o` puts there (so a 2D
            file round-trips as 2D); otherwise ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``.
    """
    Om = graph.information.detach().cpu().double().numpy()
    if planar is None:  # 2D when writing it so and reading it back gives the same graph
        planar = (graph.num_poses > 0 and graph.is_planar(tol=0.0)
                  and bool((_lift_information(Om[:, _PLANAR[:, None], _PLANAR]) == Om).all()))
    elif planar and not graph.is_planar(tol=1e-6):
        raise ValueError("planar=True but the graph is not planar (z, roll or pitch is non-zero)")
    P = graph.poses.detach().cpu().double().numpy()
    Z = graph.measurements.detach().cpu().double().numpy()
    vid = graph.vertex_ids.cpu().numpy()
    ei = vid[graph.ii.cpu().numpy()]
    ej = vid[graph.jj.cpu().numpy()]
    out: List[str] = []
    fix = [f"FIX {' '.join(map(str, vid[graph.fixed.cpu().numpy()]))}"] if graph.fixed.numel() else []
    if planar:
        out += [f"VERTEX_SE2 {i} {v}" for i, v in zip(vid, _fmt(_planar(P)))] + fix
        vals = np.concatenate([_planar(Z), Om[:, _PLANAR[:, None], _PLANAR][:, _IU3[0], _IU3[1]]], 1)
        out += [f"EDGE_SE2 {i} {j} {v}" for i, j, v in zip(ei, ej, _fmt(vals))]
    else:
        out += [f"VERTEX_SE3:QUAT {i} {v}" for i, v in zip(vid, _fmt(P))] + fix
        vals = np.concatenate([Z, Om[:, _IU6[0], _IU6[1]]], 1)
        out += [f"EDGE_SE3:QUAT {i} {j} {v}" for i, j, v in zip(ei, ej, _fmt(vals))]
    if isinstance(f, (str, os.PathLike)):
        with open(f, "w") as fh:
            fh.write("\n".join(out) + "\n")
    else:
        f.write("\n".join(out) + "\n")


def _planar(p: np.ndarray) -> np.ndarray:
    theta = 2.0 * np.arctan2(p[:, 5], p[:, 6])
    theta = (theta + math.pi) % (2.0 * math.pi) - math.pi
    return np.stack([p[:, 0], p[:, 1], theta], 1)

