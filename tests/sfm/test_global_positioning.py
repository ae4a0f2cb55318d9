"""Global positioning on exact synthetic tracks: centres up to a similarity, collinear cameras that pair
directions cannot place, a walk round a block that random centres cannot start, a camera that misses its points
placed last, the starts solved from, and a flipped camera found by its rays."""

import numpy as np
import pytest
from scipy.sparse import bsr_matrix, csr_matrix

from mvrecon import database
from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.geometry.sim3 import umeyama
from mvrecon.sfm import global_positioning
from mvrecon.sfm.config import MapperConfig
from mvrecon.sfm.global_mapper import GlobalMapper
from mvrecon.sfm.global_positioning import (
    _camera_blocks,
    _pair_slots,
    _reduce_points,
    _solve_reduced,
    _split_long_tracks,
    global_positions,
    outlier_cameras,
    solve_positions,
)
from mvrecon.sfm.translation_averaging import average_translations
from tests.sfm.test_mapper import synthetic_database
from tests.sfm.test_translation_averaging import similarity_error


def rays(C, X, cam, point):
    v = X[point] - C[cam]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_centres_are_recovered_up_to_a_similarity():
    """30 cameras, 600 points each seen by 2-5 of them, exact rays: centres from a random start."""
    rng = np.random.default_rng(1)
    C, X = rng.normal(size=(30, 3)) * 2, rng.normal(size=(600, 3))
    views = [rng.choice(30, rng.integers(2, 6), replace=False) for _ in range(600)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(600), [len(v) for v in views])
    found, points = solve_positions(cam, point, rays(C, X, cam, point), 30, 600)
    assert similarity_error(found, C) < 1e-3
    off = np.linalg.norm(umeyama(found, C).apply(points) - X, axis=1)  # the points, by the centres' similarity
    assert np.mean(off < 1e-2) > 0.95


