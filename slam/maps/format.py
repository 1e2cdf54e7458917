"""The saved-map format: a folder with a JSON manifest and three ``.npz`` files (open, versioned, no pickles).

A map folder written by :func:`save_map` holds:

* ``manifest.json``: ``format`` (``"attnloop.map"``), ``version`` (:data:`MAP_FORMAT_VERSION`), when and
  from what it was made, the descriptor that made the index (with its descriptor of a fixed probe image,
  :func:`slam.maps.relocalise.descriptor_probe`), the camera rig the poses are in, the ground-truth pose of
  the recording's first tracked frame (the world's origin; null without ground truth), and per data file its
  name and SHA-256;
* ``keyframes.npz``: per keyframe ``pose (M, 7)`` float64 (world-from-camera of the *tracked* camera,
  the colour camera on an unregistered rig; the world is the first tracked frame's depth camera as in
  every output), ``frame_index (M,)``, ``timestamp (M,)``, ``index_id (M,)`` (its id in ``index.npz``),
  ``descriptor (M, D)`` float32, the verification features concatenated over keyframes with
  ``feature_offsets (M + 1,)``: ``keypoints (N, 2)`` float32, ``orb (N, B)`` uint8 (or float32 for
  non-binary descriptors), ``points (N, 3)`` float32 (metres, in the keyframe's tracked camera),
  ``valid (N,)`` bool, ``sigma_px (N,)`` float32, and ``K (M, 3, 3)`` float64, ``image_size (M, 2)``,
  ``rgb (M, h, w, 3)`` uint8 (the downsized keyframe images);
* ``graph.npz``: the keyframe pose graph, ``ii, jj (E,)`` int64, ``T_ij (E, 7)``, ``information
  (E, 6, 6)`` float64 (unscaled), ``kind (E,)`` (:class:`slam.keyframe_graph.EdgeKind`), ``weak``,
  ``active (E,)`` bool and ``weight (E,)`` float64;
* ``index.npz``: the keyframe index itself (:func:`attnloop.index.save_index`), so that a reloaded
  map answers queries exactly as the saved one.

Every reading error is a :class:`MapFormatError` (or its :class:`MapVersionError`) naming the file.

Example:
    >>> import tempfile
    >>> try:
    ...     load_map(tempfile.mkdtemp())
    ... except MapFormatError as e:
    ...     print(str(e).endswith("no manifest.json (not a saved map)"))
    True
"""
from __future__ import annotations

import datetime
import hashlib
import json
import os
import shutil
import uuid
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from attnloop.index import IndexFileError, KeyframeIndex, load_index, save_index
from slam.keyframe_graph import EdgeKind, GraphEdge
from slam.odometry.features import FrameFeatures

Tensor = torch.Tensor

__all__ = ["MAP_FILES", "MAP_FORMAT", "MAP_FORMAT_VERSION", "MapFormatError", "MapVersionError", "SavedMap",
           "load_map", "prepare_map_dir", "save_map"]

MAP_FORMAT = "attnloop.map"
MAP_FORMAT_VERSION = 1
#: The data files of a map folder, by role (the manifest names them again with their checksums).
MAP_FILES = {"keyframes": "keyframes.npz", "graph": "graph.npz", "index": "index.npz"}
MANIFEST = "manifest.json"

_KEYFRAME_ARRAYS = ("pose", "frame_index", "timestamp", "index_id", "descriptor", "feature_offsets", "keypoints",
                    "orb", "points", "valid", "sigma_px", "K", "image_size", "rgb")
_GRAPH_ARRAYS = ("ii", "jj", "T_ij", "information", "kind", "weak", "active", "weight")


class MapFormatError(ValueError):
    """A map folder that cannot be read: the message names the file and what is wrong."""


class MapVersionError(MapFormatError):
    """A map written by a newer version of the format than this library reads."""


