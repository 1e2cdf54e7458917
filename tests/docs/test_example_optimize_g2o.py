"""examples/optimize_g2o.py: read, optimise, write a g2o file from the command line."""
from __future__ import annotations

import math
from pathlib import Path

import pytest

from slam.graph import graph_chi2, read_g2o

SCRIPT = "examples/optimize_g2o.py"


def _square_with_drift(path: Path) -> None:
    """Four poses on a 1 m square, odometry with a 0.1 rad heading error on one edge, one loop closure."""
    lines = [f"VERTEX_SE2 {i} {x} {y} {t}" for i, (x, y, t) in
             enumerate([(0, 0, 0), (1, 0, 1.5708), (1.1, 1, 3.2416), (0.1, 1.2, 4.8124)])]
    info = "1 0 0 1 0 1"
    lines += [f"EDGE_SE2 {i} {i + 1} 1 0 1.5708 {info}" for i in range(3)]
    lines.append(f"EDGE_SE2 3 0 1 0 1.5708 {info}")
    path.write_text("\n".join(lines) + "\n")


def test_optimises_and_writes_a_2d_file(tmp_path, capsys, load_script):
    ex = load_script(SCRIPT)
    src, out = tmp_path / "square.g2o", tmp_path / "square_opt.g2o"
    _square_with_drift(src)
    res = ex.main([str(src), "-o", str(out), "--kernel", "cauchy", "--initialization", "none"])  # the drift
    assert res.status == "converged" and res.chi2 < 1e-6 < res.initial_chi2  # consistent measurements
    text = out.read_text()
    assert text.startswith("VERTEX_SE2") and "EDGE_SE3" not in text  # 2D stays 2D
    back = read_g2o(out)
    assert graph_chi2(back) == pytest.approx(res.chi2, abs=1e-9)
    assert math.isclose(float(back.poses[0, 0]), 0.0, abs_tol=1e-12)  # the free gauge keeps pose 0
    printed = capsys.readouterr().out
    assert "4 poses, 4 edges" in printed and "converged" in printed and f"wrote {out}" in printed


def test_settings_reach_the_optimiser_and_bad_files_exit_with_the_line(tmp_path, load_script):
    ex = load_script(SCRIPT)
    src = tmp_path / "square.g2o"
    _square_with_drift(src)
    args = ex.parse_args([str(src), "--method", "gn", "-n", "1", "--damping", "diagonal", "--lambda-update",
                          "nielsen", "--gauge", "first"])
    assert (args.method, args.max_iterations, args.damping, args.lambda_update) == ("gn", 1, "diagonal", "nielsen")
    assert ex.main([str(src), "--method", "gn", "-n", "1"]).iterations == 1
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 one 0 0 1 0 0 1 0 1\n")
    with pytest.raises(SystemExit, match=r"bad\.g2o.*line 2"):
        ex.main([str(bad)])
    with pytest.raises(SystemExit, match="No such file"):
        ex.main([str(tmp_path / "missing.g2o")])
    for bad_args in (["--kernel-width", "2"], ["-n", "-1"]):
        with pytest.raises(SystemExit):
            ex.parse_args([str(src), *bad_args])


def test_real_benchmark_file_matches_gtsams_error(posegraph_dir, tmp_path, load_script):
    res = load_script(SCRIPT).main([str(posegraph_dir / "tinyGrid3D.g2o"), "-o", str(tmp_path / "tiny.g2o")])
    assert res.error == pytest.approx(9.313911, rel=1e-6)  # GTSAM 4.3 LM's final error on this file


def test_initialization_strict_and_warnings(tmp_path, capsys, load_script):
    ex = load_script(SCRIPT)
    src = tmp_path / "square.g2o"
    _square_with_drift(src)
    edges_only = tmp_path / "edges.g2o"
    edges_only.write_text("".join(ln + "\n" for ln in src.read_text().splitlines() if ln.startswith("EDGE")))
    for init in ("chordal", "spanning_tree", "none"):
        res = ex.main([str(edges_only), "--initialization", init])
        assert res.status == "converged" and res.chi2 < 1e-6
    assert ex.parse_args([str(src), "--initialization", "chordal"]).initialization == "chordal"
    with pytest.raises(SystemExit):
        ex.parse_args([str(src), "--initialization", "odometry"])
    bad = tmp_path / "npd.g2o"
    bad.write_text(src.read_text().replace("1.5708 1 0 0 1 0 1", "1.5708 1 2 0 1 0 1", 1))  # [[1, 2], [2, 1]]
    capsys.readouterr()
    assert ex.main([str(bad)]).status == "converged"
    err = capsys.readouterr().err
    assert err.startswith(f"warning: {bad}, line 5: EDGE_SE2 information matrix is not positive definite")
    with pytest.raises(SystemExit, match=r"npd\.g2o, line 5: .*refused with strict=True"):
        ex.main([str(bad), "--strict"])


def test_defaults_converge_on_intel_where_the_file_vertices_stall(posegraph_dir, load_script, capsys):
    """The file's vertices are raw odometry, from which LM crawls (100 iterations to chi2 109,178, status
    max_iterations); the default start (auto: their chi2 is ~4500 per edge, so a spanning tree of the edges)
    converges below 215.85, the chi2 that
    Nielsen's rule with diagonal damping reaches from the vertices in ~860 iterations."""
    path = str(posegraph_dir / "input_INTEL_g2o.g2o")
    res = load_script(SCRIPT).main([path])
    assert res.status == "converged" and res.iterations <= 10
    assert 215.0 < res.chi2 < 215.85
    assert "converged" in capsys.readouterr().out
    stalled = load_script(SCRIPT).main([path, "--initialization", "none"])
    assert stalled.status == "max_iterations" and stalled.chi2 > 1e5
    assert "initialization='chordal'" in stalled.message and "max_iterations=100" in stalled.message
