"""Accuracy metrics with the names used everywhere (reports, notes, benchmarks), as pure functions.

Poses are plain dicts `image name -> (R, t)` with R, t the world-to-camera rotation and translation
(COLMAP's cam_from_world), so the same functions serve pycolmap models, our own model and ground-truth files.
"""

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..geometry.rotation import rotation_angle_deg, rotation_error_deg, vector_angle_deg
from ..geometry.sim3 import Sim3, ransac_umeyama

Pose = tuple[np.ndarray, np.ndarray]  # (R, t) world-to-camera
AUC_THRESHOLDS = (0.5, 1.0, 5.0, 10.0)
FAILED_DEG = 180.0  # error given to a pair that is unregistered or split across models


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -np.asarray(R).T @ np.asarray(t)


def pose_auc(errors_deg: Iterable[float], thresholds: Iterable[float] = AUC_THRESHOLDS) -> dict[float, float]:
    """Area under the cumulative error curve up to each threshold, normalised to [0, 1] (COLMAP's benchmark)."""
    errors = np.sort(np.asarray(errors_deg, dtype=float))
    if errors.size == 0:
        return {t: 0.0 for t in thresholds}
    recall = np.arange(1, len(errors) + 1) / len(errors)
    errors, recall = np.r_[0.0, errors], np.r_[0.0, recall]
    out = {}
    for t in thresholds:
        k = int(np.searchsorted(errors, t))
        e = np.r_[errors[:k], t]
        r = np.r_[recall[:k], recall[k - 1]]
        out[t] = float(np.sum((e[1:] - e[:-1]) * (r[1:] + r[:-1]) / 2.0) / t)
    return out


def relative_pose_error_matrix(est: list[Pose], ref: list[Pose]) -> np.ndarray:
    """(n, n): entry (a, b) is max(rotation error, translation-direction error) in degrees of the relative pose
    a -> b against the reference's; a direction that is undefined (coincident centres) counts as FAILED_DEG.
    All pairs at once: the rotation error is the angle of D_a D_b^T with D = R_est^T R_ref, the direction error
    the angle between R_b (C_a - C_b) of the two."""
    def parts(poses):
        R = np.stack([np.asarray(p[0], float) for p in poses])
        C = np.stack([camera_center(*p) for p in poses])
        return R, np.einsum("bij,abj->bai", R, C[:, None, :] - C[None, :, :])  # [b, a] = R_b (C_a - C_b)
    (R1, v1), (R2, v2) = parts(est), parts(ref)
    d = np.einsum("nji,njk->nik", R1, R2)
    rot = rotation_angle_deg(np.einsum("aij,bkj->abik", d, d))  # [a, b] = D_a D_b^T
    direction = vector_angle_deg(v1, v2).T  # FAILED_DEG (180) where a direction is undefined
    return np.maximum(rot, direction)


def relative_pose_errors(models: list[dict], gt: dict) -> np.ndarray:
    """Errors over all pairs of ground-truth images, in the order of combinations(sorted(gt), 2); FAILED_DEG
    where a pair is not in one estimated model."""
    names = sorted(gt)
    model_of = {}
    for k, model in enumerate(models):
        for name in model:
            model_of.setdefault(name, k)  # an image in several models counts in the first (largest) one
    errors = np.full((len(names), len(names)), FAILED_DEG)
    for k, model in enumerate(models):
        members = [i for i, n in enumerate(names) if model_of.get(n) == k]
        if len(members) >= 2:
            errors[np.ix_(members, members)] = relative_pose_error_matrix([model[names[i]] for i in members],
                                                                          [gt[names[i]] for i in members])
    return errors[np.triu_indices(len(names), 1)]


MISPLACED_DEG = 5.0  # an image whose poses relative to the model's other images are off by more is misplaced


def misplaced_images(model: dict, gt: dict, max_deg: float = MISPLACED_DEG) -> list[str]:
    """The images of one model registered at a wrong pose: those whose relative poses to the model's other images
    (relative_pose_error_matrix: rotation or direction) are off by a median over `max_deg`. An image
    counted as registered should be at a right pose, and a right pose is within a degree or so of most others, so
    one wrong image stands out whatever the model's frame and scale; where most of the model is wrong, every image
    is. Empty under three shared images."""
    names = sorted(set(model) & set(gt))
    if len(names) < 3:
        return []
    err = relative_pose_error_matrix([model[n] for n in names], [gt[n] for n in names])
    np.fill_diagonal(err, np.nan)
    return [n for n, e in zip(names, np.nanmedian(err, axis=1)) if e > max_deg]


@dataclass(kw_only=True)
class Alignment:
    sim3: Sim3  # maps the estimated world frame into the reference frame
    inliers: list[str]
    rotation_errors_deg: dict[str, float]
    center_errors: dict[str, float]  # in reference units
    scene_extent: float  # reference units: the largest distance of a camera centre from their median


def align_and_compare(est: dict, ref: dict, inlier_fraction: float = 0.05, seed: int = 0) -> Alignment | None:
    """Robust Sim3 of camera centres (Umeyama in RANSAC), then per-image rotation and centre errors.

    The inlier threshold is `inlier_fraction` of the reference's extent. None when fewer than 3 images are shared.
    """
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        return None
    src = np.array([camera_center(*est[n]) for n in names])
    dst = np.array([camera_center(*ref[n]) for n in names])
    extent = float(np.max(np.linalg.norm(dst - np.median(dst, axis=0), axis=1)))
    T, mask = ransac_umeyama(src, dst, threshold=max(inlier_fraction * extent, 1e-12), seed=seed)
    aligned = T.apply(src)
    rot, cen = {}, {}
    for k, n in enumerate(names):
        R_aligned = est[n][0] @ T.R.T  # cam_from_ref = cam_from_est * est_from_ref
        rot[n] = rotation_error_deg(R_aligned, ref[n][0])
        cen[n] = float(np.linalg.norm(aligned[k] - dst[k]))
    return Alignment(sim3=T, inliers=[n for n, m in zip(names, mask) if m], rotation_errors_deg=rot,
                     center_errors=cen, scene_extent=extent)


def accuracy_summary(models: list[dict], gt: dict) -> dict:
    """The headline numbers of a run against ground truth, keyed by the project's metric names."""
    errors = relative_pose_errors(models, gt)
    auc = pose_auc(errors)
    largest = models[0] if models else {}
    registered = len(set().union(*[set(m) for m in models]) & set(gt)) if models else 0
    summary = {f"auc@{t:g}": auc[t] for t in AUC_THRESHOLDS}
    summary.update({"registered": registered, "registered_pct": 100.0 * registered / max(len(gt), 1),
                    "components": len(models), "misplaced": len(misplaced_images(largest, gt))})
    alignment = align_and_compare(largest, gt)
    if alignment is not None:
        rot = np.array(list(alignment.rotation_errors_deg.values()))
        cen = np.array(list(alignment.center_errors.values()))
        summary.update({"median_rotation_error_deg": float(np.median(rot)),
                        "max_rotation_error_deg": float(rot.max()),
                        "median_center_error": float(np.median(cen)),
                        "median_center_error_pct": float(100 * np.median(cen) / max(alignment.scene_extent, 1e-12))})
    return summary