@dataclass
class SavedMap:
    """A map in memory: what :func:`load_map` returns and :func:`save_map` writes.

    Attributes:
        poses: ``(M, 7)`` float64 keyframe poses (tracked camera, map world).
        frame_index: ``(M,)`` int64 input index of each keyframe in the mapping recording.
        timestamps: ``(M,)`` float64.
        index_ids: ``(M,)`` int64 id of each keyframe in ``index``.
        descriptors: ``(M, D)`` float32 place descriptors.
        features: ``M`` :class:`~slam.odometry.features.FrameFeatures` (what verification needs).
        rgb: ``(M, h, w, 3)`` uint8 downsized keyframe images.
        edges: the pose graph's :class:`~slam.keyframe_graph.GraphEdge` list.
        index: the :class:`~attnloop.index.KeyframeIndex` over ``descriptors``.
        info: the manifest (descriptor, rig, ground-truth origin, provenance).
        path: the folder it was read from (None for a map not read from disk).
    """

    poses: Tensor
    frame_index: Tensor
    timestamps: Tensor
    index_ids: Tensor
    descriptors: Tensor
    features: list
    rgb: np.ndarray
    edges: list
    index: KeyframeIndex
    info: dict = field(default_factory=dict)
    path: Path | None = None

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    @property
    def descriptor(self) -> dict:
        """The descriptor that made the index (``backbone``, ``fusion``, ``num_rnn``, ``seed``, ``dim``, ``probe``)."""
        return dict(self.info.get("descriptor", {}))

    @property
    def rig(self) -> dict:
        """``{"rgb_intrinsics": [fx, fy, cx, cy] | None, "rgb_from_depth": [tx, ty, tz]}``."""
        return dict(self.info.get("rig", {}))

    @property
    def groundtruth_origin(self) -> Tensor | None:
        """``(7,)`` ground truth of the mapping recording's first tracked frame (the world's origin), or None."""
        g = self.info.get("groundtruth_origin")
        return None if g is None else torch.tensor(g, dtype=torch.float64)


