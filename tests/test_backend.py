"""The SLAM back end: per-kind kernels, DCS against its closed form, a false loop switched off."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from slam.backend import DCS, EdgeKindKernel, PoseGraphBackend, make_loop_kernel
from slam.config import BackendConfig
from slam.graph import Cauchy
from slam.keyframe_graph import EdgeKind, KeyframeGraph
from slam.lie import se3_between, se3_compose, se3_exp, se3_identity, se3_log

D = torch.float64
SCALE = {EdgeKind.ODOMETRY: 1.0, EdgeKind.LOOP: 1.0}


def test_dcs_matches_its_closed_form_and_derivative():
    k = DCS(width=2.0)
    phi = 4.0
    s = torch.linspace(0.0, 60.0, 601, dtype=D)
    rho, w = k(s)
    assert torch.allclose(rho[s <= phi], s[s <= phi]) and torch.all(w[s <= phi] == 1)
    big = s > phi
    assert torch.allclose(rho[big], phi * (3 * s[big] - phi) / (phi + s[big]))
    assert torch.allclose(w[big], (2 * phi / (phi + s[big])) ** 2)
    assert float(rho.max()) < 3 * phi  # bounded: a wrong loop costs at most 3 phi
    # the weight is rho'(s): central finite differences in float64
    h = 1e-6
    for x in (0.5, 3.0, 5.0, 17.0, 55.0):
        fd = (k(torch.tensor([x + h], dtype=D))[0] - k(torch.tensor([x - h], dtype=D))[0]) / (2 * h)
        assert float(fd) == pytest.approx(float(k(torch.tensor([x], dtype=D))[1]), rel=1e-6)
    with pytest.raises(ValueError):
        DCS(width=0.0)


def test_edge_kind_kernel_routes_each_kind_to_its_kernel():
    kinds = torch.tensor([0, 1, 0, 1, 1])
    s = torch.tensor([1.0, 40.0, 40.0, 2.0, 400.0], dtype=D)
    kern = EdgeKindKernel(kinds, {0: Cauchy(3.0), 1: DCS(3.0)})
    rho, w = kern(s)
    r0, w0 = Cauchy(3.0)(s[kinds == 0])
    r1, w1 = DCS(3.0)(s[kinds == 1])
    assert torch.allclose(rho[kinds == 0], r0) and torch.allclose(w[kinds == 0], w0)
    assert torch.allclose(rho[kinds == 1], r1) and torch.allclose(w[kinds == 1], w1)
    plain = EdgeKindKernel(kinds, {0: None, 1: DCS(3.0)})
    rho, w = plain(s)
    assert torch.equal(rho[kinds == 0], s[kinds == 0]) and torch.all(w[kinds == 0] == 1)
    with pytest.raises(ValueError):
        kern(s[:3])
    assert isinstance(make_loop_kernel("dcs", None), DCS) and make_loop_kernel("none", None) is None


def _square_walk(false_loop: bool):
    """A 4 x 4 m square walked twice by 0.5 m steps with odometry that turns 0.4 deg too much per step,
    loops from the second lap to the first (the first closing the first lap), and optionally one false
    loop (2 m and 29 deg off)."""
    step, turn = 0.5, math.pi / 2
    truth = [se3_identity(dtype=D)]
    moves = []
    for lap in range(2):
        for side in range(4):
            for k in range(8):
                last = k == 7
                m = se3_exp(torch.tensor([step, 0, 0, 0, 0, turn if last else 0.0], dtype=D))
                moves.append(m)
                truth.append(se3_compose(truth[-1], m))
    g = KeyframeGraph()
    g.add_keyframe(truth[0])
    bias = se3_exp(torch.tensor([0, 0, 0, 0, 0, math.radians(0.4)], dtype=D))
    info = torch.diag(torch.tensor([100.0, 100, 100, 1000, 1000, 1000], dtype=D))
    for j, m in enumerate(moves, start=1):
        g.add_odometry(j - 1, se3_compose(m, bias), info, se3_compose(g.estimate(j - 1), se3_compose(m, bias)))
    loops = []
    for a in range(0, 30, 4):
        b = a + 32
        loops.append(g.add_loop(a, b, se3_between(truth[a], truth[b]), info))
    bad = None
    if false_loop:
        wrong = se3_compose(se3_between(truth[10], truth[50]), se3_exp(torch.tensor([2.0, 0, 0, 0, 0, 0.5], dtype=D)))
        bad = g.add_loop(10, 50, wrong, info)
    return g, torch.stack(truth), loops, bad


def _error(poses, truth):
    rel = se3_between(poses[0].expand_as(poses), poses)
    ref = se3_between(truth[0].expand_as(truth), truth)
    return float(se3_log(se3_between(rel, ref))[:, :3].norm(dim=1).max())


def test_loops_correct_the_drift():
    g, truth, _, _ = _square_walk(False)
    odo_err = _error(g.odometry_poses(), truth)
    res = PoseGraphBackend(BackendConfig(), SCALE).optimize(g)
    assert odo_err > 0.5 and _error(res.poses, truth) < 0.1 * odo_err, (odo_err, _error(res.poses, truth))
    assert all(w > 0.9 for w in res.loop_weights.values())


@pytest.mark.parametrize("loop_kernel", ["dcs", "gnc"])
def test_robust_loop_kernel_switches_a_false_loop_off(loop_kernel):
    g, truth, loops, bad = _square_walk(True)
    cfg = dataclasses.replace(BackendConfig(), loop_kernel=loop_kernel)
    res = PoseGraphBackend(cfg, SCALE).optimize(g)
    assert res.loop_weights[bad] < cfg.switch_off_weight
    assert all(res.loop_weights[e] > 0.5 for e in loops)
    assert _error(res.poses, truth) < 0.1
    assert res.solves == (cfg.gnc_steps if loop_kernel == "gnc" else 1)
    # a quadratic loop term is pulled by the false loop
    plain = PoseGraphBackend(dataclasses.replace(BackendConfig(), loop_kernel="none"), SCALE).optimize(g)
    assert _error(plain.poses, truth) > 3 * _error(res.poses, truth)
    # Cauchy (the odometry's kernel) down-weights it but is still pulled (measured 0.19 m vs 0.08 m)
    cauchy = PoseGraphBackend(dataclasses.replace(BackendConfig(), loop_kernel=None), SCALE).optimize(g)
    assert _error(cauchy.poses, truth) > 1.5 * _error(res.poses, truth)


def test_online_optimisation_is_bounded_and_inactive_edges_are_left_out():
    g, truth, loops, bad = _square_walk(True)
    cfg = dataclasses.replace(BackendConfig(), online_max_iterations=2)
    res = PoseGraphBackend(cfg, SCALE).optimize(g, online=True)
    assert res.iterations <= 2 and res.status in ("max_iterations", "converged", "lambda_limit")
    g.edges[bad].active = False
    res = PoseGraphBackend(BackendConfig(), SCALE).optimize(g)
    assert bad not in res.loop_weights and set(res.loop_weights) == set(loops)
    empty = KeyframeGraph()
    empty.add_keyframe(se3_identity(dtype=D))
    with pytest.raises(ValueError, match="no edges"):
        PoseGraphBackend(BackendConfig(), SCALE).optimize(empty)
    with pytest.raises(ValueError, match="loop kernel"):
        PoseGraphBackend(dataclasses.replace(BackendConfig(), loop_kernel="bogus"), SCALE)
