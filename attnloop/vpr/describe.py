"""Descriptors of an image collection, written as resumable shards.

``DIR/manifest.json`` lists the images, the descriptor's settings, the model's identity and, per finished
shard, its row range, SHA-256 and skipped (unreadable) images; ``DIR/shard-NNNNN.npy`` holds the float32
``(rows, D)`` descriptors of its readable images. An interrupted run goes on where it stopped. Engines:
``"local"`` (a torch DataLoader) and ``"ray"`` (Ray Data on an actor pool; ``pip install attnloop[ray]``).
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp")
LIST_SUFFIXES = (".txt", ".lst", ".list")
MANIFEST = "manifest.json"
FORMAT = "attnloop-vpr-descriptors/1"


class VPRInputError(ValueError):
    """Input that cannot be used: the message names the file, flag or folder, and what was expected."""


def load_rgb(path) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB as OpenCV's colour mode decodes it; a missing, corrupt or truncated file is a
    :class:`slam.io.images.FrameReadError` naming it."""
    from slam.io.images import decode_image

    return np.ascontiguousarray(decode_image(str(path), cv2.IMREAD_COLOR)[:, :, ::-1])


def natural_key(path) -> tuple:
    """Sort key of a file name with its digit runs compared as numbers (``2.jpg`` before ``10.jpg``, as
    VPR-Bench orders images); the name breaks ties."""
    name = Path(path).name
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)], name, str(path)


def folder_images(folder) -> list[Path]:
    """The images of ``folder`` in natural order (hidden files, e.g. macOS's ``._x.jpg``, are not images)."""
    files = sorted((p for p in Path(folder).iterdir()
                    if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")), key=natural_key)
    if not files:
        raise VPRInputError(f"{folder}: no images in this folder")
    return files


def image_paths(inputs: Sequence) -> list[str]:
    """The images named by ``inputs``, in order: folders and glob patterns (natural order), image files, or
    text files of paths (``.txt``, ``.lst``, ``.list``: one a line, ``#`` comments, relative to the list).

    Raises:
        VPRInputError: an input that exists as none of these, or matches no image.
    """
    out: list[str] = []
    for item in map(str, inputs):
        p = Path(item)
        if p.is_dir():
            out += [str(f) for f in folder_images(p)]
        elif p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES:
            out.append(item)
        elif p.is_file() and p.suffix.lower() in LIST_SUFFIXES:
            lines = [s.strip() for s in p.read_text(errors="replace").splitlines()]
            listed = [s if os.path.isabs(s) else str(p.parent / s) for s in lines if s and not s.startswith("#")]
            if not listed:
                raise VPRInputError(f"{item}: a list file with no image path in it")
            out += listed
        elif p.is_file():
            raise VPRInputError(f"{item}: neither an image ({', '.join(IMAGE_SUFFIXES)}) nor a list of paths "
                                f"({', '.join(LIST_SUFFIXES)})")
        elif glob.has_magic(item):
            found = sorted((f for f in glob.glob(item) if Path(f).suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
            if not found:
                raise VPRInputError(f"{item}: the pattern matches no image")
            out += found
        else:
            raise VPRInputError(f"{item}: no such file or folder")
    return out


class _Decode(torch.utils.data.Dataset):
    """Item i: ``(index, (H, W, 3) uint8 RGB or None, error or None)``; the DataLoader's workers decode."""

    def __init__(self, items: Sequence[tuple[int, str]]):
        self.items = list(items)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i):
        index, path = self.items[i]
        try:
            return index, load_rgb(path), None
        except Exception as e:  # noqa: BLE001  (FrameReadError, or a decoder's own error: the caller names the image)
            return index, None, getattr(e, "reason", None) or f"{type(e).__name__}: {e}"


def describe_batch(model: torch.nn.Module, decoded: Sequence[tuple[int, np.ndarray | None, str | None]]):
    """Describe decoded images: yields ``(index, (D,) float32 row or None, error or None)`` in input order.

    Consecutive images of one size form one batch; a row that is not finite or zero is an error, never a row.
    """
    run: list[tuple[int, np.ndarray]] = []
    device = next(model.parameters(), torch.empty(0)).device  # the model's (a GPU actor's): the batch goes there

    def flush():
        with torch.no_grad():
            x = torch.from_numpy(np.stack([im for _, im in run])).permute(0, 3, 1, 2).to(device)
            d = model(x).float().cpu().numpy()
        for (index, _), row in zip(run, d):
            ok = np.isfinite(row).all() and np.linalg.norm(row) > 0
            yield (index, row, None) if ok else (index, None, "the descriptor is not finite or is zero")
        run.clear()

    for index, image, error in decoded:
        if run and (image is None or image.shape != run[0][1].shape):
            yield from flush()
        if image is None:
            yield index, None, error
        else:
            run.append((index, image))
    if run:
        yield from flush()


def local_engine(model, items, batch_size: int = 16, workers: int = 2) -> Iterator:
    """``(index, row, error)`` of every ``(index, path)`` of ``items``, in order: a DataLoader decodes in
    ``workers`` processes (0: in this one), the model runs here."""
    loader = torch.utils.data.DataLoader(_Decode(items), batch_size=batch_size, num_workers=workers,
                                         collate_fn=list)
    for batch in loader:
        yield from describe_batch(model, batch)


class RayDescribe:
    """The Ray actor: builds the model once from the descriptor settings, then describes batches of paths."""

    def __init__(self, settings: dict, threads: int = 1):
        from slam.config import DescriptorConfig
        from slam.loop.closer import build_descriptor

        torch.set_num_threads(threads)
        self.model = build_descriptor(DescriptorConfig(**settings))

    def __call__(self, batch: dict) -> dict:
        decoded = _Decode(list(zip(batch["index"].tolist(), batch["path"].tolist())))
        rows = list(describe_batch(self.model, [decoded[i] for i in range(len(decoded))]))
        dim = next((r.shape[0] for _, r, _ in rows if r is not None), 0)
        return {"index": np.array([i for i, _, _ in rows], np.int64),
                "descriptor": np.stack([r if r is not None else np.full(dim, np.nan, np.float32) for _, r, _ in rows]),
                "error": np.array([e or "" for _, _, e in rows], dtype=object)}


def ray_engine(settings: dict, items, batch_size: int = 16, actors: int = 1, cpus_per_actor: float = 1,
               gpus_per_actor: float = 0, address: str | None = None) -> Iterator:
    """``(index, row, error)`` of every ``(index, path)`` of ``items`` from Ray Data (in any order), on
    ``actors`` :class:`RayDescribe` actors; a local Ray unless ``address`` names a cluster."""
    import logging

    import ray

    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"OMP_NUM_THREADS": str(max(1, int(cpus_per_actor)))}})
    context = ray.data.DataContext.get_current()
    context.enable_progress_bars = context.print_on_execution_start = False  # our tqdm bar says it
    logging.getLogger("ray.data").setLevel(logging.WARNING)
    ds = ray.data.from_items([{"index": i, "path": p} for i, p in items], override_num_blocks=max(1, actors * 4))
    ds = ds.map_batches(RayDescribe, fn_constructor_kwargs={"settings": settings,
                                                            "threads": max(1, int(cpus_per_actor))},
                        batch_size=batch_size, concurrency=actors, num_cpus=cpus_per_actor, num_gpus=gpus_per_actor)
    for batch in ds.iter_batches(batch_size=None, batch_format="numpy"):
        for index, row, error in zip(batch["index"], batch["descriptor"], batch["error"]):
            yield int(index), (None if error else row.astype(np.float32)), (error or None)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()  # a shard is tens of MB


