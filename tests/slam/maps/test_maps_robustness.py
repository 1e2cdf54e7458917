"""Edge cases of slam.maps (the saved-map format, relocalisation's checks) and slam.mapping (PLY, voxels):
each test pins a case that once gave a wrong result, with exact numbers."""
from __future__ import annotations

import hashlib
import io
import json
import pathlib
import types

import numpy as np
import pytest
import torch
from helpers import assert_same_map as _assert_same_map
from helpers import hand_map as _hand_map

from attnloop.index import IndexConfig, KeyframeIndex
from slam.keyframe_graph import GraphEdge
from slam.mapping import PLYFormatError, read_ply, voxel_downsample, write_ply
from slam.maps import MapFormatError, load_map, save_map
from slam.odometry.features import FrameFeatures


def _rewrite_npz(folder, name, **changes):
    """Change entries of a data file and update its checksum in the manifest (a consistent edit)."""
    path = folder / name
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    np.savez(path, **arrays)
    mpath = folder / "manifest.json"
    manifest = json.loads(mpath.read_text())
    role = next(r for r, f in manifest["files"].items() if f["name"] == name)
    manifest["files"][role]["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    mpath.write_text(json.dumps(manifest))


# --------------------------------------------------------------------------------------- round trip
def test_every_field_round_trips_exactly_with_float_features_and_float32_edges(tmp_path):
    m = _hand_map(M=4)
    g = torch.Generator().manual_seed(3)
    m.features = [FrameFeatures(f.keypoints, torch.rand(len(f), 8, generator=g), f.points, f.valid, f.sigma_px, f.K,
                                (48 + k, 64), False) for k, f in enumerate(m.features)]
    m.edges = [GraphEdge(e.i, e.j, e.T_ij.to(torch.float32).to(torch.float64), e.information, e.kind, e.weak,
                         e.active, e.weight) for e in m.edges]
    save_map(tmp_path / "m", m)
    back = load_map(tmp_path / "m")
    _assert_same_map(m, back)
    assert back.features[2].descriptors.dtype == torch.float32 and back.features[2].binary is False
    assert [f.image_size for f in back.features] == [(48, 64), (49, 64), (50, 64), (51, 64)]
    assert back.index_ids.tolist() == [0, 333, 666, 999] and back.edges[-1].weight == 0.25


def test_tensors_that_require_grad_are_saved(tmp_path):
    m = _hand_map(M=3)
    m.poses = m.poses.clone().requires_grad_(True)  # a pose estimate straight out of an autograd optimiser
    m.descriptors = m.descriptors.clone().requires_grad_(True)
    save_map(tmp_path / "m", m)  # was: RuntimeError "Can't call numpy() on Tensor that requires grad"
    back = load_map(tmp_path / "m")
    assert torch.equal(back.poses, m.poses.detach()) and torch.equal(back.descriptors, m.descriptors.detach())


# ---------------------------------------------------------------------------------------- checksums
@pytest.mark.parametrize("digest", [None, "delete"])
def test_a_manifest_without_a_real_checksum_is_refused(tmp_path, digest):
    folder = tmp_path / "m"
    save_map(folder, _hand_map())
    # swap in another valid keyframes file (moved poses) and drop its checksum: no longer checked at all
    with np.load(folder / "keyframes.npz") as data:
        arrays = {k: data[k] for k in data.files}
    arrays["pose"] = arrays["pose"] + 1.0
    np.savez(folder / "keyframes.npz", **arrays)
    manifest = json.loads((folder / "manifest.json").read_text())
    if digest == "delete":
        del manifest["files"]["keyframes"]["sha256"]
    else:
        manifest["files"]["keyframes"]["sha256"] = digest
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MapFormatError, match=r"manifest\.json: files\.keyframes\.sha256 must be the 64 hex digits"):
        load_map(folder)


def test_an_index_with_keyframes_the_map_does_not_hold_is_refused(tmp_path):
    m = _hand_map()
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(torch.cat([m.descriptors, m.descriptors[:1]]), ids=torch.cat([m.index_ids, torch.tensor([99999])]))
    m.index = index
    save_map(tmp_path / "m", m)
    # a search could answer id 99999, which no keyframe has (MapRelocaliser._kf_of_id: KeyError)
    with pytest.raises(MapFormatError, match=r"index\.npz: holds 7 keyframes for 6 keyframes in keyframes\.npz"):
        load_map(tmp_path / "m")


def test_graph_edits_with_a_consistent_checksum_are_still_checked(tmp_path):
    folder = tmp_path / "m"
    save_map(folder, _hand_map())
    with np.load(folder / "graph.npz") as data:
        T = data["T_ij"].copy()
        n = data["ii"].shape[0]
    T[1, 0] = np.nan
    _rewrite_npz(folder, "graph.npz", T_ij=T)
    with pytest.raises(MapFormatError, match=r"graph\.npz: entry 'T_ij' holds non-finite values"):
        load_map(folder)
    with np.load(folder / "graph.npz") as data:
        arrays = {k: data[k][: n - 1] for k in data.files}
    arrays["T_ij"][:, 0] = 0.0
    _rewrite_npz(folder, "graph.npz", **arrays)  # an edge dropped; the manifest says 6
    with pytest.raises(MapFormatError, match=r"graph\.npz: 5 edges, the manifest says 6"):
        load_map(folder)


