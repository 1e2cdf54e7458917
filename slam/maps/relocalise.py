"""Relocalisation of a new recording in a saved map, and the merge of the two into the map's world.

docs/pipeline.md, "Maps that persist", describes the map links, the placement and the merge.

Example:
    >>> cfg = RelocalisationConfig()
    >>> cfg.min_agreeing, cfg.max_candidates
    (2, 5)
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from slam.backend import PoseGraphBackend
from slam.io.trajectory import Trajectory
from slam.keyframe_graph import EdgeKind, GraphEdge, KeyframeGraph
from slam.lie import se3_between, se3_compose, se3_inv, so3_log
from slam.loop import DriftLimits, drift_limits, maximum_clique, pairwise_consistent, verify_candidate
from slam.maps.config import RelocalisationConfig
from slam.maps.format import SavedMap
from slam.odometry.features import is_binary_detector

logger = logging.getLogger(__name__)
Tensor = torch.Tensor

__all__ = ["MapLink", "MapMismatchError", "MapRelocaliser", "RelocalisationConfig", "RelocalisationReport",
           "capture_map", "descriptor_probe", "map_world_errors"]

_NO_BOUND = DriftLimits(math.inf, math.inf)


class MapMismatchError(ValueError):
    """The saved map cannot serve this run (another descriptor or camera rig); the message says which."""


@dataclass
class MapLink:
    """A verified loop between map keyframe ``map_kf`` and keyframe ``kf`` of the new recording.

    Attributes:
        map_kf, kf: the two keyframes (``T_ab``: the pose of ``kf`` in ``map_kf``).
        frame: the recording's input index of ``kf``.
        similarity: descriptor cosine similarity.
        num_inliers: RANSAC inliers of the verification.
        T_ab: ``(7,)`` float64 measured relative pose (tracked camera).
        information: ``(6, 6)`` float64 (unscaled).
    """

    map_kf: int
    kf: int
    frame: int
    similarity: float
    num_inliers: int
    T_ab: Tensor
    information: Tensor


@dataclass
class RelocalisationReport:
    """What relocalisation in a map did (``metrics.json``'s ``relocalisation``).

    Attributes:
        map_path: the map folder.
        map_keyframes: keyframes in the map.
        relocalised: the recording was placed in the map's world.
        frame, keyframe: where it first was (-1 when never).
        seconds: wall time from the start of tracking to that moment (NaN when never).
        queries: map queries made (one per keyframe of the recording).
        query_ms: mean milliseconds of a query (index search and verification of its candidates).
        links: the map links kept (those that place the recording); ``hypotheses``: every verified one.
        skipped: candidates not registered because the placement puts them out of verification's reach.
        frames_in_map: frames reported in the map's world (all or none).
        reason: why not relocalised ("" when it was).
        T_map_recording: ``(7,)`` the recording's first depth camera in the map's world (None when not).
    """

    map_path: str
    map_keyframes: int
    relocalised: bool = False
    frame: int = -1
    keyframe: int = -1
    seconds: float = math.nan
    queries: int = 0
    query_ms: float = math.nan
    links: list[MapLink] = field(default_factory=list)
    hypotheses: int = 0
    skipped: int = 0
    frames_in_map: int = 0
    reason: str = ""
    T_map_recording: Tensor | None = None

    def as_dict(self) -> dict:
        return {"map": self.map_path, "map_keyframes": self.map_keyframes, "relocalised": self.relocalised,
                "component": "map" if self.relocalised else "new (its own frame: first camera at the origin)",
                "frame": self.frame, "keyframe": self.keyframe, "seconds_to_relocalise": self.seconds,
                "queries": self.queries, "query_ms": self.query_ms, "map_links": len(self.links),
                "link_hypotheses": self.hypotheses, "candidates_out_of_reach": self.skipped,
                "frames_in_map": self.frames_in_map, "reason": self.reason,
                "T_map_recording": None if self.T_map_recording is None else self.T_map_recording.tolist()}


def _rig(config) -> dict:
    f = config.odometry.features
    return {"rgb_intrinsics": None if f.rgb_intrinsics is None else [float(v) for v in f.rgb_intrinsics],
            "rgb_from_depth": [float(v) for v in f.rgb_from_depth_translation]}


#: Largest difference (any entry) between the map's and the run's descriptor of the probe image that is
#: still one descriptor (threads and devices move an entry by ~1e-7, two recipes by ~1e-2).
PROBE_TOLERANCE = 1e-3


def _probe_image() -> torch.Tensor:
    """(1, 3, 96, 128) uint8: a fixed, smooth, seeded frame (any descriptor accepts any image size)."""
    low = torch.rand(1, 3, 6, 8, generator=torch.Generator().manual_seed(0))
    img = torch.nn.functional.interpolate(low, size=(96, 128), mode="bilinear", align_corners=False)
    return (img * 255).round().to(torch.uint8)


def descriptor_probe(model: torch.nn.Module) -> list[float] | None:
    """The descriptor of a fixed probe image: a fingerprint of everything that makes the descriptor.

    Args:
        model: maps ``(1, 3, H, W)`` uint8 images to ``(1, D)`` descriptors, on the device of its
            parameters or buffers (CPU when it has neither).

    Returns:
        the ``D`` entries, rounded to 1e-7; None (with a warning) when the model cannot describe the probe.
    """
    tensor = next(model.parameters(), None)
    tensor = next(model.buffers(), None) if tensor is None else tensor
    image = _probe_image().to(tensor.device if tensor is not None else "cpu")
    try:
        with torch.no_grad():
            d = model(image)
        return [round(float(v), 7) for v in d.reshape(-1).cpu()]
    except Exception as exc:  # a custom descriptor with its own input contract
        logger.warning("the descriptor could not describe the 96 x 128 probe image (%s: %s): the map records no "
                       "probe, and a later run cannot check its descriptor against it", type(exc).__name__, exc)
        return None


def _descriptor_info(slam) -> dict:
    d = slam.config.loop.descriptor
    model = slam.loop_closer.descriptor
    recipe = d.recipe  # the preset's values where the config leaves them None
    return {"backbone": getattr(model, "backbone_name", d.backbone), "fusion": recipe.fusion, "num_rnn": recipe.num_rnn,
            "seed": d.seed, "dim": slam.keyframe_index().dim, "probe": descriptor_probe(model)}


def _run_dim(slam, info: dict) -> int | None:
    """The length of this run's descriptors before its first keyframe (the index's, the model's ``out_dim``
    or its probe's), or None."""
    for d in (info.get("dim"), getattr(slam.loop_closer.descriptor, "out_dim", None),
              None if info.get("probe") is None else len(info["probe"])):
        if isinstance(d, (int, np.integer)) and not isinstance(d, bool) and d > 0:
            return int(d)
    return None


def capture_map(slam, sequence=None) -> SavedMap:
    """The :class:`SavedMap` of a finished run (its final keyframe poses, features, graph and index).

    Args:
        slam: a :class:`slam.system.RGBDSLAM` after :meth:`~slam.system.RGBDSLAM.finish`, with loop closure.
        sequence: the recording (for its name and the ground truth of its first keyframe's frame), or None.

    Raises:
        MapMismatchError: the run had no loop closure (no descriptors to relocalise with).
    """
    if slam.loop_closer is None:
        raise MapMismatchError("saving a map needs loop closure (its descriptors and index); drop --no-loop")
    kfs = slam.keyframes
    index = slam.keyframe_index()
    index.wait()
    if len(index) != len(kfs):
        raise RuntimeError(f"the loop closer's index holds {len(index)} keyframes, the front end {len(kfs)}")
    rgb = np.stack([kf.rgb for kf in kfs]) if kfs else np.zeros((0, 1, 1, 3), np.uint8)
    info = {"sequence": None, "source": None, "groundtruth_origin": None, "rig": _rig(slam.config),
            "descriptor": _descriptor_info(slam),
            "world": "the first tracked frame's depth camera (the frame of every reported pose); keyframe poses "
                     "are the tracked camera's (the colour camera on an unregistered rig)"}
    if sequence is not None:
        info["sequence"], info["source"] = str(sequence.name), str(sequence.root)
        # the world is the first keyframe's camera: frame 0's only when frame 0 was tracked
        g0 = sequence.groundtruth_pose(kfs[0].frame_index) if kfs else None
        if g0 is not None and np.all(np.isfinite(g0)):
            info["groundtruth_origin"] = [float(v) for v in g0]
    return SavedMap(slam.graph.estimates(), torch.tensor([kf.frame_index for kf in kfs], dtype=torch.long),
                    torch.tensor([kf.timestamp for kf in kfs], dtype=torch.float64), index.ids.to(torch.long),
                    index.descriptors, [kf.features for kf in kfs], rgb, list(slam.graph.edges), index, info)


def map_world_errors(trajectory: Tensor, groundtruth: Tensor, origin: Tensor) -> dict | None:
    """Position errors, without any alignment, of a trajectory in a map's world against ``origin^-1 G_i``.

    Args:
        trajectory: ``(N, 7)`` estimated poses in the map's world.
        groundtruth: ``(N, 7)`` ground truth of the same frames (NaN rows where unknown).
        origin: ``(7,)`` ground truth of the mapping recording's first tracked frame.

    Returns:
        ``{"rmse", "max", "num_frames"}`` (metres), None when no frame has ground truth.
    """
    if trajectory.shape != groundtruth.shape or trajectory.shape[-1:] != (7,):
        raise ValueError(f"trajectory and groundtruth must both be (N, 7), got {tuple(trajectory.shape)} and "
                         f"{tuple(groundtruth.shape)}")
    ok = torch.isfinite(groundtruth).all(dim=-1) & torch.isfinite(trajectory).all(dim=-1)
    if not bool(ok.any()):
        return None
    gt = se3_compose(se3_inv(origin.to(torch.float64))[None], groundtruth[ok].to(torch.float64))
    err = (trajectory[ok, :3].to(torch.float64) - gt[:, :3]).norm(dim=-1)
    return {"rmse": float(err.square().mean().sqrt()), "max": float(err.max()), "num_frames": int(ok.sum())}


def _out_of_reach(estimate: Tensor, limits: DriftLimits, config) -> bool:
    """No measurement can pass verification (the estimate is beyond the view distance plus ``limits``)."""
    t = float(estimate[:3].norm())
    r = math.degrees(float(so3_log(estimate[3:]).norm()))
    return t > config.max_translation + limits.translation or r > config.max_rotation_deg + limits.rotation_deg


class MapRelocaliser:
    """Relocalises a recording in a saved map while it is tracked, and merges it into the map's world.

    Args:
        saved: the map (:func:`slam.maps.load_map`).
        slam: the new recording's :class:`slam.system.RGBDSLAM` (with loop closure), before its first frame.
        config: :class:`RelocalisationConfig`.

    Raises:
        MapMismatchError: the run has no loop closure, or its descriptor, feature detector or camera rig
            differ from the map's.

    Call :meth:`observe` after every :meth:`RGBDSLAM.track` (or ``skip``), then :meth:`finish`.
    """

    def __init__(self, saved: SavedMap, slam, config: RelocalisationConfig | None = None):
        self.map = saved
        self.slam = slam
        self.config = config or RelocalisationConfig()
        where = str(saved.path) if saved.path is not None else "the map"
        if slam.loop_closer is None:
            raise MapMismatchError(f"{where}: relocalisation uses loop closure's descriptor and verification; "
                                   "drop --no-loop")
        mine = _descriptor_info(slam)
        theirs = saved.descriptor
        # without RNNs on both sides, and both probes there to compare, two seeds give one descriptor
        probes = theirs.get("probe") is not None and mine["probe"] is not None
        seeded = bool(theirs.get("num_rnn", 1)) or bool(mine["num_rnn"]) or not probes
        for key in ("backbone", "fusion", "num_rnn") + (("seed",) if seeded else ()):
            if key in theirs and theirs[key] != mine[key]:
                remedy = ""
                if key == "num_rnn":
                    remedy = ("; the default descriptor has no RNNs (loop.descriptor.num_rnn = 0): "
                              f"set loop.descriptor.num_rnn = {theirs[key]!r} to use this map, or record its "
                              "session again")
                raise MapMismatchError(f"{where}: the map was made with descriptor {key}={theirs[key]!r}, this run "
                                       f"uses {mine[key]!r}; its index cannot be searched with another descriptor"
                                       + remedy)
        # without probes, nothing else would tell a map of another descriptor length before its first search
        dims = {theirs["dim"]} if isinstance(theirs.get("dim"), int) and not isinstance(theirs["dim"], bool) else set()
        if len(saved) and saved.descriptors.ndim == 2:
            dims.add(int(saved.descriptors.shape[1]))
        run_dim = _run_dim(slam, mine)
        if run_dim is not None and any(d != run_dim for d in dims):
            raise MapMismatchError(f"{where}: the map's descriptors have {' or '.join(str(d) for d in sorted(dims))} "
                                   f"entries, this run's {run_dim}; its index cannot be searched with another "
                                   "descriptor")
        if "probe" not in theirs and theirs.get("backbone") == "efficientnet_lite0":
            raise MapMismatchError(
                f"{where}: saved without a descriptor probe, by a version whose EfficientNet-Lite0 default tapped "
                "stage6 and stage7 (this version's taps stage5): its index cannot be searched with this "
                "descriptor; record the map's session again with this version")
        if not probes:
            logger.warning("%s: no descriptor probe to compare (%s): the map's descriptor is assumed to be this "
                           "run's (%s %s)", where, "none recorded in the map" if theirs.get("probe") is None
                           else "this run's descriptor gave none", mine["backbone"], mine["fusion"])
        else:
            probe = torch.tensor(theirs["probe"], dtype=torch.float64)
            own = torch.tensor(mine["probe"], dtype=torch.float64)
            gap = float((probe - own).abs().max()) if probe.shape == own.shape else float("inf")
            if not gap <= PROBE_TOLERANCE:
                raise MapMismatchError(
                    f"{where}: the map's descriptor of the probe image differs from this run's by {gap:.3g} (largest "
                    f"entry; at most {PROBE_TOLERANCE:g} is one descriptor), though both are {mine['backbone']} "
                    f"{mine['fusion']} seed {mine['seed']}: another tap, recipe, attnloop version or weights made "
                    "the map; its index cannot be searched with this descriptor (run with the descriptor that made "
                    "the map, or record the map's session again with this one)")
        rig, map_rig = _rig(slam.config), saved.rig
        if map_rig and (map_rig.get("rgb_intrinsics") != rig["rgb_intrinsics"]
                        or not np.allclose(map_rig.get("rgb_from_depth", [0, 0, 0]), rig["rgb_from_depth"])):
            raise MapMismatchError(f"{where}: the map's camera rig {map_rig} differs from this run's {rig}; run "
                                   "with the map's rig (the poses are the tracked camera's)")
        detector = slam.config.odometry.features.detector
        # one kind for every keyframe (the format stores one dtype): the first says it
        if len(saved.features) and bool(saved.features[0].binary) != is_binary_detector(detector):
            kind = "binary (ORB)" if saved.features[0].binary else "float (SIFT)"
            raise MapMismatchError(f"{where}: the map's keyframes hold {kind} feature descriptors, this run's "
                                   f"detector is {detector!r}: loops to the map could not be verified; run with "
                                   "the detector that made the map")
        self.links: list[MapLink] = []
        self.report = RelocalisationReport(where, len(saved))
        self._alignment: Tensor | None = None  # T_map_rec of the tracked camera's worlds, once relocalised
        self._anchors: list[int] = []
        self._frame_kf: list[int] = []
        self._kf_of_id: dict[int, int] = {int(i): k for k, i in enumerate(saved.index_ids.tolist())}
        self._t0 = time.perf_counter()
        self._query_seconds = 0.0
        self._merged_poses: Tensor | None = None  # the recording's keyframes in the map's world (finish)
        self._released = 0  # localisation: keyframes before this one have been released
        if slam.localize != self.config.localize:
            raise ValueError(f"RelocalisationConfig.localize is {self.config.localize}, but the system was built "
                             f"with localize={slam.localize}: build RGBDSLAM(config, localize=config.localize)")

    def check_mergeable(self, keyframe_image_shape) -> None:
        """Raise :class:`MapMismatchError` when keyframe images of ``keyframe_image_shape`` ``(h, w, 3)``
        cannot join the map's in a grown map (:meth:`merged_map`; one image size per map).
        """
        if len(self.map) and tuple(keyframe_image_shape) != tuple(self.map.rgb.shape[1:]):
            raise MapMismatchError(f"{self.report.map_path}: keyframe images of {tuple(self.map.rgb.shape[1:3])} px "
                                   f"in the map, {tuple(keyframe_image_shape[:2])} in this recording: a grown map "
                                   "cannot hold both; record at the map's image size, or run without saving the map")

    @property
    def relocalised(self) -> bool:
        """The recording has been placed in the map (so far)."""
        return self._alignment is not None

    @property
    def alignment(self) -> Tensor | None:
        """``(7,)`` the current placement of the recording's (tracked-camera) world in the map's, or None."""
        return None if self._alignment is None else self._alignment.clone()

    def observe(self, state) -> None:
        """Record a frame's :class:`~slam.system.FrameState`; query the map with its new keyframes."""
        self._frame_kf.append(int(state.keyframe_id))
        for kf_id in state.new_keyframes:
            t = time.perf_counter()
            with self.slam.timer("map_relocalisation"):
                queried = self._query(kf_id)
            self._query_seconds += time.perf_counter() - t
            self.report.queries += queried
        if self.slam.localize:  # queried, and no longer tracking's reference: nothing registers against them
            last = len(self.slam.keyframes) - 1
            for k in range(self._released, last):
                self.slam.release_keyframe(k)
            self._released = max(self._released, last)

    def _query(self, kf_id: int) -> bool:
        """Query the map with a new keyframe (False: not queried, a revisit of the recording's own place)."""
        cfg, loop_cfg = self.config, self.slam.config.loop
        kf = self.slam.keyframes[kf_id]
        if self.slam.localize:  # no loop closing, no index of the recording: described here, once
            with self.slam.timer("descriptor"):
                desc = self.slam.loop_closer.describe(kf).detach().to("cpu", torch.float32)
        else:
            desc = self.slam.loop_closer.descriptor_of(kf_id)  # the descriptor it just computed
            if desc is None:  # a revisit (LoopClosureConfig.release_revisits): the keyframe it repeats has queried
                return False
        ids, sims = self.map.index.search(desc, k=cfg.max_candidates)
        graph = self.slam.graph
        lengths = None
        for map_id, sim in zip(ids.tolist(), sims.tolist()):
            a = self._kf_of_id[int(map_id)]
            if self._alignment is None:
                estimate, limits = torch.tensor([0, 0, 0, 0, 0, 0, 1.0], dtype=torch.float64), _NO_BOUND
            else:
                if lengths is None:
                    L = graph.path_lengths(kf_id, through_loops=self._through_loops())
                    lengths = float(min(L[b] for b in self._anchors))
                estimate = se3_between(self.map.poses[a], se3_compose(self._alignment, graph.estimate(kf_id)))
                limits = drift_limits(lengths, loop_cfg.drift)
                if _out_of_reach(estimate, limits, loop_cfg):
                    self.report.skipped += 1
                    continue
            v = verify_candidate(self.map.features[a], kf.features, estimate, limits, loop_cfg)
            if not v.accepted:
                logger.debug("map candidate %d for keyframe %d rejected: %s", a, kf_id, v.reason)
                continue
            self.links.append(MapLink(a, kf_id, int(kf.frame_index), float(sim), v.num_inliers, v.T_ab, v.information))
            logger.info("map link: map keyframe %d <-> keyframe %d (frame %d), %d inliers", a, kf_id,
                        kf.frame_index, v.num_inliers)
            if self._alignment is not None:
                self._anchors.append(kf_id)
        if self._alignment is None and self.links:
            group = self._consistent_group(self.slam.graph.estimates())
            if len({self.links[k].kf for k in group}) >= cfg.min_agreeing:
                self._place(group, self.slam.graph.estimates())
                self.report.frame, self.report.keyframe = int(kf.frame_index), kf_id
                self.report.seconds = time.perf_counter() - self._t0
                logger.info("relocalised in %s at frame %d (keyframe %d): %d agreeing map links", self.report.map_path,
                            kf.frame_index, kf_id, len(group))
        return True

    def _through_loops(self) -> bool:
        """Whether the recording's drift bounds may follow its own loops (it has an active one)."""
        return bool(self.slam.graph.loop_edges(active_only=True))

    def _consistent_group(self, estimates: Tensor) -> list[int]:
        """The largest set of links that agree pairwise on where the recording lies in the map."""
        n = len(self.links)
        A = np.zeros((n, n), bool)
        lengths = {}
        through_loops = self._through_loops()  # the graph does not change in this loop
        for i in range(n):
            li = self.links[i]
            if li.kf not in lengths:
                lengths[li.kf] = self.slam.graph.path_lengths(li.kf, through_loops=through_loops)
            for j in range(i + 1, n):
                lj = self.links[j]
                T_a = se3_between(self.map.poses[li.map_kf], self.map.poses[lj.map_kf])
                T_b = se3_between(estimates[li.kf], estimates[lj.kf])
                limits = drift_limits(float(lengths[li.kf][lj.kf]), self.slam.config.loop.drift)
                A[i, j] = A[j, i] = pairwise_consistent(li.T_ab, lj.T_ab, T_a, T_b, limits)[0]
        return maximum_clique(A) if n else []

    def _place(self, group: list[int], estimates: Tensor) -> None:
        lb = max((self.links[k] for k in group), key=lambda link: link.num_inliers)
        self._alignment = se3_compose(se3_compose(self.map.poses[lb.map_kf], lb.T_ab), se3_inv(estimates[lb.kf]))
        self._anchors = sorted({self.links[k].kf for k in group})

    def finish(self, result):
        """Merge the finished recording into the map's world.

        Args:
            result: the recording's :class:`~slam.system.SLAMResult` (from ``slam.finish()``).

        Returns:
            ``(result, report)``: when relocalised, a copy of ``result`` whose trajectories are in the map's
            world (the keyframe graph optimised with its map links, the map's keyframes fixed); else
            ``result`` itself (its own frame), and the :class:`RelocalisationReport`.
        """
        rep = self.report
        rep.hypotheses = len(self.links)
        rep.query_ms = 1000.0 * self._query_seconds / rep.queries if rep.queries else math.nan
        est = self.slam.graph.estimates()  # the recording's final keyframe poses, its own world
        group = self._consistent_group(est)
        agreeing = len({self.links[k].kf for k in group})
        if agreeing < self.config.min_agreeing:
            rep.relocalised, rep.frame, rep.keyframe, rep.seconds = False, -1, -1, math.nan
            rep.reason = (f"no place of the map was recognised: {len(self.links)} verified link(s), "
                          f"{agreeing} agreeing keyframe(s) of the "
                          f"{self.config.min_agreeing} needed, after {rep.queries} queries")
            self._alignment = None
            return result, rep
        self._place(group, est)
        rep.links = [self.links[k] for k in group]
        poses = self._merge(est, rep.links)
        self._merged_poses = poses
        old_kf = self.slam.depth_camera_pose(est)
        new_kf = self.slam.depth_camera_pose(poses)
        correction = se3_compose(new_kf, se3_inv(old_kf))  # per keyframe: old world -> map world
        kf_of_frame = torch.tensor([max(k, 0) for k in self._frame_kf], dtype=torch.long)
        traj = result.trajectory
        if kf_of_frame.numel() != traj.poses.shape[0]:
            raise RuntimeError(f"{kf_of_frame.numel()} frames observed, the result has {traj.poses.shape[0]}")
        moved = se3_compose(correction[kf_of_frame], traj.poses)  # relocalised: keyframes and frames exist
        align_out = self.slam.depth_camera_pose(self._alignment)
        odo = result.odometry_trajectory
        merged = dataclasses.replace(
            result, trajectory=Trajectory(traj.timestamps, moved),
            odometry_trajectory=Trajectory(odo.timestamps, se3_compose(align_out.expand_as(odo.poses), odo.poses)),
            keyframe_trajectory=Trajectory(result.keyframe_trajectory.timestamps, new_kf))
        rep.relocalised, rep.reason = True, ""
        rep.frames_in_map = int(moved.shape[0])
        rep.T_map_recording = align_out
        return merged, rep

    def merged_map(self, sequence=None) -> SavedMap:
        """The map grown by this recording (after a :meth:`finish` that relocalised it): the map's keyframes
        unchanged, then the recording's in the map's world, its graph, and its map links as loop edges.

        Args:
            sequence: the recording (named in the manifest's ``sessions``), or None.

        Raises:
            RuntimeError: not finished, or not relocalised (its own map is :func:`capture_map`'s).
        """
        if self._merged_poses is None:
            raise RuntimeError("merged_map() needs a finish() that relocalised the recording")
        own = capture_map(self.slam, sequence)
        base = self.map
        M = len(base)
        if len(own):
            self.check_mergeable(own.rgb.shape[1:])
        shift = (int(base.index_ids.max()) + 1 if M else 0) - (int(own.index_ids.min()) if len(own) else 0)
        ids = torch.cat([base.index_ids, own.index_ids + shift])
        descriptors = torch.cat([base.descriptors, own.descriptors])
        from attnloop.index import KeyframeIndex

        index = KeyframeIndex(base.index.config)
        index.add(descriptors, ids=ids, timestamps=torch.cat([base.timestamps, own.timestamps]))
        edges = list(base.edges) + [dataclasses.replace(e, i=e.i + M, j=e.j + M) for e in own.edges]
        edges += [GraphEdge(lk.map_kf, lk.kf + M, lk.T_ab.clone(), lk.information.clone(), EdgeKind.LOOP)
                  for lk in self.report.links]
        info = dict(base.info)
        info["descriptor"] = own.info["descriptor"]  # the map's, as checked on loading, with this run's probe
        sessions = list(info.get("sessions") or [{"sequence": info.get("sequence"), "source": info.get("source"),
                                                   "keyframes": [0, M]}])
        sessions.append({"sequence": own.info.get("sequence"), "source": own.info.get("source"),
                         "keyframes": [M, M + len(own)]})
        info["sessions"] = sessions
        return SavedMap(torch.cat([base.poses, self._merged_poses]), torch.cat([base.frame_index, own.frame_index]),
                        torch.cat([base.timestamps, own.timestamps]), ids, descriptors,
                        list(base.features) + list(own.features), np.concatenate([base.rgb, own.rgb]), edges, index,
                        info)

    def _merge(self, est: Tensor, links: list[MapLink]) -> Tensor:
        """Optimise the recording's keyframe graph with its map links, the linked map keyframes fixed."""
        slam = self.slam
        used = sorted({lk.map_kf for lk in links})
        slot = {a: s for s, a in enumerate(used)}
        U = len(used)
        start = se3_compose(self._alignment.expand_as(est), est)
        g = KeyframeGraph()
        for a in used:
            g.add_keyframe(self.map.poses[a])
        g.add_keyframe(start[0])
        loops = []
        for e in slam.graph.edges:  # the odometry edges in creation order: edge j - 1 adds keyframe j
            if e.kind is EdgeKind.ODOMETRY:
                g.add_odometry(e.i + U, e.T_ij, e.information, estimate=start[e.j], weak=e.weak)
            elif e.active:
                loops.append(e)
        for e in loops:
            g.add_loop(e.i + U, e.j + U, e.T_ij, e.information)
        for lk in links:
            g.add_loop(slot[lk.map_kf], lk.kf + U, lk.T_ab, lk.information)
        scales = {EdgeKind.ODOMETRY: slam.config.backend.odometry_information_scale,
                  EdgeKind.LOOP: slam.config.loop.information_scale}
        backend = PoseGraphBackend(slam.config.backend, scales)
        with slam.timer("map_merge"):
            res = backend.optimize(g, fixed=list(range(U)))
        logger.info("merged into the map: %d keyframes, %d map links, chi2 %.3g -> %.3g, %s", est.shape[0], len(links),
                    res.initial_chi2, res.chi2, res.status)
        return res.poses[U:]
