"""A view's PatchMatch work in tiles: bands of rows, run on threads inside one process (the numba kernels
release the GIL, so the threads run on as many cores).

The bands depend on the image's size alone, never on the number of threads, and each band of a pass
starts from the same state - the planes as they were before the pass, its own rows and one row either
side (its halo: the neighbours its border pixels try, so a good plane crosses a band's border one pass
later) - and writes back only its own rows, with its own random seed. So a depth map is the same, bit
for bit, whatever the number of threads.
"""

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .patchmatch import _plane_costs, _propagation_pass

TILE_ROWS = 96  # at most, per band: 9 bands in a 1037x773 view, 5 at its 518x386 coarse level
HALO = 1  # rows either side a band reads: a pass tries the planes of a pixel's 4-neighbours


def bands(rows: int, tile_rows: int = TILE_ROWS) -> list[tuple[int, int]]:
    """The (first, end) rows of each band of an image of `rows` rows: as few bands as hold at most `tile_rows`
    rows each, of equal heights (to a row); one band when `tile_rows` <= 0."""
    count = 1 if tile_rows <= 0 else -(-rows // tile_rows)
    edges = [round(i * rows / count) for i in range(count + 1)]
    return list(zip(edges[:-1], edges[1:]))


def run_tasks(tasks: list[Callable[[], None]], threads: int) -> None:
    """Run the tasks (independent of each other), on up to `threads` threads (in this thread when one)."""
    if threads <= 1 or len(tasks) == 1:
        for task in tasks:
            task()
        return
    with ThreadPoolExecutor(min(threads, len(tasks))) as pool:
        for future in [pool.submit(task) for task in tasks]:
            future.result()


def plane_costs(ref: np.ndarray, stack: np.ndarray, sizes: np.ndarray, A: np.ndarray, b: np.ndarray,
                q: np.ndarray, gx: np.ndarray, gy: np.ndarray, radius: int, step: int, best_k: int,
                min_var: float, *, threads: int = 1, tile_rows: int = TILE_ROWS) -> np.ndarray:
    """The cost of every pixel's plane (`patchmatch._plane_costs`), band by band (each pixel's on its own)."""
    cost = np.zeros_like(q)

    def band(y0: int, y1: int) -> Callable[[], None]:
        return lambda: _plane_costs(ref, stack, sizes, A, b, q, gx, gy, radius, step, best_k, min_var, cost,
                                    y0, y1)

    run_tasks([band(y0, y1) for y0, y1 in bands(ref.shape[0], tile_rows)], threads)
    return cost


def propagation_pass(ref: np.ndarray, stack: np.ndarray, sizes: np.ndarray, A: np.ndarray, b: np.ndarray,
                     q: np.ndarray, gx: np.ndarray, gy: np.ndarray, cost: np.ndarray, dq: float, tilt: float,
                     radius: int, step: int, best_k: int, min_var: float, reverse: bool, seed: int,
                     settled: float, *, threads: int = 1, tile_rows: int = TILE_ROWS) -> None:
    """One PatchMatch pass (`patchmatch._propagation_pass`) over every band, updating (q, gx, gy, cost) in
    place: each band on a copy of its rows and halo taken before the pass, its own rows written back after.
    Band i's random changes are seeded with seed + 104729 i (one band: `seed`, as an untiled pass)."""
    rows = q.shape[0]
    parts = []
    for i, (y0, y1) in enumerate(bands(rows, tile_rows)):
        lo, hi = max(y0 - HALO, 0), min(y1 + HALO, rows)
        parts.append((y0, y1, lo, seed + 104729 * i, [a[lo:hi].copy() for a in (q, gx, gy, cost)]))

    def band(y0: int, y1: int, lo: int, band_seed: int, planes: list[np.ndarray]) -> Callable[[], None]:
        return lambda: _propagation_pass(ref, stack, sizes, A, b, *planes, dq, tilt, radius, step, best_k,
                                         min_var, reverse, band_seed, settled, lo, y0 - lo, y1 - lo)

    run_tasks([band(*part) for part in parts], threads)
    for y0, y1, lo, _, planes in parts:
        for full, part in zip((q, gx, gy, cost), planes):
            full[y0:y1] = part[y0 - lo: y1 - lo]
