"""Shared fixtures: the reference machine and an identified pose on it."""

from __future__ import annotations

import numpy as np
import pytest

from xmalign.formats.pose import LaunchPose
from xmalign.machine import Machine, default_machine_path, load_machine


@pytest.fixture
def machine() -> Machine:
    return load_machine(default_machine_path())


def make_pose(
    position_mm=(100.0, 100.0, -680.0),
    gamma_deg: float = 30.0,
    sigma_mm: float = 0.05,
    sigma_gamma_rad: float = 20e-6,
    offsets_deg: dict | None = None,
) -> LaunchPose:
    covariance = np.diag([sigma_mm**2] * 3 + [sigma_gamma_rad**2])
    offsets = {"c2": 0.01, "c3": -0.02, "c4": 0.005} if offsets_deg is None else offsets_deg
    return LaunchPose(
        position_mm=np.array(position_mm, dtype=float),
        gamma_rad=np.radians(gamma_deg),
        covariance=covariance,
        encoder_offsets_rad={k: np.radians(v) for k, v in offsets.items()},
    )


@pytest.fixture
def pose() -> LaunchPose:
    return make_pose()
