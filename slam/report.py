"""The report of a run (:class:`RunReport`, ``metrics.json``), computed by :func:`evaluate_run`."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Optional

import torch

from slam.config import SLAMConfig, describe_rig
from slam.system import SLAMResult

__all__ = ["RunReport", "evaluate_run", "loop_ground_truth_for_step", "loop_precision_recall", "loop_worker_metrics"]


@dataclass(frozen=True)
class RunReport:
    """What a run did and how well, field by field the keys of ``metrics.json`` (:meth:`as_dict`).

    A field that is None is left out of the file, except ``backbone``, ``descriptor`` and ``ate_rmse``
    (null: no loop closure, no ATE) and ``ate_tracked`` beside an ``ate`` (null: the run did not record which
    frames were tracked). Units: seconds, metres, degrees; ``time_per_stage`` in ms (:class:`slam.timing.StageTimer`).

    Attributes:
        sequence: the sequence's name.
        num_frames: frames processed (every ``frame_step``-th input frame).
        frame_step: the step between processed input frames.
        num_keyframes, num_loops, num_lost, num_skipped: keyframes, accepted loops, frames lost by tracking,
            frames that could not be read.
        released_keyframes: revisits that added nothing, their features, image and map points dropped
            (``LoopClosureConfig.release_revisits``).
        fps: frames per second over ``wall_seconds`` (reading, tracking, loops, final optimisation).
        wall_seconds: the run's wall time.
        time_per_stage: the system's stage timings (:attr:`slam.system.SLAMResult.timings`).
        backbone: the descriptor's backbone as built (None without loop closure).
        loop_hypotheses: every verified loop by its final status (kept / inconsistent / switched_off).
        online_corrections: ``count``, ``total_ms``, ``max_ms`` of the online pose-graph corrections.
        loop_worker: the loop worker's lag (:func:`loop_worker_metrics`).
        error: why the run stopped early (a :class:`slam.system.LoopWorkerError`).
        descriptor: the descriptor's settings (preset, backbone, dim, fusion, seed, weights, recipe).
        rig: the camera rig the run tracked with, in words.
        camera: the sequence's camera (:func:`slam.pipeline.camera_of`).
        map: points of the merged map, keyframes, points and MB kept during the run, voxel size (m).
        pose_graph: keyframes, edges, initial and final chi2, status and iterations of the final optimisation.
        ate_rmse: the ATE's RMSE (m; rigid SE(3) alignment, TUM association), None with ``ate_unavailable``.
        num_tracked: the frames placed by tracking (the first one included).
        status: ``"ok"``, or ``"failed"`` below ``SLAMConfig.min_tracked_fraction`` (``failure`` says why).
        failure: why the run failed.
        ate_unavailable: why there is no ATE (no ground truth, fewer than 3 frames with it, ...).
        ate: the ATE's rmse, mean, median, std, max (m) and num_pairs.
        odometry_ate_rmse: the ATE of the odometry before the pose graph (m).
        ate_tracked: the ATE over the tracked frames alone (rmse, num_pairs), or why not.
        rpe_1frame, rpe_1s: the RPE over 1 frame and 1 s (translation m, rotation deg, num_pairs), or why not.
        loop_ground_truth: the :class:`slam.eval.LoopGroundTruthConfig` the loops were judged with.
        loops_true, loops_false: accepted loops judged by ground-truth distance and angle.
        loop_hypotheses_false: the false ones among the verified loops, by final status.
        loop_detection: the detector's precision/recall before and after verification
            (:func:`loop_precision_recall`).
        relocalisation: the relocalisation in a saved map (:class:`slam.maps.RelocalisationReport`'s dict).
    """

    sequence: Optional[str] = None
    num_frames: Optional[int] = None
    frame_step: Optional[int] = None
    num_keyframes: Optional[int] = None
    released_keyframes: Optional[int] = None
    num_loops: Optional[int] = None
    num_lost: Optional[int] = None
    num_skipped: Optional[int] = None
    fps: Optional[float] = None
    wall_seconds: Optional[float] = None
    time_per_stage: Optional[dict] = None
    backbone: Optional[str] = None
    loop_hypotheses: Optional[dict] = None
    online_corrections: Optional[dict] = None
    loop_worker: Optional[dict] = None
    error: Optional[str] = None
    descriptor: Optional[dict] = None
    rig: Optional[str] = None
    camera: Optional[dict] = None
    map: Optional[dict] = None
    pose_graph: Optional[dict] = None
    ate_rmse: Optional[float] = None
    num_tracked: Optional[int] = None
    status: Optional[str] = None
    failure: Optional[str] = None
    ate_unavailable: Optional[str] = None
    ate: Optional[dict] = None
    odometry_ate_rmse: Optional[float] = None
    ate_tracked: Optional[dict] = None
    rpe_1frame: Optional[dict] = None
    rpe_1s: Optional[dict] = None
    loop_ground_truth: Optional[dict] = None
    loops_true: Optional[int] = None
    loops_false: Optional[int] = None
    loop_hypotheses_false: Optional[dict] = None
    loop_detection: Optional[dict] = None
    relocalisation: Optional[dict] = None

    def as_dict(self) -> dict[str, Any]:
        """The ``metrics.json`` dict: the fields in order, those that are None left out (see the class)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is not None or f.name in ("backbone", "descriptor", "ate_rmse") or (
                    f.name == "ate_tracked" and self.ate is not None):
                out[f.name] = value
        return out


def loop_ground_truth_for_step(frame_step: int = 1):
    """The default :class:`slam.eval.LoopGroundTruthConfig` for a run on every ``frame_step``-th frame: its
    ``min_frame_gap`` (input frames) becomes ``ceil(gap / frame_step)`` of the run's frames, the same time.

    Example:
        >>> loop_ground_truth_for_step(6).min_frame_gap, loop_ground_truth_for_step(1).min_frame_gap
        (17, 100)
    """
    from slam.eval import LoopGroundTruthConfig

    base = LoopGroundTruthConfig()
    return dataclasses.replace(base, min_frame_gap=max(1, math.ceil(base.min_frame_gap / int(frame_step))))


def evaluate_run(run) -> RunReport:
    """The report of a run: what ``metrics.json`` holds (:class:`RunReport`); also sets ``run.report``,
    ``run.map_cloud`` and ``run.loop_curves``. Without usable ground truth ``ate_unavailable`` says why.

    Args:
        run: a :class:`slam.pipeline.RunResult`; its loops are judged by :func:`loop_ground_truth_for_step`.
    """
    from slam.eval import ate, is_true_loop, rpe

    res = run.result
    m: dict[str, object] = {
        "sequence": run.sequence_name,
        "num_frames": res.num_frames,
        "frame_step": run.frame_step,
        "num_keyframes": res.num_keyframes,
        "released_keyframes": len(res.released),
        "num_loops": len(res.loops),
        "num_lost": res.num_lost,
        "num_skipped": res.num_skipped,
        "fps": round(run.fps, 3),
        "wall_seconds": round(run.wall_seconds, 3),
        "time_per_stage": res.timings,
        "backbone": run.backbone,
        "loop_hypotheses": _by_status(res.loop_hypotheses),
        "online_corrections": {"count": len(res.corrections),
                               "total_ms": round(1000 * sum(c.seconds for c in res.corrections), 3),
                               "max_ms": round(1000 * max((c.seconds for c in res.corrections), default=0.0), 3)},
    }
    m["loop_worker"] = loop_worker_metrics(res, run.config)
    if res.error is not None:
        m["error"] = res.error  # the run stopped early: the outputs hold the frames tracked before it
    if run.config is not None:
        d = run.config.loop.descriptor
        recipe = dataclasses.asdict(d.recipe)
        m["descriptor"] = ({"preset": d.preset, "backbone": run.backbone, "requested_backbone": d.backbone,
                            "dim": run.descriptor_dim, "fusion": recipe["fusion"], "seed": d.seed,
                            "weights": None if d.weights is None else str(d.weights), "recipe": recipe}
                           if run.config.loop.enabled else None)
        m["rig"] = describe_rig(run.config)
    if run.camera is not None:
        m["camera"] = run.camera
    if run.map is not None:
        run.map_cloud = run.map.points(res.keyframe_trajectory.poses)
        m["map"] = {"points": int(run.map_cloud[0].shape[0]), "keyframes": len(run.map),
                    "kept_points": run.map.num_points, "kept_mb": round(run.map.nbytes / 1e6, 3),
                    "voxel_size": run.map.config.voxel_size}
    if res.optimization is not None:
        opt = res.optimization
        m["pose_graph"] = {"keyframes": res.graph.num_poses, "edges": res.graph.num_edges,
                           "initial_chi2": opt.initial_chi2, "chi2": opt.chi2, "status": str(opt.status),
                           "iterations": opt.iterations}
    m["ate_rmse"] = None
    tracked = res.num_frames - res.num_lost - res.num_skipped  # the first frame counts: it sets the origin
    m["num_tracked"] = tracked
    least = run.config.min_tracked_fraction if run.config is not None else SLAMConfig.min_tracked_fraction
    m["status"] = "ok" if tracked >= least * res.num_frames else "failed"
    if m["status"] == "failed":
        m["failure"] = (f"{tracked} of {res.num_frames} frames tracked ({res.num_lost} lost, {res.num_skipped} "
                        f"unreadable), fewer than {least:.0%} (SLAMConfig.min_tracked_fraction)"
                        + (f"; the first: {run.first_untracked}" if run.first_untracked else ""))
    if run.groundtruth is None:
        m["ate_unavailable"] = run.groundtruth_note or "the sequence has no ground truth"
    elif len(run.groundtruth) < 3:
        m["ate_unavailable"] = f"only {len(run.groundtruth)} frame(s) with ground truth (the alignment needs 3)"
    elif tracked <= 1:
        m["ate_unavailable"] = (f"no frame was tracked ({res.num_lost} lost, {res.num_skipped} unreadable of "
                                f"{res.num_frames}): nothing to align")
    elif float((run.groundtruth.poses[:, :3] - run.groundtruth.poses[:1, :3]).norm(dim=-1).max()) < 1e-6:
        m["ate_unavailable"] = "the ground-truth camera never moves: the alignment is not defined"
    else:
        try:
            a = ate(run.groundtruth, res.trajectory)
            odo = ate(run.groundtruth, res.odometry_trajectory).rmse
        except ValueError as e:  # e.g. a camera that never moves: the alignment is not defined
            m["ate_unavailable"] = f"ATE not computed: {e}"
        else:
            if not (math.isfinite(a.rmse) and math.isfinite(odo)):
                m["ate_unavailable"] = (f"the ATE is not finite ({a.rmse}, odometry {odo}): ground-truth "
                                        f"positions out of range?")
        if "ate_unavailable" not in m:
            m["ate_rmse"] = a.rmse
            m["ate"] = {"rmse": a.rmse, "mean": a.mean, "median": a.median, "std": a.std, "max": a.max,
                        "num_pairs": a.num_pairs}
            m["odometry_ate_rmse"] = odo
            # over the tracked frames alone (lost and unreadable ones are guesses)
            m["ate_tracked"] = None
            if res.tracked is not None:
                kept = torch.nonzero(res.tracked).flatten()
                try:
                    t = a if len(kept) == res.num_frames else ate(run.groundtruth, res.trajectory.subset(kept))
                    m["ate_tracked"] = {"rmse": t.rmse, "num_pairs": t.num_pairs}
                except ValueError as e:  # too few tracked frames with ground truth to align
                    m["ate_tracked"] = {"unavailable": str(e)}
    if m["ate_rmse"] is not None:
        for key, kw in (("rpe_1frame", {"delta": 1, "delta_unit": "frames"}),
                        ("rpe_1s", {"delta": 1.0, "delta_unit": "seconds"})):
            try:
                r = rpe(run.groundtruth, res.trajectory, **kw)
                m[key] = {"trans_rmse_m": r.translation.rmse, "rot_rmse_deg": r.rotation.rmse,
                          "num_pairs": int(r.pairs.shape[0])}
            except ValueError as e:  # too short for the delta
                m[key] = {"error": str(e)}
        cfg = loop_ground_truth_for_step(run.frame_step)
        m["loop_ground_truth"] = dataclasses.asdict(cfg)
        def judge(loops):  # an accepted loop is judged by closeness alone (the frame gap counts revisits)
            pairs = torch.tensor([[lp.frame_b, lp.frame_a] for lp in loops], dtype=torch.long).reshape(-1, 2)
            return is_true_loop(run.gt_poses_per_frame, pairs, dataclasses.replace(cfg, min_frame_gap=1))

        judged = judge(res.loops)
        m["loops_true"] = int(judged.sum())
        m["loops_false"] = int((~judged).sum())
        hyp = res.loop_hypotheses
        m["loop_hypotheses_false"] = _by_status([lp for lp, t in zip(hyp, judge(hyp).tolist()) if not t])
        m["loop_detection"] = loop_precision_recall(run, cfg)
    if run.relocalisation is not None:
        m["relocalisation"] = _relocalisation_metrics(run)
    run.report = RunReport(**m)
    return run.report


def _by_status(loops) -> dict[str, int]:
    return {s: sum(lp.status == s for lp in loops) for s in ("kept", "inconsistent", "switched_off")}


def loop_worker_metrics(result: SLAMResult, config: SLAMConfig | None = None) -> dict[str, object]:
    """The loop worker's lag over a run (``metrics.json``'s ``loop_worker``): the keyframes whose loop work was
    waiting when each frame was tracked (:attr:`slam.system.RGBDSLAM.loop_lag`), its maximum and, per fifth of
    the run's frames, its maximum and mean; ``backlog`` is ``BackendConfig.loop_backlog``.

    Example:
        >>> from types import SimpleNamespace
        >>> r = SimpleNamespace(loop_lag=torch.tensor([0, 1, 1, 0, 2, 0, 0, 1, 0, 3]))
        >>> m = loop_worker_metrics(r)
        >>> m["lag_max"], m["lag_per_fifth"]["max"], m["lag_per_fifth"]["mean"]
        (3, [1, 1, 2, 1, 3], [0.5, 0.5, 1.0, 0.5, 1.5])
    """
    lag = result.loop_lag if result.loop_lag is not None else torch.zeros(0, dtype=torch.int64)
    backlog = config.backend.loop_backlog if config is not None else None
    out: dict[str, object] = {"backlog": backlog,
                              "mode": None if backlog is None else ("waits" if backlog == 0 else "runs ahead"),
                              "lag_max": int(lag.max()) if lag.numel() else 0}
    parts = [p for p in torch.tensor_split(lag, 5) if p.numel()] if lag.numel() else []
    out["lag_per_fifth"] = {"max": [int(p.max()) for p in parts],
                            "mean": [round(float(p.double().mean()), 3) for p in parts]}
    return out


def _relocalisation_metrics(run) -> dict[str, object]:
    """The map relocalisation's report, with the errors in the map's world without alignment when the map
    knows the ground truth of its origin (:func:`slam.maps.map_world_errors`)."""
    from slam.maps import map_world_errors

    rep = run.relocalisation.as_dict()
    rep["map_world_errors"] = None
    if run.relocalisation.relocalised and run.map_origin is not None and run.gt_poses_per_frame is not None:
        rep["map_world_errors"] = map_world_errors(run.result.trajectory.poses, run.gt_poses_per_frame,
                                                   run.map_origin)
    return rep


def loop_precision_recall(run, config=None) -> dict[str, object]:
    """Precision/recall of the loop detector over the keyframe queries, before and after verification: each
    query's most similar candidate, then its most similar verified one (``-inf`` when none). A keyframe that
    followed a revisit (``LoopQuery.followed``) was not a query: it counts in neither.

    Args:
        run: a :class:`slam.pipeline.RunResult`.
        config: :class:`slam.eval.LoopGroundTruthConfig` (default: :func:`loop_ground_truth_for_step`).

    Returns:
        ``{"before_verification": {...}, "after_verification": {...}}`` with ``max_recall_at_full_precision``,
        ``average_precision`` and ``num_positives``; the curves themselves go to ``run.loop_curves``.
    """
    from slam.eval import evaluate_loop_candidates

    cfg = config or loop_ground_truth_for_step(run.frame_step)
    res = run.result
    frames = res.keyframe_frames
    if run.gt_poses_per_frame is None or not res.queries:
        return {}
    similarity = {(lp.kf_a, lp.kf_b): lp.similarity for lp in res.loop_hypotheses}
    before_pairs, before_scores, after_pairs, after_scores = [], [], [], []
    for q in res.queries:
        if q.top_kf < 0 or q.followed:  # followed: no descriptor, nothing of the detector's to score
            continue
        before_pairs.append([int(frames[q.kf]), int(frames[q.top_kf])])
        before_scores.append(q.top_score)
        best = q.verified[0] if q.verified else q.top_kf  # candidates come most similar first
        after_pairs.append([int(frames[q.kf]), int(frames[best])])
        after_scores.append(similarity[(best, q.kf)] if q.verified else float("-inf"))
    if not before_pairs:
        return {}
    out: dict[str, object] = {}
    # a followed keyframe found its loop without the detector: not a query, nor a positive of the detector's
    queried = torch.tensor([int(frames[q.kf]) for q in res.queries if not q.followed], dtype=torch.long)
    for name, pairs, scores in (("before_verification", before_pairs, before_scores),
                                ("after_verification", after_pairs, after_scores)):
        ev = evaluate_loop_candidates(torch.tensor(pairs), torch.tensor(scores, dtype=torch.float64),
                                      run.gt_poses_per_frame, cfg, indices=frames, queries=queried)
        out[name] = ev.curve.to_dict()
        run.loop_curves[name] = ev.curve
    return out
