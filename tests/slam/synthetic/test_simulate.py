"""The simulated Manhattan-world pose graphs (benchmarks.simulate): determinism, the parallel chain
composition against a sequential loop, the noise-free case, the noise law (chi-square statistics at the
ground truth) and an end-to-end optimisation that must reach the expected minimum.

Statistical checks use a fixed seed (so they are deterministic) and a tolerance of 4 standard deviations
of the statistic under the generator's stated law: a generator that does not follow the law fails them.
"""
import math

import pytest
import torch

from benchmarks.simulate import SimulatedGraph, compose_chain, manhattan_world
from slam.eval.align import umeyama_alignment
from slam.graph import CHI2_95_6DOF, edge_chi2, edge_residuals, graph_chi2, optimize
from slam.lie import quat_to_rotmat, se3_between, se3_compose, se3_exp, se3_identity

F64 = torch.float64


def _pose_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest difference between poses ``a (N, 7)`` and ``b (N, 7)``: translations, and quaternions up to
    their sign (q and -q are one rotation; fixing ``qw >= 0`` is ambiguous at a yaw of 180 degrees)."""
    dq = torch.minimum((a[:, 3:] - b[:, 3:]).abs().amax(-1), (a[:, 3:] + b[:, 3:]).abs().amax(-1))
    return max(float((a[:, :3] - b[:, :3]).abs().max()), float(dq.max()))


def _aligned_rmse(est: torch.Tensor, ref: torch.Tensor) -> float:
    """RMSE of the positions of ``est (N, 7)`` after the rigid (Umeyama) alignment onto ``ref (N, 7)``."""
    R, t, _ = umeyama_alignment(est[:, :3].double(), ref[:, :3].double())
    err = est[:, :3].double() @ R.T + t - ref[:, :3].double()
    return float(err.pow(2).sum(-1).mean().sqrt())


# ------------------------------------------------------------------------------------------------
# determinism and structure
# ------------------------------------------------------------------------------------------------
def test_same_seed_same_graph_other_seed_other_graph():
    a, b, c = manhattan_world(300, seed=3), manhattan_world(300, seed=3), manhattan_world(300, seed=4)
    for x, y in ((a.graph.ii, b.graph.ii), (a.graph.jj, b.graph.jj), (a.graph.poses, b.graph.poses),
                 (a.graph.measurements, b.graph.measurements), (a.graph.information, b.graph.information),
                 (a.ground_truth, b.ground_truth)):
        assert torch.equal(x, y)
    assert a.num_loops == b.num_loops
    # another seed: another walk (different positions) and other noise
    assert not torch.equal(a.ground_truth[:, :3], c.ground_truth[:, :3])
    assert not torch.allclose(a.graph.measurements[:299], c.graph.measurements[:299])


def test_structure_of_the_walk():
    n = 600
    sim = manhattan_world(n, seed=1)
    g, gt = sim.graph, sim.ground_truth
    assert isinstance(sim, SimulatedGraph)
    assert g.num_poses == n and gt.shape == (n, 7) and g.dtype == F64
    assert g.num_edges == n - 1 + sim.num_loops and sim.num_loops > 0.1 * n
    # odometry first: edges (k, k + 1); then loops from an earlier pose to a later one in the same cell
    assert torch.equal(g.ii[:n - 1], torch.arange(n - 1)) and torch.equal(g.jj[:n - 1], torch.arange(1, n))
    li, lj = g.ii[n - 1:], g.jj[n - 1:]
    assert bool((li < lj - 1).all())
    assert torch.equal(gt[li, :3], gt[lj, :3])
    # positions on the integer grid, two floors, one-metre steps, pose 0 the identity
    assert torch.equal(gt[:, :3], gt[:, :3].round())
    assert set(gt[:, 2].tolist()) == {0.0, 1.0}
    assert torch.equal((gt[1:, :3] - gt[:-1, :3]).abs().sum(-1), torch.ones(n - 1, dtype=F64))
    assert torch.equal(gt[0], se3_identity(dtype=F64))
    # quaternions are unit (the graph validated them to 1e-3; here to rounding)
    for p in (gt, g.poses, g.measurements):
        assert torch.allclose(p[:, 3:].norm(dim=-1), torch.ones(p.shape[0], dtype=F64), atol=1e-12)


def test_tilt_law_is_the_same_for_every_heading():
    # R = Rz(yaw) exp([roll, pitch, 0]): the angle between the body z axis and the world z axis has
    # E[angle^2] = 2 tilt^2 whatever the heading (a single rotation vector [roll, pitch, yaw] would give
    # 0.64^2 and 0.3^2 of that for the yaws 180 and 270 degrees).
    tilt = 0.05
    sim = manhattan_world(4000, seed=0, tilt=tilt)
    R = quat_to_rotmat(sim.ground_truth[:, 3:])
    angle2 = torch.arccos(R[:, 2, 2].clamp(-1.0, 1.0)) ** 2
    heading = torch.remainder(torch.round(torch.atan2(R[:, 1, 0], R[:, 0, 0]) / (math.pi / 2)), 4)
    for h in range(4):
        a2 = angle2[heading == h]
        assert a2.numel() > 500
        # angle^2 / tilt^2 ~ chi2(2) (small angles): mean 2, std 2 per sample; 4 standard errors
        assert abs(float(a2.mean()) / tilt ** 2 - 2.0) < 4 * 2.0 / math.sqrt(a2.numel()), h


def test_float32_graph():
    sim = manhattan_world(50, seed=0, dtype=torch.float32)
    assert sim.graph.dtype == torch.float32 and sim.ground_truth.dtype == torch.float32
    ref = manhattan_world(50, seed=0)
    assert torch.allclose(sim.graph.poses.double(), ref.graph.poses, atol=1e-5)


@pytest.mark.parametrize("kwargs", [{"num_poses": 1}, {"num_poses": 2.5}, {"sigma_t": -0.1},
                                    {"sigma_r": float("nan")}, {"tilt": -1.0}, {"dtype": torch.long},
                                    {"sigma_t": 1e-200}])
def test_bad_arguments(kwargs):
    kw = {"num_poses": 20, "seed": 0}
    kw.update(kwargs)
    with pytest.raises(ValueError):
        manhattan_world(**kw)


# ------------------------------------------------------------------------------------------------
# compose_chain
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [0, 1, 2, 7, 64, 100])
def test_compose_chain_equals_sequential_loop(k):
    gen = torch.Generator().manual_seed(k)
    first = se3_exp(torch.randn(6, generator=gen, dtype=F64))
    steps = se3_exp(0.5 * torch.randn(k, 6, generator=gen, dtype=F64))
    ref = [first]
    for s in steps:
        ref.append(se3_compose(ref[-1], s))
    out = compose_chain(first, steps)
    assert out.shape == (k + 1, 7) and out.dtype == F64
    # no canonicalisation on either side: the quaternion products are the same up to rounding
    assert torch.allclose(out, torch.stack(ref), atol=1e-12, rtol=0)


def test_compose_chain_follows_the_dtype_of_steps():
    steps = se3_exp(0.1 * torch.randn(5, 6, generator=torch.Generator().manual_seed(0)))
    out = compose_chain(se3_identity(dtype=F64), steps)
    assert out.dtype == torch.float32
    assert torch.allclose(out.double(), compose_chain(se3_identity(dtype=F64), steps.double()), atol=1e-5)


@pytest.mark.parametrize("first_shape, steps_shape", [((6,), (3, 7)), ((1, 7), (3, 7)), ((7,), (7,)),
                                                      ((7,), (3, 6)), ((7,), (2, 3, 7))])
def test_compose_chain_rejects_bad_shapes(first_shape, steps_shape):
    with pytest.raises(ValueError, match="shape"):
        compose_chain(torch.zeros(first_shape, dtype=F64), torch.zeros(steps_shape, dtype=F64))


def test_compose_chain_rejects_integer_steps():
    with pytest.raises(ValueError, match="floating"):
        compose_chain(se3_identity(dtype=F64), torch.zeros(2, 7, dtype=torch.long))


# ------------------------------------------------------------------------------------------------
# the noise model
# ------------------------------------------------------------------------------------------------
def test_zero_noise_measurements_are_the_true_relative_poses():
    # sigma = 0: exact measurements; the (infinite) information is replaced by 1 (documented)
    sim = manhattan_world(400, seed=2, sigma_t=0.0, sigma_r=0.0)
    g, gt = sim.graph, sim.ground_truth
    assert _pose_difference(g.measurements, se3_between(gt[g.ii], gt[g.jj])) < 1e-14
    # the odometry chain composed over 399 steps: rounding only
    assert _pose_difference(g.poses, gt) < 1e-11
    assert torch.equal(g.information, torch.eye(6, dtype=F64).expand(g.num_edges, 6, 6))
    assert graph_chi2(g.with_poses(gt)) < 1e-20
    res = optimize(g)
    assert str(res.status) == "converged" and res.chi2 < 1e-20


def test_zero_rotation_noise_only():
    # sigma_r = 0 alone: rotations exact (unit weight), translations noisy with weight sigma_t^-2
    sim = manhattan_world(200, seed=2, sigma_t=0.1, sigma_r=0.0)
    info = sim.graph.information[0]
    assert torch.allclose(torch.diagonal(info), torch.tensor([100.0] * 3 + [1.0] * 3, dtype=F64), rtol=1e-14)
    assert torch.equal(info, torch.diag(torch.diagonal(info)))
    r, _ = edge_residuals(sim.ground_truth, sim.graph.ii, sim.graph.jj, sim.graph.measurements)
    assert float(r[:, 3:].abs().max()) < 1e-12 and float(r[:, :3].abs().max()) > 0.1


@pytest.mark.parametrize("sigma_t, sigma_r", [(0.05, 0.01), (0.2, 0.1)])
def test_residuals_at_the_ground_truth_follow_the_stated_law(sigma_t, sigma_r):
    # at the ground truth r = Log(exp(n)^-1) = -n: whitened, each of the 6 components is N(0, 1) and the
    # chi2 of an edge is chi-square with 6 degrees of freedom (mean 6, variance 12)
    sim = manhattan_world(2000, seed=5, sigma_t=sigma_t, sigma_r=sigma_r)
    g = sim.graph
    r, _ = edge_residuals(sim.ground_truth, g.ii, g.jj, g.measurements)
    e = g.num_edges
    chi2 = edge_chi2(r, g.information)
    assert abs(float(chi2.mean()) - 6.0) < 4 * math.sqrt(12.0 / e)
    w = r / torch.tensor([sigma_t] * 3 + [sigma_r] * 3, dtype=F64)  # whitened (diagonal information)
    assert torch.allclose(w.pow(2).sum(-1), chi2, rtol=1e-10)
    assert float(w.mean(0).abs().max()) < 4 / math.sqrt(e)  # mean 0, standard error 1/sqrt(E)
    assert float((w.var(0) - 1.0).abs().max()) < 4 * math.sqrt(2.0 / e)  # var 1, standard error sqrt(2/E)
    frac = float((chi2 > CHI2_95_6DOF).double().mean())  # the 95% quantile of chi2(6)
    assert abs(frac - 0.05) < 4 * math.sqrt(0.05 * 0.95 / e)


# ------------------------------------------------------------------------------------------------
# end to end
# ------------------------------------------------------------------------------------------------
def test_optimize_reaches_the_expected_minimum_and_the_ground_truth():
    # With Gaussian noise and a (nearly) linear problem, the minimum of chi2 over the 6 (N - 1) free
    # parameters (the gauge removes 6) is chi-square with 6 E - 6 (N - 1) = 6 * num_loops degrees of
    # freedom: mean 6 L, standard deviation sqrt(12 L). The odometry edges alone could be fitted exactly;
    # every loop adds 6 redundant residual components.
    sim = manhattan_world(400, seed=0)
    g, gt = sim.graph, sim.ground_truth
    L = sim.num_loops
    assert L > 50
    res = optimize(g)
    assert str(res.status) == "converged", res.message
    assert res.chi2 < graph_chi2(g) * 1e-2  # the odometry guess is far from the minimum
    assert abs(res.chi2 - 6 * L) < 4 * math.sqrt(12 * L), (res.chi2, 6 * L)
    # at least as good as the ground truth (which has chi2 ~ 6 E > 6 L)
    assert res.chi2 <= graph_chi2(g.with_poses(gt))
    ate_init, ate_opt = _aligned_rmse(g.poses, gt), _aligned_rmse(res.graph.poses, gt)
    # seed 0: 1.08 m -> 0.15 m (the rotation drift between loops is what remains)
    assert ate_opt < 0.25 * ate_init, (ate_opt, ate_init)
