"""Feature tracks: the union of verified matches, split where one image's keypoints would join, and the
components labelled as scipy labels them."""

import numpy as np

from mvrecon.database import PairGeometry
from mvrecon.sfm.tracks import build_tracks


def test_tracks_union_find_splits_inconsistent_components():
    pairs = [PairGeometry(image_id1=1, image_id2=2, config="CALIBRATED",
                          inliers=np.array([[0, 0], [1, 1], [2, 2]])),
             PairGeometry(image_id1=2, image_id2=3, config="CALIBRATED", inliers=np.array([[0, 5], [1, 6]])),
             # with the last pair, keypoints 2 and 3 of image 1 end in one component: it must be split
             PairGeometry(image_id1=1, image_id2=3, config="CALIBRATED", inliers=np.array([[3, 7], [0, 5]])),
             PairGeometry(image_id1=2, image_id2=3, config="CALIBRATED", inliers=np.array([[2, 7]]))]
    tracks = build_tracks([1, 2, 3], [4, 3, 8], pairs)
    assert tracks.split_inconsistent == 1
    elements = sorted(sorted(zip(tracks.image[a:b].tolist(), tracks.keypoint[a:b].tolist()))
                      for a, b in zip(tracks.ptr[:-1], tracks.ptr[1:]))
    # the stronger pairs' matches are kept; the weakest, which would join two image-1 keypoints, is dropped
    assert elements == [[(0, 0), (1, 0), (2, 5)], [(0, 1), (1, 1), (2, 6)],
                        [(0, 2), (1, 2)], [(0, 3), (2, 7)]]
    for k, track in enumerate(zip(tracks.ptr[:-1], tracks.ptr[1:])):
        for img, kp in zip(tracks.image[track[0]:track[1]], tracks.keypoint[track[0]:track[1]]):
            assert tracks.track_of[img][kp] == k
    assert tracks.track_of[2][0] == -1


def test_track_components_equal_scipy_connected_components():
    """The numpy hooking-and-jumping components label every node as scipy's connected_components does (same
    numbering), on random graphs and on a long shuffled chain (the slowest case for label propagation)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from mvrecon.sfm.tracks import _components

    rng = np.random.default_rng(0)
    chain = rng.permutation(20000)
    sizes = [(1, 0), (500, 200), (20000, 15000)]
    graphs = [(n, rng.integers(0, n, e), rng.integers(0, n, e)) for n, e in sizes]
    graphs.append((20000, chain[:-1], chain[1:]))
    for n, rows, cols in graphs:
        count, expected = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                               directed=False)
        labels = _components(n, rows, cols)
        assert labels.max() + 1 == count
        np.testing.assert_array_equal(labels, expected)
