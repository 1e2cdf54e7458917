"""Helpers shared by several test files (a test file imports from here, never from another test file).

* :func:`condition_head`: random-weight EfficientNet-Lite networks whose seeded gradient is well conditioned,
  for comparing two computations of G.
* :data:`MUTATIONS`, :func:`mutate`: seeded mutations of real input files, for the fuzz tests (readers, CLI).
  ``mutate(data, kind, rng)`` returns a mutated copy of a file's bytes. Each kind models a way files from the
  wild go wrong: cut short, a corrupted byte, a byte that is not UTF-8, a number replaced by NaN / inf / a huge
  value, a line with a field too many or too few, an empty file, a repeated line, comments (whole-line and
  trailing), Windows line endings and a byte-order mark, text where a number belongs. ``rng`` is a
  :class:`random.Random`, so a case is reproduced from its seed.
* :func:`perturb_trajectory`: an estimate with known drift, noise and a global rigid motion, for the metrics.
* :data:`COMMAND_START`, :func:`script_of`, :func:`synopsis_flags`: the commands and ``--flags`` that a
  documentation text names, for the docs tests.
* :func:`unit_rows`: seeded unit-norm rows, for the keyframe index.
* :func:`hand_map`, :func:`assert_same_map`: a made-up saved map and map equality, for the map tests.
* :func:`write_rgbd_bag`: RGB-D frames written as a ROS1 or ROS2 bag with rosbags' writer, for the bag reader.
* :func:`free_space_distance`: a synthetic camera's clearance from every surface, for the synthetic scenes.

Example:
    >>> import random
    >>> mutate(b"1.0 2.0 3.0\\n", "huge_number", random.Random(0)) != b"1.0 2.0 3.0\\n"
    True
"""
from __future__ import annotations

import math
import random
import re

import numpy as np
import torch
import torch.nn.functional as F

from attnloop.index import IndexConfig, KeyframeIndex
from slam.keyframe_graph import EdgeKind, GraphEdge
from slam.lie import se3_compose, se3_exp
from slam.maps import SavedMap
from slam.odometry.features import FrameFeatures

__all__ = ["COMMAND_START", "MUTATIONS", "TUM_BAG_TOPICS", "condition_head", "free_space_distance", "mutate",
           "perturb_trajectory", "script_of", "synopsis_flags", "write_rgbd_bag"]


# ------------------------------------------------------------------------------------------ lite nets
def condition_head(net, seed: int = 0):
    """Scale a random-weight EfficientNet-Lite's head conv and classifier: head pre-activations and logits of std 2.

    Random weights fade to ~1e-9 by the head and leave a softmax flat to 1e-10. There G = J^T S is a
    cancellation (S_k - |S|^2) at rounding level, and two correct summation orders (autograd's, the closed
    form's) do not agree on it. Scaled, ReLU6 masks about half of the head and the seed is far from zero.
    The head's batch-norm gets random affine weights and statistics first (every factor of its backward
    then counts).
    Deterministic: two networks of one seed stay identical.

    Args:
        net: an :class:`attnloop.backbones.efficientnet_lite.EfficientNetLite0` (any dtype), changed in place.
        seed: seed of the images the scales are measured on.

    Returns:
        ``net``.
    """
    dtype = net._fc.weight.dtype
    gen = torch.Generator().manual_seed(seed)
    images = 0.1 + 0.8 * torch.rand(4, 3, *net.input_size, generator=gen)
    with torch.no_grad():
        # batch-norm statistics and affine weights of a trained head, not the init's ones and zeros
        bn = net._bn1
        for t, lo, hi in ((bn.weight, 0.5, 2.0), (bn.bias, -0.5, 0.5), (bn.running_mean, -0.5, 0.5),
                          (bn.running_var, 0.5, 2.0)):
            t.copy_(lo + (hi - lo) * torch.rand(t.shape, generator=gen, dtype=torch.float64))
        h = F.relu6(net._bn0(net._conv_stem(net.preprocess(images.to(dtype)))))
        for block in net._blocks:
            h = block(h)
        slope = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        net._conv_head.weight.mul_(2.0 / float((net._conv_head(h) * slope[:, None, None]).std()))
        pooled = F.relu6(bn(net._conv_head(h))).mean(dim=(2, 3))
        net._fc.weight.mul_(2.0 / float(net._fc(pooled).std()))
    return net


