"""Odometry benchmark on 7-Scenes redkitchen: ATE and time per frame, ours beside OpenCV anchors.

Runs every method on the same frames in one process and prints a markdown table:

* ``ours``: :class:`slam.odometry.RGBDOdometry` with its default config (frames treated as registered);
* ``ours-rgbK``: the same with ``FeatureConfig.rgb_intrinsics = (525, 525, 320, 240)``: the Kinect v1
  colour camera's focal length instead of the depth camera's 585 for the keypoints (7-Scenes colour and
  depth are unregistered);
* ``ours-rig``: the Kinect v1 rig ``attnloop-slam`` uses on 7-Scenes: the depth warped into the colour
  camera (f = 525, 2.5 cm baseline, :mod:`slam.odometry.depth_registration`), poses of the depth camera;
* ``sift-3d3d``: OpenCV SIFT (all keypoints), ratio test 0.75, 3D-3D RANSAC (numpy Kabsch, 500
  hypotheses, 2 cm), frame-to-frame;
* ``orb-pnp``: OpenCV ORB (1000), cross-checked Hamming matches, ``cv2.solvePnPRansac``, frame-to-frame.

ATE: RMSE of the positions after a rigid (no scale) Umeyama alignment of the whole trajectory, as
``evo_ape -a`` computes it (cross-checked with evo when it is installed). Time: wall and CPU (process)
milliseconds of the tracking call per frame, image decoding excluded (reported apart); ours also per stage.

Usage::

    python -m benchmarks.odometry                       # all methods, all 1000 frames
    python -m benchmarks.odometry --methods ours --max-frames 300 --threads 2   # default: 1 thread
    python -m benchmarks.odometry --methods ours-rig                 # the default run's odometry, per stage
    python -m benchmarks.odometry --markdown out.md     # also write the table to a file

Frames are read by a private loader (cv2) until the project's ``slam.io`` reader is switched in.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from benchmarks._common import data_root
from slam.config import override
from slam.io.frame import RGBDFrame
from slam.lie import se3_from_matrix
from slam.odometry import OdometryConfig, RGBDOdometry, TrackStatus

K_7SCENES = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# data
# ----------------------------------------------------------------------------------------------
def load_frame(folder: Path, i: int) -> RGBDFrame:
    """Frame ``i`` of a 7-Scenes folder: RGB (cv2 reads BGR), depth in metres (0 and 65535 invalid)."""
    stem = str(folder / f"frame-{i:06d}")
    bgr = cv2.imread(stem + ".color.jpg", cv2.IMREAD_COLOR)
    raw = cv2.imread(stem + ".depth.png", cv2.IMREAD_UNCHANGED)
    if bgr is None or raw is None:
        raise FileNotFoundError(f"cannot read frame {i} at {stem}.color.jpg / .depth.png")
    depth = np.where(raw == 65535, 0, raw).astype(np.float32) / 1000.0
    pose = se3_from_matrix(torch.from_numpy(np.loadtxt(stem + ".pose.txt"))).numpy()
    return RGBDFrame(i, i / 30.0, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth, K_7SCENES.copy(), pose)


# ----------------------------------------------------------------------------------------------
# evaluation
# ----------------------------------------------------------------------------------------------
def ate_rmse(est: np.ndarray, gt: np.ndarray) -> float:
    """RMSE of positions ``(N, 3)`` after the least-squares rigid alignment of ``est`` onto ``gt``."""
    mu_e, mu_g = est.mean(0), gt.mean(0)
    U, _, Vt = np.linalg.svd((gt - mu_g).T @ (est - mu_e))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    aligned = (est - mu_e) @ R.T + mu_g
    return float(np.sqrt(((aligned - gt) ** 2).sum(1).mean()))


def evo_ate(est: np.ndarray, gt: np.ndarray, stamps: np.ndarray):
    """The same ATE from evo (``ape``, translation part, rigid alignment), or None without evo."""
    try:
        from evo.core import metrics
        from evo.core.trajectory import PoseTrajectory3D
    except ImportError:
        return None
    # evo wants quaternions w-first
    ref = PoseTrajectory3D(gt[:, :3], gt[:, [6, 3, 4, 5]], stamps)
    e = PoseTrajectory3D(est[:, :3], est[:, [6, 3, 4, 5]], stamps)
    e.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


# ----------------------------------------------------------------------------------------------
# anchors (plain OpenCV / numpy, frame-to-frame)
# ----------------------------------------------------------------------------------------------
def _backproject_np(kp: np.ndarray, depth: np.ndarray, K: np.ndarray):
    u = np.round(kp[:, 0]).astype(int).clip(0, depth.shape[1] - 1)
    v = np.round(kp[:, 1]).astype(int).clip(0, depth.shape[0] - 1)
    z = depth[v, u]
    ok = (z > 0.3) & (z < 4.0)
    pts = np.stack([(kp[:, 0] - K[0, 2]) / K[0, 0] * z, (kp[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1)
    return pts, ok


def _kabsch_np(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    ms, md = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((dst - md).T @ (src - ms))
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, md - R @ ms
    return T


def _ransac_np(src, dst, rng, iters=500, thr=0.02):
    """4x4 ``dst ~ T src`` by 3-point RANSAC + refit on the inliers, or None."""
    n = len(src)
    if n < 6:
        return None
    best, best_n = None, 0
    for _ in range(iters):
        idx = rng.choice(n, 3, replace=False)
        T = _kabsch_np(src[idx], dst[idx])
        inl = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < thr
        if inl.sum() > best_n:
            best, best_n = inl, int(inl.sum())
    if best_n < 10:
        return None
    return _kabsch_np(src[best], dst[best])


class SiftRansacAnchor:
    """OpenCV SIFT + ratio test + 3D-3D RANSAC, frame to frame."""

    def __init__(self):
        self.sift = cv2.SIFT_create()
        self.bf = cv2.BFMatcher(cv2.NORM_L2)
        self.rng = np.random.default_rng(0)
        self.prev = None
        self.T = np.eye(4)
        self.failures = 0

    def track(self, f: RGBDFrame) -> np.ndarray:
        gray = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        kps, desc = self.sift.detectAndCompute(gray, None)
        kp = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
        pts, ok = _backproject_np(kp, f.depth, f.K)
        cur = (pts[ok], desc[ok] if desc is not None else None)
        if self.prev is not None and cur[1] is not None and self.prev[1] is not None and len(cur[1]) > 1:
            knn = self.bf.knnMatch(cur[1], self.prev[1], k=2)
            m = [(a.queryIdx, a.trainIdx) for a, b in (p for p in knn if len(p) == 2)
                 if a.distance < 0.75 * b.distance]
            m = np.array(m, int).reshape(-1, 2)
            T_prev_cur = _ransac_np(cur[0][m[:, 0]], self.prev[0][m[:, 1]], self.rng)
            if T_prev_cur is None:
                self.failures += 1
            else:
                self.T = self.T @ T_prev_cur
        self.prev = cur
        return se3_from_matrix(torch.from_numpy(self.T)).numpy()


class OrbPnpAnchor:
    """OpenCV ORB + cross-checked Hamming matching + PnP-RANSAC, frame to frame."""

    def __init__(self):
        self.orb = cv2.ORB_create(nfeatures=1000)
        self.bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.prev = None
        self.T = np.eye(4)
        self.failures = 0

    def track(self, f: RGBDFrame) -> np.ndarray:
        gray = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY)
        kps, desc = self.orb.detectAndCompute(gray, None)
        kp = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
        pts, ok = _backproject_np(kp, f.depth, f.K)
        if self.prev is not None and desc is not None and self.prev[2] is not None:
            _prev_kp, prev_pts, prev_desc, prev_ok = self.prev
            matches = self.bf.match(prev_desc, desc)
            m = np.array([(x.queryIdx, x.trainIdx) for x in matches], int).reshape(-1, 2)
            m = m[prev_ok[m[:, 0]]] if len(m) else m
            good = False
            if len(m) >= 6:
                ok_pnp, rvec, tvec, inl = cv2.solvePnPRansac(prev_pts[m[:, 0]], kp[m[:, 1]], f.K, None,
                                                             iterationsCount=100, reprojectionError=3.0)
                if ok_pnp and inl is not None and len(inl) >= 10:
                    T_cur_prev = np.eye(4)
                    T_cur_prev[:3, :3] = cv2.Rodrigues(rvec)[0]
                    T_cur_prev[:3, 3] = tvec[:, 0]
                    self.T = self.T @ np.linalg.inv(T_cur_prev)
                    good = True
            if not good:
                self.failures += 1
        self.prev = (kp, pts, desc, ok)
        return se3_from_matrix(torch.from_numpy(self.T)).numpy()


class Ours:
    def __init__(self, config: OdometryConfig):
        self.odo = RGBDOdometry(config)
        self.failures = 0
        feats = config.features
        # with a colour/depth baseline the colour camera is tracked: report the depth camera (the ground truth's)
        self.rig = None
        if feats.rgb_intrinsics is not None and any(x != 0.0 for x in feats.rgb_from_depth_translation):
            from slam.odometry.depth_registration import rig_pose

            self.rig = rig_pose(feats.rgb_from_depth_translation)

    def track(self, f: RGBDFrame) -> np.ndarray:
        r = self.odo.track(f)
        if r.status is TrackStatus.LOST:
            self.failures += 1
        if self.rig is None:
            return r.pose.numpy()
        from slam.odometry.depth_registration import depth_camera_poses

        return depth_camera_poses(r.pose, self.rig).numpy()


def make(name: str):
    if name == "ours":
        return Ours(OdometryConfig())
    if name == "ours-rgbK":
        cfg = OdometryConfig()
        cfg = override(cfg, {"features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0)})
        return Ours(cfg)
    if name == "ours-rig":  # what attnloop-slam runs on 7-Scenes: the depth warped into the colour camera
        cfg = OdometryConfig()
        cfg = override(cfg, {
            "features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0),
            "features.rgb_from_depth_translation": (-0.025, 0.0, 0.0)})
        return Ours(cfg)
    if name == "sift-3d3d":
        return SiftRansacAnchor()
    if name == "orb-pnp":
        return OrbPnpAnchor()
    raise SystemExit(f"unknown method {name!r}")


# ----------------------------------------------------------------------------------------------
def run(name: str, folder: Path, n: int) -> dict:
    method = make(name)
    est, gt = [], []
    wall = cpu = io = 0.0
    for i in range(n):
        t = time.perf_counter()
        f = load_frame(folder, i)
        io += time.perf_counter() - t
        t, c = time.perf_counter(), time.process_time()
        est.append(method.track(f))
        wall += time.perf_counter() - t
        cpu += time.process_time() - c
        gt.append(f.pose_gt)
    est, gt = np.array(est), np.array(gt)
    out = {"method": name, "frames": n, "ate": ate_rmse(est[:, :3], gt[:, :3]),
           "evo": evo_ate(est, gt, np.arange(n) / 30.0), "wall_ms": wall / n * 1e3, "cpu_ms": cpu / n * 1e3,
           "io_ms": io / n * 1e3, "failures": method.failures, "keyframes": "", "stages": ""}
    if isinstance(method, Ours):
        out["keyframes"] = len(method.odo.keyframes)
        out["stages"] = ", ".join(f"{k} {v / n * 1e3:.1f}" for k, v in method.odo.stage_seconds.items())
    return out


def main(argv=None) -> None:
    default_data = data_root() / "7scenes-redkitchen"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=default_data, help="7-Scenes sequence folder")
    ap.add_argument("--max-frames", type=int, default=1000, help="kitchen frames to track")
    ap.add_argument("--methods", default="ours,ours-rgbK,sift-3d3d,orb-pnp", help="comma-separated methods to run")
    # One thread by default: the per-frame tensors are small, and on a shared 2-core machine torch's
    # OpenMP regions wait for descheduled workers (measured: 2 threads 850 ms/frame, 1 thread 66 ms).
    ap.add_argument("--threads", type=int, default=1, help="torch/OpenCV threads (0: library default)")
    ap.add_argument("--markdown", type=Path, default=None, help="also write the table to this file")
    args = ap.parse_args(argv)
    if not (args.data / "frame-000000.color.jpg").is_file():
        raise SystemExit(f"no 7-Scenes frames in {args.data} (set ATTNLOOP_DATA or pass --data)")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
        cv2.setNumThreads(args.threads)
    n = min(args.max_frames, len(list(args.data.glob("frame-*.color.jpg"))))
    rows = []
    for name in args.methods.split(","):
        r = run(name.strip(), args.data, n)
        rows.append(r)
        print(f"[{name}] ATE {r['ate']:.4f} m, {r['wall_ms']:.1f} ms/frame wall, {r['cpu_ms']:.1f} ms CPU",
              file=sys.stderr, flush=True)
    lines = [
        (f"Sequence `{args.data.name}`, {n} frames; {datetime.date.today().isoformat()}; "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch threads "
        f"{torch.get_num_threads()}, OpenCV threads {cv2.getNumThreads()}."),
        "",
        ("| method | ATE RMSE (m) | ATE evo (m) | wall ms/frame | CPU ms/frame | lost/failed frames | keyframes |"
        " ours: wall ms per stage |"),
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        evo = "-" if r["evo"] is None else f"{r['evo']:.4f}"
        lines.append(f"| {r['method']} | {r['ate']:.4f} | {evo} | {r['wall_ms']:.1f} | {r['cpu_ms']:.1f} | "
                     f"{r['failures']} | {r['keyframes']} | {r['stages']} |")
    io = np.mean([r["io_ms"] for r in rows])
    lines += ["", f"Image decoding (not included above): {io:.1f} ms/frame."]
    text = "\n".join(lines)
    print(text)
    if args.markdown is not None:
        args.markdown.write_text(text + "\n")


if __name__ == "__main__":
    main()
