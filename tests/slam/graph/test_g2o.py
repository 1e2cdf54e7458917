"""g2o reader/writer: round trips, the shared benchmark files, and clear errors for malformed input."""
import io

import pytest
import torch

from slam.graph import G2OFormatError, PoseGraph, graph_chi2, read_g2o, write_g2o
from slam.lie import se3_between, se3_compose, se3_exp

F64 = torch.float64
INFO3 = " ".join(["100 0 0 0 0 0", "100 0 0 0 0", "100 0 0 0", "25 0 0", "25 0", "25"])


def _graph(n=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    P = se3_exp(torch.randn(n, 6, generator=g, dtype=F64))
    ii = torch.tensor([0, 1, 2, 3, 0])[: n]
    jj = torch.tensor([1, 2, 3, 4, 3])[: n]
    Z = se3_compose(se3_between(P[ii], P[jj]), se3_exp(0.1 * torch.randn(n, 6, generator=g, dtype=F64)))
    A = torch.randn(n, 6, 6, generator=g, dtype=F64)
    info = A @ A.mT + torch.eye(6, dtype=F64)
    return PoseGraph(P, ii, jj, Z, info, vertex_ids=torch.tensor([3, 7, 8, 20, 21]))


def _read(text):
    return read_g2o(io.StringIO(text))


def test_roundtrip_3d_is_exact(tmp_path):
    g = _graph()
    path = tmp_path / "g.g2o"
    write_g2o(path, g)
    text = path.read_text()
    assert text.count("VERTEX_SE3:QUAT") == 5 and text.count("EDGE_SE3:QUAT") == 5
    assert text.startswith("VERTEX_SE3:QUAT 3 ")
    h = read_g2o(path)
    assert h.vertex_ids.tolist() == [3, 7, 8, 20, 21]
    assert torch.equal(h.ii, g.ii) and torch.equal(h.jj, g.jj)
    # quaternions are re-normalised on reading: equal to round-off
    for a, b in ((h.poses, g.poses), (h.measurements, g.measurements), (h.information, g.information)):
        assert torch.allclose(a, b, atol=1e-15, rtol=1e-15)
    assert graph_chi2(h) == pytest.approx(graph_chi2(g), rel=1e-14)


def test_roundtrip_2d_stays_2d():
    text = ("# a comment\n\nVERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.0 0.1 0.5\nVERTEX_SE2 2 2.0 0.3 3.0\n"
            "FIX 0\nEDGE_SE2 0 1 1.1 0.0 0.4 10 1 0 20 0 30\nEDGE_SE2 1 2 0.9 0.2 2.6 11 0 0 12 0 13\n")
    g = _read(text)
    assert g.poses.shape == (3, 7) and g.is_planar() and g.chart == "se3"
    # the 3x3 block sits at (x, y, yaw); z gets (Ixx + Iyy) / 2, roll and pitch get Itheta
    assert g.information[0, [0, 1, 5]][:, [0, 1, 5]].tolist() == [[10, 1, 0], [1, 20, 0], [0, 0, 30]]
    assert g.information[0].diagonal().tolist() == [10, 20, 15, 30, 30, 30]
    assert float(2 * torch.atan2(g.poses[2, 5], g.poses[2, 6])) == pytest.approx(3.0)
    buf = io.StringIO()
    write_g2o(buf, g)
    out = buf.getvalue()
    assert "VERTEX_SE2" in out and "EDGE_SE2" in out and "SE3" not in out
    h = _read(out)
    assert torch.allclose(h.poses, g.poses, atol=1e-15) and torch.allclose(h.information, g.information)
    buf3 = io.StringIO()
    write_g2o(buf3, g, planar=False)
    assert torch.allclose(_read(buf3.getvalue()).measurements, g.measurements, atol=1e-15)
    with pytest.raises(ValueError, match="not planar"):
        write_g2o(io.StringIO(), _graph(), planar=True)


def test_edges_before_vertices_and_r3so3_chart():
    text = "EDGE_SE2 5 9 1 0 0 1 0 0 1 0 1\nVERTEX_SE2 9 1 0 0\nVERTEX_SE2 5 0 0 0\n"
    g = _read(text)
    assert g.vertex_ids.tolist() == [5, 9] and g.ii.tolist() == [0] and g.jj.tolist() == [1]
    assert read_g2o(io.StringIO(text), chart_2d="r3so3").chart == "r3so3"


def test_shared_files_match_gtsam_initial_error(posegraph_dir):
    g = read_g2o(posegraph_dir / "tinyGrid3D.g2o")
    assert (g.num_poses, g.num_edges) == (9, 11)
    # GTSAM 4.3: readG2o + graph.error(initial) = 143.31787355350406 (error = chi2 / 2)
    assert graph_chi2(g) / 2 == pytest.approx(143.31787355350406, rel=1e-10)
    m = read_g2o(posegraph_dir / "input_M3500_g2o.g2o")
    assert (m.num_poses, m.num_edges) == (3500, 5453) and m.is_planar()
    # GTSAM's Pose2 error of the 2D file (its BetweenFactor<Pose2> uses the SE(2) logarithm)
    assert graph_chi2(m) / 2 == pytest.approx(1317356.2725119137, rel=1e-9)


@pytest.mark.parametrize("text, pattern", [
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
     "EDGE_SE3:QUAT 0 1 1 0 x 0 0 0 1 " + INFO3 + "\n",
     r"line 3: EDGE_SE3:QUAT field 5 is 'x', expected a number"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
     "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + INFO3[:-3] + "\n",
     r"line 3: EDGE_SE3:QUAT expects 30 fields .*, got 29"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_XYZ 1 0 0 0\n", r"line 2: unsupported element 'VERTEX_XYZ'"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
     "EDGE_SE3:QUAT 0 4 1 0 0 0 0 0 1 " + INFO3 + "\n",
     r"line 3: EDGE_SE3:QUAT refers to vertex 4, which no VERTEX_SE3:QUAT line defines"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 0 1 0 0 0 0 0 1\n",
     r"line 2: vertex id 0 is defined twice, with other values on line 1"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 0\n",
     r"line 2: VERTEX_SE3:QUAT has a zero quaternion"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n", r"no edges"),
    ("# nothing\n", r"no vertices"),
    ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE2 1 0 0 0\n", r"line 2: 2D element in a file with 3D"),
    ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", r"line 2: EDGE_SE2 connects vertex 0 to itself"),
    ("VERTEX_SE2 a 0 0 0\n", r"line 1: VERTEX_SE2 field 1 is 'a', expected an integer vertex id"),
    ("VERTEX_SE2 0 0 0 nan\n", r"line 1: VERTEX_SE2 has a non-finite value"),
])
def test_malformed_input_names_line_and_expectation(text, pattern):
    with pytest.raises(G2OFormatError, match=pattern):
        _read(text)


def test_error_names_the_file_and_allow_no_edges(tmp_path):
    path = tmp_path / "bad.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(G2OFormatError) as err:
        read_g2o(path)
    assert str(path) in str(err.value) and err.value.line == 2
    assert isinstance(err.value, ValueError)
    only_vertices = read_g2o(io.StringIO("VERTEX_SE2 0 0 0 0\n"), allow_no_edges=True)
    assert only_vertices.num_poses == 1 and only_vertices.num_edges == 0
    assert only_vertices.information.shape == (0, 6, 6)