# ------------------------------------------------------------------------------------------ mutations
_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_BAD_NUMBERS = (b"nan", b"inf", b"-inf", b"NaN", b"1e309")
_HUGE_NUMBERS = (b"1e300", b"-1e300", b"1e200", b"1e20", b"100000000000000000000", b"1e-320", b"9" * 400)
_NOT_UTF8 = (b"\xff", b"\xfe", b"\xe9", b"\xc3\x28", b"\x80", b"\xed\xa0\x80")


def _lines(data: bytes) -> list:
    return data.split(b"\n")


def _numbers(data: bytes) -> list:
    return list(_NUMBER.finditer(data))


def _replace_number(data: bytes, rng: random.Random, choices) -> bytes:
    found = _numbers(data)
    if not found:
        return data + rng.choice(choices)
    m = rng.choice(found)
    return data[:m.start()] + rng.choice(choices) + data[m.end():]


def _content_lines(lines: list) -> list:
    return [k for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith(b"#")] or [0]


def _truncate(data, rng):
    return data[:rng.randrange(len(data) + 1)] if data else data


def _flip_byte(data, rng):
    if not data:
        return bytes([rng.randrange(256)])
    k = rng.randrange(len(data))
    return data[:k] + bytes([data[k] ^ (1 << rng.randrange(8))]) + data[k + 1:]


def _not_utf8(data, rng):
    k = rng.randrange(len(data) + 1)
    return data[:k] + rng.choice(_NOT_UTF8) + data[k:]


def _field_count(data, rng):
    lines = _lines(data)
    k = rng.choice(_content_lines(lines))
    fields = lines[k].split()
    if fields and rng.random() < 0.5:
        fields.pop(rng.randrange(len(fields)))
    else:
        fields.insert(rng.randrange(len(fields) + 1), rng.choice([b"0", b"1.5", b"7"]))
    lines[k] = b" ".join(fields)
    return b"\n".join(lines)


def _duplicate_line(data, rng):
    lines = _lines(data)
    k = rng.choice(_content_lines(lines))
    lines.insert(k + rng.choice([0, 1, 2]), lines[k])
    return b"\n".join(lines)


def _comments(data, rng):
    lines = _lines(data)
    k = rng.choice(_content_lines(lines))
    if rng.random() < 0.5:
        lines[k] = lines[k] + rng.choice([b" # trailing comment", b"\t#x", b" #"])
    else:
        lines.insert(k, rng.choice([b"# a comment", b"   # indented", b"#", b""]))
    return b"\n".join(lines)


def _text_for_number(data, rng):
    return _replace_number(data, rng, (b"x", b"one", b"1,5", b"--1", b"0x10", b"1.2.3", b""))


def _line_endings(data, rng):
    out = data.replace(b"\n", b"\r\n") if rng.random() < 0.5 else data.replace(b"\n", b"\r")
    return (b"\xef\xbb\xbf" + out) if rng.random() < 0.5 else out


def _swap_lines(data, rng):
    lines = _lines(data)
    idx = _content_lines(lines)
    a, b = rng.choice(idx), rng.choice(idx)
    lines[a], lines[b] = lines[b], lines[a]
    return b"\n".join(lines)