def test_long_tracks_are_solved_as_parts_past_the_budget_and_the_cameras_are_placed():
    """40 cameras on a ring round 300 points, each point seen by 25-40 of them, exact rays. Within the budget nothing
    is split. Past it, each point of more than K views becomes the fewest parts of at most K, as equal as can be, K
    the largest that keeps the pairs of observations of a point, summed, within the budget; every ray is kept, and
    the centres solved from the parts are the true ones up to a similarity."""
    rng = np.random.default_rng(3)
    n, m, budget = 40, 300, 120_000
    angle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    C = np.c_[6 * np.cos(angle), 6 * np.sin(angle), rng.normal(scale=0.3, size=n)]
    X = rng.normal(size=(m, 3))
    views = [np.sort(rng.choice(n, rng.integers(25, 41), replace=False)) for _ in range(m)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(m), [len(v) for v in views])
    assert np.array_equal(_split_long_tracks(point, budget=np.sum(np.bincount(point) ** 2)), point)
    split = _split_long_tracks(point, budget)
    K = np.bincount(split).max()

    def pairs(k):  # the sum of squares of the fewest parts of at most k, as equal as can be
        return sum(np.sum(np.bincount(np.arange(len(v)) % -(-len(v) // k)) ** 2) for v in views)

    assert 10 <= K < 25 and np.sum(np.bincount(split) ** 2) == pairs(K) <= budget < pairs(K + 1)
    for p in range(m):
        sizes = np.bincount(split[point == p])
        sizes = sizes[sizes > 0]
        assert len(sizes) == -(-len(views[p]) // K) and np.ptp(sizes) <= 1
        assert not np.isin(split[point == p], split[point != p]).any()
    ids, split = np.unique(split, return_inverse=True)
    found, _ = solve_positions(cam, split, rays(C, X, cam, point), n, len(ids))
    assert similarity_error(found, C) < 1e-3


def test_centres_are_the_same_whether_the_reduced_system_is_factorised_dense_or_sparse_or_solved_iteratively(
        monkeypatch):
    """The dense Cholesky, the sparse LU and the conjugate gradients solve the same reduced systems: the same
    centres to 1e-9 of their spread, from noisy rays (so that the loss's weights matter)."""
    rng = np.random.default_rng(2)
    C, X = rng.normal(size=(20, 3)) * 2, rng.normal(size=(400, 3))
    views = [rng.choice(20, rng.integers(2, 6), replace=False) for _ in range(400)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(400), [len(v) for v in views])
    v = rays(C, X, cam, point) + rng.normal(scale=0.003, size=(len(cam), 3))
    iterative = global_positioning._conjugate_gradients
    solved_iteratively = []

    def spy(S, rhs):
        x = iterative(S, rhs)
        solved_iteratively.append(x is not None)
        return x

    monkeypatch.setattr(global_positioning, "_conjugate_gradients", spy)
    found = {}
    for solver, share, min_cameras in (("dense", 0.0, 10**6), ("lu", 2.0, 10**6), ("cg", 2.0, 1)):
        monkeypatch.setattr(global_positioning, "_DENSE_SHARE", share)
        monkeypatch.setattr(global_positioning, "_ITERATIVE_MIN_CAMERAS", min_cameras)
        found[solver], _ = solve_positions(cam, point, v, 20, 400)
    assert solved_iteratively and all(solved_iteratively)  # every step of the last run, and only of it
    assert np.abs(found["dense"] - found["lu"]).max() < 1e-9
    assert np.abs(found["cg"] - found["lu"]).max() < 1e-9
    assert similarity_error(found["dense"], C) < 0.02


def test_conjugate_gradients_solve_a_block_sparse_system_and_leave_an_indefinite_one_to_the_lu(monkeypatch):
    """A chain of 600 cameras, each coupled to the next: solved to 1e-9 of the exact solution; stopped short of
    convergence by the iteration cap, they give None and the direct solvers decide. With one camera's diagonal
    block indefinite (so the system is not positive definite), they give None, and `_solve_reduced` solves it by
    the LU."""
    rng = np.random.default_rng(3)
    num = 600
    block = np.arange(3 * num) // 3
    dense = rng.normal(size=(3 * num, 3 * num)) * 0.1 * (np.abs(np.subtract.outer(block, block)) <= 1)
    dense = dense @ dense.T + np.eye(3 * num)  # block pentadiagonal, positive definite
    rhs = rng.normal(size=3 * num)
    x = global_positioning._conjugate_gradients(bsr_matrix(dense, blocksize=(3, 3)), rhs)
    exact = np.linalg.solve(dense, rhs)
    assert np.abs(x - exact).max() < 1e-9 * np.abs(exact).max()
    with monkeypatch.context() as m:
        m.setattr(global_positioning, "_CG_MAX_ITERATIONS", 2)
        assert global_positioning._conjugate_gradients(bsr_matrix(dense, blocksize=(3, 3)), rhs) is None
        x = _solve_reduced(bsr_matrix(dense, blocksize=(3, 3)), rhs)
        assert np.abs(x - exact).max() < 1e-9 * np.abs(exact).max()
    dense[:3, :3] = np.diag([2.0, -3.0, 1.0])
    S = bsr_matrix(dense, blocksize=(3, 3))
    assert global_positioning._conjugate_gradients(S, rhs) is None
    assert np.allclose(dense @ _solve_reduced(S, rhs), rhs)


def test_a_reduced_system_that_is_not_positive_definite_is_solved_by_lu_and_a_singular_one_gives_nan():
    dense = np.array([[2.0, 1.0, 0.0], [1.0, -3.0, 0.5], [0.0, 0.5, 1.0]])  # symmetric, indefinite
    rhs = np.array([1.0, 2.0, 3.0])
    x = _solve_reduced(bsr_matrix(dense, blocksize=(3, 3)), rhs)
    assert np.allclose(dense @ x, rhs)
    assert np.isnan(_solve_reduced(csr_matrix(np.zeros((3, 3))), rhs)).all()


def test_the_reduced_systems_blocks_are_the_camera_pairs_that_share_a_point():
    """The reduced camera system's CSR blocks are exactly the ordered camera pairs seen together in a point; every
    unordered pair of a point's observations is given its own cameras' block above the diagonal, and each block
    below it is paired with its transpose."""
    rng = np.random.default_rng(4)
    views = [rng.choice(25, rng.integers(2, 8), replace=False) for _ in range(300)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(300), [len(v) for v in views])
    order = np.argsort(point, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(point, minlength=300))]
    by_cam = np.argsort(cam, kind="stable")
    cam_bounds = np.r_[0, np.cumsum(np.bincount(cam, minlength=25))]
    indptr, cols = _camera_blocks(cam, point, order, bounds, by_cam, cam_bounds)
    rows = np.repeat(np.arange(25), np.diff(indptr))
    assert set(zip(rows.tolist(), cols.tolist())) == {(a, b) for v in views for a in v.tolist() for b in v.tolist()}
    slots = _pair_slots(cam, order, bounds, indptr, cols)
    seen = [cam[order[bounds[p]:bounds[p + 1]]].tolist() for p in range(300)]
    pairs = [(min(v[a], v[b]), max(v[a], v[b])) for v in seen for a in range(len(v)) for b in range(a, len(v))]
    assert len(slots) == len(pairs)
    assert list(zip(rows[slots].tolist(), cols[slots].tolist())) == pairs
    layout = global_positioning._ReducedLayout.of(cam, point, 25, 300)
    assert (rows[layout.lower] > cols[layout.lower]).all() and len(layout.lower) == np.sum(rows > cols)
    assert (rows[layout.upper] == cols[layout.lower]).all() and (cols[layout.upper] == rows[layout.lower]).all()


def test_the_points_are_eliminated_into_the_schur_complement():
    """The reduced system's blocks and right-hand side, as `_reduce_points` sums them point by point, equal the
    Schur complement - H_CX H_XX^-1 H_XC and - H_CX H_XX^-1 rhs_X formed densely, also where one camera sees a
    point twice (every fourth point's views drawn with repeats)."""
    rng = np.random.default_rng(7)
    num_cams, num_points = 6, 40
    views = [rng.choice(num_cams, rng.integers(2, 6), replace=p % 4 == 0) for p in range(num_points)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(num_points), [len(v) for v in views])
    e, d, coef = rng.normal(size=(len(cam), 3)), rng.uniform(1, 2, len(cam)), rng.uniform(0, 0.5, len(cam))
    Q = np.array([c * np.outer(x, x) - w * np.eye(3) for x, w, c in zip(e, d, coef)])  # (C, X) blocks
    H_XX = np.zeros((num_points, 3, 3))
    np.add.at(H_XX, point, -Q)
    H_XX += 0.1 * np.eye(3)
    Xinv = np.linalg.inv(H_XX)
    rhs_X = rng.normal(size=(num_points, 3))
    layout = global_positioning._ReducedLayout.of(cam, point, num_cams, num_points)
    indptr, cols = layout.indptr, layout.block_col
    blocks, rhs_C = np.zeros((len(cols), 3, 3)), np.zeros((num_cams, 3))
    _reduce_points(cam, layout.order, layout.bounds, layout.slot_of_pair, layout.lower, layout.upper, e, d, coef,
                   Xinv, rhs_X, blocks, rhs_C)
    H_CX = np.zeros((3 * num_cams, 3 * num_points))
    for k, (a, p) in enumerate(zip(cam.tolist(), point.tolist())):
        H_CX[3 * a:3 * a + 3, 3 * p:3 * p + 3] += Q[k]
    dense_XX = np.zeros((3 * num_points, 3 * num_points))
    for p in range(num_points):
        dense_XX[3 * p:3 * p + 3, 3 * p:3 * p + 3] = H_XX[p]
    dense_inv = np.linalg.inv(dense_XX)
    reduced = bsr_matrix((blocks, cols, indptr), shape=(3 * num_cams, 3 * num_cams)).toarray()
    assert np.allclose(reduced, -H_CX @ dense_inv @ H_CX.T, rtol=1e-12, atol=1e-12)
    assert np.allclose(rhs_C.ravel(), -H_CX @ dense_inv @ rhs_X.ravel(), rtol=1e-12, atol=1e-12)


def test_collinear_cameras_are_placed_where_pair_directions_cannot_place_them():
    """A street: 20 cameras unevenly spaced along a line. Every pair direction is the line itself, so translation
    averaging cannot tell the spacing; the points beside the street do."""
    rng = np.random.default_rng(2)
    n = 20
    C = np.c_[np.linspace(0, 10, n) + rng.uniform(0, 0.3, n), np.zeros(n), np.zeros(n)]
    X = np.c_[rng.uniform(-2, 12, 800), rng.uniform(-1, 1, 800), rng.uniform(3, 8, 800) * rng.choice([-1, 1], 800)]
    views = [rng.choice(np.flatnonzero(np.abs(C[:, 0] - x) < 4), 4, replace=False) for x in X[:, 0]]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(len(X)), 4)
    found, _ = solve_positions(cam, point, rays(C, X, cam, point), n, len(X))
    assert similarity_error(found, C) < 1e-6
    ij = np.array([(i, j) for i in range(n) for j in range(i + 1, min(n, i + 4))])
    pairs = average_translations(n, ij, rays(C, C, ij[:, 0], ij[:, 1]))
    assert similarity_error(pairs.centers, C) > 0.1


def block_walk(rng, n=80, half=(20.0, 12.0), street=5.0, reach=15.0, fov_deg=35.0, m=15000):
    """(centres, points, cam, point): n cameras 1.5 m above a rectangular loop of half sides `half` round a
    block, each looking ahead along the loop (turning over 6 m at a corner), and m points on the facades
    `street` m either side of it up to 8 m high, each seen by the cameras within `reach` m whose view
    (`fov_deg` off the heading) holds it, and by two at least."""
    w, h = half

    def on_loop(s, w, h):
        s = np.asarray(s) % (4 * (w + h))
        legs = [(2 * w, (-w, -h), (1, 0)), (2 * h, (w, -h), (0, 1)), (2 * w, (w, h), (-1, 0)),
                (2 * h, (-w, h), (0, -1))]
        p, t, start = np.zeros((len(s), 2)), np.zeros((len(s), 2)), 0.0
        for length, origin, heading in legs:
            on = (s >= start) & (s < start + length)
            p[on] = np.array(origin) + (s[on] - start)[:, None] * np.array(heading)
            t[on] = heading
            start += length
        return p, t

    s = np.arange(n) * 4 * (w + h) / n
    heading = sum(on_loop(s + d, w, h)[1] for d in np.linspace(-3, 3, 7))
    heading = np.c_[heading / np.linalg.norm(heading, axis=1, keepdims=True), np.zeros(n)]
    C = np.c_[on_loop(s, w, h)[0], np.full(n, 1.5)]
    X = np.vstack([np.c_[on_loop(rng.uniform(0, 4 * (w + h + 2 * off), m // 2), w + off, h + off)[0],
                         rng.uniform(0, 8, m // 2)] for off in (-street, street)])
    d = X[None] - C[:, None]
    dist = np.linalg.norm(d, axis=2)
    sees = (dist < reach) & (np.einsum("nmi,ni->nm", d, heading) > dist * np.cos(np.radians(fov_deg)))
    sees &= sees.sum(axis=0) >= 2
    point, cam = np.nonzero(sees.T)
    used, point = np.unique(point, return_inverse=True)
    return C, X[used], cam, point


def noisy_block_walk():
    """`block_walk`'s cameras and points (seed 0) with its rays 0.1 deg noisy: (centres, points, cam, point, v)."""
    rng = np.random.default_rng(0)
    C, X, cam, point = block_walk(rng)
    v = rays(C, X, cam, point) + rng.normal(scale=np.radians(0.1), size=(len(cam), 3))
    return C, X, cam, point, v / np.linalg.norm(v, axis=1, keepdims=True)


def test_a_walk_round_a_block_is_placed_from_cameras_placed_in_turn():
    """80 cameras walking round a block, looking ahead, rays 0.1 deg noisy: from random centres the solver stops
    in a wrong minimum; from the centres placed in turn it finds the loop."""
    C, X, cam, point, v = noisy_block_walk()
    n, m = len(C), len(X)
    in_turn = global_positioning.centres_in_turn(cam, point, v, n, m)
    start = np.random.default_rng(0)
    random_start = global_positioning._minimise(
        cam, point, v, start.uniform(-1, 1, (n, 3)), start.uniform(-1, 1, (m, 3)), np.ones(len(v)), 100,
        global_positioning._ReducedLayout.of(cam, point, n, m))[0]
    found, _ = solve_positions(cam, point, v, n, m)
    assert similarity_error(random_start, C) > 0.1
    assert np.isfinite(in_turn).all() and similarity_error(in_turn, C) < 0.05
    assert similarity_error(found, C) < 0.01


def test_a_camera_whose_rays_miss_the_points_is_placed_once_no_other_can_be():
    """A street of 16 cameras, one of them (its rotation 3 deg off) seeing points that the others triangulated:
    its centre misses them by far more than the others' do, so it waits while the other cameras are placed,
    which are then exact, and it is placed last rather than left out. Placed as soon as it sees enough points,
    the points it triangulates move the cameras placed from them by 1e-3 of the street's spread."""
    rng = np.random.default_rng(0)
    n, wrong = 16, 6
    C = np.c_[np.linspace(0, 15, n) + rng.uniform(0, 0.3, n), np.zeros(n), np.zeros(n)]
    X = np.c_[rng.uniform(0, 15, 1200), rng.uniform(-1, 1, 1200), rng.uniform(3, 8, 1200) * rng.choice([-1, 1], 1200)]
    views = [rng.choice(np.flatnonzero(np.abs(C[:, 0] - x) < 4), 4, replace=False) for x in X[:, 0]]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(len(X)), 4)
    v = rays(C, X, cam, point)
    v[cam == wrong] = v[cam == wrong] @ angle_axis_to_rotmat(np.array([0.0, 0.0, np.radians(3.0)])).T
    in_turn = global_positioning.centres_in_turn(cam, point, v, n, len(X))
    others = np.arange(n) != wrong
    assert np.isfinite(in_turn).all()
    assert similarity_error(in_turn[others], C[others]) < 1e-6


def test_the_pairs_start_is_solved_from_only_where_placing_in_turn_leaves_a_camera_out(monkeypatch):
    """Round the block every camera is placed in turn, so the `initial` centres (here a wrong start far from any
    solution) are neither asked for nor solved from: two solves, random and in turn, and the centres within 1%
    of the truth."""
    C, X, cam, point, v = noisy_block_walk()
    n, m = len(C), len(X)
    solves = []  # the whole problem's solves (placing in turn adjusts its placed cameras without Cauchy's loss)
    minimise = global_positioning._minimise
    monkeypatch.setattr(global_positioning, "_minimise", lambda *a, **k: solves.append(
        k.get("robust_iterations", global_positioning._ROBUST_ITERATIONS)) or minimise(*a, **k))
    wrong = np.random.default_rng(5).uniform(-1, 1, (n, 3))
    asked = []
    found, _ = solve_positions(cam, point, v, n, m, initial=lambda: asked.append(1) or wrong)
    assert solves.count(global_positioning._ROBUST_ITERATIONS) == 2 and not asked
    assert similarity_error(found, C) < 0.01


def noisy_grid(rng, rows: int, cols: int, m: int, wrong: float = 0.0):
    """A rows x cols grid of cameras 5 above the ground and m points within 1 of it, each seen by the cameras
    within 1.6 across, rays 0.003 noisy and the share `wrong` of them in random directions: (centres, cam,
    point, v)."""
    C = np.c_[np.repeat(np.arange(rows), cols), np.tile(np.arange(cols), rows), np.full(rows * cols, 5.0)]
    X = np.c_[rng.uniform(0, rows - 1, m), rng.uniform(0, cols - 1, m), rng.uniform(-1, 1, m)]
    views = [np.flatnonzero(d < 1.6) for d in np.linalg.norm(X[:, None, :2] - C[None, :, :2], axis=2)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(m), [len(v) for v in views])
    v = rays(C, X, cam, point) + rng.normal(scale=0.003, size=(len(cam), 3))
    if wrong:
        bad = rng.random(len(v)) < wrong
        v[bad] = rng.normal(size=(int(bad.sum()), 3))
    return C, cam, point, v / np.linalg.norm(v, axis=1, keepdims=True)


def test_two_starts_solved_at_once_give_the_centres_of_one_after_the_other():
    """With a second worker the random start is solved in a thread beside the start placed in turn. The result is
    the same to the bit as one after the other: round the block, where the start placed in turn wins, and over a
    6 x 8 grid of cameras above the ground (noisy rays), where that start lies near the random start's solution
    and its own solution, a hair's breadth away at a cost lower by 1e-13, is dropped (its solve stopped once the
    random start's solution is known)."""
    C, cam, point, v = noisy_grid(np.random.default_rng(3), 6, 8, 1500)
    block, _, block_cam, block_point, block_v = noisy_block_walk()
    for truth, cam, point, v in ((block, block_cam, block_point, block_v), (C, cam, point, v)):
        n, m = len(truth), len(np.unique(point))
        alone, _ = solve_positions(cam, point, v, n, m, workers=1)
        beside, _ = solve_positions(cam, point, v, n, m, workers=2)
        assert np.array_equal(alone, beside)
        assert similarity_error(beside, truth) < 0.02


def true_synthetic_scene(tmp_path):
    """pycolmap's synthetic scene as the global mapper reads it: (mapper, a model with the true calibration, the true
    rotations, the true centres)."""
    gt = synthetic_database(tmp_path / "database.db")
    mapper = GlobalMapper(database.read_correspondences(tmp_path / "database.db"), MapperConfig(mapper="global"))
    model = mapper._new_model(mapper.cameras)
    model.cameras[1].params = np.array([600.0, 320.0, 240.0, 0.02])
    R = np.array([gt[name][0] for name in mapper.names])
    C = np.array([-gt[name][0].T @ gt[name][1] for name in mapper.names])
    return mapper, model, R, C


@pytest.mark.parametrize("turn_deg", [10.0, 40.0])
def test_a_flipped_camera_is_found_by_its_rays(tmp_path, turn_deg):
    """pycolmap's synthetic scene with its true rotations, but one camera's turned (a rotation the averaging got
    wrong): that camera alone is an outlier, with a reason, and the others are placed right."""
    mapper, model, R, C = true_synthetic_scene(tmp_path)
    R[5] = angle_axis_to_rotmat(np.radians(turn_deg) * np.array([0.6, 0.8, 0.0])) @ R[5]
    result = global_positions(model, R, np.ones(len(R), bool), mapper.tracks)
    assert result.solved.all() and result.points > 100
    out = outlier_cameras(result)
    assert list(out) == [5] and out[5].startswith("its global pose was an outlier: its rays miss")
    good = np.arange(len(R)) != 5
    assert similarity_error(result.centers[good], C[good]) < 0.02


def test_global_positions_solves_long_tracks_as_parts_past_the_budget(tmp_path, monkeypatch):
    """pycolmap's synthetic scene (8 images, every point seen by all of them) with its true rotations and
    calibration, global positioning's budget of pairs of observations set so low that every track is solved as parts
    of at most 3 views: every ray is still used, there are three times the points, and the centres are as right as
    with the tracks whole (parts dealt in the images' order would leave no point between the even and the odd
    cameras)."""
    mapper, model, R, C = true_synthetic_scene(tmp_path)
    whole = global_positions(model, R, np.ones(len(R), bool), mapper.tracks)
    monkeypatch.setattr(global_positioning, "_PAIR_BUDGET", 1.0)
    monkeypatch.setattr(global_positioning, "_MIN_PART_VIEWS", 3)
    parts = global_positions(model, R, np.ones(len(R), bool), mapper.tracks)
    assert parts.solved.all() and parts.observations == whole.observations and parts.points == 3 * whole.points
    assert similarity_error(whole.centers, C) < 0.01 and similarity_error(parts.centers, C) < 0.01


def test_a_survey_of_150_cameras_is_placed_from_neighbours_alone():
    """A 10 x 15 grid of cameras over the ground, each point seen by the cameras within 1.6 spacings: the reduced
    camera system is sparse (a camera shares points with its neighbours only), and the centres come out exact."""
    rng = np.random.default_rng(3)
    rows, cols, m = 10, 15, 3000
    n = rows * cols
    C = np.c_[np.repeat(np.arange(rows), cols), np.tile(np.arange(cols), rows), np.full(n, 5.0)].astype(float)
    X = np.c_[rng.uniform(0, rows - 1, m), rng.uniform(0, cols - 1, m), rng.uniform(-1, 1, m)]
    views = [np.flatnonzero(d < 1.6) for d in np.linalg.norm(X[:, None, :2] - C[None, :, :2], axis=2)]
    cam = np.concatenate(views)
    point = np.repeat(np.arange(m), [len(v) for v in views])
    found, _ = solve_positions(cam, point, rays(C, X, cam, point), n, m)
    assert similarity_error(found, C) < 1e-6


def test_a_street_ahead_is_placed_from_translation_averagings_start():
    """A camera moving straight ahead along a street, each point seen by 3 of the cameras behind it, rays 0.1 deg
    noisy and 5% of them wild: from random centres global positioning stops in a wrong minimum; started from the
    pairs' directions' centres as well (the lower cost kept) it finds the street."""
    rng = np.random.default_rng(2)
    n, m = 30, 800
    z = np.cumsum(rng.uniform(0.5, 1.5, n))
    C = np.c_[0.1 * rng.normal(size=n), 0.05 * rng.normal(size=n), z]
    ahead_z = rng.uniform(z[0] + 4, z[-1] + 30, m)
    X = np.c_[rng.choice([-1, 1], m) * rng.uniform(2, 5, m), rng.uniform(-1, 3, m), ahead_z]
    views = []
    for k in range(m):
        ahead = np.flatnonzero((X[k, 2] - C[:, 2] > 4) & (X[k, 2] - C[:, 2] < 30))
        views.append(rng.choice(ahead, min(len(ahead), 3), replace=False) if len(ahead) >= 2 else np.zeros(0, int))
    cam = np.concatenate(views).astype(int)
    point = np.repeat(np.arange(m), [len(v) for v in views])
    v = rays(C, X, cam, point) + rng.normal(scale=np.radians(0.1), size=(len(cam), 3))
    wild = rng.random(len(v)) < 0.05
    v[wild] = rng.normal(size=(wild.sum(), 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    ij = np.array([(i, j) for i in range(n) for j in range(i + 1, min(n, i + 5))])
    pairs = average_translations(n, ij, rays(C, C, ij[:, 0], ij[:, 1]) + rng.normal(scale=0.02, size=(len(ij), 3)))
    random_start, _ = solve_positions(cam, point, v, n, m)
    both, _ = solve_positions(cam, point, v, n, m, initial=lambda: pairs.centers)
    assert similarity_error(random_start, C) > 0.12
    assert similarity_error(both, C) < 0.08


def test_a_phase_ends_once_an_undamped_step_no_longer_moves_the_centres(monkeypatch):
    """Over an 8 x 10 grid of cameras above the ground (noisy rays, 5% of them wrong) the last steps of each
    phase lower the cost a little while the centres stay put: the phases end at the first undamped step that
    moves no centre by `_MOVE_TOLERANCE` of their spread, in fewer steps than the cost's tolerance alone takes,
    at the same centres to 1e-4 of their spread."""
    C, cam, point, v = noisy_grid(np.random.default_rng(4), 8, 10, 2500, wrong=0.05)
    n, m = len(C), len(np.unique(point))
    layout = global_positioning._ReducedLayout.of(cam, point, n, m)
    start = np.random.default_rng(0)
    C0, X0 = start.uniform(-1, 1, (n, 3)), start.uniform(-1, 1, (m, 3))
    steps = []
    terms = global_positioning._normal_terms
    monkeypatch.setattr(global_positioning, "_normal_terms", lambda *a: steps.append(1) or terms(*a))

    def solve():
        steps.clear()
        found = global_positioning._minimise(cam, point, v, C0, X0, np.ones(len(v)), 100, layout)[0]
        return found, len(steps)

    settled, settled_steps = solve()
    monkeypatch.setattr(global_positioning, "_MOVE_TOLERANCE", 0.0)
    converged, converged_steps = solve()
    assert settled_steps < converged_steps
    assert similarity_error(settled, converged) < 1e-4
    assert similarity_error(settled, C) < 0.02


def test_a_walk_round_a_block_through_a_narrow_lens_is_placed_again_where_placing_stops_at_a_corner():
    """120 cameras walking round a block, each seeing 19 deg either side of its heading, rays 0.1 deg noisy: past
    a corner a camera sees few points that the cameras before it see at 2 deg, so placing in turn stops about half
    way round; placed again from points seen at 1 deg (those seeing 30 points or more in the order they came to see
    them) every camera is placed, and the solution's error is under 0.35 of the centres' spread (0.58 without the
    second placing)."""
    rng = np.random.default_rng(2)
    C, X, cam, point = block_walk(rng, n=120, fov_deg=19.0, reach=25.0)
    v = rays(C, X, cam, point) + rng.normal(scale=np.radians(0.1), size=(len(cam), 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    n, m = len(C), len(X)
    at_two = global_positioning.centres_in_turn(cam, point, v, n, m)
    at_one = global_positioning.centres_in_turn(cam, point, v, n, m, global_positioning._TURN_NARROW_ANGLE_DEG,
                                                global_positioning._TURN_READY_POINTS)
    found, _ = solve_positions(cam, point, v, n, m)
    assert np.isfinite(at_two).all(axis=1).sum() < 0.6 * n
    assert np.isfinite(at_one).all()
    assert similarity_error(found, C) < 0.35


def test_cameras_placed_in_turn_that_end_above_the_random_start_are_placed_again_at_the_narrow_angle(monkeypatch):
    """Through a narrow lens the placing at 2 deg can place every camera and still go astray: on a 300-frame walk
    round a block it crossed a corner on a few far points and made the far side's steps about 5x the near side's.
    Here the placing at 2 deg gives such a start (the walk's steps from its 60th camera on 3x too long), whose
    solution ends above the random start's cost; the cameras are then placed again from points seen at 1 deg, and
    that solution is within 1% of the truth (without it the random start's was kept, 0.41 off)."""
    rng = np.random.default_rng(7)
    C, X, cam, point = block_walk(rng, n=120, fov_deg=22.0, reach=25.0)
    v = rays(C, X, cam, point) + rng.normal(scale=np.radians(0.1), size=(len(cam), 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    n, m = len(C), len(X)
    steps = np.diff(C, axis=0)
    steps[60:] *= 3.0
    astray = np.vstack([C[:1], C[0] + np.cumsum(steps, axis=0)])
    place = global_positioning.centres_in_turn

    def placing(cam, point, v, n, m, min_angle_deg=global_positioning._TURN_MIN_ANGLE_DEG, ready_points=np.inf):
        if min_angle_deg == global_positioning._TURN_MIN_ANGLE_DEG:
            return astray.copy()
        return place(cam, point, v, n, m, min_angle_deg, ready_points)

    monkeypatch.setattr(global_positioning, "centres_in_turn", placing)
    layout = global_positioning._ReducedLayout.of(cam, point, n, m)
    start = np.random.default_rng(0)
    C0, X0 = start.uniform(-1, 1, (n, 3)), start.uniform(-1, 1, (m, 3))
    random_end = global_positioning._minimise(cam, point, v, C0, X0, np.ones(len(v)), 100, layout)
    astray_end = global_positioning._minimise(
        cam, point, v, *global_positioning._start(cam, point, v, astray, C0, m), 100, layout)
    found, _ = solve_positions(cam, point, v, n, m)
    assert astray_end[2] > random_end[2]
    assert similarity_error(random_end[0], C) > 0.3 and similarity_error(astray_end[0], C) > 0.3
    assert similarity_error(found, C) < 0.01


def test_cameras_placed_in_turn_that_end_at_the_random_starts_centres_are_not_placed_again(monkeypatch):
    """Where the solve from the cameras placed in turn ends at the random start's centres at a cost a hair above
    it (two solves of one problem stop at slightly different points and scales), the placing did not go astray, and
    the cameras are not placed again at the narrow angle: that placing would only solve the same problem a third
    time. Here the placing gives the true centres moved by a tenth of their spacing (not near the solution by
    `_near`, but in its basin), and the second solve's cost is raised by one part in a million."""
    C, cam, point, v = noisy_grid(np.random.default_rng(3), 6, 8, 1500)
    n, m = len(C), len(np.unique(point))
    moved = C + np.random.default_rng(1).normal(scale=0.1, size=C.shape)
    placings = []  # the angle of each placing asked for

    def placing(cam, point, v, n, m, min_angle_deg=global_positioning._TURN_MIN_ANGLE_DEG, ready_points=np.inf):
        placings.append(min_angle_deg)
        return moved.copy()

    monkeypatch.setattr(global_positioning, "centres_in_turn", placing)
    solves = []
    minimise = global_positioning._minimise

    def solve(*a, **k):
        C_end, X_end, cost = minimise(*a, **k)
        solves.append(C_end)
        return C_end, X_end, cost * (1 + 1e-6) if len(solves) == 2 else cost

    monkeypatch.setattr(global_positioning, "_minimise", solve)
    found, _ = solve_positions(cam, point, v, n, m)
    assert len(solves) == 2 and not global_positioning._near(moved, solves[0])
    assert global_positioning._near(solves[1], solves[0])
    assert placings == [global_positioning._TURN_MIN_ANGLE_DEG]
    assert similarity_error(found, C) < 0.02
