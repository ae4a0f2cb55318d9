"""Dense reconstruction on the CPU: a finished sparse model -> depth and normal maps, a fused point cloud and a
mesh, in COLMAP's dense workspace layout (`run_dense`).

- views.py: the undistorted PINHOLE views and their sparse points; the workspace layout;
- select.py: source views and depth range of each view, from the sparse model;
- sweep.py: a view's depth by a plane sweep with NCC photo-consistency, coarse to fine (numba kernels);
- patchmatch.py: per-pixel slanted planes refined PatchMatch-style (numba kernels);
- tiles.py: a view's PatchMatch work in bands of rows on threads, the same result on any number of them;
- fuse.py: geometric consistency across views, fusion into one cloud;
- mesh.py: Poisson mesh of the fused cloud;
- run.py: `run_dense`, the steps in order, in worker processes, resumable.
"""

from .run import DenseSettings, DenseSummary, dense_from_run, run_dense

__all__ = ["DenseSettings", "DenseSummary", "dense_from_run", "run_dense"]
