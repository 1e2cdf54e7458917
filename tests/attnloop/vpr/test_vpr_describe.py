"""attnloop.vpr.describe: image lists, shards and manifest, resuming without recomputing, unreadable images."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from attnloop.vpr import VPRInputError, describe, image_paths, load_descriptors


def colour(i: int) -> tuple[int, int, int]:
    """The RGB colour of test image i (uniform)."""
    return 10 + i, 20 + 2 * i, 30 + 3 * i


def write_images(folder, n: int, size=(12, 16)) -> list[str]:
    """n uniform PNG images named 1.png .. n.png (lossless: the mean colour is exactly :func:`colour`)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        rgb = np.empty((*size, 3), np.uint8)
        rgb[:] = colour(i)
        paths.append(str(folder / f"{i + 1}.png"))
        cv2.imwrite(paths[-1], rgb[:, :, ::-1])
    return paths


class MeanColour(nn.Module):
    """(B, 3, H, W) uint8 -> (B, 4): mean R, G, B and 1; counts the images it describes, and can stop after some."""

    def __init__(self, stop_after: int | None = None):
        super().__init__()
        self.images = 0
        self.stop_after = stop_after

    def forward(self, x):
        self.images += x.shape[0]
        if self.stop_after is not None and self.images > self.stop_after:
            raise KeyboardInterrupt  # the run is interrupted here
        return torch.cat([x.float().mean((2, 3)), torch.ones(x.shape[0], 1)], dim=1)


def expected(indices) -> np.ndarray:
    return np.array([[*colour(i), 1.0] for i in indices], np.float32)


def run(images, out, model, **kw):
    kw = {"shard_size": 4, "progress": False, "batch_size": 4, "workers": 0, **kw}
    return describe(images, out, model, {"name": "mean colour"}, **kw)


def test_image_paths_folder_glob_and_list(tmp_path):
    paths = write_images(tmp_path / "a", 11)
    (tmp_path / "a" / ".hidden.png").write_bytes(b"")
    assert image_paths([tmp_path / "a"]) == paths  # natural order: 2.png before 10.png
    assert image_paths([str(tmp_path / "a" / "1*.png")]) == [paths[0], paths[9], paths[10]]
    (tmp_path / "list.txt").write_text(f"# two images\na/2.png\n\n{paths[4]}\n")
    assert image_paths([tmp_path / "list.txt"]) == [str(tmp_path / "a" / "2.png"), paths[4]]
    with pytest.raises(VPRInputError, match="nowhere"):
        image_paths([tmp_path / "nowhere"])
    np.save(tmp_path / "x.npy", np.zeros(3))
    with pytest.raises(VPRInputError, match="x.npy: neither an image"):
        image_paths([tmp_path / "x.npy"])


def test_shards_manifest_and_rows(tmp_path):
    images = write_images(tmp_path / "img", 10)
    m = run([tmp_path / "img"], tmp_path / "out", MeanColour(), workers=2)  # decoded in two processes
    assert [s["file"] for s in m["shards"]] == ["shard-00000.npy", "shard-00001.npy", "shard-00002.npy"]
    assert json.loads((tmp_path / "out" / "manifest.json").read_text())["paths"] == images
    paths, x = load_descriptors(tmp_path / "out")
    assert paths == images and x.dtype == np.float32
    np.testing.assert_array_equal(x, expected(range(10)))


def test_interrupted_run_resumes_without_recomputing_finished_shards(tmp_path):
    write_images(tmp_path / "img", 10)
    with pytest.raises(KeyboardInterrupt):
        run([tmp_path / "img"], tmp_path / "out", MeanColour(stop_after=6))  # shard 0 finished, shard 1 not
    assert len(json.loads((tmp_path / "out" / "manifest.json").read_text())["shards"]) == 1
    again = MeanColour()
    run([tmp_path / "img"], tmp_path / "out", again)
    assert again.images == 6  # images 5-10 only
    np.testing.assert_array_equal(load_descriptors(tmp_path / "out")[1], expected(range(10)))
    # a finished shard whose file no longer matches its checksum is recomputed, the others are kept
    np.save(tmp_path / "out" / "shard-00001.npy", np.zeros((4, 4), np.float32))
    third = MeanColour()
    run([tmp_path / "img"], tmp_path / "out", third)
    assert third.images == 4
    np.testing.assert_array_equal(load_descriptors(tmp_path / "out")[1], expected(range(10)))


def test_unreadable_image_is_named_and_skipped_never_a_zero_row(tmp_path):
    images = write_images(tmp_path / "img", 6)
    (tmp_path / "img" / "4.png").write_bytes(b"not a png")
    lines = []
    m = run([tmp_path / "img"], tmp_path / "out", MeanColour(), warn=lines.append)
    assert len(lines) == 1 and lines[0].startswith(images[3]) and "skipped" in lines[0]
    assert m["shards"][0]["skipped"][0]["index"] == 3
    paths, x = load_descriptors(tmp_path / "out")
    assert paths == images[:3] + images[4:]
    np.testing.assert_array_equal(x, expected([0, 1, 2, 4, 5]))


def test_strict_refuses_and_keeps_finished_shards(tmp_path):
    images = write_images(tmp_path / "img", 6)
    (tmp_path / "img" / "6.png").write_bytes(b"")
    with pytest.raises(VPRInputError, match=images[5]):
        run([tmp_path / "img"], tmp_path / "out", MeanColour(), strict=True)
    shard = json.loads((tmp_path / "out" / "manifest.json").read_text())["shards"]
    assert [s["file"] for s in shard] == ["shard-00000.npy"]
    np.testing.assert_array_equal(np.load(tmp_path / "out" / "shard-00000.npy"), expected(range(4)))
    with pytest.raises(VPRInputError, match="2 shards finished|1 of 2 shards"):
        load_descriptors(tmp_path / "out")


def test_folder_of_other_images_or_model_is_refused_untouched(tmp_path):
    write_images(tmp_path / "img", 5)
    run([tmp_path / "img"], tmp_path / "out", MeanColour())
    before = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    with pytest.raises(VPRInputError, match="another descriptor"):
        describe([tmp_path / "img"], tmp_path / "out", MeanColour(), {"name": "other"}, shard_size=4, progress=False)
    with pytest.raises(VPRInputError, match="of other images"):
        run([str(tmp_path / "img" / "[1-3].png")], tmp_path / "out", MeanColour())
    assert {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()} == before
