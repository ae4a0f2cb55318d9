"""Source views and depth ranges from the sparse model: overlapping views chosen best first, and a clear reason
for a view with too few sparse points or no overlapping view."""

import numpy as np

from mvrecon.dense.select import MIN_POINTS, select_sources
from mvrecon.dense.views import View

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _view(index: int, center, ids, points) -> View:
    R = np.eye(3)  # all look along +z
    return View(index, f"{index}.png", K, R, -R @ np.asarray(center, float), 640, 480, points[ids], np.asarray(ids))


def test_overlapping_views_are_chosen_and_the_others_get_reasons():
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-2, 2, 400), rng.uniform(-1.5, 1.5, 400), rng.uniform(4, 6, 400)])
    shared = np.arange(300)
    views = [
        _view(0, [0.0, 0, 0], shared, points),
        _view(1, [0.5, 0, 0], shared, points),  # about 6 degrees from view 0: the best source
        _view(2, [1.5, 0, 0], shared, points),  # about 17 degrees
        _view(3, [0.001, 0, 0], shared, points),  # the same place: no triangulation angle
        _view(4, [0.0, 1, 0], np.arange(300, 400), points),  # sees points no other view sees
        _view(5, [0.2, 0, 0], np.arange(MIN_POINTS - 1), points),  # too few points
    ]
    sel = select_sources(views, max_sources=8)
    assert sel[0].sources[:2] == [1, 2] and 3 not in sel[0].sources and sel[0].reason is None
    near, far = sel[0].depth_range
    assert 2.0 < near < 4.1 and 5.9 < far < 12.0
    assert sel[4].sources == [] and "no source view shares" in sel[4].reason
    assert sel[5].sources == [] and f"sees {MIN_POINTS - 1} sparse points (needs {MIN_POINTS})" in sel[5].reason
    assert len(select_sources(views, max_sources=1)[0].sources) == 1
