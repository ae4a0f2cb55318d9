"""Global positioning of the global mapper: camera centres and points at once from the tracks (GLOMAP's key step).

With the rotations known (rotation_averaging.py), each observation of a track gives the world-frame unit
direction v from its camera's centre C to the point X. All centres and points are found together by minimising
sum rho(|v - s (X - C)|^2) over the observations, one scale s >= 0 per observation (GLOMAP's BATA-style
residual: it cannot shrink to zero, and a far point costs no more than a near one), rho Huber's loss at 0.1
(GLOMAP's) from random centres and points as GLOMAP starts, then Cauchy's at 0.01 from there, which lets the rays
of a camera whose rotation is wrong go rather than bend every point towards them. The problem is solved by
Levenberg-Marquardt on the normal equations, the scales and then the points eliminated (a Schur complement), so
each step solves one 3 x cameras system.

Why points and not pair directions: a pair's translation direction is a fit to its matches alone and, on a ring
of cameras with narrow views, many are degrees off in ways that no outlier test sees; a track seen by several
cameras ties their centres together directly, and collinear motion (a street) is no degeneracy for it.
templeSparseRing (16 views, 24 deg field of view): AUC@5 0.156 from pair directions, 0.741 from tracks
(docs/global-mapper.md).
"""

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
from numba import njit
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import bsr_matrix, coo_matrix, triu
from scipy.sparse.linalg import splu

from ..executor import in_background
from ..geometry.kernels import symmetric_inverses
from .model import Reconstruction, sum_rows
from .track_parts import deal_long_tracks
from .tracks import Tracks

_TRACKS_PER_IMAGE = 500  # tracks are taken longest first while one of their images holds fewer than this
_PAIR_BUDGET = 2e7  # a step's work: the pairs of observations of one point, summed; past it the longest tracks are
_MIN_PART_VIEWS = 10  # solved as parts (`_split_long_tracks`) of no fewer views than this
_MIN_OBSERVATIONS = 6  # a camera with fewer selected observations is left out of the problem
_HUBER = 0.1  # GLOMAP's loss width, on the unit directions
_CAUCHY = 0.01  # the redescending loss's width that follows (0.6 deg; the shared sets' rays miss by 0.01-0.06)
_ITERATIONS = 100
_ROBUST_ITERATIONS = 30
# a phase stops when a step lowers its cost by less than this share; the Huber phase only brings the Cauchy
# one near, which its last steps hardly change (docs/benchmarks.md, "Global positioning's solver") ...
_HUBER_TOLERANCE = 1e-5
_CAUCHY_TOLERANCE = 1e-7
# ... or at its first undamped step that moves no centre by this share of the centres' spread (`_settled`)
_MOVE_TOLERANCE = 1e-5
_LAMBDA = 1e-4  # Levenberg-Marquardt's damping at the start of a phase; a step at no more is undamped
_MIN_SCALE = 1e-5
_DENSE_SHARE = 0.1  # the reduced system is factorised dense from this share of non-zero entries ...
_DENSE_MAX_CAMERAS = 2000  # ... up to this many cameras (`_solve_reduced`)
_ITERATIVE_MIN_CAMERAS = 500  # from this many cameras the reduced system is solved by conjugate gradients first
_CG_TOLERANCE = 1e-10  # their residual's norm, relative to the right-hand side's: the direct solvers' steps to 1e-9
_CG_MAX_ITERATIONS = 1000  # a system not solved within this many is left to the direct solvers
# centres placed in turn (`centres_in_turn`): a point is triangulated once two of its rays from placed cameras meet
# at this angle; the placed cameras are adjusted together each time their number has grown by the factor, in
# this many LM steps under Huber's loss
_TURN_MIN_ANGLE_DEG = 2.0
_TURN_NARROW_ANGLE_DEG = 1.0  # where that angle leaves a camera unplaced, the cameras are placed again at this one
_TURN_GROWTH = 1.5
_TURN_STEPS = 15
_TURN_MAX_MISS_DEG = 1.0  # a triangulated point's rays miss it by at most this (wrong matches go)
_TURN_MIN_POINTS = 6  # a camera is placed from at least this many triangulated points, the first pair from as many
_TURN_READY_POINTS = 30  # then cameras seeing this many points are placed in the order they came to see them
_NEAR_SHARE = 0.02  # a start with every centre this near a solution (of their spread) is in its basin
_OUTLIER_DEG = 0.5  # a camera whose rays miss its points by a median over this (and over _OUTLIER_FACTOR x the
_OUTLIER_FACTOR = 5.0  # cameras' median) is an outlier pose: the others' are 0.01-0.06 deg on the shared sets


@dataclass
class PositioningResult:
    centers: np.ndarray  # (n,3) camera centres, NaN outside `solved`
    solved: np.ndarray  # (n,) bool
    points: int  # tracks used
    observations: int
    residual_deg: np.ndarray | None = None  # (n,) per camera: median angle between its rays and its points


def select_tracks(tracks: Tracks, usable: np.ndarray, per_image: int = _TRACKS_PER_IMAGE) -> np.ndarray:
    """Track ids with >= 2 elements in `usable` images, longest first, each taken while one of its usable images
    holds fewer than `per_image` taken tracks: every camera gets tracks, the longest constrain most. The quota is
    large enough that an image is not held by its longest tracks alone: past repeated structure (a facade of
    identical windows) wrong matches across the repeats join the longest tracks, and the images at the ends of a
    walk were placed by those (docs/benchmarks.md, "Global positioning: tracks per image")."""
    inside = usable[tracks.image]
    length = np.add.reduceat(inside.astype(np.int64), tracks.ptr[:-1]) if len(tracks) else np.zeros(0, np.int64)
    length[np.diff(tracks.ptr) == 0] = 0
    candidates = np.flatnonzero(length >= 2)
    candidates = candidates[np.argsort(-length[candidates], kind="stable")]
    held = np.zeros(len(usable), np.int64)
    taken = []
    for t in candidates.tolist():
        images = tracks.image[tracks.ptr[t]:tracks.ptr[t + 1]]
        images = images[usable[images]]
        if held[images].min() < per_image:
            held[images] += 1
            taken.append(t)
    return np.array(taken, dtype=np.int64)


