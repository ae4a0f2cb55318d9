"""The two start-up measures that make a whole `reconstruct` measurably faster, kept here together.

Each was kept because removing it slowed a whole `reconstruct` of templeSparseRing by more than 5% (medians of
alternated runs before and after, in docs/benchmarks.md; on the larger templeRing less): the feature workers
and the `mvrecon` process keep the memory they free (`keep_freed_memory`, glibc's mallopt), so that SIFT's
scale space and matching's blocks are not faulted in again for every image, nor the mapper's linear systems at
every iteration of a bundle adjustment (`hand_back_freed_memory` trims the heaps between them); and the
libraries of the later stages load in a thread while the workers extract (`load_later_stages`), rather than on
one core between the stages. The other start-up measures (skipping the interpreter's teardown, freezing the
garbage collector at exit, preloading the forkserver) saved less than that and are gone. The matcher's
onnxruntime product (matching/int_product.py) is no start-up measure: it makes the matching stage itself about
a third faster.
"""

import ctypes
import importlib

_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8  # glibc's mallopt parameters


def keep_freed_memory(one_arena: bool = False) -> None:
    """This process keeps the memory it frees for its next item instead of handing it back to the kernel.
    SIFT allocates and frees its scale space on every image (about 1 GB for a 3072 x 2048 photo, 80 MB for
    640 x 480), and glibc maps large blocks on their own and unmaps them when freed, or trims the heap's free top:
    each image then faulted all of that memory in again. The `mvrecon` process does the same for matching, which
    prepares each image's descriptors and their products in blocks of a few MB. A no-op where the C library has
    no mallopt (not glibc).

    With `one_arena` (the feature workers) every thread allocates from the one heap. A worker's last image runs
    on every core's OpenCV thread (stages.features._extraction_jobs), and the extra thread took a malloc arena of
    its own, faulting in fresh memory while the main heap held the earlier images' free (herzjesu's process tree
    peaked 110 MB higher). The mvrecon process keeps glibc's arenas: one arena there made no run faster."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_MAX, 0)  # large blocks from the heap too, where freed memory is reused
    mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)  # and the heap never trimmed (the largest value mallopt takes)
    if one_arena:
        mallopt(_M_ARENA_MAX, 1)


def hand_back_freed_memory() -> None:
    """Hand back to the kernel, now, the free pages this process's heaps hold (glibc's malloc_trim); the process
    goes on keeping what it frees (`keep_freed_memory`). The mapper calls it after each global BA: kept for the
    whole run, the freed linear systems and their fragments made most of the process's growth with the model;
    handed back as they were freed, each iteration of GTSAM's Levenberg-Marquardt, which builds and frees its
    linear system, faulted it in anew, the kernel's work growing faster than the model (docs/benchmarks.md,
    "Freed memory kept through a bundle adjustment"). A no-op where the C library has no malloc_trim (not
    glibc)."""
    try:
        malloc_trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return
    malloc_trim(0)


def load_later_stages() -> None:
    """Import what matching and mapping need, and make the matcher's session, while the feature workers run:
    between the stages this is 0.15-0.2 s on one core. Imported by name, so that this module stays at the bottom
    of the layers. A library that fails to load here fails again where it is needed, with its error reported
    there."""
    try:
        # numpy.ma: the initial pair's np.median imports it
        for name in ("cv2", "gtsam", "numpy.ma", "mvrecon.io.colmap_model", "mvrecon.sfm.incremental"):
            importlib.import_module(name)
        importlib.import_module("mvrecon.matching.int_product").warm_up()  # makes its onnxruntime session
    except Exception:  # noqa: BLE001
        pass