# ------------------------------------------------------------------------------------------- saving
def test_saving_over_a_foreign_folder_with_a_manifest_loses_nothing(tmp_path):
    web = tmp_path / "webapp"
    web.mkdir()
    (web / "manifest.json").write_text('{"name": "my app", "start_url": "/"}')
    (web / "app.js").write_text("console.log(1)")
    with pytest.raises(MapFormatError, match=r"manifest\.json: 'format' is None, not 'attnloop\.map'"):
        save_map(web, _hand_map())
    assert sorted(p.name for p in web.iterdir()) == ["app.js", "manifest.json"]
    assert (web / "app.js").read_text() == "console.log(1)"


def test_saving_over_a_map_with_other_files_in_its_folder_loses_nothing(tmp_path):
    folder = tmp_path / "m"
    save_map(folder, _hand_map(seed=0))
    (folder / "notes.txt").write_text("kitchen, Monday")
    with pytest.raises(MapFormatError, match=r"a saved map with other files in it \(notes\.txt\)"):
        save_map(folder, _hand_map(M=3, seed=1))
    assert (folder / "notes.txt").read_text() == "kitchen, Monday" and len(load_map(folder)) == 6
    (folder / "notes.txt").unlink()
    save_map(folder, _hand_map(M=3, seed=1))  # a folder holding only a map is replaced as before
    assert len(load_map(folder)) == 3


