"""Translation averaging on exact synthetic view graphs: positions up to a similarity, outlier directions."""

import numpy as np

from mvrecon.geometry.sim3 import umeyama
from mvrecon.sfm.translation_averaging import average_translations


def directions_graph(n=30, density=0.3, outliers=0.2, seed=1, centers=None):
    rng = np.random.default_rng(seed)
    C = rng.normal(size=(n, 3)) if centers is None else centers
    ij = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < density])
    d = C[ij[:, 1]] - C[ij[:, 0]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    bad = rng.random(len(ij)) < outliers
    d[bad] = rng.normal(size=(int(bad.sum()), 3))
    return C, ij, d, bad


def similarity_error(est, truth):
    """Largest centre error after the best similarity, relative to the spread of the true centres."""
    s = umeyama(est, truth)
    return np.abs(s.apply(est) - truth).max() / np.ptp(truth, axis=0).max()


def test_positions_are_recovered_up_to_a_similarity():
    C, ij, d, _ = directions_graph(outliers=0.0)
    result = average_translations(len(C), ij, d)
    assert result.solved.all() and result.inliers.all()
    assert similarity_error(result.centers, C) < 1e-6


def test_outlier_directions_are_rejected():
    C, ij, d, bad = directions_graph(outliers=0.2)
    result = average_translations(len(C), ij, d)
    assert result.solved.all()
    true = C[ij[:, 1]] - C[ij[:, 0]]
    off = np.degrees(np.arccos(np.clip(np.einsum("mi,mi->m", true / np.linalg.norm(true, axis=1, keepdims=True),
                                                 d / np.linalg.norm(d, axis=1, keepdims=True)), -1, 1)))
    assert not (result.inliers & (off > 10)).any()  # only outliers that happen to point nearly right are kept
    assert (result.inliers & ~bad).sum() >= 0.8 * (~bad).sum()
    assert similarity_error(result.centers, C) < 1e-4


def test_an_orbit_of_cameras_is_recovered():
    """Cameras on a circle with neighbours up to three apart: the directions of an orbit around an object."""
    n = 24
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    C = np.c_[np.cos(a), np.sin(a), 0.1 * np.sin(3 * a)]
    ij = np.array([(i, (i + k) % n) for i in range(n) for k in (1, 2, 3)])
    d = C[ij[:, 1]] - C[ij[:, 0]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    result = average_translations(n, ij, d)
    assert result.solved.all()
    assert similarity_error(result.centers, C) < 1e-5
