"""Rotation averaging on exact synthetic view graphs: outlier pairs found, rotations recovered, components."""

import numpy as np
from scipy.spatial.transform import Rotation

from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.sfm.rotation_averaging import average_rotations, edge_residuals_deg


def view_graph(n=40, density=0.4, outliers=0.2, seed=0):
    """(true cam_from_world rotations, edges ij, relative rotations R_j R_i^T with `outliers` of them replaced
    by random rotations, outlier mask). Every image keeps at least four correct edges."""
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    ij = np.array([(i, j) for i in range(n) for j in range(i + 1, n) if rng.random() < density])
    Rij = np.einsum("mab,mcb->mac", R[ij[:, 1]], R[ij[:, 0]])
    bad = rng.random(len(ij)) < outliers
    good_degree = np.bincount(ij[~bad].ravel(), minlength=n)
    assert good_degree.min() >= 4
    Rij[bad] = Rotation.random(int(bad.sum()), random_state=seed + 1).as_matrix()
    return R, ij, Rij, bad


def errors_deg(R_est, R_true, nodes):
    """Per-node rotation errors after the best global rotation (the gauge) is taken out."""
    G = R_est[nodes[0]].T @ R_true[nodes[0]]
    return np.array([np.degrees(Rotation.from_matrix(R_est[i] @ G @ R_true[i].T).magnitude()) for i in nodes])


def test_rotations_are_recovered_with_a_fifth_of_the_pairs_wrong():
    R, ij, Rij, bad = view_graph()
    result = average_rotations(len(R), ij, Rij, np.full(len(ij), 100.0))
    assert result.solved.all()
    assert errors_deg(result.R, R, np.arange(len(R))).max() < 0.1
    assert np.array_equal(result.inliers, ~bad)  # every outlier found, no correct pair lost


def test_noisy_relative_rotations_average_to_within_their_noise():
    R, ij, Rij, bad = view_graph(outliers=0.0, seed=3)
    rng = np.random.default_rng(3)
    noisy = np.einsum("mab,mbc->mac", Rotation.from_rotvec(rng.normal(0, np.radians(0.5), (len(ij), 3))).as_matrix(),
                      Rij)
    result = average_rotations(len(R), ij, noisy, np.ones(len(ij)))
    assert result.inliers.all()
    assert np.median(errors_deg(result.R, R, np.arange(len(R)))) < 0.5  # each edge 0.87 deg off
    assert np.median(edge_residuals_deg(result.R, ij, noisy)) < 1.0


def test_the_largest_of_two_components_is_averaged():
    R, ij, Rij, _ = view_graph(n=30, outliers=0.0, density=0.5, seed=5)
    split = (ij < 12).all(axis=1) | (ij >= 12).all(axis=1)
    result = average_rotations(len(R), ij[split], Rij[split], np.ones(int(split.sum())))
    assert np.array_equal(result.solved, np.arange(30) >= 12)
    assert errors_deg(result.R, R, np.arange(12, 30)).max() < 0.01


def test_a_street_whose_average_shonan_cannot_certify_is_still_averaged():
    """60 images along a street, each paired with the next four, every relative rotation 1.5 deg off at random:
    no rank up to 6 of GTSAM's Shonan averaging is certified optimal there (on a 100-frame street rendered from
    another seed the global mapper failed with it), so the local optimum at rank 3 is kept. Every rotation comes
    out, as near the truth as at the seeds Shonan certifies (medians 1.4-2.4 deg there: the error of a chain
    grows along it)."""
    rng = np.random.default_rng(2)
    n = 60
    R = np.array([angle_axis_to_rotmat(rng.normal(size=3) * 0.3) for _ in range(n)])
    ij = np.array([(i, j) for i in range(n) for j in range(i + 1, min(n, i + 5))])
    Rij = np.array([angle_axis_to_rotmat(np.radians(1.5) * rng.normal(size=3)) @ R[j] @ R[i].T for i, j in ij])
    result = average_rotations(n, ij, Rij, np.ones(len(ij)))
    U, _, Vt = np.linalg.svd(np.einsum("nji,njk->ik", result.R, R))  # the gauge that fits every rotation best
    errors = np.degrees(Rotation.from_matrix(result.R @ (U @ Vt) @ R.transpose(0, 2, 1)).magnitude())
    assert result.solved.all() and result.inliers.mean() > 0.95
    assert np.median(errors) < 3.0 and errors.max() < 6.0
