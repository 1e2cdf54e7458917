"""The files of a run (``trajectory.txt``, ``loops.txt``, ``metrics.json``, ``trajectory.png``, ``map.ply``;
docs/pipeline.md says what each holds), each written under a temporary name and renamed into place
(:func:`write_outputs`); :func:`prepare_output_dir` checks the folder before a run and clears the previous outputs.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import tempfile
import uuid
from pathlib import Path

import cv2
import numpy as np
import torch

from slam.io.trajectory import write_tum_trajectory
from slam.mapping import write_ply
from slam.pipeline import RunResult
from slam.report import evaluate_run

__all__ = ["OUTPUT_FILES", "OutputDirError", "json_safe", "prepare_output_dir", "replace_atomically", "write_outputs"]

#: The files a run writes into its output folder (``map.ply`` unless the map is off).
OUTPUT_FILES = ("trajectory.txt", "loops.txt", "metrics.json", "trajectory.png", "map.ply")


class OutputDirError(OSError):
    """The output folder cannot take a run's outputs (a file, not writable, or an output name taken)."""


def json_safe(value, path: str = "", bad: list[str] | None = None):
    """A copy of ``value`` that :func:`json.dumps` writes as valid JSON: non-finite floats become None.

    Args:
        value: dicts, lists, tuples, numbers (python, numpy, 0-d tensors), strings, None.
        path: the key path of ``value`` (for the report).
        bad: collects the key paths of the values that were not finite.

    Example:
        >>> bad = []
        >>> json_safe({"a": float("inf"), "b": [1.0, float("nan")]}, bad=bad), bad
        ({'a': None, 'b': [1.0, None]}, ['a', 'b[1]'])
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v, f"{path}.{k}" if path else str(k), bad) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, f"{path}[{i}]", bad) for i, v in enumerate(value)]
    if isinstance(value, np.generic) or (isinstance(value, torch.Tensor) and value.numel() == 1):
        value = value.item()
    if value is None or isinstance(value, (int, str)):  # bool is an int
        return value
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        if bad is not None:
            bad.append(path)
        return None
    return str(value)


def replace_atomically(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path`` and rename it into place (the umask's mode)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "xb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def prepare_output_dir(out_dir: str | os.PathLike, clear: bool = True) -> Path:
    """Check (and create) an output folder before a run, and remove the previous run's outputs.

    Args:
        out_dir: the folder (created with its parents).
        clear: remove existing regular files of the names in :data:`OUTPUT_FILES`.

    Raises:
        OutputDirError: ``out_dir`` is a file, cannot be created or written to, or an output name is taken
            by something other than a regular file (a folder, say); nothing is removed then.
    """
    out = Path(out_dir).expanduser()
    if out.exists() and not out.is_dir():
        raise OutputDirError(f"--out {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputDirError(f"--out {out}: cannot create the folder ({e.strerror or e})") from None
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise OutputDirError(f"--out {out}: cannot write into the folder ({e.strerror or e})") from None
    taken = [n for n in OUTPUT_FILES if (out / n).exists() or (out / n).is_symlink()]
    for name in taken:
        p = out / name
        if p.is_symlink() or not p.is_file():
            raise OutputDirError(f"{p}: an output name is taken by something that is not a regular file "
                                 "(a folder?); move it away or choose another --out")
    if clear:
        for name in taken:
            (out / name).unlink()
    return out


def write_outputs(run: RunResult, out_dir: str | os.PathLike) -> Path:
    """Write ``trajectory.txt``, ``loops.txt``, ``metrics.json``, ``trajectory.png`` and ``map.ply`` into ``out_dir``.

    A failed run (``report.status == "failed"``) writes ``metrics.json`` alone, with ``failure`` saying why, and
    removes the other outputs an earlier run left.

    Args:
        run: a :class:`slam.pipeline.RunResult` (:func:`slam.report.evaluate_run` is called if its ``report``
            is None).
        out_dir: created if needed.

    Returns:
        the output folder.

    Raises:
        OutputDirError: the folder cannot take the outputs.
    """
    out = prepare_output_dir(out_dir, clear=False)
    report = evaluate_run(run) if run.report is None else run.report
    metrics = report.as_dict()
    if report.status == "failed":  # guessed poses are no result: metrics.json says what happened
        prepare_output_dir(out, clear=True)  # an earlier run's files would pass for this one's
        replace_atomically(out / "metrics.json", (json.dumps(json_safe(metrics), indent=2, allow_nan=False)
                                                  + "\n").encode("utf-8"))
        return out
    res = run.result
    # everything is computed before the first file is replaced
    traj_text = io.StringIO()
    write_tum_trajectory(traj_text, res.trajectory)
    loops_text = "# timestamp_a timestamp_b  (accepted loop closures between keyframes)\n" + "".join(
        f"{lp.timestamp_a:.6f} {lp.timestamp_b:.6f}\n" for lp in res.loops)
    ply = None
    if run.map is not None:
        pts, cols = run.map_cloud if run.map_cloud is not None else run.map.points(res.keyframe_trajectory.poses)
        buf = io.BytesIO()
        write_ply(buf, pts, cols, comment=f"attnloop map of {run.sequence_name}: {len(run.map)} keyframes, "
                                          f"voxel {run.map.config.voxel_size:g} m, the trajectory's frame")
        ply = buf.getvalue()
    from slam.eval import plot_trajectory

    loops = torch.tensor([[lp.timestamp_a, lp.timestamp_b] for lp in res.loops], dtype=torch.float64
                         ).reshape(-1, 2)
    ate_txt = f", ATE {report.ate_rmse * 100:.1f} cm" if report.ate_rmse is not None else ""
    # aligned to the ground truth as the ATE is, unless the ATE found no alignment (it says why)
    img = plot_trajectory(None, res.trajectory, run.groundtruth, loops=loops,
                          align=report.ate_rmse is not None,
                          title=f"{run.sequence_name}: {len(res.loops)} loops{ate_txt}")
    ok, png = cv2.imencode(".png", img)
    if not ok:
        raise OSError("could not encode trajectory.png")
    bad: list[str] = []
    metrics = json_safe(metrics, bad=bad)
    if bad:
        metrics["non_finite"] = {"keys": bad, "reason": "not finite, written as null"}
    metrics_text = json.dumps(metrics, indent=2, allow_nan=False)
    replace_atomically(out / "trajectory.txt", traj_text.getvalue().encode("utf-8"))
    replace_atomically(out / "loops.txt", loops_text.encode("utf-8"))
    if ply is not None:
        replace_atomically(out / "map.ply", ply)
    replace_atomically(out / "trajectory.png", png.tobytes())
    replace_atomically(out / "metrics.json", (metrics_text + "\n").encode("utf-8"))  # last: the run is complete
    return out