_KINDS = {
    "truncate": _truncate,
    "flip_byte": _flip_byte,
    "not_utf8": _not_utf8,
    "non_finite": lambda d, r: _replace_number(d, r, _BAD_NUMBERS),
    "huge_number": lambda d, r: _replace_number(d, r, _HUGE_NUMBERS),
    "field_count": _field_count,
    "empty": lambda d, r: b"" if r.random() < 0.5 else b"\n\n# only a comment\n",
    "duplicate_line": _duplicate_line,
    "comments": _comments,
    "text_for_number": _text_for_number,
    "line_endings": _line_endings,
    "swap_lines": _swap_lines,
}

# the kinds of mutation, in a fixed order
MUTATIONS = tuple(_KINDS)


def mutate(data: bytes, kind: str, rng: random.Random) -> bytes:
    """A mutated copy of ``data`` (the bytes of a file); ``kind`` is one of :data:`MUTATIONS`."""
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {MUTATIONS}, got {kind!r}")
    return _KINDS[kind](bytes(data), rng)


# ------------------------------------------------------------------------------------------ trajectories
def perturb_trajectory(poses: torch.Tensor, stamps: torch.Tensor, seed: int, scale: float = 1.0) -> torch.Tensor:
    """Known drift (growing yaw and translation), per-pose noise, then a global rigid motion."""
    g = torch.Generator().manual_seed(seed)
    n = poses.shape[0]
    dt = (stamps - stamps[0])[:, None]
    drift = torch.cat([dt * torch.tensor([0.01, -0.005, 0.008], dtype=torch.float64),
                       dt * torch.tensor([0.0, 0.0, 0.004], dtype=torch.float64)], -1)
    noise = torch.cat([torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.005,
                       torch.randn(n, 3, generator=g, dtype=torch.float64) * math.radians(0.3)], -1)
    est = se3_compose(se3_exp(drift), se3_compose(poses, se3_exp(noise)))
    est = torch.cat([est[:, :3] * scale, est[:, 3:]], -1)
    world = se3_exp(torch.tensor([0.4, -1.0, 2.0, 0.3, -0.2, 1.1], dtype=torch.float64))
    return se3_compose(world.expand(n, 7), est)


# ------------------------------------------------------------------------------------------ docs
COMMAND_START = re.compile(r"^(attnloop-slam|attnloop-eval|attnloop-vpr"
                           r"|python3? (?:examples|benchmarks)/\w+\.py|python3? -m benchmarks\.\w+)\b")


def script_of(command: str) -> str:
    """The script a command runs: ``benchmarks.x`` (``python -m benchmarks.x``) is ``benchmarks/x.py``."""
    if re.fullmatch(r"benchmarks\.\w+", command):
        return command.replace(".", "/", 1) + ".py"
    return command


def synopsis_flags(text: str) -> list[tuple]:
    """(command, flag) for each ``--flag`` in lines of ``text`` that start with a command (or continue one)."""
    found, command = [], None
    for line in text.splitlines():
        s = line.strip()
        m = COMMAND_START.match(s)
        if m:
            command = script_of(m.group(1).split()[-1])
        elif not (s.startswith(("[", "--"))) or command is None:
            command = None
            continue
        for flag in re.findall(r"(?<![\w-])(--[a-z][\w-]*)", s):
            found.append((command, flag))
    return found