def global_positions(model: Reconstruction, R: np.ndarray, solved: np.ndarray, tracks: Tracks,
                     seed: int = 0, initial: Callable[[], np.ndarray] | None = None,
                     workers: int = 1) -> PositioningResult:
    """Camera centres of the `solved` images (rotations R, cam_from_world) from their tracks (see the module
    docstring), the model's current calibration turning keypoints into rays. Images with too few observations are
    left out; the centres are up to a similarity. The problem is solved from a random start and from centres placed
    in turn; where those leave a camera unplaced or end above the random start's cost, also from centres placed in
    turn again from points seen at a narrower angle; where a camera is left unplaced, also from the centres
    `initial()` gives (n,3; NaN where unknown) when given; the solution of lowest cost is kept (`solve_positions`):
    from random centres a street of cameras moving straight ahead can stop in a wrong minimum, which centres placed
    in turn start clear of (a walk round a block, whose streets the pairs' directions leave short) and, where those
    stop short, centres from the pairs' directions (a street seen far ahead). With `workers` > 1 two starts are
    solved at once (`solve_positions`)."""
    n = len(R)
    centers = np.full((n, 3), np.nan)
    chosen = select_tracks(tracks, solved)
    if len(chosen) == 0:
        return PositioningResult(centers, np.zeros(n, bool), 0, 0)
    starts, ends = tracks.ptr[chosen], tracks.ptr[chosen + 1]
    element = np.concatenate([np.arange(a, b) for a, b in zip(starts.tolist(), ends.tolist())])
    point = np.repeat(np.arange(len(chosen)), ends - starts)
    image, kp = tracks.image[element], tracks.keypoint[element]
    keep = solved[image]
    image, kp, point = image[keep], kp[keep], point[keep]
    x = model.normalized_at(image, kp)
    ok = np.isfinite(x).all(axis=1)
    image, point, x = image[ok], point[ok], x[ok]
    # a camera with too few observations cannot be placed; a point left with < 2 views constrains nothing
    for _ in range(3):
        counts = np.bincount(image, minlength=n)
        views = np.bincount(point, minlength=len(chosen))
        good = (counts[image] >= _MIN_OBSERVATIONS) & (views[point] >= 2)
        if good.all():
            break
        image, point, x = image[good], point[good], x[good]
    placed = np.zeros(n, bool)
    placed[image] = True
    if placed.sum() < 2:
        return PositioningResult(centers, np.zeros(n, bool), 0, 0)
    cams = np.flatnonzero(placed)
    local = np.full(n, -1)
    local[cams] = np.arange(len(cams))
    point = _split_long_tracks(point, _PAIR_BUDGET)
    pts, point = np.unique(point, return_inverse=True)
    rays = np.c_[x, np.ones(len(x))]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    v = np.einsum("kji,kj->ki", R[image], rays)  # world frame: R^T ray
    start = None if initial is None else lambda: initial()[cams]
    C, X = solve_positions(local[image], point, v, len(cams), len(pts), seed, initial=start, workers=workers)
    centers[cams] = C
    angle = _ray_angles_deg(v, X[point], C[local[image]])
    residual = np.full(n, np.nan)
    order = np.argsort(image, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(image, minlength=n))]
    for i in cams.tolist():
        residual[i] = float(np.median(angle[order[bounds[i]:bounds[i + 1]]]))
    return PositioningResult(centers, placed, len(pts), len(v), residual)


def _split_long_tracks(point: np.ndarray, budget: float) -> np.ndarray:
    """Point ids for the observations (`point`, one per observation): where the pairs of observations of
    one point, summed over the points, pass `budget`, each point of more than K observations is split into the
    fewest points of at most K, K the largest (not under `_MIN_PART_VIEWS`) that brings the sum within the budget,
    its observations dealt out at random (the same for the same input; `track_parts.deal_long_tracks`), each part a
    sample of the whole track. Every ray is kept; what is given up is only that the parts meet. Why split: a step's
    work and memory grow with those pairs (`_reduce_points`, `_pair_slots`), and round an object seen by 1,000
    cameras the tracks taken have 47 views on average and up to 312: 48 million pairs a step. Why only past a
    budget: along a 1,000-frame street (tracks of 17 views on average) parts of at most 20 (dealt in order) bent
    the loop (AUC@5 0.77 against 0.96; docs/benchmarks.md, "Global positioning: long tracks solved as parts past a
    budget")."""
    if len(point) == 0:
        return point
    dealt = deal_long_tracks(point, np.bincount(point), budget, _MIN_PART_VIEWS,
                             np.random.default_rng(0).random(len(point)))
    if dealt is None:
        return point
    turn, parts = dealt
    return np.r_[0, np.cumsum(parts)[:-1]][point] + turn


