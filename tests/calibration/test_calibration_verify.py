"""Form fits used by verification, against exact synthetic shapes."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.calibration.verify import fit_plane, fit_sphere


def test_sphere_fit_recovers_diameter_from_a_cap() -> None:
    rng = np.random.default_rng(2)
    d = rng.normal(size=(3000, 3))
    d[:, 2] = -np.abs(d[:, 2])  # the half a scanner sees
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centre = np.array([10.0, -5.0, 600.0])
    pts = centre + 25.0 * d + rng.normal(0, 0.01, (3000, 3))
    c, r, rms = fit_sphere(pts)
    np.testing.assert_allclose(c, centre, atol=0.01)
    assert 2 * r == pytest.approx(50.0, abs=0.01)
    assert rms == pytest.approx(0.01 * np.sqrt(1.0), rel=0.3)


def test_plane_fit_flatness() -> None:
    rng = np.random.default_rng(4)
    uv = rng.uniform(-100, 100, (2000, 2))
    n = np.array([0.0, 0.1, -1.0]) / np.linalg.norm([0.0, 0.1, -1.0])
    a = np.cross(n, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    dev = rng.uniform(-0.02, 0.02, 2000)
    pts = np.array([0.0, 0.0, 650.0]) + uv[:, :1] * a + uv[:, 1:] * b + dev[:, None] * n
    normal, offset, flat = fit_plane(pts)
    sign = np.sign(normal @ n)
    assert sign * normal @ n == pytest.approx(1.0, abs=1e-6)
    assert sign * offset == pytest.approx(n @ [0.0, 0.0, 650.0], abs=0.01)
    # the fitted plane may tilt within the noise: peak-to-valley within 10 % of the true 0.04 mm
    assert flat == pytest.approx(dev.max() - dev.min(), rel=0.1)
