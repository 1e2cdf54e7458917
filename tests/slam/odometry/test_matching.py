"""Guided matching without the dense matrix (for the frame rate): the pairs within the radius, the ratio test
on them and numpy's popcount give the same matches as Kornia on the full (Na, Nb) matrix, on real kitchen
frames and on generated input full of ties, empty rows and degenerate positions."""
import kornia.feature as KF
import numpy as np
import pytest
import torch

from slam.config import override
from slam.odometry.config import MatchConfig
from slam.odometry.matching import (
    _FORBIDDEN,
    _popcount64,
    guided_pairs,
    hamming_distance,
    match_descriptors,
    match_features,
)


def _dense_mask(kp, uv, radius):
    """The guided mask as the first implementation formed it."""
    dx = kp[:, 0:1] - uv[None, :, 0]
    dy = kp[:, 1:2] - uv[None, :, 1]
    return dx * dx + dy * dy <= radius * radius


def _kornia_reference(desc_a, desc_b, allowed, config):
    """Kornia's matcher on the full distance matrix, forbidden pairs at _FORBIDDEN (the first implementation)."""
    dm = torch.where(allowed, hamming_distance(desc_a, desc_b), torch.full(allowed.shape, _FORBIDDEN))
    match = {"smnn": lambda: KF.match_smnn(desc_a, desc_b, config.ratio, dm=dm),
             "snn": lambda: KF.match_snn(desc_a, desc_b, config.ratio, dm=dm),
             "mnn": lambda: KF.match_mnn(desc_a, desc_b, dm=dm)}[config.method]
    _, idx = match()
    dist = dm[idx[:, 0], idx[:, 1]]
    keep = dist <= config.max_hamming
    return idx[keep], dist[keep]


def _pairs_of(mask):
    return torch.nonzero(mask)


def _sorted_rows(pairs):
    return pairs[torch.argsort(pairs[:, 0] * 1_000_000 + pairs[:, 1])]


@pytest.mark.parametrize("seed", range(8))
def test_guided_pairs_are_the_dense_masks_pairs(seed):
    g = torch.Generator().manual_seed(seed)
    n, m = int(torch.randint(0, 300, (1,), generator=g)), int(torch.randint(0, 300, (1,), generator=g))
    kp = torch.rand(n, 2, generator=g) * torch.tensor([640.0, 480.0])
    uv = torch.randn(m, 2, generator=g) * 200 + torch.tensor([320.0, 240.0])
    if m > 4:
        uv[0] = float("nan")
        uv[1] = torch.tensor([1e30, -1e30])
        uv[2] = float("inf")
    if n > 2 and m > 6:  # on the circle, to the float32 bit: the exact test must decide as the mask does
        uv[5] = kp[1] + torch.tensor([24.0, 32.0])  # 40 px away
        uv[6] = kp[2] + torch.tensor([0.0, -40.0])
    radius = [40.0, 40.0 * 320 / 640, 7.5, 100.0][seed % 4]
    ref = _pairs_of(_dense_mask(kp, uv, radius))
    got = guided_pairs(kp, uv, radius)
    assert got.dtype == torch.long and got.shape[1] == 2
    assert bool((got[1:, 0] >= got[:-1, 0]).all())  # ordered by i
    assert torch.equal(_sorted_rows(got), ref)
    if n > 2 and m > 6 and radius == 40.0:
        assert {(1, 5), (2, 6)} <= set(map(tuple, got.tolist()))  # the two on the circle count


def test_guided_pairs_edge_cases():
    assert guided_pairs(torch.zeros(0, 2), torch.zeros(3, 2), 40.0).shape == (0, 2)
    assert guided_pairs(torch.zeros(3, 2), torch.zeros(0, 2), 40.0).shape == (0, 2)
    far = guided_pairs(torch.zeros(2, 2), torch.full((2, 2), 500.0), 40.0)
    assert far.shape == (0, 2)
    same = guided_pairs(torch.full((3, 2), 5.0), torch.full((2, 2), 5.0), 1.0)  # everything in one cell
    assert same.tolist() == [[0, 0], [0, 1], [1, 0], [1, 1], [2, 0], [2, 1]]


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize("method", ["smnn", "snn"])
def test_pair_matching_equals_kornia_on_the_full_matrix(seed, method):
    g = torch.Generator().manual_seed(seed)
    n, m = int(torch.randint(2, 120, (1,), generator=g)), int(torch.randint(2, 120, (1,), generator=g))
    # few distinct descriptors: many equal distances (ties in the nearest and second nearest), zeros too
    palette = torch.randint(0, 256, (6, 32), generator=g, dtype=torch.uint8)
    desc_a = palette[torch.randint(0, 6, (n,), generator=g)].clone()
    desc_b = palette[torch.randint(0, 6, (m,), generator=g)].clone()
    flip = torch.rand(n, 32, generator=g) < 0.03
    desc_a[flip] ^= 1
    allowed = torch.rand(n, m, generator=g) < [0.02, 0.05, 0.2][seed % 3]
    allowed[0] = False  # a row without pairs
    if m > 3:
        allowed[1] = False
        allowed[1, 3] = True  # a row with one pair: its second nearest is _FORBIDDEN
    config = MatchConfig(method=method, max_hamming=[64.0, 256.0][seed % 2])
    ref = _kornia_reference(desc_a, desc_b, allowed, config)
    got = match_descriptors(desc_a, desc_b, True, config, allowed_pairs=_pairs_of(allowed))
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])
    # the same pairs in another order give the same matches
    perm = torch.randperm(int(allowed.sum()), generator=g)
    got2 = match_descriptors(desc_a, desc_b, True, config, allowed_pairs=_pairs_of(allowed)[perm])
    assert torch.equal(got2[0], ref[0]) and torch.equal(got2[1], ref[1])


