"""Joint solution of a tilt series: tracks, Tomasi-Kanade factorisation, metric upgrade, least-squares adjustment.

Two parallel-projection views fix heights only once the tilt difference is known (the bas-relief ambiguity:
a larger tilt with flatter heights explains the same parallax). Three or more views fix the tilts too: the
affine factorisation of the measurement matrix gives cameras up to a 3x3 affine map, and asking every camera to
be an orthographic rotation with the reference pixel scale (rows orthonormal) makes it metric. The relative
rotations then give the tilt axis and angles, which seed a least-squares adjustment of every observation
(tilts, axis, per-image drift and points) with a robust loss. World frame, units and signs: see `parallax.py`.
"""

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.rotation import nearest_rotation
from .parallax import tilt_rotation


@dataclass(frozen=True)
class Observations:
    """Track observations: image index, track (point) index and centred pixel coordinates of each."""

    image: np.ndarray  # (K,) int
    point: np.ndarray  # (K,) int
    uv: np.ndarray  # (K,2) float, pixels relative to the image centre

    @property
    def num_points(self) -> int:
        return int(self.point.max()) + 1 if len(self.point) else 0


@dataclass(frozen=True)
class TiltSolution:
    """Cameras and points of a tilt series. tilts_deg are absolute when given, else relative to the reference."""

    tilts_deg: np.ndarray
    axis_deg: float
    shifts: np.ndarray  # (F,2) per-image drift in pixels, zero for the reference image
    points: np.ndarray  # (P,3) world points (reference pixels), NaN for tracks dropped as outliers
    reference: int
    rms_px: float
    observations_used: int


def build_tracks(pair_matches: dict, centred_keypoints: list) -> Observations:
    """Union-find over pairwise matches {(i, j): (M,2) keypoint indices}; tracks seen twice in one image are dropped."""
    offsets = np.cumsum([0] + [len(k) for k in centred_keypoints])
    parent = np.arange(offsets[-1])

    def find(x):
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for (i, j), m in pair_matches.items():
        for a, b in zip(offsets[i] + m[:, 0], offsets[j] + m[:, 1]):
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    used = np.unique(np.concatenate([np.concatenate([offsets[i] + m[:, 0], offsets[j] + m[:, 1]])
                                     for (i, j), m in pair_matches.items()] or [np.zeros(0, int)]))
    roots = np.array([find(x) for x in used], dtype=int)
    image = np.searchsorted(offsets, used, side="right") - 1
    _, track = np.unique(roots, return_inverse=True)
    # a track with two keypoints in one image is an inconsistent chain of matches: drop it
    key = track * len(centred_keypoints) + image
    _, counts = np.unique(key, return_counts=True)
    dup_tracks = np.unique(track[np.isin(key, np.unique(key)[counts > 1])])
    keep = ~np.isin(track, dup_tracks)
    image, used, track = image[keep], used[keep], track[keep]
    per_track = np.bincount(track)
    keep = per_track[track] >= 2
    image, used, track = image[keep], used[keep], track[keep]
    _, track = np.unique(track, return_inverse=True)
    uv = np.array([centred_keypoints[i][u - offsets[i]] for i, u in zip(image, used)]).reshape(-1, 2)
    return Observations(image=image, point=track, uv=uv)


