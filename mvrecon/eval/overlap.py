"""Which image pairs of a ground-truth scene overlap, and how many of them a pair selection found.

A catalog scene's `gt/sparse` model lists, for every surface point, the views that see it (its track, occlusion
checked against the rendered depth). Two views overlap when at least `min_fraction` of the points the sparser
of them sees are seen by both: the pairs that matching must not leave out. `pair_recall` is the share of those
pairs a selection (`matching.pairs`) kept.
"""

from collections import Counter
from collections.abc import Iterable
from itertools import combinations
from pathlib import Path

from ..io.colmap_model import load_reconstruction

MIN_FRACTION = 0.25  # of the sparser view's points seen by both views


def shared_points(gt_sparse: Path | str) -> tuple[dict[tuple[str, str], int], dict[str, int]]:
    """({(name1, name2): points seen by both, name1 < name2}, {name: points it sees}) of a ground-truth model."""
    rec = load_reconstruction(gt_sparse)
    names = {image_id: image.name for image_id, image in rec.images.items()}
    shared, seen = Counter(), Counter()
    for point in rec.points3D.values():
        views = sorted({names[e.image_id] for e in point.track.elements})
        seen.update(views)
        shared.update(combinations(views, 2))
    return dict(shared), dict(seen)


def overlapping_pairs(gt_sparse: Path | str, min_fraction: float = MIN_FRACTION) -> set[tuple[str, str]]:
    """The pairs (name1 < name2) of a ground-truth model that share at least `min_fraction` of the points of the
    view that sees fewer."""
    shared, seen = shared_points(gt_sparse)
    return {pair for pair, n in shared.items() if n >= min_fraction * min(seen[pair[0]], seen[pair[1]])}


def pair_recall(selected: Iterable[tuple[str, str]], overlapping: set[tuple[str, str]]) -> float:
    """The share of the `overlapping` pairs among the `selected` ones (either order); 1.0 when none overlap."""
    if not overlapping:
        return 1.0
    chosen = {tuple(sorted(p)) for p in selected}
    return sum(tuple(sorted(p)) in chosen for p in overlapping) / len(overlapping)
