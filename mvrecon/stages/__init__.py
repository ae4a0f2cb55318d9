"""The stages of a reconstruction, one module each, every one `stage(config, inputs, workspace) -> summary`:

- features.py: images -> cameras, keypoints and descriptors (a pool of worker processes: executor.WorkerPool);
- matching.py: pairs -> verified two-view geometries (a pool of threads);
- mapping.py: verified pairs -> models (the incremental mapper, sfm/incremental.py);
- report.py: report.json, written at the end of a run and read back to not redo a finished one.

pipeline.py runs them in order. A second mapper (a global one) plugs in at mapping.py's `_run_mapper`. With a
Dask cluster (mvrecon/cluster.py) features.py's `_hand_out` and matching.py's `_match_all` send their work there.
"""