# ---------------------------------------------------------------------------------------------- maps
def hand_map(M: int = 6, D: int = 16, seed: int = 0) -> SavedMap:
    """A small map with made-up contents (every array of the format, with varying feature counts)."""
    g = torch.Generator().manual_seed(seed)
    feats = []
    for m in range(M):
        n = 5 + 3 * m
        feats.append(FrameFeatures(torch.rand(n, 2, generator=g) * 100,
                                   torch.randint(0, 256, (n, 32), generator=g, dtype=torch.uint8),
                                   torch.rand(n, 3, generator=g), torch.rand(n, generator=g) > 0.3,
                                   torch.rand(n, generator=g), torch.eye(3, dtype=torch.float64) * (500 + m), (48, 64)))
    desc = torch.nn.functional.normalize(torch.randn(M, D, generator=g), dim=1)
    ids = torch.arange(M) * 333
    index = KeyframeIndex(IndexConfig(backend="exact"))
    index.add(desc, ids=ids)
    poses = torch.cat([torch.randn(M, 3, generator=g, dtype=torch.float64),
                       torch.nn.functional.normalize(torch.randn(M, 4, generator=g, dtype=torch.float64), dim=1)], 1)
    edges = [GraphEdge(m, m + 1, poses[m + 1].clone(), torch.eye(6, dtype=torch.float64) * (m + 1), EdgeKind.ODOMETRY,
                       weak=m == 2) for m in range(M - 1)]
    edges.append(GraphEdge(0, M - 1, poses[0].clone(), torch.eye(6, dtype=torch.float64), EdgeKind.LOOP, active=False,
                           weight=0.25))
    rgb = torch.randint(0, 256, (M, 12, 16, 3), generator=g, dtype=torch.uint8).numpy()
    info = {"descriptor": {"backbone": "efficientnet_lite0", "fusion": "dam", "num_rnn": 16, "seed": 0, "dim": D},
            "rig": {"rgb_intrinsics": None, "rgb_from_depth": [0.0, 0.0, 0.0]}, "groundtruth_origin": None}
    return SavedMap(poses, torch.arange(M) * 10, torch.arange(M, dtype=torch.float64) / 3, ids, desc, feats, rgb,
                    edges, index, info)


def assert_same_map(a: SavedMap, b: SavedMap) -> None:
    """Every array, edge and index answer of two maps equal."""
    assert torch.equal(a.poses, b.poses) and torch.equal(a.frame_index, b.frame_index)
    assert torch.equal(a.timestamps, b.timestamps) and torch.equal(a.index_ids, b.index_ids)
    assert torch.equal(a.descriptors, b.descriptors) and np.array_equal(a.rgb, b.rgb)
    assert len(a.features) == len(b.features)
    for fa, fb in zip(a.features, b.features):
        for name in ("keypoints", "descriptors", "points", "valid", "sigma_px", "K"):
            assert torch.equal(getattr(fa, name), getattr(fb, name)), name
        assert tuple(fa.image_size) == tuple(fb.image_size) and fa.binary == fb.binary
    assert len(a.edges) == len(b.edges)
    for ea, eb in zip(a.edges, b.edges):
        fields = ("i", "j", "kind", "weak", "active", "weight")
        assert [getattr(ea, f) for f in fields] == [getattr(eb, f) for f in fields]
        assert torch.equal(ea.T_ij, eb.T_ij) and torch.equal(ea.information, eb.information)
    # the index answers every stored descriptor (and a perturbed one) identically
    queries = torch.cat([a.descriptors, a.descriptors + 0.01])
    for q in queries:
        ia, sa = a.index.search(q, k=3)
        ib, sb = b.index.search(q, k=3)
        assert torch.equal(ia, ib) and torch.equal(sa, sb)


# ---------------------------------------------------------------------------------------------- index
def unit_rows(n: int, d: int, seed: int = 0) -> torch.Tensor:
    """``(n, d)`` rows of a seeded normal draw, each scaled to unit norm."""
    x = torch.randn(n, d, generator=torch.Generator().manual_seed(seed))
    return x / x.norm(dim=-1, keepdim=True)


# ---------------------------------------------------------------------------------------------- ROS bags
#: TUM RGB-D's bag topics: colour, depth, colour camera info.
TUM_BAG_TOPICS = ("/camera/rgb/image_color", "/camera/depth/image", "/camera/rgb/camera_info")


