"""Verification skips the registration of a candidate that the estimate puts beyond what any accepted loop
could be (the views' limit plus the drift bound), and decides every candidate as the full checks do."""
from __future__ import annotations

import math

import pytest
import torch

from slam.config import LoopClosureConfig
from slam.lie import quat_angle, se3_between, se3_compose, se3_exp
from slam.loop import verification
from slam.loop.verification import DriftLimits, verify_candidate
from slam.odometry.registration import RegistrationResult

D = torch.float64


def _pose(v):
    return se3_exp(torch.as_tensor(v, dtype=D))


def _registering(monkeypatch, T_ab):
    """``register`` replaced by one that measures ``T_ab`` with 200 inliers of 300 matches; returns its calls."""
    calls = []

    def fake(a, b, config, **kwargs):
        calls.append(1)
        return RegistrationResult(T_ab, 300, 200, 0.01, torch.eye(6, dtype=D), True, "",
                                  torch.zeros(0, 2, dtype=torch.long), torch.zeros(0, dtype=torch.bool))

    monkeypatch.setattr(verification, "register", fake)
    return calls


def test_a_candidate_beyond_reach_is_not_registered(monkeypatch):
    cfg = LoopClosureConfig()  # views at most 0.4 m / 40 deg apart
    limits = DriftLimits(0.3, 10.0)
    calls = _registering(monkeypatch, _pose([0.1, 0, 0, 0, 0, 0]))
    far = verify_candidate(None, None, _pose([0.75, 0, 0, 0, 0, 0]), limits, cfg)  # 0.4 + 0.3 < 0.75 m
    turned = verify_candidate(None, None, _pose([0, 0, 0, 0, 0, math.radians(55.0)]), limits, cfg)  # > 40 + 10 deg
    assert not calls and not far.accepted and not turned.accepted
    assert far.reason.startswith("contradicts the estimate") and "0.75 m" in far.reason and "0.70 m" in far.reason
    assert "55 deg" in turned.reason and "50 deg" in turned.reason
    near = verify_candidate(None, None, _pose([0.65, 0, 0, 0, 0, 0]), limits, cfg)  # within reach: registered
    assert len(calls) == 1 and not near.accepted and near.disagreement == pytest.approx(0.55)


@pytest.mark.parametrize("seed", range(3))
def test_decisions_are_those_of_the_full_checks(monkeypatch, seed):
    """Random measurements and estimates: accepted exactly when the measurement is within the views' limits
    and within the bound of the estimate (computed here from the poses), registered only when within reach."""
    cfg = LoopClosureConfig()
    limits = DriftLimits(0.3, 10.0)
    gen = torch.Generator().manual_seed(seed)
    skipped = accepted = 0
    for _ in range(200):
        T = _pose((torch.rand(6, generator=gen, dtype=D) - 0.5) * torch.tensor([0.8, 0.8, 0.4, 0.6, 0.6, 1.2], dtype=D))
        noise = (torch.rand(6, generator=gen, dtype=D) - 0.5) * torch.tensor([1.0, 1.0, 0.4, 0.2, 0.2, 0.3], dtype=D)
        est = se3_compose(T, _pose(noise))  # off the measurement by up to 0.7 m / 12 deg
        calls = _registering(monkeypatch, T)
        v = verify_candidate(None, None, est, limits, cfg)
        diff = se3_between(est, T)
        expected = (float(T[:3].norm()) <= cfg.max_translation
                    and math.degrees(float(quat_angle(T[3:]))) <= cfg.max_rotation_deg
                    and float(diff[:3].norm()) <= limits.translation
                    and math.degrees(float(quat_angle(diff[3:]))) <= limits.rotation_deg)
        assert v.accepted == expected, v.reason
        skipped += not calls
        accepted += v.accepted
    assert 20 < skipped < 180 and accepted >= 10, (skipped, accepted)  # the gate acted on some candidates, not all
