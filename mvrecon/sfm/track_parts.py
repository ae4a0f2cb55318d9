"""Long tracks dealt out to parts: where a solver's work or memory grows with the square of each point's views, the
longest points are split into parts of fewer views, every view kept (the bundle adjustment's sub-points,
sfm/bundle.py; global positioning's points, sfm/global_positioning.py)."""

import numpy as np


def deal_long_tracks(inverse: np.ndarray, views: np.ndarray, budget: float, min_views: int,
                     key: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(turn, parts), or None where the points' `views` squared, summed, are within `budget`. Otherwise each point
    of more than K views is split into parts = ceil(views / K) parts as equal as can be, K the largest (not under
    `min_views`) whose parts' views squared, summed, are within the budget; `inverse` gives each observation's
    point (an index into `views`), and each point's observations are dealt to its parts in turn in the order of
    `key`: turn is each observation's part, 0 to parts - 1. The key must differ from one point to the next (a
    scramble): dealt in the order of their images, the tracks of a set that every image sees split alike, and the
    even and the odd images then share no point (pycolmap's synthetic scene: centres 36-46% off in global
    positioning)."""
    def parts_at(cap: int) -> np.ndarray:
        return np.maximum(-(-views // cap), 1)  # a point without views counts as one part of none

    def pairs(cap: int) -> float:
        n = parts_at(cap)
        q, r = np.divmod(views, n)
        return float((r * (q + 1) ** 2 + (n - r) * q ** 2).sum())

    if pairs(int(views.max(initial=1))) <= budget:
        return None
    low, high = min_views, max(int(views.max()), min_views)  # the largest cap within the budget, else min_views
    while low < high:
        mid = (low + high + 1) // 2
        low, high = (mid, high) if pairs(mid) <= budget else (low, mid - 1)
    parts = parts_at(low)
    order = np.lexsort((key, inverse))
    start = np.searchsorted(inverse[order], inverse[order])
    turn = np.empty(len(order), np.int64)
    turn[order] = (np.arange(len(order)) - start) % parts[inverse[order]]  # 0, 1, ..., n - 1, 0, 1, ... in that order
    return turn, parts


def scrambled(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random 64-bit key per pair (a, b) (splitmix64's mix): orders that differ from one `a` to
    the next, where a linear key would order every `a`'s `b`s alike."""
    x = (a.astype(np.uint64) << np.uint64(32)) ^ b.astype(np.uint64)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))
