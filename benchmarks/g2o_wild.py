"""g2o files from the wild, each kind built from the shared benchmark files, read and optimised side by side
with GTSAM 4.3.

Each kind is made from the shared files (seeded):

* ``non-PD``: 1 % of the edges get their smallest information eigenvalue made slightly negative (-1 % of
  it: a covariance printed with too few digits);
* ``edges only``: the file without its VERTEX lines (ours: poses composed along the BFS tree of the edges;
  GTSAM's ``readG2o`` composes a 2D file's missing poses along the edges in file order, and has none in 3D);
* ``FIX``: ``FIX`` lines holding two poses (GTSAM: ``NonlinearEquality`` on them);
* ``big noise``: the file's poses re-measured with large Gaussian noise on every edge, its information
  the inverse of that noise, the initial guess the composed odometry (the construction of GTSAM's
  ``sphere_bignoise_vertex3.g2o``).

For each: ours from the file's guess and from ``initialization="chordal"``; GTSAM's LM from the file's
guess and from its own initialisation (``InitializePose3`` in 3D, ``lago`` in 2D, a prior on the first
pose). Every solution is scored with one cost, ``graph_chi2`` of the graph as read here (GTSAM's error
is chi2 / 2; for the non-PD files GTSAM's own noise model is not this cost, so it is re-scored).
Times are wall seconds of one run (init + LM) on a shared machine: indicative only.

A second table compares the spanning trees tried for files with edges only (BFS by hops, the choice;
Dijkstra on the covariance trace; a minimum spanning tree on it; the odometry chain). A third times the
chordal guess alone against GTSAM's ``InitializePose3`` on the 3D files (interleaved, median of
``--repeats``) and gives the chi2 of each guess.

Usage:
    python -m benchmarks.g2o_wild [--data DIR] [--out FILE.md] [--repeats 3] [--only-init]
"""
from __future__ import annotations

import argparse
import datetime
import io
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]

import scipy.sparse as sp
from scipy.sparse import csgraph

from benchmarks.simulate import compose_chain
from slam.graph import PoseGraph, graph_chi2, optimize, read_g2o, write_g2o
from slam.graph import initialization as init_mod
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity, se3_inv

FILES = ["tinyGrid3D", "smallGrid3D", "sphere2500", "parking-garage", "input_M3500_g2o", "input_INTEL_g2o"]


def data_dir(arg):
    if arg:
        return Path(arg)
    return Path(os.environ.get("ATTNLOOP_DATA", ROOT.parent / "shared" / "data")) / "posegraph"