def write_rgbd_bag(path, frames, K, ros2: bool = False, depth_encoding: str = "32FC1", rgb_encoding: str = "rgb8",
                   topics=TUM_BAG_TOPICS):
    """Write RGB-D frames as a ROS bag with rosbags' own writer and typestore (sensor_msgs/Image, CameraInfo).

    Args:
        path: a ``.bag`` file (ROS1) or a new folder (``ros2=True``, sqlite3 storage).
        frames: iterable of ``(timestamp s, rgb (H, W, 3) uint8 RGB, depth (H, W) float32 metres, 0 = none)``
            and optionally the depth's own timestamp; read one at a time. ``rgb`` or ``depth`` None: no message.
        K: ``(3, 3)`` intrinsics written once on the camera-info topic.
        depth_encoding: ``"32FC1"`` (metres, NaN where 0) or ``"16UC1"`` (millimetres, 0 where none).
        rgb_encoding: ``"rgb8"``, ``"bgr8"`` or ``"mono8"`` (the first channel) or any other name (rgb8 bytes).
        topics: colour, depth and camera-info topics.
    """
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    Image, Info = store.types["sensor_msgs/msg/Image"], store.types["sensor_msgs/msg/CameraInfo"]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    Roi = store.types["sensor_msgs/msg/RegionOfInterest"]
    if ros2:
        from rosbags.rosbag2 import Writer

        writer, serialize = Writer(path, version=9), store.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), store.serialize_ros1

    def header(ns: int):
        stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
        return Header(stamp=stamp, frame_id="camera") if ros2 else Header(seq=0, stamp=stamp, frame_id="camera")

    def image(ns, pixels, encoding):
        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).reshape(-1).view(np.uint8)
        return Image(header=header(ns), height=h, width=w, encoding=encoding, is_bigendian=0,
                     step=data.size // h, data=data)

    with writer:
        rgb_c, depth_c, info_c = (writer.add_connection(t, m, typestore=store) for t, m in zip(
            topics, ("sensor_msgs/msg/Image", "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo")))
        for k, (t, rgb, depth, *depth_t) in enumerate(frames):
            ns = round(t * 1e9)
            depth_ns = round(depth_t[0] * 1e9) if depth_t else ns
            if k == 0:
                arrays = {n: np.zeros(s) for n, s in (("d", 5), ("r", 9), ("p", 12))}
                arrays["k"] = np.asarray(K, np.float64).reshape(9)
                fields = arrays if ros2 else {n.upper(): a for n, a in arrays.items()}
                h, w = (rgb if rgb is not None else depth).shape[:2]
                info = Info(header=header(ns), height=h, width=w, distortion_model="plumb_bob",
                            binning_x=0, binning_y=0, roi=Roi(x_offset=0, y_offset=0, height=0, width=0,
                                                               do_rectify=False), **fields)
                writer.write(info_c, ns, serialize(info, "sensor_msgs/msg/CameraInfo"))
            if rgb is not None:
                colour = {"bgr8": rgb[..., ::-1], "mono8": rgb[..., 0]}.get(rgb_encoding, rgb)
                writer.write(rgb_c, ns, serialize(image(ns, colour, rgb_encoding), "sensor_msgs/msg/Image"))
            if depth is None:
                continue
            if depth_encoding == "16UC1":
                d = np.round(depth * 1000.0).astype(np.uint16)
            else:
                d = np.where(depth > 0, depth, np.float32(np.nan)).astype(np.float32)
            writer.write(depth_c, depth_ns, serialize(image(depth_ns, d, depth_encoding), "sensor_msgs/msg/Image"))
    return path


def free_space_distance(scene, points: torch.Tensor) -> torch.Tensor:
    """Signed clearance ``(N,)`` of world points ``(N, 3)`` in a :class:`slam.synthetic.scene.Scene`: > 0 inside
    the room and outside every object (metres to the nearest surface), < 0 inside an object or outside the room."""
    from slam.synthetic.scene import box_signed_distance

    sd = box_signed_distance(points, scene.centers, scene.rotations, scene.half_sizes)
    return torch.where(scene.inside.to(points.device)[None], -sd, sd).min(-1).values
