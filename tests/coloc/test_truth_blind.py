"""Estimators must not read frame.truth: identical output when every truth field is scrambled."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from infra_frames import infra_frames, scrambled  # noqa: E402

from coloc.core.models import MotionParams  # noqa: E402
from coloc.methods.fg_topology import FgTopologyInfra  # noqa: E402
from coloc.methods.infra import InfraMethodParams, RsuBpInfra, SmeInfra  # noqa: E402


@pytest.mark.parametrize("cls", [RsuBpInfra, SmeInfra, FgTopologyInfra])
def test_infra_methods_ignore_truth(cls):
    frames = infra_frames(n_steps=20, n_veh=5)
    rng = np.random.default_rng(0)
    params = InfraMethodParams(motion=MotionParams(sigma_cross=0.1), rsu_bp_particles=60)
    a, b = cls(params), cls(params)
    for f in frames:
        ra, rb = a.step(f), b.step(scrambled(f, rng))
        assert ra.mean.tobytes() == rb.mean.tobytes() and ra.cov.tobytes() == rb.cov.tobytes()
        np.testing.assert_array_equal(ra.covered, rb.covered)
        if ra.v2f_assignment is not None:
            np.testing.assert_array_equal(ra.v2f_assignment, rb.v2f_assignment)