def test_a_failed_save_keeps_the_previous_map(tmp_path, monkeypatch):
    folder = tmp_path / "m"
    save_map(folder, _hand_map(seed=0))
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    import slam.maps.format as fmt

    calls = []
    real_savez = np.savez

    def savez_fails_second(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise OSError("disk full")
        return real_savez(*args, **kwargs)

    monkeypatch.setattr(fmt.np, "savez", savez_fails_second)
    with pytest.raises(OSError, match="disk full"):
        save_map(folder, _hand_map(M=3, seed=1))
    monkeypatch.setattr(fmt.np, "savez", real_savez)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no temporary folder left
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before and len(load_map(folder)) == 6

    # the final rename failing (a full or read-only parent) must put the previous map back
    real_rename = pathlib.Path.rename

    def rename(self, target):
        if self.name.endswith(".tmp"):
            raise OSError("rename refused")
        return real_rename(self, target)

    monkeypatch.setattr(pathlib.Path, "rename", rename)
    with pytest.raises(OSError, match="rename refused"):
        save_map(folder, _hand_map(M=3, seed=1))
    monkeypatch.setattr(pathlib.Path, "rename", real_rename)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # was: only '.m.XXXX.old', the map gone
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before and len(load_map(folder)) == 6


# ------------------------------------------------------------------------------------ relocalisation
def _fake_run(dim: int):
    from slam.config import SLAMConfig, override

    class Describe(torch.nn.Module):
        backbone_name = "efficientnet_lite0"
        out_dim = dim

        def forward(self, images):
            return torch.full((images.shape[0], dim), 1.0 / dim ** 0.5)

    cfg = override(SLAMConfig(), {"loop.descriptor.fusion": "dam", "loop.descriptor.num_rnn": 16,
                                  "loop.descriptor.seed": 0})
    index = KeyframeIndex(IndexConfig(backend="exact"))  # empty: the run has not started
    closer = types.SimpleNamespace(descriptor=Describe())
    return types.SimpleNamespace(config=cfg, loop_closer=closer, localize=False, keyframe_index=lambda: index)


def test_a_map_of_another_descriptor_length_is_refused_without_probes(caplog):
    from slam.maps import MapMismatchError, MapRelocaliser

    m = _hand_map()  # 16-entry descriptors, names as the fake run's
    m.info["descriptor"]["probe"] = None  # a map whose descriptor could not describe the probe
    assert MapRelocaliser(m, _fake_run(16)).report.map_keyframes == 6  # the same length: accepted
    with pytest.raises(MapMismatchError, match="the map's descriptors have 16 entries, this run's 8"):
        MapRelocaliser(m, _fake_run(8))  # was accepted; the first search then failed on the shapes


# ----------------------------------------------------------------------------------------------- PLY
def test_ply_refuses_coordinates_float32_cannot_hold():
    with pytest.raises(ValueError, match=r"beyond float32's range .*1 point\(s\), the first row 1"):
        write_ply(io.BytesIO(), np.array([[0.0, 0, 0], [1e39, 0, 0]]), np.zeros((2, 3), np.uint8))
    buf = io.BytesIO()  # the largest float32 still round-trips
    big = float(np.finfo(np.float32).max)
    write_ply(buf, np.array([[big, -big, 1e-30]]), np.array([[1, 2, 3]], np.uint8))
    xyz, rgb = read_ply(io.BytesIO(buf.getvalue()))
    assert xyz.tolist() == [[big, -big, float(np.float32(1e-30))]] and rgb.tolist() == [[1, 2, 3]]


def test_ply_with_end_header_in_a_comment_round_trips():
    buf = io.BytesIO()
    write_ply(buf, np.array([[1.5, -2.0, 3.25]]), np.array([[10, 20, 30]], np.uint8),
              comment="written before end_header by a test")
    xyz, rgb = read_ply(io.BytesIO(buf.getvalue()))  # was: "the first element must be 'vertex'"
    assert xyz.tolist() == [[1.5, -2.0, 3.25]] and rgb.tolist() == [[10, 20, 30]]


HEAD = b"ply\nformat %s 1.0\nelement vertex %s\nproperty float x\nproperty float y\nproperty float z\n"


def test_ply_edge_cases_read_or_name_the_problem(tmp_path):
    empty = read_ply(io.BytesIO(HEAD % (b"ascii", b"0") + b"end_header\n"))  # was refused
    assert empty[0].shape == (0, 3) and empty[1] is None
    buf = io.BytesIO()
    write_ply(buf, np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    assert read_ply(io.BytesIO(buf.getvalue()))[0].shape == (0, 3)
    # a mesh: the face element's list property is not read, the vertices are
    mesh = (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
            b"element face 1\nproperty list uchar int vertex_indices\nend_header\n1 2 3\n3 0 0 0\n")
    assert read_ply(io.BytesIO(mesh))[0].tolist() == [[1.0, 2.0, 3.0]]
    path = tmp_path / "neg.ply"  # a negative count read the whole body (as many vertices as fitted)
    path.write_bytes(HEAD % (b"binary_little_endian", b"-1") + b"end_header\n" + np.zeros(6, "<f4").tobytes())
    with pytest.raises(PLYFormatError, match=r"neg\.ply:3: the element count must be a non-negative integer"):
        read_ply(path)
    with pytest.raises(PLYFormatError, match=r":3: the element count must be a non-negative integer"):
        read_ply(io.BytesIO(HEAD % (b"ascii", b"many") + b"end_header\n"))  # was a bare ValueError
    with pytest.raises(PLYFormatError, match=r"expected 'ply' \.\.\. 'end_header'"):
        read_ply(io.BytesIO(HEAD % (b"ascii", b"1") + b"end_head"))
    with pytest.raises(PLYFormatError, match=r":9: a vertex line of 2 values, expected 3 \(x, y, z\)"):
        read_ply(io.BytesIO(HEAD % (b"ascii", b"2") + b"end_header\n1 2 3\n4 5\n"))
    short = HEAD % (b"binary_little_endian", b"2") + b"end_header\n" + np.zeros(5, "<f4").tobytes()
    with pytest.raises(PLYFormatError, match=r"2 vertices announced, 20 bytes of data \(need 24\)"):
        read_ply(io.BytesIO(short))


# -------------------------------------------------------------------------------------------- voxels
def test_voxel_downsample_by_hand():
    p = np.array([[0.01, 0.01, 0.01], [0.09, 0.05, 0.01], [0.15, 0.0, 0.0], [-0.05, 0.0, 0.0]])
    c = np.array([[0, 0, 0], [100, 50, 11], [9, 9, 9], [7, 7, 7]], np.uint8)
    q, d = voxel_downsample(p, c, 0.1)
    # voxels x in [-0.1, 0), [0, 0.1), [0.1, 0.2): ordered by voxel
    assert np.allclose(q, [[-0.05, 0, 0], [0.05, 0.03, 0.01], [0.15, 0, 0]], atol=1e-7)
    assert d.tolist() == [[7, 7, 7], [50, 25, 6], [9, 9, 9]]  # 5.5 rounds to even: 6


def test_voxel_downsample_keeps_far_points_apart_and_refuses_nan():
    p = np.array([[1e30, 0, 0], [-1e30, 0, 0], [0.0, 0, 0], [0.001, 0, 0]])
    q, d = voxel_downsample(p, np.arange(12, dtype=np.uint8).reshape(4, 3), 0.1)
    # was: one garbage voxel from the int64 overflow ([[0, 0, 0], [0, 0, 0]])
    assert q.tolist() == [[np.float32(-1e30), 0, 0], [np.float32(0.0005), 0, 0], [np.float32(1e30), 0, 0]]
    assert d.tolist() == [[3, 4, 5], [8, 8, 10], [0, 1, 2]]  # 7.5, 8.5, 9.5 round to even
    with pytest.raises(ValueError, match=r"points must be finite: 1 of 2 are not \(the first: row 1\)"):
        voxel_downsample(np.array([[1.0, 0, 0], [np.nan, 0, 0]]), np.zeros((2, 3), np.uint8), 0.1)