def model_identity(model: torch.nn.Module) -> dict:
    """The model's class, backbone and a SHA-256 of its parameters and buffers (in state-dict order)."""
    h = hashlib.sha256()
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return {"class": type(model).__name__, "backbone": getattr(model, "backbone_name", None), "sha256": h.hexdigest()}


def _write_atomic(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def read_manifest(out) -> dict:
    """The manifest of a descriptor folder (:class:`VPRInputError` naming the folder when there is none)."""
    path = Path(out) / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise VPRInputError(f"{out}: no {MANIFEST} (not a folder written by attnloop-vpr describe)") from None
    except (OSError, ValueError) as e:
        raise VPRInputError(f"{path}: not a readable manifest ({e})") from None
    if manifest.get("format") != FORMAT:
        raise VPRInputError(f"{path}: format {manifest.get('format')!r}, expected {FORMAT!r}")
    return manifest


def describe(inputs: Sequence, out, model: torch.nn.Module, settings: dict | None = None, *,
             shard_size: int | None = None, engine: str = "local", strict: bool = False, progress: bool = True,
             warn=None, **engine_options) -> dict:
    """Describe every image of ``inputs`` into shards in ``out``, going on from a previous run there.

    Args:
        inputs: folders, globs, image files or list files (:func:`image_paths`).
        out: the descriptor folder (created).
        model: the descriptor, ``(B, 3, H, W)`` uint8 -> ``(B, D)``.
        settings: the :class:`slam.config.DescriptorConfig` fields the model was built from (recorded; the
            Ray engine's actors build their model from them).
        shard_size: images per shard (default: the folder's, else 4096).
        engine: ``"local"`` or ``"ray"``; ``engine_options`` go to :func:`local_engine` / :func:`ray_engine`.
        strict: refuse the first unreadable image (:class:`VPRInputError`; finished shards are kept).
        progress: a tqdm bar on stderr.
        warn: called with one line per skipped image (default: printed to stderr).

    Returns:
        the manifest.

    Raises:
        VPRInputError: bad inputs, or ``out`` holding descriptors of other images, settings or model.
    """
    from attnloop import __version__

    out = Path(out)
    old = read_manifest(out) if (out / MANIFEST).is_file() else None
    shard_size = shard_size or (old["shard_size"] if old else 4096)
    if isinstance(shard_size, bool) or int(shard_size) != shard_size or shard_size < 1:
        raise VPRInputError(f"shard_size must be a positive integer, got {shard_size!r}")
    warn = warn or (lambda line: print(line, file=sys.stderr))
    paths = image_paths(inputs)
    identity = {"format": FORMAT, "paths": paths, "shard_size": int(shard_size), "descriptor": settings,
                "recipe": asdict(model.recipe) if hasattr(model, "recipe") else None, "model": model_identity(model)}
    manifest = {**identity, "library": {"attnloop": __version__, "torch": torch.__version__}, "dim": None,
                "shards": []}
    if old:
        for key, value in identity.items():
            if json.loads(json.dumps(value)) != old.get(key):
                what = "of other images" if key == "paths" else f"with another {key.replace('_', ' ')}"
                raise VPRInputError(f"{out}: holds descriptors {what}; describe into a new --out folder")
        manifest.update(dim=old.get("dim"), shards=[s for s in old["shards"] if (out / s["file"]).is_file()
                                                    and _sha256(out / s["file"]) == s["sha256"]])
    out.mkdir(parents=True, exist_ok=True)
    done = {s["start"] for s in manifest["shards"]}
    pending = [(start, min(start + shard_size, len(paths))) for start in range(0, len(paths), shard_size)
               if start not in done]
    items = [(i, paths[i]) for a, b in pending for i in range(a, b)]
    if engine == "local":
        rows = local_engine(model, items, **engine_options)
    elif engine == "ray" and settings is None:
        raise VPRInputError("the Ray engine's actors build their model from the settings: give them")
    elif engine == "ray":
        rows = ray_engine(settings, items, **engine_options)
    else:
        raise VPRInputError(f"engine must be 'local' or 'ray', got {engine!r}")
    from tqdm import tqdm

    bar = tqdm(total=len(paths), initial=len(paths) - len(items), unit="img", disable=not progress)
    shard_of = {i: k for k, (a, b) in enumerate(pending) for i in range(a, b)}
    buffers: dict[int, dict[int, tuple]] = {}
    for index, row, error in rows:
        bar.update(1)
        if error is not None:
            if strict:
                raise VPRInputError(f"{paths[index]}: {error} (strict: nothing after it described)")
            warn(f"{paths[index]}: {error}; skipped")
        k = shard_of[index]
        buf = buffers.setdefault(k, {})
        buf[index] = (row, error)
        a, b = pending[k]
        if len(buf) == b - a:
            _finish_shard(out, manifest, a, b, [buf[i] for i in range(a, b)])
            del buffers[k]
    bar.close()
    return manifest


def _finish_shard(out: Path, manifest: dict, start: int, stop: int, results: list[tuple]) -> None:
    rows = [r for r, e in results if e is None]
    dim = manifest["dim"] or (rows[0].shape[0] if rows else None)
    manifest["dim"] = dim
    x = np.stack(rows).astype(np.float32) if rows else np.zeros((0, dim or 0), np.float32)
    name = f"shard-{start // manifest['shard_size']:05d}.npy"
    def save(p):
        with open(p, "wb") as f:
            np.save(f, x)

    _write_atomic(out / name, save)
    skipped = [{"index": start + i, "error": e} for i, (_, e) in enumerate(results) if e is not None]
    manifest["shards"].append({"file": name, "start": start, "stop": stop, "rows": len(rows),
                               "sha256": _sha256(out / name), "skipped": skipped})
    manifest["shards"].sort(key=lambda s: s["start"])
    _write_atomic(out / MANIFEST, lambda p: p.write_text(json.dumps(manifest, indent=1)))


def load_descriptors(out) -> tuple[list[str], np.ndarray]:
    """The described images of a finished descriptor folder and their descriptors.

    Returns:
        ``(paths, X)``: the readable images in input order and their ``(N, D)`` float32 descriptors.

    Raises:
        VPRInputError: no manifest, unfinished shards, or a shard file whose content is not what the
            manifest says.
    """
    out = Path(out)
    m = read_manifest(out)
    expected = -(-len(m["paths"]) // m["shard_size"])
    if len(m["shards"]) != expected:
        raise VPRInputError(f"{out}: {len(m['shards'])} of {expected} shards finished; run describe again to finish")
    paths, blocks = [], []
    for s in m["shards"]:
        x = np.load(out / s["file"])
        if x.shape != (s["rows"], m["dim"]) or x.dtype != np.float32:
            raise VPRInputError(f"{out / s['file']}: shape {x.shape} {x.dtype}, the manifest says ({s['rows']}, "
                                f"{m['dim']}) float32")
        skipped = {k["index"] for k in s["skipped"]}
        paths += [m["paths"][i] for i in range(s["start"], s["stop"]) if i not in skipped]
        blocks.append(x)
    return paths, np.concatenate(blocks) if blocks else np.zeros((0, m["dim"] or 0), np.float32)


def describe_images(model, inputs: Iterable, **engine_options) -> tuple[list[str], np.ndarray]:
    """Describe images in memory (no shards): ``(paths, X)`` of the readable ones; unreadable ones are
    refused (:class:`VPRInputError` naming the first)."""
    paths = image_paths(list(inputs))
    rows = []
    for index, row, error in local_engine(model, list(enumerate(paths)), **engine_options):
        if error is not None:
            raise VPRInputError(f"{paths[index]}: {error}")
        rows.append(row)
    return paths, np.stack(rows)