def affine_factorization(W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tomasi-Kanade: W (2F,P) rows u_0, v_0, u_1, ... -> (M (2F,3), S (3,P), t (2F,)) with W ~ M S + t."""
    W = np.asarray(W, dtype=float)
    t = W.mean(axis=1)
    U, s, Vt = np.linalg.svd(W - t[:, None], full_matrices=False)
    root = np.sqrt(s[:3])
    return U[:, :3] * root, root[:, None] * Vt[:3], t


def _quadric_row(a, b) -> np.ndarray:
    """Coefficients of a^T L b in the 6 unknowns (l11, l12, l13, l22, l23, l33) of a symmetric L."""
    return np.array([a[0] * b[0], a[0] * b[1] + a[1] * b[0], a[0] * b[2] + a[2] * b[0],
                     a[1] * b[1], a[1] * b[2] + a[2] * b[1], a[2] * b[2]])


def metric_upgrade(M: np.ndarray) -> np.ndarray:
    """Q (3x3) making every camera M_i Q an orthographic projection at unit scale (orthonormal rows).

    Solves linearly for L = Q Q^T from |m1 L m1| = |m2 L m2| = 1 and m1 L m2 = 0 per view, then factors L.
    """
    M = np.asarray(M, dtype=float)
    rows, rhs = [], []
    for i in range(len(M) // 2):
        m1, m2 = M[2 * i], M[2 * i + 1]
        rows += [_quadric_row(m1, m1), _quadric_row(m2, m2), _quadric_row(m1, m2)]
        rhs += [1.0, 1.0, 0.0]
    q = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    L = np.array([[q[0], q[1], q[2]], [q[1], q[3], q[4]], [q[2], q[4], q[5]]])
    w, V = np.linalg.eigh(L)
    w = np.maximum(w, 1e-9 * w.max())
    return V * np.sqrt(w)


def _closest_rotation(rows2) -> np.ndarray:
    return nearest_rotation(np.vstack([rows2, np.cross(rows2[0], rows2[1])]))


def tilts_from_factorization(W: np.ndarray, reference: int,
                             axis_deg: float | None = None) -> tuple[np.ndarray, float]:
    """(tilts_deg relative to `reference`, axis_deg) from a complete measurement matrix W (2F,P), centred pixels.

    The relative rotations R_i R_ref^T of the metric cameras all turn about the tilt axis; the axis is their mean
    rotation vector projected into the image plane (or `axis_deg` when given). The depth-reversal ambiguity is
    resolved by the convention that tilts increase along the image order.
    """
    M, _, _ = affine_factorization(W)
    Q = metric_upgrade(M)
    Rs = [_closest_rotation(M[2 * i:2 * i + 2] @ Q) for i in range(len(M) // 2)]
    rotvecs = np.array([Rotation.from_matrix(R @ Rs[reference].T).as_rotvec() for R in Rs])
    lead = rotvecs[np.argmax(np.linalg.norm(rotvecs, axis=1))]
    signs = np.where(rotvecs @ lead < 0, -1.0, 1.0)
    axis3 = (rotvecs * signs[:, None]).sum(axis=0)
    if axis_deg is None:
        axis_deg = float(np.degrees(np.arctan2(axis3[1], axis3[0])) % 180.0)
    a = np.array([np.cos(np.radians(axis_deg)), np.sin(np.radians(axis_deg)), 0.0])
    tilts = -np.degrees(rotvecs @ a)  # a tilt by theta turns about -a (see parallax.tilt_rotation)
    if tilts[-1] < tilts[0]:
        tilts = -tilts
    return tilts, axis_deg


def _rotations(tilts_deg, axis_deg) -> np.ndarray:
    return np.array([tilt_rotation(axis_deg, t) for t in tilts_deg])


def triangulate_tracks(obs: Observations, tilts_deg: np.ndarray, axis_deg: float,
                       shifts: np.ndarray) -> np.ndarray:
    """Linear least-squares points (P,3) from all observations of each track, cameras known."""
    A = _rotations(tilts_deg, axis_deg)[:, :2, :][obs.image]  # (K,2,3)
    b = obs.uv - np.asarray(shifts)[obs.image]
    n = obs.num_points
    AtA = np.zeros((n, 3, 3))
    Atb = np.zeros((n, 3))
    np.add.at(AtA, obs.point, np.einsum("kji,kjl->kil", A, A))
    np.add.at(Atb, obs.point, np.einsum("kji,kj->ki", A, b))
    AtA += 1e-12 * np.eye(3)
    return np.linalg.solve(AtA, Atb[..., None])[..., 0]


def _initial_shifts(obs: Observations, tilts_deg, axis_deg, reference: int, num_images: int) -> np.ndarray:
    """Per-image drift by alternating triangulation and median residuals (reference drift held at zero)."""
    shifts = np.zeros((num_images, 2))
    R = _rotations(tilts_deg, axis_deg)
    for _ in range(5):
        X = triangulate_tracks(obs, tilts_deg, axis_deg, shifts)
        res = obs.uv - np.einsum("kij,kj->ki", R[obs.image, :2, :], X[obs.point])
        for i in range(num_images):
            if i != reference and np.any(obs.image == i):
                shifts[i] = np.median(res[obs.image == i], axis=0)
    return shifts


def _camera_jacobian(obs: Observations, tilts, axis, X, free, fit_tilts, fit_axis) -> np.ndarray:
    """(K,2,m) derivatives of each prediction by the camera parameters [axis, free tilts, free drifts] (degrees, px)."""
    K = len(obs.image)
    cols = []
    if fit_axis:
        eps = 1e-5
        dR = (_rotations(tilts, axis + eps) - _rotations(tilts, axis - eps)) / (2 * eps)
        cols.append(np.einsum("kij,kj->ki", dR[obs.image, :2, :], X[obs.point]))
    if fit_tilts:  # R = exp(-theta [a]x), so dR/dtheta = -[a]x R (per degree)
        a = -np.array([np.cos(np.radians(axis)), np.sin(np.radians(axis)), 0.0])
        ax = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        dR = np.radians(1.0) * np.einsum("ij,fjk->fik", ax, _rotations(tilts, axis))
        d = np.einsum("kij,kj->ki", dR[obs.image, :2, :], X[obs.point])
        for i in free:
            cols.append(np.where((obs.image == i)[:, None], d, 0.0))
    for i in free:
        for j in range(2):
            col = np.zeros((K, 2))
            col[obs.image == i, j] = 1.0
            cols.append(col)
    return np.stack(cols, axis=-1) if cols else np.zeros((K, 2, 0))


def adjust(obs: Observations, tilts_deg: np.ndarray, axis_deg: float, shifts: np.ndarray, points: np.ndarray,
           reference: int, fit_tilts: bool, fit_axis: bool, huber_px: float = 1.0,
           max_iterations: int = 50) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, float]:
    """Least-squares adjustment of all observations: Levenberg-Marquardt with the points eliminated (Schur
    complement), Huber weights on pixel residuals (iteratively reweighted).

    Free: points, per-image drift (reference fixed at zero) and, when asked, the tilts (reference fixed) and the
    axis. Eliminating the 3x3 point blocks leaves a system the size of the camera parameters, so each step is
    exact and cheap even with tens of thousands of points.
    Returns (tilts_deg, axis_deg, shifts, points, residuals (K,2)).
    """
    F, P = len(tilts_deg), len(points)
    free = [i for i in range(F) if i != reference]
    tilts, axis = np.asarray(tilts_deg, dtype=float).copy(), float(axis_deg)
    d, X = np.asarray(shifts, dtype=float).copy(), np.asarray(points, dtype=float).copy()

    def residual(tilts, axis, d, X):
        R = _rotations(tilts, axis)
        return np.einsum("kij,kj->ki", R[obs.image, :2, :], X[obs.point]) + d[obs.image] - obs.uv

    def robust_cost(r):
        e = np.linalg.norm(r, axis=1)
        return float(np.sum(np.where(e <= huber_px, 0.5 * e ** 2, huber_px * (e - 0.5 * huber_px))))

    def apply(dc, dX):
        t, a, dd = tilts.copy(), axis, d.copy()
        k = 0
        if fit_axis:
            a, k = axis + dc[0], 1
        if fit_tilts:
            t[free] += dc[k:k + len(free)]
            k += len(free)
        dd[free] += dc[k:].reshape(-1, 2)
        return t, a, dd, X + dX

    r = residual(tilts, axis, d, X)
    cost, lam = robust_cost(r), 1e-3
    for _ in range(max_iterations):
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12))
        B = _rotations(tilts, axis)[obs.image, :2, :]  # (K,2,3)
        A = _camera_jacobian(obs, tilts, axis, X, free, fit_tilts, fit_axis)  # (K,2,m)
        m = A.shape[2]
        Hpp = np.zeros((P, 3, 3))
        np.add.at(Hpp, obs.point, w[:, None, None] * np.einsum("kji,kjl->kil", B, B))
        gp = np.zeros((P, 3))
        np.add.at(gp, obs.point, w[:, None] * np.einsum("kji,kj->ki", B, r))
        Hcp = np.zeros((P, m, 3))
        np.add.at(Hcp, obs.point, w[:, None, None] * np.einsum("kji,kjl->kil", A, B))
        Hcc = np.einsum("k,kji,kjl->il", w, A, A)
        gc = np.einsum("k,kji,kj->i", w, A, r)
        while True:
            Hpp_d = Hpp + lam * np.eye(3) * np.maximum(np.einsum("pii->pi", Hpp), 1e-9)[:, :, None]
            Hpp_inv = np.linalg.inv(Hpp_d)
            HcpHinv = np.einsum("pmi,pij->pmj", Hcp, Hpp_inv)
            S = Hcc + lam * np.diag(np.maximum(np.diag(Hcc), 1e-9)) - np.einsum("pmj,pnj->mn", HcpHinv, Hcp)
            rhs = -gc + np.einsum("pmj,pj->m", HcpHinv, gp)
            dc = np.linalg.solve(S, rhs) if m else np.zeros(0)
            dX = -np.einsum("pij,pj->pi", Hpp_inv, gp + np.einsum("pmi,m->pi", Hcp, dc))
            candidate = apply(dc, dX)
            r_new = residual(*candidate)
            new_cost = robust_cost(r_new)
            if new_cost < cost:
                break
            lam *= 10.0
            if lam > 1e8:
                break
        if new_cost >= cost:
            break
        tilts, axis, d, X = candidate
        improvement = (cost - new_cost) / max(cost, 1e-300)
        r, cost, lam = r_new, new_cost, max(lam / 10.0, 1e-9)
        if improvement < 1e-10:
            break
    if abs(np.sin(np.radians(tilts[reference]))) < 1e-12:  # gauge: heights relative to their mean
        offset = X[:, 2].mean()
        X[:, 2] -= offset
        d += offset * _rotations(tilts, axis)[:, :2, 2]
    return tilts, float(axis % 180.0), d, X, residual(tilts, axis, d, X)


def solve_tilt_series(obs: Observations, num_images: int, reference: int,
                      tilts_deg: Sequence[float] | None = None, axis_deg: float | None = None,
                      axis_guess_deg: float = 90.0, outlier_px: float = 3.0) -> TiltSolution:
    """Cameras and points of a tilt series from its tracks, estimating whatever of tilts and axis is not given.

    Unknown tilts need >= 3 images and tracks seen in all of them (the factorisation's complete measurement
    matrix); an unknown axis with known tilts starts from `axis_guess_deg` (e.g. from the affine F). Observations
    with a residual above `outlier_px` after the first adjustment are dropped and the adjustment rerun.
    """
    fit_tilts, fit_axis = tilts_deg is None, axis_deg is None
    if fit_tilts:
        if num_images < 3:
            raise ValueError("estimating tilt angles needs at least 3 images (two views leave the tilt and the "
                             "height scale ambiguous); give --tilts")
        counts = np.bincount(obs.point, minlength=obs.num_points)
        complete = np.flatnonzero(counts == num_images)
        if len(complete) < 8:
            raise ValueError(f"only {len(complete)} features are matched in all {num_images} images; the tilt "
                             "estimate needs at least 8")
        W = np.zeros((2 * num_images, len(complete)))
        sel = np.isin(obs.point, complete)
        col = np.searchsorted(complete, obs.point[sel])
        W[2 * obs.image[sel], col] = obs.uv[sel, 0]
        W[2 * obs.image[sel] + 1, col] = obs.uv[sel, 1]
        tilts, axis = tilts_from_factorization(W, reference, axis_deg)
    else:
        tilts = np.asarray(tilts_deg, dtype=float)
        axis = axis_guess_deg if fit_axis else axis_deg
    shifts = _initial_shifts(obs, tilts, axis, reference, num_images)
    points = triangulate_tracks(obs, tilts, axis, shifts)
    tilts, axis, shifts, points, res = adjust(obs, tilts, axis, shifts, points, reference, fit_tilts, fit_axis)
    err = np.linalg.norm(res, axis=1)
    keep = err < outlier_px
    if not keep.all():
        counts = np.bincount(obs.point[keep], minlength=obs.num_points)
        keep &= counts[obs.point] >= 2
        kept_points = np.flatnonzero(counts >= 2)
        remap = np.full(obs.num_points, -1)
        remap[kept_points] = np.arange(len(kept_points))
        sub = Observations(obs.image[keep], remap[obs.point[keep]], obs.uv[keep])
        tilts, axis, shifts, sub_points, res = adjust(sub, tilts, axis, shifts, points[kept_points], reference,
                                                      fit_tilts, fit_axis)
        points = np.full_like(points, np.nan)
        points[kept_points] = sub_points
    rms = float(np.sqrt(np.mean(np.sum(res ** 2, axis=1))))
    return TiltSolution(tilts_deg=np.asarray(tilts), axis_deg=axis, shifts=shifts, points=points,
                        reference=reference, rms_px=rms, observations_used=int(len(res)))