# --------------------------------------------------------------------------------------------- kinds
def non_pd(g: PoseGraph, seed=0) -> PoseGraph:
    k = np.random.default_rng(seed).choice(g.num_edges, size=max(1, g.num_edges // 100), replace=False)
    info = g.information.clone()
    d = [0, 1, 5] if g.is_planar() else list(range(6))
    sub = info[k][:, d][:, :, d]
    w, V = torch.linalg.eigh(sub)
    w[:, 0] = -0.01 * w[:, 0]
    sub = V @ torch.diag_embed(w) @ V.mT
    sub = 0.5 * (sub + sub.mT)
    for a, da in enumerate(d):
        for b, db in enumerate(d):
            info[k, da, db] = sub[:, a, b]
    if g.is_planar():  # keep the lift of read_g2o, so that the file is written as 2D
        info[k, 2, 2] = 0.5 * (info[k, 0, 0] + info[k, 1, 1])
        info[k, 3, 3] = info[k, 5, 5]
        info[k, 4, 4] = info[k, 5, 5]
    return PoseGraph(g.poses, g.ii, g.jj, g.measurements, info, vertex_ids=g.vertex_ids)


def big_noise(g: PoseGraph, sigma_t: float, sigma_r: float, seed=0) -> PoseGraph:
    X = g.poses
    gen = torch.Generator().manual_seed(seed)
    planar = g.is_planar()
    sig = torch.tensor([sigma_t] * 3 + [sigma_r] * 3, dtype=torch.float64)
    noise = sig * torch.randn(g.num_edges, 6, generator=gen, dtype=torch.float64)
    if planar:
        noise[:, 2:5] = 0.0
    Z = se3_compose(se3_between(X[g.ii], X[g.jj]), se3_exp(noise))
    info = torch.diag(sig ** -2).expand(g.num_edges, 6, 6).clone()
    if planar:  # the lift of read_g2o: z gets (Ixx + Iyy) / 2, roll and pitch get Itheta
        info[:, 2, 2] = sigma_t ** -2
        info[:, 3, 3] = info[:, 4, 4] = sigma_r ** -2
    odo = g.jj == g.ii + 1
    P = compose_chain(X[0], Z[odo][torch.argsort(g.ii[odo])])
    return PoseGraph(P, g.ii, g.jj, Z, info, vertex_ids=g.vertex_ids)


# --------------------------------------------------------------------------------------------- GTSAM
def gtsam_runs(path: Path, ours: PoseGraph, fixed=()):
    """GTSAM LM from the file's guess and from its own initialisation: ``{name: (poses, seconds)}``."""
    try:
        import gtsam
    except ImportError:
        return {}
    is3 = not ours.is_planar()
    G, V = gtsam.readG2o(str(path), is3)
    ids = ours.vertex_ids.tolist()
    for k in fixed:
        vid = ids[k]
        G.add(gtsam.NonlinearEqualityPose3(vid, V.atPose3(vid)) if is3 else
              gtsam.NonlinearEqualityPose2(vid, V.atPose2(vid)))
    out = {}
    params = gtsam.LevenbergMarquardtParams()
    if V.size():
        t = time.perf_counter()
        res = gtsam.LevenbergMarquardtOptimizer(G, V, params).optimize()
        out["file guess"] = (_poses(res, ids, is3), time.perf_counter() - t)
    first = ids[fixed[0]] if fixed else ids[0]
    anchor = ours.poses[fixed[0] if fixed else 0]
    G2 = gtsam.NonlinearFactorGraph(G)
    t = time.perf_counter()
    label = "InitializePose3" if is3 else "lago"
    try:
        start = _gtsam_initial(gtsam, G2, is3, first, anchor)
    except (RuntimeError, ValueError) as e:  # e.g. lago: "assumes diagonal noise model"
        out[label] = (None, f"{type(e).__name__}: {e}")
        return out
    if start.size() < len(ids):
        out[label] = (None, f"returned {start.size()} of {len(ids)} poses")
        return out
    for k in fixed:  # NonlinearEquality needs its exact value in the starting point
        vid = ids[k]
        start.update(vid, V.atPose3(vid) if is3 else V.atPose2(vid))
    res = gtsam.LevenbergMarquardtOptimizer(G, start, params).optimize()
    out[label] = (_poses(res, ids, is3), time.perf_counter() - t)
    return out


def _gtsam_initial(gtsam, G2, is3, first, anchor):
    with _quiet():
        if is3:
            q = anchor[3:].tolist()
            pose = gtsam.Pose3(gtsam.Rot3.Quaternion(q[3], q[0], q[1], q[2]), gtsam.Point3(*anchor[:3].tolist()))
            G2.add(gtsam.PriorFactorPose3(first, pose, gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
            return gtsam.InitializePose3.initialize(G2)
        else:
            theta = 2 * float(torch.atan2(anchor[5], anchor[6]))
            G2.add(gtsam.PriorFactorPose2(first, gtsam.Pose2(float(anchor[0]), float(anchor[1]), theta),
                                          gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)))
            return gtsam.lago.initialize(G2)


class _quiet:
    """GTSAM's initialisers print to stdout (C++): silence file descriptor 1 meanwhile."""

    def __enter__(self):
        sys.stdout.flush()
        self.saved = os.dup(1)
        self.null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(self.null, 1)

    def __exit__(self, *exc):
        os.dup2(self.saved, 1)
        os.close(self.null)
        os.close(self.saved)


def _poses(values, ids, is3) -> torch.Tensor:
    P = np.zeros((len(ids), 7))
    for k, vid in enumerate(ids):
        if is3:
            p = values.atPose3(vid)
            q = p.rotation().toQuaternion()
            P[k] = [*p.translation(), q.x(), q.y(), q.z(), q.w()]
        else:
            p = values.atPose2(vid)
            P[k] = [p.x(), p.y(), 0, 0, 0, np.sin(p.theta() / 2), np.cos(p.theta() / 2)]
    return torch.from_numpy(P)


# --------------------------------------------------------------------------------------------- runs
def run_case(name: str, kind: str, path: Path, rows: list, fixed=()):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        g = read_g2o(path)
    notes = f"{len(caught)} warning" + ("s" if len(caught) != 1 else "") if caught else "-"
    row = {"file": name, "kind": kind, "read": notes, "poses": g.num_poses, "edges": g.num_edges}
    for init in ("none", "chordal"):
        t = time.perf_counter()
        res = optimize(g, initialization=init)
        row[f"ours {init}"] = (res.chi2, time.perf_counter() - t, res.iterations)
    for label, (P, secs) in gtsam_runs(path, g, fixed).items():
        row[f"gtsam {label}"] = (graph_chi2(g.with_poses(P)), secs, None) if P is not None else secs
    rows.append(row)
    print(_fmt_row(row), flush=True)


def _cell(v):
    if v is None:
        return "n/a"
    if isinstance(v, str):
        return f"fails ({v.split(':')[0]})" if ":" in v else f"fails ({v})"
    chi2, secs, it = v
    return f"{chi2:.7g} ({secs:.2f} s{'' if it is None else f', {it} it'})"


def _fmt_row(row):
    gt = [row.get("gtsam file guess"), row.get("gtsam InitializePose3") or row.get("gtsam lago")]
    ok = [v[0] for v in gt if isinstance(v, tuple)]
    best_g = min(ok) if ok else None
    ratio = f"{row['ours chordal'][0] / best_g - 1:+.1e}" if best_g else "n/a"
    return (f"| {row['file']} | {row['kind']} | {row['poses']}/{row['edges']} | {row['read']} | "
            f"{_cell(row['ours none'])} | {_cell(row['ours chordal'])} | {_cell(gt[0])} | {_cell(gt[1])} | {ratio} |")


HEADER = ("| file | kind | poses/edges | read | ours, file guess | ours, chordal | GTSAM LM, file guess | "
          "GTSAM LM, InitializePose3 / lago | ours chordal vs best GTSAM (relative) |\n"
          "|---|---|---|---|---|---|---|---|---|")


def tree_table(folder: Path):
    """Final chi2 and LM iterations from each spanning tree, on each file with its VERTEX lines removed."""
    lines = ["| file | BFS (hops) | Dijkstra (cov. trace) | min. spanning tree (cov. trace) | odometry chain |",
             "|---|---|---|---|---|"]
    for name in FILES:
        text = (folder / f"{name}.g2o").read_text().splitlines()
        g = read_g2o(io.StringIO("\n".join(ln for ln in text if not ln.startswith("VERTEX")) + "\n"))
        cells = []
        for mode in ("bfs", "cov", "mst", "chain"):
            P = init_mod.spanning_tree_poses(g) if mode == "bfs" else _other_tree(g, mode)
            gg = g.with_poses(P)
            res = optimize(gg)
            note = "" if res.converged else ", not converged"
            cells.append(f"{graph_chi2(gg):.3g} -> {res.chi2:.8g} ({res.iterations} it{note})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines


def _other_tree(g: PoseGraph, mode: str) -> torch.Tensor:
    n = g.num_poses
    ii, jj = g.ii.numpy(), g.jj.numpy()
    cost = init_mod._edge_cost(g.information.numpy())
    a, b = np.minimum(ii, jj), np.maximum(ii, jj)
    key = a * n + b
    order = np.lexsort((cost, key))
    first = np.ones(order.size, bool)
    first[1:] = key[order][1:] != key[order][:-1]
    best = order[first]
    w = cost[best] if mode != "chain" else np.where(b[best] == a[best] + 1, 1.0, 1e6)
    adj = sp.coo_matrix((w, (a[best], b[best])), shape=(n, n)).tocsr()
    if mode == "mst":
        _, pred = csgraph.breadth_first_order(csgraph.minimum_spanning_tree(adj), 0, directed=False,
                                              return_predecessors=True)
    else:
        _, pred = csgraph.dijkstra(adj, directed=False, indices=0, return_predecessors=True)
    child = np.nonzero(pred >= 0)[0]
    p = pred[child]
    parent, edge = np.full(n, -1), np.full(n, -1)
    parent[child] = p
    edge[child] = best[np.searchsorted(key[best], np.minimum(p, child) * n + np.maximum(p, child))]
    tree = init_mod.SpanningTree(parent, edge, np.array([0]))
    rel = se3_identity(n, dtype=torch.float64)
    e = edge[child]
    z = g.measurements[torch.from_numpy(e)]
    fwd = torch.from_numpy(ii[e] == parent[child])[:, None]
    rel[torch.from_numpy(child)] = torch.where(fwd, z, se3_inv(z))
    return init_mod._compose_tree(tree, g.poses, rel)


def init_table(folder: Path, repeats: int):
    """The chordal guess alone vs GTSAM's InitializePose3 (prior on the first pose), interleaved."""
    import statistics

    import gtsam

    lines = ["| file | ours chordal: s (median) | chi2 of the guess | GTSAM InitializePose3: s (median) | "
             "chi2 of the guess |", "|---|---|---|---|---|"]
    for name in ("tinyGrid3D", "smallGrid3D", "parking-garage", "sphere2500"):
        path = folder / f"{name}.g2o"
        g = read_g2o(path)
        G, V = gtsam.readG2o(str(path), True)
        G2 = gtsam.NonlinearFactorGraph(G)
        G2.add(gtsam.PriorFactorPose3(0, V.atPose3(0), gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
        ours, theirs = [], []
        for _ in range(repeats):
            t = time.perf_counter()
            P = init_mod.chordal_poses(g)
            ours.append(time.perf_counter() - t)
            t = time.perf_counter()
            with _quiet():
                start = gtsam.InitializePose3.initialize(G2)
            theirs.append(time.perf_counter() - t)
        chi_g = graph_chi2(g.with_poses(_poses(start, g.vertex_ids.tolist(), True)))
        lines.append(f"| {name} | {statistics.median(ours):.3f} | {graph_chi2(g.with_poses(P)):.4g} | "
                     f"{statistics.median(theirs):.3f} | {chi_g:.4g} |")
        print(lines[-1], flush=True)
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=None, help="folder of the g2o files (default $ATTNLOOP_DATA/posegraph)")
    ap.add_argument("--out", default=None, help="also write the tables (markdown) here")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each initial guess in the third table")
    ap.add_argument("--only-init", action="store_true", help="only the third table (initial guesses alone)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    folder = data_dir(args.data)
    if args.only_init:
        out = init_table(folder, args.repeats)
        if args.out:
            Path(args.out).write_text("\n".join(out) + "\n")
        return
    rows: list = []
    out = [f"g2o files from the wild ({datetime.date.today()}, torch {torch.__version__}, 1 thread, shared machine)",
           "", HEADER]
    print(HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)

        def case(name, kind, graph=None, text=None, fixed=()):
            path = tmp / f"{name}_{kind.replace(' ', '_').replace('/', '-')}.g2o"
            if text is not None:
                path.write_text(text)
            else:  # a planar graph as a 2D file (its composed odometry has z ~ 1e-17 from round-off)
                write_g2o(path, graph, planar=graph.is_planar())
            run_case(name, kind, path, rows, fixed)

        for name in ("parking-garage", "input_INTEL_g2o"):
            case(name, "non-PD", non_pd(read_g2o(folder / f"{name}.g2o")))
        for name in FILES:
            text = (folder / f"{name}.g2o").read_text().splitlines()
            case(name, "edges only", text="\n".join(ln for ln in text if not ln.startswith("VERTEX")) + "\n")
        for name, fix in (("tinyGrid3D", (0, 5)), ("input_M3500_g2o", (0, 100))):
            text = (folder / f"{name}.g2o").read_text()
            case(name, f"FIX {fix[0]} {fix[1]}", text=text + f"FIX {fix[0]} {fix[1]}\n", fixed=fix)
        sphere = read_g2o(folder / "sphere2500.g2o")
        for st, sr in ((0.1, 0.05), (0.2, 0.1), (0.3, 0.2), (0.5, 0.3)):
            case("sphere2500", f"big noise {st} m / {sr} rad", big_noise(sphere, st, sr))
        m3500 = read_g2o(folder / "input_M3500_g2o.g2o")
        for st, sr in ((0.1, 0.1), (0.1, 0.2), (0.1, 0.3)):
            case("input_M3500_g2o", f"big noise {st} m / {sr} rad", big_noise(m3500, st, sr))
    out += [_fmt_row(r) for r in rows]
    out += ["", "Spanning trees for files with edges only: chi2 of the composed guess -> after LM (iterations)", ""]
    out += tree_table(folder)
    out += ["", "Initial guesses alone (seconds: median of interleaved runs; chi2 of the guess)", ""]
    out += init_table(folder, args.repeats)
    if args.out:
        Path(args.out).write_text("\n".join(out) + "\n")


if __name__ == "__main__":
    main()
