"""Ground-truth overlapping pairs of a catalog scene and the share of them a pair selection keeps."""

from mvrecon.eval.overlap import overlapping_pairs, pair_recall, shared_points


def test_overlap_falls_with_the_distance_along_the_orbit(object_orbit_small):
    gt = object_orbit_small / "gt" / "sparse"
    shared, seen = shared_points(gt)
    names = sorted(seen)
    assert len(names) == 10 and all(a < b for a, b in shared)
    # a half orbit 20 degrees a step around one object: view 0 shares less and less with the views farther on
    fraction = [shared[(names[0], b)] / min(seen[names[0]], seen[b]) for b in names[1:]]
    assert fraction[0] > 0.8 and fraction[0] > fraction[1] > fraction[2] > fraction[-1] and fraction[-1] < 0.4
    close = overlapping_pairs(gt, min_fraction=0.7)
    neighbours = {(names[i], names[i + 1]) for i in range(9)}
    assert neighbours <= close and all(int(b[:4]) - int(a[:4]) <= 2 for a, b in close)
    assert overlapping_pairs(gt, min_fraction=0.0) == set(shared) and len(shared) == 45
    assert pair_recall(neighbours, close) == 9 / len(close) < 1.0
    assert pair_recall([(b, a) for a, b in close], close) == 1.0  # either order
    assert pair_recall([], set()) == 1.0