def solve_positions(cam: np.ndarray, point: np.ndarray, v: np.ndarray, num_cams: int, num_points: int,
                    seed: int = 0, iterations: int = _ITERATIONS,
                    initial: Callable[[], np.ndarray] | None = None,
                    workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(centres (num_cams,3), points (num_points,3)) minimising sum rho(|v_k - s_k (X_point[k] - C_cam[k])|) from a
    random start (uniform in [-1, 1]^3, scales 1), rho Huber's loss and then Cauchy's; camera 0 is held (the gauge), and
    the result is moved and scaled to centres of zero mean and unit RMS distance from it. It is solved from the centres
    placed in turn (`centres_in_turn`) too; where those leave a camera unplaced, or their solution ends away from the
    random start's (`_near`) at a cost no lower than it, from the centres placed in turn again from points seen at
    `_TURN_NARROW_ANGLE_DEG` (the cameras ready longest first, `_TURN_READY_POINTS`); and where a camera is left
    unplaced, from the centres `initial()` gives (num_cams,3; NaN where unknown) when given (`_start`), asked for only
    then (the mapper's come from translation averaging); the solution of the lowest final cost is returned. Why the
    second placing: through a narrow lens (640 px wide at 768 px focal) a camera that has turned a corner of a street
    shares with the placed cameras few points seen at 2 deg or more, so placing stops there while the cameras behind the
    first pair are placed the long way round a loop; on such a 300-frame walk round a block every frame ended misplaced
    (AUC@5 0.26), and with the second placing none at two mapper seeds of three (AUC@5 0.76 and 0.65;
    docs/benchmarks.md, "Global positioning: a second placing at 1 deg where the first stops"). Why also where the first
    placing ends above the random start: the centres placed in turn are the informed start, and on that walk at other
    seeds the placing at 2 deg placed every camera, but crossed a corner on a few far points and made the far side's
    steps about 5x the near side's; its solution and the random start's ended 0.44-0.80 of the centres' spread off, the
    second placing's 0.02 (docs/benchmarks.md, "Global positioning: placed again where the first placing ends above the
    random start"). Why not where it ends at the random start's centres: two solves of one problem stop at slightly
    different points and scales, so one of them ends a hair above the other, and placing again solves the same problem a
    third time (round the 1,000-view orbit, half of positioning's time; docs/benchmarks.md, "Global positioning: no
    third placing where two starts end together"). The mapper suite's models are unchanged by each of these. A start
    already near the best solution (`_near`) is not solved from: it would end there. Why the `initial` start only then:
    where every camera is placed in turn, the mapper suite's models are better without it on the whole over three seeds,
    and a solve is saved (docs/benchmarks.md, "Global positioning: compiled steps, and the pairs' start only where
    cameras are left unplaced"). With `workers` > 1 the random start is solved in a second thread while the cameras are
    placed in turn and solved from there (the compiled steps, the conjugate gradients and LAPACK run without the GIL);
    that solve stops, and its solution is dropped, once the start proves near the random one's solution: the same result
    as one after the other, in about the time of the longer of the two (docs/benchmarks.md, "Global positioning: two
    starts at once")."""
    rng = np.random.default_rng(seed)
    C = rng.uniform(-1, 1, (num_cams, 3))
    X = rng.uniform(-1, 1, (num_points, 3))
    layout = _ReducedLayout.of(cam, point, num_cams, num_points)

    def usable(start):
        return start is not None and np.isfinite(start).all(axis=1).sum() >= 2

    def solve_from(start, stop=None):
        return _minimise(cam, point, v, *_start(cam, point, v, start, C, num_points), iterations, layout, stop=stop)

    solve_random = partial(_minimise, cam, point, v, C, X, np.ones(len(v)), iterations, layout)
    random = in_background(solve_random) if workers > 1 else None
    in_turn = centres_in_turn(cam, point, v, num_cams, num_points)
    complete = in_turn is not None and np.isfinite(in_turn).all()
    from_turn = None
    if random is not None and usable(in_turn):
        from_turn = solve_from(in_turn, stop=lambda: random.done() and random.exception() is None
                               and _near(in_turn, random.result()[0]))  # moot once near the random solution
    best = solve_random() if random is None else random.result()
    placing_lost = False  # the centres placed in turn ended elsewhere above the random start's cost: they went astray
    if usable(in_turn) and not _near(in_turn, best[0]):
        other = from_turn if from_turn is not None else solve_from(in_turn)
        placing_lost = other[2] >= best[2] and not _near(other[0], best[0])
        best = other if other[2] < best[2] else best
    narrow = None
    if not complete or placing_lost:
        narrow = centres_in_turn(cam, point, v, num_cams, num_points, _TURN_NARROW_ANGLE_DEG, _TURN_READY_POINTS)
    for start in (narrow, None if complete or initial is None else initial()):
        if usable(start) and not _near(start, best[0]):
            other = solve_from(start)
            best = other if other[2] < best[2] else best
    C, X, _ = best
    C0 = C.mean(axis=0)
    scale = _spread(C) or 1.0
    return (C - C0) / scale, (X - C0) / scale


def _near(start: np.ndarray, centres: np.ndarray) -> bool:
    """Whether every camera of `start` (all known) lies within `_NEAR_SHARE` of the centres' RMS spread of
    `centres` once scaled and moved onto them (the rotations fix the frame): a start that close lies in the
    solution's basin, and solving from it again would only repeat the solution."""
    if not np.isfinite(start).all():
        return False
    a, b = start - start.mean(axis=0), centres - centres.mean(axis=0)
    spread = _spread(centres)
    scale = np.sum(a * b) / max(np.sum(a * a), 1e-300)
    return spread > 0 and bool(np.linalg.norm(scale * a - b, axis=1).max() <= _NEAR_SHARE * spread)


def _off_rays(v: np.ndarray) -> np.ndarray:
    """(k,3,3) the projections off each unit ray of `v` (k,3): I - v v^T, which takes a point's offset from the
    ray's origin to its distance vector off the ray."""
    return np.eye(3)[None] - v[:, :, None] * v[:, None, :]


def _start(cam, point, v, initial, fallback, num_points):
    """(centres, points, scales) to start from: the known `initial` centres (scaled to unit RMS distance from
    their mean; the others from `fallback`), each point where its rays from them pass closest, each scale the
    one that best fits its ray."""
    known = np.isfinite(initial).all(axis=1)
    C = fallback.copy()
    c0 = initial[known].mean(axis=0)
    spread = _spread(initial[known]) or 1.0
    C[known] = (initial[known] - c0) / spread
    P = _off_rays(v)
    A = sum_rows(point, P, num_points) + 1e-9 * np.eye(3)
    b = sum_rows(point, (P @ C[cam][:, :, None])[:, :, 0], num_points)
    X = np.linalg.solve(A, b[:, :, None])[:, :, 0]
    e = X[point] - C[cam]
    s = np.maximum(np.einsum("ki,ki->k", e, v) / np.maximum(np.einsum("ki,ki->k", e, e), 1e-300), _MIN_SCALE)
    return C, X, s


def centres_in_turn(cam: np.ndarray, point: np.ndarray, v: np.ndarray, num_cams: int, num_points: int,
                    min_angle_deg: float = _TURN_MIN_ANGLE_DEG, ready_points: float = np.inf) -> np.ndarray | None:
    """Centres (num_cams,3; NaN for a camera never placed) placed as an incremental mapper grows a model, the rotations
    known, for `solve_positions` to start from; None when no pair of cameras shares `_TURN_MIN_POINTS` points seen at
    `min_angle_deg` or more. The pair among the 50 sharing most points that sees most of them at that angle comes first,
    its baseline the direction normal to their rays' planes; then the camera seeing most triangulated points (seen at
    `min_angle_deg` or more) is placed where its rays pass nearest them (least squares in angle, Cauchy weights), or, of
    the cameras seeing `ready_points` or more, the one that came to see them first, its points are triangulated, and
    every time the placed cameras have grown by `_TURN_GROWTH` they and their points are adjusted together (`_minimise`,
    Huber's loss, `_TURN_STEPS` steps). Why: a camera walking round a block looks ahead along four straight streets;
    from random centres each street is solved on its own and the corners come apart, and the pairs' directions
    (collinear motion) fix no street's length, while each camera placed next to those it shares points with keeps the
    loop whole (docs/benchmarks.md, "Global positioning: cameras placed in turn"). A camera whose centre misses its
    points by a median over `outlier_cameras`' limit (against the placed cameras' misses) waits until it sees new
    points, or until no other camera can be placed, when the best-fitting of those waiting is placed: placed at once, a
    camera put near a corner by far points it missed by 1.6 deg sent the next streets of a walk round a block astray,
    and 65 of its 100 frames ended misplaced (docs/benchmarks.md, "Global positioning: a camera that misses its points
    waits"). Why `ready_points` (breadth first from the first pair, rather than the camera seeing most points first): in
    the second placing of a narrow-lens walk round a block (`solve_positions`) the mapper's AUC@5 was 0.76 and 0.65 at
    seeds 0 and 1 with it, 0.58 and 0.57 without (docs/benchmarks.md, "Global positioning: a second placing at 1 deg
    where the first stops")."""
    by_cam = np.argsort(cam, kind="stable")
    cam_bounds = np.r_[0, np.cumsum(np.bincount(cam, minlength=num_cams))]
    by_point = np.argsort(point, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(point, minlength=num_points))]
    cos_max = np.cos(np.radians(min_angle_deg))
    first = _first_pair(cam, point, v, by_cam, cam_bounds, num_cams, num_points, cos_max)
    if first is None:
        return None
    a, b, baseline = first
    C = np.full((num_cams, 3), np.nan)
    X = np.full((num_points, 3), np.nan)
    placed = np.zeros(num_cams, bool)
    C[a], C[b] = 0.0, baseline
    placed[[a, b]] = True
    everything = np.arange(num_points)
    _triangulate(everything, by_point, bounds, cam, v, placed, C, X, cos_max)
    adjusted = 2
    tried = placed.copy()
    misses = []  # the placed cameras' median misses, each at its placing
    waiting: dict[int, tuple[int, float]] = {}  # camera set aside -> (points it saw, its miss) then
    ready_since = np.full(num_cams, np.inf)  # the step at which each camera came to see `ready_points`
    step = 0
    while True:
        step += 1
        seen = np.isfinite(X[point, 0])
        counts = np.bincount(cam[seen], minlength=num_cams)
        counts[tried] = -1
        for w, (count, _) in waiting.items():
            if counts[w] <= count:  # no new point of its since it was set aside
                counts[w] = -1
        ready = counts >= ready_points
        ready_since[ready & ~np.isfinite(ready_since)] = step
        if ready.any():  # the camera ready longest, of those the one seeing most
            ready &= ready_since == ready_since[ready].min()
            c = int(np.argmax(np.where(ready, counts, -1)))
        else:
            c = int(np.argmax(counts))
        fallback = counts[c] < _TURN_MIN_POINTS
        if fallback and not waiting:
            break
        if fallback:  # nothing else to place: of the cameras set aside, the one that fitted best
            c = min(waiting, key=lambda w: waiting[w][1])
        mine = by_cam[cam_bounds[c]:cam_bounds[c + 1]]
        mine = mine[seen[mine]]
        centre = _centre_from_points(v[mine], X[point[mine]]) if len(mine) >= _TURN_MIN_POINTS else np.full(3, np.nan)
        if not np.isfinite(centre).all():
            tried[c] = True
            waiting.pop(c, None)
            continue
        miss = float(np.median(_ray_angles_deg(v[mine], X[point[mine]], centre)))
        if not fallback and misses and miss > _outlier_limit_deg(float(np.median(misses))):
            waiting[c] = (int(counts[c]), miss)
            continue
        waiting.pop(c, None)
        tried[c] = True
        C[c] = centre
        placed[c] = True
        misses.append(miss)
        if placed.sum() >= _TURN_GROWTH * adjusted:
            adjusted = int(placed.sum())
            _adjust_placed(cam, point, v, placed, C, num_points)
            X[:] = np.nan
            _triangulate(everything, by_point, bounds, cam, v, placed, C, X, cos_max)
        else:
            ours = by_cam[cam_bounds[c]:cam_bounds[c + 1]]
            _triangulate(point[ours], by_point, bounds, cam, v, placed, C, X, cos_max)
    return C


def _first_pair(cam, point, v, by_cam, cam_bounds, num_cams, num_points, cos_max):
    """(a, b, baseline C_b - C_a of unit length) for `centres_in_turn`, or None."""
    shared = coo_matrix((np.ones(len(cam)), (point, cam)), shape=(num_points, num_cams)).tocsc()
    shared = triu(shared.T @ shared, k=1).tocoo()
    best = None
    for k in np.argsort(-shared.data, kind="stable")[:50].tolist():
        a, b = int(shared.row[k]), int(shared.col[k])
        oa, ob = by_cam[cam_bounds[a]:cam_bounds[a + 1]], by_cam[cam_bounds[b]:cam_bounds[b + 1]]
        _, ia, ib = np.intersect1d(point[oa], point[ob], return_indices=True)
        va, vb = v[oa[ia]], v[ob[ib]]
        wide = np.einsum("ki,ki->k", va, vb) <= cos_max
        if wide.sum() >= _TURN_MIN_POINTS and (best is None or wide.sum() > best[0]):
            best = (int(wide.sum()), a, b, va[wide], vb[wide])
    if best is None:
        return None
    _, a, b, va, vb = best
    # C_b - C_a lies in the plane of each pair of rays: normal to their cross products (of unit length, in
    # rounds of Cauchy weights on the sine of its angle off each plane, so that a wrong match goes)
    normal = np.cross(va, vb)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    w = np.ones(len(normal))
    for _ in range(5):
        baseline = np.linalg.svd(normal * w[:, None], full_matrices=False)[2][-1]
        off = np.abs(normal @ baseline)
        w = 1 / np.sqrt(1 + (off / max(3 * float(np.median(off)), 1e-4)) ** 2)
    # the sign that puts the points ahead of both cameras: X = C_a + l_a v_a = C_b + l_b v_b
    M = np.stack([va, -vb], axis=2)
    depth = np.linalg.solve(np.einsum("kia,kib->kab", M, M), np.einsum("kia,i->ka", M, baseline)[:, :, None])
    return a, b, baseline if np.median(depth[:, :, 0]) > 0 else -baseline


def _centre_from_points(v: np.ndarray, X: np.ndarray) -> np.ndarray:
    """The centre whose rays `v` pass nearest the points `X` in angle: least squares of the distances off the
    rays, each weighted by 1 / its distance squared, in 5 rounds of Cauchy weights (a wrong track goes); a point
    behind the camera counts as missed by a radian."""
    off = _off_rays(v)
    w = np.ones(len(v))
    for _ in range(5):
        try:
            C = np.linalg.solve(np.einsum("k,kij->ij", w, off), np.einsum("k,kij,kj->i", w, off, X))
        except np.linalg.LinAlgError:  # every ray parallel
            return np.full(3, np.nan)
        d = X - C
        dist = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        miss = np.linalg.norm(np.cross(d / dist[:, None], v), axis=1)
        miss[np.einsum("ki,ki->k", d, v) < 0] = 1.0
        width = max(3 * float(np.median(miss)), 1e-3)
        w = 1 / (1 + (miss / width) ** 2) / dist ** 2
    return C


def _ray_angles_deg(v: np.ndarray, X: np.ndarray, C: np.ndarray) -> np.ndarray:
    """(k,) the angle, in degrees, between each ray of `v` (k,3) from its centre `C` (k,3, or one (3,)) and the
    direction to its point of `X` (k,3): how far a camera's rays miss its points."""
    d = X - C
    cos = np.einsum("ki,ki->k", d, v) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _outlier_limit_deg(typical: float) -> float:
    """The median miss over which a camera's rays disagree with its points, given the cameras' typical one:
    `_OUTLIER_DEG` and `_OUTLIER_FACTOR` x `typical` (`outlier_cameras`, and the cameras set aside in
    `centres_in_turn`)."""
    return max(_OUTLIER_DEG, _OUTLIER_FACTOR * typical)


def _adjust_placed(cam, point, v, placed, C, num_points) -> None:
    """The placed cameras' centres (in C) adjusted with the points two of them see (`_minimise`)."""
    keep = placed[cam]
    c, p, rays = cam[keep], point[keep], v[keep]
    keep = np.bincount(p, minlength=num_points)[p] >= 2
    c, p, rays = c[keep], p[keep], rays[keep]
    cams = np.flatnonzero(placed)
    local = np.full(len(placed), -1)
    local[cams] = np.arange(len(cams))
    pts, p = np.unique(p, return_inverse=True)
    layout = _ReducedLayout.of(local[c], p, len(cams), len(pts))
    start = _start(local[c], p, rays, C[cams], C[cams], len(pts))
    C[cams] = _minimise(local[c], p, rays, *start, _TURN_STEPS, layout, robust_iterations=0)[0]


@njit(cache=True, nogil=True)
def _triangulate(points, by_point, bounds, cam, v, placed, C, X, cos_max):  # pragma: no cover - compiled
    """X[p] for each of `points` not yet triangulated whose rays from placed cameras include two at an angle
    whose cosine is at most `cos_max`: the point nearest those rays (least squares), the ray it misses most left
    out while it misses one by over `_TURN_MAX_MISS_DEG` and three rays or more remain; left untriangulated if
    it still misses one by that much, lies behind a camera, or the rays left are parallel."""
    sin_miss = np.sin(np.radians(_TURN_MAX_MISS_DEG))
    x = np.zeros(3)
    for p in points:
        if np.isfinite(X[p, 0]):
            continue
        rays = np.empty(bounds[p + 1] - bounds[p], np.int64)
        n = 0
        lowest = 1.0
        for a in range(bounds[p], bounds[p + 1]):
            k = by_point[a]
            if placed[cam[k]]:
                for b in range(n):
                    kk = rays[b]
                    lowest = min(lowest, v[k, 0] * v[kk, 0] + v[k, 1] * v[kk, 1] + v[k, 2] * v[kk, 2])
                rays[n] = k
                n += 1
        if n < 2 or lowest > cos_max:
            continue
        while True:
            A = np.zeros((3, 3))
            rhs = np.zeros(3)
            for b in range(n):
                k = rays[b]
                for r in range(3):
                    for q in range(3):
                        off = (1.0 if r == q else 0.0) - v[k, r] * v[k, q]
                        A[r, q] += off
                        rhs[r] += off * C[cam[k], q]
            if np.linalg.det(A) <= 1e-12:  # the rays left are parallel: no point
                miss = np.inf
                break
            x = np.linalg.solve(A, rhs)
            worst, miss, behind = -1, 0.0, False
            for b in range(n):
                k = rays[b]
                d = x - C[cam[k]]
                dist = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
                along = d[0] * v[k, 0] + d[1] * v[k, 1] + d[2] * v[k, 2]
                behind |= along <= 0
                off = np.sqrt(max(dist ** 2 - along ** 2, 0.0)) / max(dist, 1e-300)
                if off > miss:
                    worst, miss = b, off
            if miss <= sin_miss or n <= 2:
                break
            rays[worst] = rays[n - 1]
            n -= 1
        if miss <= sin_miss and not behind:
            X[p] = x


@dataclass
class _ReducedLayout:
    """Where each term of the reduced camera system goes, fixed by which cameras see which points: the system is
    sparse, a 3x3 block per pair of cameras that share a point and one per camera, in CSR order (`indptr`,
    `block_col`); each unordered pair of observations of one point adds to one block of the upper triangle
    (`slot_of_pair`, in the order of `order`, the observations sorted by point, `bounds` each point's range), and
    each block below the diagonal (`lower`) is the transpose of one above it (`upper`)."""
    order: np.ndarray
    bounds: np.ndarray
    indptr: np.ndarray
    block_col: np.ndarray
    slot_of_pair: np.ndarray
    slot_of_cam: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    gauge: np.ndarray  # the blocks of camera 0's row and column: held, its rows and columns are the identity's

    @classmethod
    def of(cls, cam, point, num_cams: int, num_points: int) -> "_ReducedLayout":
        order = np.argsort(point, kind="stable")
        bounds = np.r_[0, np.cumsum(np.bincount(point, minlength=num_points))]
        by_cam = np.argsort(cam, kind="stable")
        cam_bounds = np.r_[0, np.cumsum(np.bincount(cam, minlength=num_cams))]
        indptr, block_col = _camera_blocks(cam, point, order, bounds, by_cam, cam_bounds)
        block_row = np.repeat(np.arange(num_cams), np.diff(indptr))
        lower = np.flatnonzero(block_row > block_col)
        # the pattern is symmetric, so the blocks sorted by column, then row, are one for one the transposes of the
        # blocks in CSR order
        upper = np.lexsort((block_row, block_col))[lower]
        return cls(order, bounds, indptr, block_col, _pair_slots(cam, order, bounds, indptr, block_col),
                   np.flatnonzero(block_row == block_col), lower, upper, (block_row == 0) | (block_col == 0))


def _minimise(cam, point, v, C, X, s, iterations, layout: _ReducedLayout, robust_iterations: int = _ROBUST_ITERATIONS,
              stop: Callable[[], bool] | None = None):
    """(centres, points, final cost) of the Levenberg-Marquardt described in `solve_positions`, from C, X, s.
    Each step's per-observation terms are summed in compiled passes (`_normal_terms`, `_reduce_points`,
    `_point_steps`, `_robust_cost`), which keep no 3x3 block per observation. Once `stop()` says the solution is
    no longer wanted, it ends at the next step with an infinite cost."""
    num_cams, num_points = len(C), len(X)
    eye = np.eye(3)
    order, bounds, slot_of_cam, gauge = layout.order, layout.bounds, layout.slot_of_cam, layout.gauge
    # Huber's loss from the random start, then Cauchy's from there: a redescending loss lets the rays of a wrong
    # rotation go instead of pulling every point (a camera turned 10 deg: its rays' median miss 0.7 deg against
    # the others' 0.15 under Huber's alone)
    for cauchy, steps, tolerance in ((False, iterations, _HUBER_TOLERANCE), (True, robust_iterations,
                                                                          _CAUCHY_TOLERANCE)):
        lam = _LAMBDA
        cost, w = _robust_cost(cam, point, v, C, X, s, cauchy)
        for _ in range(steps):
            if stop is not None and stop():
                return C, X, np.inf
            e, g_s, h_s, d, coef, H_CC, H_XX, rhs_C, rhs_X = _normal_terms(cam, point, v, C, X, s, w, lam,
                                                                         num_cams, num_points)
            Xinv = symmetric_inverses(H_XX)
            blocks = np.zeros((len(layout.block_col), 3, 3))
            blocks[slot_of_cam] = H_CC
            _reduce_points(cam, order, bounds, layout.slot_of_pair, layout.lower, layout.upper, e, d, coef, Xinv,
                           rhs_X, blocks, rhs_C)
            blocks[gauge] = 0.0
            blocks[slot_of_cam[0]] = eye
            rhs_C[0] = 0.0
            dC = _solve_reduced(bsr_matrix((blocks, layout.block_col, layout.indptr),
                                           shape=(3 * num_cams, 3 * num_cams)), rhs_C.ravel())
            if not np.isfinite(dC).all():
                lam *= 10
                continue
            dC = dC.reshape(num_cams, 3)
            dX, ds = _point_steps(cam, order, bounds, e, d, coef, Xinv, rhs_X, dC, g_s, h_s, w * s)
            C_new, X_new = C + dC, X + dX
            s_new = np.maximum(s + ds, _MIN_SCALE)
            cost_new, w_new = _robust_cost(cam, point, v, C_new, X_new, s_new, cauchy)
            if cost_new < cost:
                converged = cost - cost_new < tolerance * cost or (lam <= _LAMBDA and _settled(dC, C))
                C, X, s, w, cost = C_new, X_new, s_new, w_new, cost_new
                lam = max(lam / 3, 1e-9)
                if converged:
                    break
            else:
                lam *= 4
                if lam > 1e8:
                    break
    return C, X, cost


def _settled(dC: np.ndarray, C: np.ndarray) -> bool:
    """Whether the step `dC` moves no centre of `C` by more than `_MOVE_TOLERANCE` of the centres' RMS distance
    from their mean. The centres are what positioning gives the mapper, and once an undamped step leaves them
    where they are, the steps that follow move the points and scales, whose cost on a large survey goes on
    falling by more than the Cauchy phase's tolerance for many steps with the centres fixed (docs/benchmarks.md,
    "Global positioning: a phase ends once its centres stay put"). `_minimise` asks this of undamped steps only:
    a step shortened by a damping raised after refused steps moves little wherever it stands, and a walk whose
    centres crawl along a valley of the cost moves them more than this at every step."""
    spread = _spread(C)
    return bool(spread > 0 and np.abs(dC).max() < _MOVE_TOLERANCE * spread)


def _spread(C: np.ndarray) -> float:
    """The RMS distance of the centres `C` (n,3) from their mean: the scale of a solution up to a similarity."""
    return float(np.sqrt(np.mean(np.sum((C - C.mean(axis=0)) ** 2, axis=1))))


def _solve_reduced(S: bsr_matrix, rhs: np.ndarray) -> np.ndarray:
    """S^-1 rhs for the reduced camera system S (3x3 blocks, a row of them per camera; symmetric positive
    definite under LM's damping; NaN where it is singular). From `_ITERATIVE_MIN_CAMERAS` cameras it is solved by
    preconditioned conjugate gradients where they converge: each iteration costs one product with the sparse S,
    while a factorisation's cost grows with the cube of the cameras (docs/benchmarks.md, "Global positioning: conjugate
    gradients from 500 cameras"). Otherwise, and where they fail, a system of up to `_DENSE_MAX_CAMERAS`
    cameras with at least `_DENSE_SHARE` of its entries non-zero is factorised dense by Cholesky (LAPACK),
    faster there than scipy's sparse LU (docs/benchmarks.md, "Global positioning's solver"); a sparser or larger
    one by the sparse LU."""
    n = S.shape[0]
    if n >= 3 * _ITERATIVE_MIN_CAMERAS:
        x = _conjugate_gradients(S, rhs)
        if x is not None:
            return x
    if n <= 3 * _DENSE_MAX_CAMERAS and S.nnz >= _DENSE_SHARE * n * n:
        try:
            return cho_solve(cho_factor(S.toarray(), lower=True, check_finite=False), rhs, check_finite=False)
        except np.linalg.LinAlgError:  # not positive definite after all: the LU decides
            pass
    try:
        return splu(S.tocsc()).solve(rhs)
    except RuntimeError:  # exactly singular
        return np.full(n, np.nan)


def _conjugate_gradients(S: bsr_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """S^-1 rhs by conjugate gradients preconditioned by the inverses of S's 3x3 diagonal blocks (one per camera:
    they hold most of its weight, so the iterations needed stay few), to a residual of `_CG_TOLERANCE` of the
    right-hand side's norm; None where a diagonal block is missing or not positive definite, or where
    `_CG_MAX_ITERATIONS` do not converge, for the direct solvers to decide. The iterations run compiled and
    without the GIL (`_block_cg`): the two starts that `solve_positions` solves at once spend most of their
    steps here from `_ITERATIVE_MIN_CAMERAS` cameras, and scipy's iterations held the GIL between its products."""
    num_cams = S.shape[0] // 3
    rows = np.repeat(np.arange(num_cams), np.diff(S.indptr))
    diagonal = np.flatnonzero(S.indices == rows)
    if len(diagonal) != num_cams:
        return None
    blocks = S.data[diagonal]
    if not (np.isfinite(blocks).all() and (np.linalg.eigvalsh(blocks) > 0).all()):
        return None
    x, converged = _block_cg(np.ascontiguousarray(S.data, dtype=np.float64), S.indices.astype(np.int64),
                             S.indptr.astype(np.int64), np.linalg.inv(blocks), np.ascontiguousarray(rhs, np.float64),
                             _CG_TOLERANCE, _CG_MAX_ITERATIONS)
    return x if converged and np.isfinite(x).all() else None


@njit(cache=True, nogil=True)
def _block_product(data, indices, indptr, x, out):  # pragma: no cover - compiled
    """out = S x for S in 3x3-block CSR form (data (blocks,3,3), indices, indptr) and x of 3 entries a block row."""
    for a in range(len(indptr) - 1):
        y0 = y1 = y2 = 0.0
        for k in range(indptr[a], indptr[a + 1]):
            c = 3 * indices[k]
            x0, x1, x2 = x[c], x[c + 1], x[c + 2]
            y0 += data[k, 0, 0] * x0 + data[k, 0, 1] * x1 + data[k, 0, 2] * x2
            y1 += data[k, 1, 0] * x0 + data[k, 1, 1] * x1 + data[k, 1, 2] * x2
            y2 += data[k, 2, 0] * x0 + data[k, 2, 1] * x1 + data[k, 2, 2] * x2
        out[3 * a], out[3 * a + 1], out[3 * a + 2] = y0, y1, y2


@njit(cache=True, nogil=True)
def _block_cg(data, indices, indptr, inverses, rhs, tolerance, max_iterations):  # pragma: no cover - compiled
    """(x, converged): preconditioned conjugate gradients on the block-CSR system S x = rhs from x = 0, each
    residual multiplied by the inverse of its camera's diagonal block, until |r| <= tolerance |rhs|."""
    n = len(rhs)
    x, r = np.zeros(n), rhs.copy()
    z, p, Sp = np.empty(n), np.empty(n), np.empty(n)
    goal = tolerance * np.sqrt(np.dot(rhs, rhs))
    if np.sqrt(np.dot(r, r)) <= goal:
        return x, True
    _precondition(inverses, r, z)
    p[:] = z
    rz = np.dot(r, z)
    for _ in range(max_iterations):
        _block_product(data, indices, indptr, p, Sp)
        alpha = rz / np.dot(p, Sp)
        for i in range(n):
            x[i] += alpha * p[i]
            r[i] -= alpha * Sp[i]
        if np.sqrt(np.dot(r, r)) <= goal:
            return x, True
        _precondition(inverses, r, z)
        rz, previous = np.dot(r, z), rz
        beta = rz / previous
        for i in range(n):
            p[i] = z[i] + beta * p[i]
    return x, False


@njit(cache=True, nogil=True)
def _precondition(inverses, r, out):  # pragma: no cover - compiled
    """out = the block-diagonal inverses (cameras,3,3) times r."""
    for a in range(len(inverses)):
        r0, r1, r2 = r[3 * a], r[3 * a + 1], r[3 * a + 2]
        for i in range(3):
            out[3 * a + i] = inverses[a, i, 0] * r0 + inverses[a, i, 1] * r1 + inverses[a, i, 2] * r2


@njit(cache=True)
def _camera_blocks(cam, point, order, bounds, by_cam, cam_bounds):  # pragma: no cover - compiled
    """(indptr, columns) of the reduced camera system's blocks in CSR form, columns sorted in each row: camera a's
    row holds itself and every camera that shares a point with it. Built camera by camera over its points'
    observations, so that its memory grows with the blocks and not with the pairs of observations (a point seen
    L times makes L^2 of those)."""
    num_cams = len(cam_bounds) - 1
    mark = np.full(num_cams, -1, np.int64)
    indptr = np.zeros(num_cams + 1, np.int64)
    for sweep in range(2):
        cols = np.empty(indptr[-1], np.int64)
        for a in range(num_cams):
            mark[a] = a + sweep * num_cams  # its own block first, seen in a point or not
            if sweep:
                cols[indptr[a]] = a
            n = 1
            for i in range(cam_bounds[a], cam_bounds[a + 1]):
                p = point[by_cam[i]]
                for j in range(bounds[p], bounds[p + 1]):
                    c = cam[order[j]]
                    if mark[c] != a + sweep * num_cams:
                        mark[c] = a + sweep * num_cams
                        if sweep:
                            cols[indptr[a] + n] = c
                        n += 1
            if sweep:
                cols[indptr[a]:indptr[a] + n].sort()
            else:
                indptr[a + 1] = indptr[a] + n
    return indptr, cols


@njit(cache=True)
def _pair_slots(cam, order, bounds, indptr, cols):  # pragma: no cover - compiled
    """For every unordered pair (k, l) of observations of one point, k no later than l in `order`, point by point,
    the block of (cam[k], cam[l]) in the upper triangle of `_camera_blocks`' CSR layout (row <= column): 4 bytes
    a pair."""
    total = 0
    for p in range(len(bounds) - 1):
        n = bounds[p + 1] - bounds[p]
        total += n * (n + 1) // 2
    slots = np.empty(total, np.int32)
    q = 0
    for p in range(len(bounds) - 1):
        for a in range(bounds[p], bounds[p + 1]):
            ca = cam[order[a]]
            for b in range(a, bounds[p + 1]):
                cb = cam[order[b]]
                row, col = min(ca, cb), max(ca, cb)
                lo, hi = indptr[row], indptr[row + 1]
                slots[q] = lo + np.searchsorted(cols[lo:hi], col)
                q += 1
    return slots


@njit(cache=True, nogil=True)
def _robust_cost(cam, point, v, C, X, s, cauchy):  # pragma: no cover - compiled
    """(cost, weights): the robust cost of the residuals r_k = v_k - s_k (X_point - C_cam), Huber's or Cauchy's
    loss on |r_k|, and each observation's IRLS weight."""
    cost = 0.0
    w = np.empty(len(v))
    for k in range(len(v)):
        sq = 0.0
        for i in range(3):
            r = v[k, i] - s[k] * (X[point[k], i] - C[cam[k], i])
            sq += r * r
        if cauchy:
            cost += _CAUCHY ** 2 * np.log1p(sq / _CAUCHY ** 2)
            w[k] = 1.0 / (1.0 + sq / _CAUCHY ** 2)
        else:
            norm = np.sqrt(sq)
            if norm > _HUBER:
                cost += 2 * _HUBER * norm - _HUBER ** 2
                w[k] = _HUBER / norm
            else:
                cost += sq
                w[k] = 1.0
    return cost, w


@njit(cache=True, nogil=True)
def _normal_terms(cam, point, v, C, X, s, w, lam, num_cams, num_points):  # pragma: no cover - compiled
    """One LM step's weighted normal equations with each observation's scale eliminated, in one pass over the
    observations. With e = X - C and r = v - s e, half the cost's gradient is g = J^T W r (J_C = s I, J_X = -s I,
    J_s = -e); eliminating s (its damped Gauss-Newton term h_s) couples C and X by the block d I - coef e e^T,
    d = w s^2, coef = (w s)^2 / h_s, which adds to both diagonal blocks and, negated, is their (C, X) block Q.
    Returns e, g_s, h_s, d, coef per observation, the damped diagonal blocks H_CC and H_XX and the right-hand
    sides rhs_C and rhs_X."""
    k_all = len(v)
    e = np.empty((k_all, 3))
    g_s, h_s, d, coef = np.empty(k_all), np.empty(k_all), np.empty(k_all), np.empty(k_all)
    H_CC, H_XX = np.zeros((num_cams, 3, 3)), np.zeros((num_points, 3, 3))
    rhs_C, rhs_X = np.zeros((num_cams, 3)), np.zeros((num_points, 3))
    r = np.empty(3)
    for k in range(k_all):
        a, p = cam[k], point[k]
        ee = er = 0.0
        for i in range(3):
            e[k, i] = X[p, i] - C[a, i]
            r[i] = v[k, i] - s[k] * e[k, i]
            ee += e[k, i] * e[k, i]
            er += e[k, i] * r[i]
        ws = w[k] * s[k]
        g_s[k] = -w[k] * er
        d[k] = ws * s[k]
        h_s[k] = w[k] * ee * (1 + lam) + 1e-12
        coef[k] = ws * ws / h_s[k]
        shift = ws * g_s[k] / h_s[k]
        for i in range(3):
            # rhs = -g with the scale's share moved over: -g_C - shift e, -g_X + shift e
            rhs_C[a, i] -= ws * r[i] + shift * e[k, i]
            rhs_X[p, i] += ws * r[i] + shift * e[k, i]
            for j in range(3):
                b = -coef[k] * e[k, i] * e[k, j]
                if i == j:
                    b += d[k]
                H_CC[a, i, j] += b
                H_XX[p, i, j] += b
    for a in range(num_cams):
        for i in range(3):
            H_CC[a, i, i] *= 1 + lam
    for p in range(num_points):
        for i in range(3):
            H_XX[p, i, i] = H_XX[p, i, i] * (1 + lam) + 1e-12
    return e, g_s, h_s, d, coef, H_CC, H_XX, rhs_C, rhs_X


@njit(cache=True, nogil=True)
def _q_block(e, d, coef, k, out):  # pragma: no cover - compiled
    """out = Q_k, observation k's (C, X) block coef e e^T - d I (symmetric)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = coef[k] * e[k, i] * e[k, j]
        out[i, i] -= d[k]


@njit(cache=True, nogil=True)
def _reduce_points(cam, order, bounds, slot, lower, upper, e, d, coef, Xinv, rhs_X, blocks,
                   rhs_C):  # pragma: no cover - compiled
    """The points eliminated from the normal equations: blocks[(cam_k, cam_l)] -= Q_k Xinv_p Q_l for every ordered
    pair (k, l) of observations of one point p, and rhs_C[cam_k] -= Q_k Xinv_p rhs_X[p]; in one pass over the
    points, each point's products formed once. Each unordered pair's product goes to its block in the upper
    triangle alone (`_pair_slots`; Q_l Xinv Q_k is (Q_k Xinv Q_l)^T), and the blocks below the diagonal (`lower`)
    are the transposes of theirs (`upper`) at the end: each pair writes one block instead of two in different rows,
    and its slot takes half the memory (docs/benchmarks.md, "Global positioning: each pair of a point's views
    summed once")."""
    q = 0
    longest = 0
    for p in range(len(bounds) - 1):
        longest = max(longest, bounds[p + 1] - bounds[p])
    QX = np.empty((longest, 3, 3))
    Qs = np.empty((longest, 3, 3))
    for p in range(len(bounds) - 1):
        n = bounds[p + 1] - bounds[p]
        for a in range(n):
            k = order[bounds[p] + a]
            _q_block(e, d, coef, k, Qs[a])
            for i in range(3):
                for j in range(3):
                    QX[a, i, j] = (Qs[a, i, 0] * Xinv[p, 0, j] + Qs[a, i, 1] * Xinv[p, 1, j]
                                   + Qs[a, i, 2] * Xinv[p, 2, j])
            for i in range(3):
                rhs_C[cam[k], i] -= QX[a, i, 0] * rhs_X[p, 0] + QX[a, i, 1] * rhs_X[p, 1] + QX[a, i, 2] * rhs_X[p, 2]
        for a in range(n):
            ca = cam[order[bounds[p] + a]]
            for b in range(a, n):
                cb = cam[order[bounds[p] + b]]
                t = slot[q]
                q += 1
                straight = ca <= cb
                transposed = ca > cb or (ca == cb and a != b)  # its transpose is another pair's product
                for i in range(3):
                    for j in range(3):
                        m = QX[a, i, 0] * Qs[b, 0, j] + QX[a, i, 1] * Qs[b, 1, j] + QX[a, i, 2] * Qs[b, 2, j]
                        if straight:
                            blocks[t, i, j] -= m
                        if transposed:
                            blocks[t, j, i] -= m
    for k in range(len(lower)):
        for i in range(3):
            for j in range(3):
                blocks[lower[k], i, j] = blocks[upper[k], j, i]


@njit(cache=True, nogil=True)
def _point_steps(cam, order, bounds, e, d, coef, Xinv, rhs_X, dC, g_s, h_s, ws):  # pragma: no cover - compiled
    """The points' and the scales' steps once the centres' step dC is known: dX_p = Xinv_p (rhs_X[p] - sum over
    its observations of Q_k dC[cam_k]), ds_k = (-g_s - w s e . (dX - dC)) / h_s."""
    dX = np.zeros((len(bounds) - 1, 3))
    ds = np.empty(len(e))
    Q = np.empty((3, 3))
    b = np.empty(3)
    for p in range(len(bounds) - 1):
        b[:] = rhs_X[p]
        for a in range(bounds[p], bounds[p + 1]):
            k = order[a]
            _q_block(e, d, coef, k, Q)
            for i in range(3):
                b[i] -= Q[i, 0] * dC[cam[k], 0] + Q[i, 1] * dC[cam[k], 1] + Q[i, 2] * dC[cam[k], 2]
        for i in range(3):
            dX[p, i] = Xinv[p, i, 0] * b[0] + Xinv[p, i, 1] * b[1] + Xinv[p, i, 2] * b[2]
        for a in range(bounds[p], bounds[p + 1]):
            k = order[a]
            step = 0.0
            for i in range(3):
                step += e[k, i] * (dX[p, i] - dC[cam[k], i])
            ds[k] = (-g_s[k] - ws[k] * step) / h_s[k]
    return dX, ds


def outlier_cameras(result: PositioningResult) -> dict[int, str]:
    """Image -> reason, for the cameras whose rays disagree with the points of their tracks (median angle over
    `_OUTLIER_DEG` and `_OUTLIER_FACTOR` x the cameras' median): a rotation the averaging got wrong (a camera
    flipped) or a camera the tracks do not hold gets a pose no bundle adjustment repairs, and would be written
    flipped or thrown far away; it is left out, to be registered against the model's points if it can be."""
    r = result.residual_deg
    if r is None or not np.isfinite(r).any():
        return {}
    typical = float(np.nanmedian(r))
    limit = _outlier_limit_deg(typical)
    return {int(i): (f"its global pose was an outlier: its rays miss the points of its tracks by {r[i]:.1f} deg "
                     f"(median), the model's cameras by {typical:.2f} deg (a flipped or far-thrown camera)")
            for i in np.flatnonzero(np.isfinite(r) & (r > limit))}
