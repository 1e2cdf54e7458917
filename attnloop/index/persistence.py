"""Saving and loading a :class:`~attnloop.index.KeyframeIndex` as one ``.npz`` file.

An uncompressed numpy ``.npz``: ``meta`` a JSON string (format, version, config, backend, sizes, the
structure's record), ``descriptors (N, D)``, ``ids (N,)``, ``timestamps (N,)`` and ``structure.*`` (the
serialised graph or tree, its PCA code). No pickles: loading runs no code.
"""
from __future__ import annotations

import json
import os
import uuid
import zipfile

import numpy as np

__all__ = ["IndexFileError", "file_name", "read_index_file", "save_index"]


class IndexFileError(ValueError):
    """A keyframe-index file that cannot be read: the message names the file and what is wrong."""


def file_name(file) -> str:
    """How a path or file object is named in messages."""
    return os.fspath(file) if isinstance(file, (str, os.PathLike)) else str(getattr(file, "name", "<file object>"))


def save_index(index, file) -> None:
    """Write ``index`` to ``file`` (a path, written as named and atomically, or a binary file object)."""
    state = index.state_dict()
    meta = state.pop("meta")
    if not isinstance(file, (str, os.PathLike)):
        np.savez(file, meta=np.array(json.dumps(meta)), **state)
        return
    path = os.fspath(file)
    folder, base = os.path.split(path)
    tmp = os.path.join(folder, f".{base}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.array(json.dumps(meta)), **state)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def read_index_file(file) -> dict:
    """The state (:meth:`~attnloop.index.KeyframeIndex.state_dict`) saved by :func:`save_index` in ``file``.

    Raises:
        FileNotFoundError: no such file.
        IndexFileError: not a keyframe-index ``.npz`` file, or its ``meta`` entry is missing or not JSON.
    """
    name = file_name(file)
    try:
        data = np.load(file, allow_pickle=False)
        if isinstance(data, np.lib.npyio.NpzFile):
            with data:
                arrays = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise IndexFileError(f"{name}: not a keyframe-index .npz file ({exc})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):  # a single .npy array
        raise IndexFileError(f"{name}: a .npy array, not a keyframe-index .npz file")
    if "meta" not in arrays:
        raise IndexFileError(f"{name}: no 'meta' entry (not a keyframe-index file)")
    try:
        meta = json.loads(str(arrays.pop("meta")))
    except json.JSONDecodeError as exc:
        raise IndexFileError(f"{name}: the 'meta' entry is not JSON ({exc})") from exc
    return {"meta": meta, **arrays}