def test_pair_matching_falls_back_to_the_dense_path():
    """Many allowed pairs (>= 25 %), mnn, or a ratio >= 1 (ties could pass): the dense matrix, as before."""
    g = torch.Generator().manual_seed(3)
    desc_a = torch.randint(0, 256, (30, 32), generator=g, dtype=torch.uint8)
    desc_b = torch.randint(0, 256, (25, 32), generator=g, dtype=torch.uint8)
    for density, config in ((0.5, MatchConfig()), (0.05, MatchConfig(method="mnn")),
                            (0.05, MatchConfig(ratio=1.0))):
        allowed = torch.rand(30, 25, generator=g) < density
        ref = _kornia_reference(desc_a, desc_b, allowed, config)
        got = match_descriptors(desc_a, desc_b, True, config, allowed_pairs=_pairs_of(allowed))
        assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])
    with pytest.raises(ValueError, match=r"allowed_pairs must have shape \(P, 2\)"):
        match_descriptors(desc_a, desc_b, True, allowed_pairs=torch.zeros(4, dtype=torch.long))
    none = match_descriptors(desc_a, desc_b, True, allowed_pairs=torch.zeros(0, 2, dtype=torch.long))
    assert none[0].shape == (0, 2) and none[1].shape == (0,)


def test_popcount_equals_python_bit_count():
    g = torch.Generator().manual_seed(0)
    x = torch.randint(-2**63, 2**63 - 1, (200, 4), generator=g, dtype=torch.int64)
    x[0, 0], x[0, 1], x[0, 2], x[0, 3] = -1, 0, -2**63, 2**63 - 1
    ref = torch.tensor([[bin(v & (2**64 - 1)).count("1") for v in row] for row in x.tolist()])
    assert torch.equal(_popcount64(x), ref)
    assert _popcount64(x[:, 0]).tolist() == ref[:, 0].tolist()
    assert _popcount64(torch.zeros(0, 4, dtype=torch.int64)).shape == (0, 4)


def test_guided_matching_on_kitchen_frames_equals_the_dense_one(redkitchen_dir):
    """Real frames with the default rig: the guided matches of a frame against the frames 1-10 before it
    are the dense mask's, through Kornia on the full matrix."""
    from slam.io import open_sequence
    from slam.odometry import extract_features, register
    from slam.odometry.config import OdometryConfig
    from slam.odometry.geometry import project, transform_points

    cfg = OdometryConfig()
    cfg = override(cfg, {
        "features.rgb_intrinsics": (525.0, 525.0, 320.0, 240.0),
        "features.rgb_from_depth_translation": (-0.025, 0.0, 0.0)})
    seq = open_sequence(redkitchen_dir)
    feats = {i: extract_features(seq[i].rgb, seq[i].depth, seq.K, cfg.features) for i in (300, 303, 310)}
    mc = cfg.registration.matching
    checked = 0
    for a, b in ((300, 303), (300, 310), (303, 310)):
        fa, fb = feats[a], feats[b]
        prior = register(fa, fb, cfg.registration).T_ab  # the motion, as a prior
        for good, pr in ((True, prior), (False, prior.clone().index_fill_(0, torch.tensor([0]), 0.3))):
            ia, ib = torch.nonzero(fa.valid).squeeze(1), torch.nonzero(fb.valid).squeeze(1)
            uv = project(transform_points(pr, fb.points[ib].double()), fa.K.double()).float()
            mask = _dense_mask(fa.keypoints[ia].float(), uv, mc.guided_radius_px)
            assert 0 < int(mask.sum()) < 0.25 * mask.numel()
            idx, dist = _kornia_reference(fa.descriptors[ia], fb.descriptors[ib], mask, mc)
            ref = torch.stack([ia[idx[:, 0]], ib[idx[:, 1]]], dim=1)
            got = match_features(fa, fb, mc, prior_ab=pr)
            assert got[0].shape[0] > (50 if good else 0)  # a poor prior (tx = 0.3 m) leaves a few
            assert torch.equal(got[0], ref) and torch.equal(got[1], dist)
            checked += 1
    assert checked == 6
    np.testing.assert_array_equal(hamming_distance(fa.descriptors[:5], fb.descriptors[:7]).numpy(),
                                  hamming_distance(fa.descriptors[:5], fb.descriptors[:7],
                                                   torch.cartesian_prod(torch.arange(5), torch.arange(7)))
                                  .reshape(5, 7).numpy())
