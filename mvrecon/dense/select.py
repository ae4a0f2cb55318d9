"""Source views of each reference view and its depth range, from the sparse model, as COLMAP and MVSNet choose
them: the views that see many of the same sparse points at a useful triangulation angle and a similar
resolution.

A shared point counts exp(-(a - 5 deg)^2 / (2 s^2)) with s = 1 deg below 5 deg and 10 deg above (MVSNet's
piecewise Gaussian), times min(r, 1/r) for the ratio r of the pixel footprints of the point in the two views
(a view much closer or farther sees the surface at another scale).
"""

from dataclasses import dataclass

import numpy as np

from .views import View

MIN_POINTS = 12  # sparse points a view must see for its depth range
MIN_SHARED = 8  # sparse points a source view must share with the reference
MIN_ANGLE_DEG = 1.0  # median triangulation angle of a usable source view
PREFERRED_ANGLE_DEG = 5.0


@dataclass
class Selection:
    """A reference view's sources (best first, their scores) and depth range, or why it has none."""

    sources: list[int]
    scores: list[float]
    depth_range: tuple[float, float] | None
    reason: str | None = None


def depth_range(view: View, margin: float = 0.25) -> tuple[float, float] | None:
    """(near, far) around the sparse points in front of the view (2nd to 98th percentile of their depths,
    widened by `margin` in inverse depth at both ends); None with fewer than MIN_POINTS."""
    z = view.depths(view.points)
    z = z[z > 0]
    if len(z) < MIN_POINTS:
        return None
    lo, hi = np.percentile(z, [2, 98])
    q_far, q_near = 1.0 / hi, 1.0 / lo
    span = q_near - q_far
    q_far = max(q_far - margin * span, 0.5 * q_far)
    q_near = q_near + margin * span
    return 1.0 / q_near, 1.0 / q_far


def _score(ref: View, src: View) -> tuple[float, float, int]:
    """(score, median triangulation angle in degrees, shared points) of `src` as a source of `ref`."""
    shared, i_ref, _ = np.intersect1d(ref.point_ids, src.point_ids, return_indices=True)
    if len(shared) == 0:
        return 0.0, 0.0, 0
    xyz = ref.points[i_ref]
    a, b = xyz - ref.center, xyz - src.center
    da, db = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    cos = np.sum(a * b, axis=1) / np.maximum(da * db, 1e-12)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    sigma = np.where(angle < PREFERRED_ANGLE_DEG, 1.0, 10.0)
    weight = np.exp(-((angle - PREFERRED_ANGLE_DEG) ** 2) / (2 * sigma**2))
    footprint = (da / ref.K[0, 0]) / np.maximum(db / src.K[0, 0], 1e-12)
    weight *= np.minimum(footprint, 1.0 / np.maximum(footprint, 1e-12))
    return float(weight.sum()), float(np.median(angle)), len(shared)


def select_sources(views: list[View], max_sources: int) -> list[Selection]:
    """Per view, up to `max_sources` source views by score (best first) and its depth range; `reason` says why a
    view gets no depth map (too few sparse points, no overlapping source view)."""
    out = []
    for ref in views:
        rng = depth_range(ref)
        if rng is None:
            out.append(Selection([], [], None, f"sees {len(ref.points)} sparse points (needs {MIN_POINTS}) to "
                                               "bound its depths"))
            continue
        scored = []
        for src in views:
            if src.index == ref.index:
                continue
            score, angle, shared = _score(ref, src)
            if shared >= MIN_SHARED and angle >= MIN_ANGLE_DEG and score > 0:
                scored.append((score, src.index))
        scored.sort(reverse=True)
        scored = scored[:max_sources]
        reason = None if scored else (f"no source view shares {MIN_SHARED} sparse points with it at a "
                                      f"triangulation angle of {MIN_ANGLE_DEG:g} degrees or more")
        out.append(Selection([i for _, i in scored], [s for s, _ in scored], rng, reason))
    return out