def prepare_map_dir(path) -> Path:
    """Check that ``path`` can take a map (absent, an empty folder or a previous map) before the work.

    Raises:
        MapFormatError: a file, a non-empty folder that is not a saved map, or a saved map with other files
            in its folder (they would be deleted with it); nothing is removed.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise MapFormatError(f"{p}: exists and is not a folder; --save-map needs a folder")
    if p.is_dir() and any(p.iterdir()):
        if not (p / MANIFEST).is_file():
            raise MapFormatError(f"{p}: a non-empty folder that is not a saved map; choose an empty or new folder")
        try:  # a manifest.json of something else (a web app's, a dataset's) is not a previous map
            manifest = json.loads((p / MANIFEST).read_text())
            fmt = manifest.get("format") if isinstance(manifest, dict) else None
        except ValueError:  # not JSON (UnicodeDecodeError included) among map files: a damaged map, replaced
            fmt = MAP_FORMAT
        if fmt != MAP_FORMAT:
            raise MapFormatError(f"{p / MANIFEST}: 'format' is {fmt!r}, not {MAP_FORMAT!r}: a non-empty folder that "
                                 "is not a saved map; choose an empty or new folder")
        foreign = sorted(q.name for q in p.iterdir() if q.name not in (MANIFEST, *MAP_FILES.values()))
        if foreign:
            raise MapFormatError(f"{p}: a saved map with other files in it ({', '.join(foreign[:5])}"
                                 f"{', ...' if len(foreign) > 5 else ''}), which replacing the map would delete; "
                                 "move them or choose another folder")
    parent = p.resolve().parent
    if not os.access(parent if parent.exists() else Path.cwd(), os.W_OK):
        raise MapFormatError(f"{p}: cannot write into {parent}")
    return p


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _features_arrays(features: list) -> dict:
    offsets = np.zeros(len(features) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(f) for f in features])
    binary = {bool(f.binary) for f in features}
    if len(binary) > 1:
        raise ValueError("the keyframes mix binary and float feature descriptors")
    is_binary = binary.pop() if binary else True

    def cat(name, dtype, width):
        parts = [getattr(f, name).detach().cpu().numpy().astype(dtype).reshape(len(f), *width) for f in features]
        return np.concatenate(parts) if parts else np.zeros((0, *width), dtype)

    width = features[0].descriptors.shape[1] if features else 32
    return {"feature_offsets": offsets, "keypoints": cat("keypoints", np.float32, (2,)),
            "orb": cat("descriptors", np.uint8 if is_binary else np.float32, (width,)),
            "points": cat("points", np.float32, (3,)), "valid": cat("valid", bool, ()),
            "sigma_px": cat("sigma_px", np.float32, ()),
            "K": np.stack([f.K.detach().cpu().numpy().astype(np.float64) for f in features]) if features
            else np.zeros((0, 3, 3)),
            "image_size": np.array([tuple(f.image_size) for f in features], dtype=np.int64).reshape(-1, 2)}


def save_map(path, saved: SavedMap) -> Path:
    """Write ``saved`` into the folder ``path`` (the format of the module docstring).

    Written into a temporary folder beside ``path`` and renamed into place once complete.

    Raises:
        MapFormatError: ``path`` cannot take a map (:func:`prepare_map_dir`).
        ValueError: inconsistent contents (shapes that do not agree).
    """
    target = prepare_map_dir(path)
    M = len(saved)
    for name, arr, shape in (("poses", saved.poses, (M, 7)), ("frame_index", saved.frame_index, (M,)),
                             ("timestamps", saved.timestamps, (M,)), ("index_ids", saved.index_ids, (M,))):
        if tuple(arr.shape) != shape:
            raise ValueError(f"SavedMap.{name} must have shape {shape}, got {tuple(arr.shape)}")
    if saved.descriptors.ndim != 2 or saved.descriptors.shape[0] != M or len(saved.features) != M \
            or saved.rgb.ndim != 4 or saved.rgb.shape[0] != M:
        raise ValueError(f"SavedMap: {M} poses but descriptors {tuple(saved.descriptors.shape)}, "
                         f"{len(saved.features)} feature sets, rgb {tuple(saved.rgb.shape)}")
    tmp = target.parent / f".{target.name}.{uuid.uuid4().hex[:8]}.tmp"
    tmp.mkdir(parents=True)
    try:
        def host(t: Tensor, dtype) -> np.ndarray:  # any device, with or without autograd
            return t.detach().to("cpu", dtype).numpy()

        kf = {"pose": host(saved.poses, torch.float64), "frame_index": host(saved.frame_index, torch.int64),
              "timestamp": host(saved.timestamps, torch.float64), "index_id": host(saved.index_ids, torch.int64),
              "descriptor": host(saved.descriptors, torch.float32), "rgb": np.ascontiguousarray(saved.rgb),
              **_features_arrays(saved.features)}
        np.savez(tmp / MAP_FILES["keyframes"], **kf)
        e = saved.edges
        np.savez(tmp / MAP_FILES["graph"],
                 ii=np.array([x.i for x in e], np.int64), jj=np.array([x.j for x in e], np.int64),
                 T_ij=np.stack([host(x.T_ij, torch.float64) for x in e]) if e else np.zeros((0, 7)),
                 information=np.stack([host(x.information, torch.float64) for x in e]) if e else np.zeros((0, 6, 6)),
                 kind=np.array([int(x.kind) for x in e], np.int64), weak=np.array([x.weak for x in e], bool),
                 active=np.array([x.active for x in e], bool), weight=np.array([x.weight for x in e], np.float64))
        save_index(saved.index, tmp / MAP_FILES["index"])
        reserved = ("format", "version", "created", "num_keyframes", "num_edges", "files")  # this file's own
        manifest = {"format": MAP_FORMAT, "version": MAP_FORMAT_VERSION,
                    "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                    "num_keyframes": M, "num_edges": len(e),
                    **{k: v for k, v in saved.info.items() if k not in reserved},
                    "files": {role: {"name": name, "sha256": _sha256(tmp / name)} for role, name in MAP_FILES.items()}}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
        old = None
        if target.exists():
            old = target.parent / f".{target.name}.{uuid.uuid4().hex[:8]}.old"
            target.rename(old)
        try:
            tmp.rename(target)
        except BaseException:
            if old is not None:  # put the previous map back: a failed save loses nothing
                old.rename(target)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def _read_npz(path: Path, names: tuple) -> dict:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise MapFormatError(f"{path}: missing (the manifest lists it)") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise MapFormatError(f"{path}: not a readable .npz file ({exc})") from exc
    missing = [n for n in names if n not in arrays]
    if missing:
        raise MapFormatError(f"{path}: missing entries {', '.join(missing)}")
    return arrays


def _check_rows(path: Path, arrays: dict, rows: dict) -> None:
    for name, shape in rows.items():
        got = arrays[name].shape
        if len(got) != len(shape) or any(s is not None and g != s for g, s in zip(got, shape)):
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise MapFormatError(f"{path}: entry '{name}' has shape {got}, expected {want}")


def _read_manifest(folder: Path) -> dict:
    mpath = folder / MANIFEST
    if not folder.is_dir():
        # a process killed between save_map's two renames leaves the map only in the hidden folders beside it
        left = sorted(p for p in folder.parent.glob(f".{folder.name}.*.old") if (p / MANIFEST).is_file()) + \
            sorted(p for p in folder.parent.glob(f".{folder.name}.*.tmp") if (p / MANIFEST).is_file())
        if left:
            raise FileNotFoundError(f"{folder}: no such map folder, but a save that was replacing it stopped "
                                    f"half-way: the previous map (.old) and the new one (.tmp) are in "
                                    f"{', '.join(str(p) for p in left)}; rename the one to keep to {folder}")
        raise FileNotFoundError(f"{folder}: no such map folder")
    if not mpath.is_file():
        raise MapFormatError(f"{folder}: no {MANIFEST} (not a saved map)")
    try:
        manifest = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise MapFormatError(f"{mpath}: not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != MAP_FORMAT:
        fmt = manifest.get("format") if isinstance(manifest, dict) else None
        raise MapFormatError(f"{mpath}: 'format' is {fmt!r}, expected {MAP_FORMAT!r}")
    version = manifest.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise MapFormatError(f"{mpath}: 'version' must be a positive integer, got {version!r}")
    if version > MAP_FORMAT_VERSION:
        raise MapVersionError(f"{mpath}: map format version {version} is newer than this library reads "
                              f"({MAP_FORMAT_VERSION}); upgrade attnloop")
    files = manifest.get("files")
    if not isinstance(files, dict) or any(role not in files for role in MAP_FILES):
        raise MapFormatError(f"{mpath}: 'files' must name {', '.join(MAP_FILES)}")
    for role in MAP_FILES:
        entry = files[role]
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) or "/" in entry["name"] \
                or "\\" in entry["name"] or entry["name"].startswith("."):
            raise MapFormatError(f"{mpath}: files.{role} must be {{'name': a file in the folder, 'sha256': ...}}")
        fpath = folder / entry["name"]
        if not fpath.is_file():
            raise MapFormatError(f"{fpath}: missing (the manifest lists it as the {role} file)")
        digest = entry.get("sha256")
        if not isinstance(digest, str) or len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
            raise MapFormatError(f"{mpath}: files.{role}.sha256 must be the 64 hex digits of the file's SHA-256, "
                                 f"got {digest!r}")
        if _sha256(fpath) != digest:
            raise MapFormatError(f"{fpath}: corrupt (its SHA-256 differs from the manifest's)")
    return manifest


def load_map(path) -> SavedMap:
    """Read a map folder written by :func:`save_map`.

    Args:
        path: the folder.

    Returns:
        :class:`SavedMap`.

    Raises:
        FileNotFoundError: no such folder.
        MapVersionError: a newer format version.
        MapFormatError: anything else wrong, naming the file (and the entry or shape).
    """
    folder = Path(path)
    manifest = _read_manifest(folder)
    files = {role: folder / manifest["files"][role]["name"] for role in MAP_FILES}
    kp = files["keyframes"]
    kf = _read_npz(kp, _KEYFRAME_ARRAYS)
    M = kf["pose"].shape[0] if kf["pose"].ndim == 2 else -1
    N = int(kf["keypoints"].shape[0])
    _check_rows(kp, kf, {"pose": (M, 7), "frame_index": (M,), "timestamp": (M,), "index_id": (M,),
                         "descriptor": (M, None), "feature_offsets": (M + 1,), "keypoints": (N, 2),
                         "orb": (N, None), "points": (N, 3), "valid": (N,), "sigma_px": (N,), "K": (M, 3, 3),
                         "image_size": (M, 2), "rgb": (M, None, None, 3)})
    if M != manifest.get("num_keyframes"):
        raise MapFormatError(f"{kp}: {M} keyframes, the manifest says {manifest.get('num_keyframes')}")
    off = kf["feature_offsets"]
    if off[0] != 0 or off[-1] != N or np.any(np.diff(off) < 0):
        raise MapFormatError(f"{kp}: 'feature_offsets' must rise from 0 to {N} (the number of keypoints)")
    if not np.all(np.isfinite(kf["pose"])):
        raise MapFormatError(f"{kp}: entry 'pose' holds non-finite values")
    binary = kf["orb"].dtype == np.uint8
    feats = []
    for m in range(M):
        s = slice(int(off[m]), int(off[m + 1]))
        feats.append(FrameFeatures(torch.from_numpy(kf["keypoints"][s].astype(np.float32)),
                                   torch.from_numpy(kf["orb"][s].copy()),
                                   torch.from_numpy(kf["points"][s].astype(np.float32)),
                                   torch.from_numpy(kf["valid"][s].astype(bool)),
                                   torch.from_numpy(kf["sigma_px"][s].astype(np.float32)),
                                   torch.from_numpy(kf["K"][m].astype(np.float64)),
                                   (int(kf["image_size"][m][0]), int(kf["image_size"][m][1])), binary))
    gp = files["graph"]
    g = _read_npz(gp, _GRAPH_ARRAYS)
    E = g["ii"].shape[0] if g["ii"].ndim == 1 else -1
    _check_rows(gp, g, {"ii": (E,), "jj": (E,), "T_ij": (E, 7), "information": (E, 6, 6), "kind": (E,),
                        "weak": (E,), "active": (E,), "weight": (E,)})
    if E and (g["ii"].min() < 0 or g["jj"].min() < 0 or max(g["ii"].max(), g["jj"].max()) >= M):
        raise MapFormatError(f"{gp}: an edge joins a keyframe outside [0, {M})")
    if "num_edges" in manifest and E != manifest["num_edges"]:
        raise MapFormatError(f"{gp}: {E} edges, the manifest says {manifest['num_edges']}")
    for name in ("T_ij", "information"):
        if not np.all(np.isfinite(g[name])):
            raise MapFormatError(f"{gp}: entry '{name}' holds non-finite values")
    kinds = {int(k) for k in EdgeKind}
    if any(int(k) not in kinds for k in g["kind"]):
        raise MapFormatError(f"{gp}: entry 'kind' holds codes other than {sorted(kinds)}")
    edges = [GraphEdge(int(g["ii"][e]), int(g["jj"][e]), torch.from_numpy(g["T_ij"][e].astype(np.float64)),
                       torch.from_numpy(g["information"][e].astype(np.float64)), EdgeKind(int(g["kind"][e])),
                       bool(g["weak"][e]), bool(g["active"][e]), float(g["weight"][e])) for e in range(E)]
    try:
        index = load_index(files["index"])
    except IndexFileError as exc:
        raise MapFormatError(str(exc)) from exc
    ids = kf["index_id"].astype(np.int64)
    try:
        index.rows_of(ids)
    except ValueError as exc:
        raise MapFormatError(f"{files['index']}: does not hold the keyframes' index ids ({exc})") from exc
    if len(np.unique(ids)) != M or len(index) != M:  # a search must answer only this map's keyframes
        raise MapFormatError(f"{files['index']}: holds {len(index)} keyframes for {M} keyframes in {kp.name} "
                             f"({len(np.unique(ids))} distinct index ids); each keyframe must be in it exactly once")
    D = kf["descriptor"].shape[1]
    if M and index.dim != D:  # else the first map query fails, mid-run, without naming the map
        raise MapFormatError(f"{files['index']}: descriptors of {index.dim} values, the keyframes' ({kp.name}) "
                             f"have {D}")
    info = {k: v for k, v in manifest.items() if k not in ("format", "version", "files")}
    return SavedMap(torch.from_numpy(kf["pose"].astype(np.float64)),
                    torch.from_numpy(kf["frame_index"].astype(np.int64)),
                    torch.from_numpy(kf["timestamp"].astype(np.float64)), torch.from_numpy(ids),
                    torch.from_numpy(kf["descriptor"].astype(np.float32)), feats, np.ascontiguousarray(kf["rgb"]),
                    edges, index, info, folder)
