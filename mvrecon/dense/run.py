"""`run_dense`: a finished sparse model -> COLMAP's dense workspace with depth and normal maps, fused.ply and
mesh.ply.

Steps, each recorded in DENSE/.stages/dense.json (`io.record.Record`) so that a rerun after Ctrl-C redoes only
what is missing, and a change of settings or code redoes what depends on it:
1. undistortion to PINHOLE (`views.undistort_into`, the project's export);
2. per view, its source views and depth range (`select`), then its photometric depth map (`sweep`), in a pool
   of worker processes, one view per worker, the last views in tiles on the cores the others leave (`tiles`);
3. per view, the geometric depth map: depths confirmed by at least two source views (`fuse.geometric_filter`);
4. fusion of the geometric maps into fused.ply, and a Poisson mesh.ply (`mesh`).
A view without a depth map (too few sparse points, no source view overlapping it) is reported with the reason,
and the others go on.
"""

import logging
import multiprocessing
import signal
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..executor import WorkerPool, default_workers
from ..io.colmap_array import read_colmap_array, write_colmap_array
from ..io.colmap_model import load_reconstruction
from ..io.files import replace_whole
from ..io.images import write_image
from ..io.pfm import write_pfm
from ..io.ply import write_ply
from ..io.record import Record, code_digest, digest
from ..progress import progress
from ..workspace import Workspace
from .fuse import DepthView, fuse, geometric_filter
from .mesh import poisson_mesh
from .select import select_sources
from .sweep import pyramid_depth, warm_up
from .views import View, read_views, undistort_into

log = logging.getLogger(__name__)

COST_SOURCES = 4  # source views in the photo-consistency (the best ones); all `views` serve the consistency check
BEST_K = 2  # each plane's cost: the mean of the best BEST_K source costs (a pixel hidden in one source is kept)


@dataclass
class DenseSettings:
    """What the depth maps are made with (`sweep.pyramid_depth`, `fuse.geometric_filter`)."""

    views: int = 8
    window: int = 7
    coarse_size: int = 400
    max_cost: float = 0.5
    rel_tolerance: float = 0.01
    max_reprojection: float = 2.0
    min_consistent: int = 2


@dataclass
class DenseSummary:
    """What `run_dense` made: the dense folder, per view its depth map's figures (sources, valid and
    kept shares of pixels, seconds) or the reason it has none, the fused points and the mesh."""

    dense_dir: Path
    views: dict[str, dict] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    fused_points: int = 0
    mesh_vertices: int = 0
    mesh_triangles: int = 0
    megapixels: float = 0.0  # of the views given depth maps
    depth_seconds: float = 0.0  # wall time of the depth and consistency maps (this run's, reused ones count 0)
    seconds: float = 0.0

    def text(self) -> str:
        kept = [v["kept"] for v in self.views.values()]
        out = [f"Dense: {len(self.views)} depth maps ({self.megapixels:.2f} Mpx, mean share of pixels kept "
               f"{np.mean(kept) if kept else 0:.0%}), {self.fused_points} fused points, mesh of "
               f"{self.mesh_triangles} triangles, in {self.seconds:.1f} s; {self.dense_dir}."]
        for name, why in sorted(self.skipped.items()):
            out.append(f"{name}: no depth map: {why}.")
        return "\n".join(out)


def depth_path(dense_dir: Path, name: str, kind: str) -> Path:
    return dense_dir / "stereo" / "depth_maps" / f"{name}.{kind}.bin"


def normal_path(dense_dir: Path, name: str, kind: str) -> Path:
    return dense_dir / "stereo" / "normal_maps" / f"{name}.{kind}.bin"


def _grey(dense_dir: Path, name: str) -> np.ndarray:
    image = cv2.imdecode(np.fromfile(dense_dir / "images" / name, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{dense_dir / 'images' / name}: unreadable image")
    return image.astype(np.float32) / 255.0


def _relative(ref: View, src: View) -> tuple[np.ndarray, np.ndarray]:
    R = src.R @ ref.R.T
    return R, src.t - R @ ref.t


def _quiet_end() -> None:
    """In a worker: end quietly on the pool's SIGTERM. This module imports pycolmap (the export), whose glog
    installs a handler that prints a stack dump when the pool ends its workers (executor._init_worker resets
    the signal, but before the job's module is imported). In-process (one worker) the run's own handler stays."""
    if multiprocessing.parent_process() is not None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _photometric_job(job) -> dict:
    """Worker: the photometric depth and normal maps of one view, written to the workspace."""
    _quiet_end()
    dense_dir, ref, sources, depth_range, settings, threads = job
    t0 = time.perf_counter()
    cost_sources = sources[:COST_SOURCES]
    c0 = time.process_time()
    depth, _, normals = pyramid_depth(_grey(dense_dir, ref.name), [_grey(dense_dir, s.name) for s in cost_sources],
                                      ref.K, [s.K for s in cost_sources], [_relative(ref, s) for s in cost_sources],
                                      depth_range, coarse_size=settings.coarse_size, window=settings.window,
                                      best_k=BEST_K, max_cost=settings.max_cost, threads=threads)
    _write_maps(dense_dir, ref, depth, normals, "photometric")
    return {"valid": float(np.mean(depth > 0)), "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0, "threads": threads}


def view_threads(position: int, jobs: int, workers: int, cores: int) -> int:
    """Threads for the view at `position` (from 0) of `jobs` handed in order to `workers` processes on
    `cores`: the cores shared among the views that run with it. While at least as many views remain as
    workers, each view has a core; the last views, fewer than the workers, split the cores the finished ones
    leave (the last of 2 views on 2 cores: 2 threads). Its depth map does not depend on it (`tiles`)."""
    return max(1, cores // max(1, min(workers, jobs - position)))


def _geometric_job(job) -> dict:
    """Worker: the geometric depth and normal maps of one view (its depths confirmed by its sources)."""
    _quiet_end()
    dense_dir, ref, sources, settings = job
    t0, c0 = time.perf_counter(), time.process_time()
    ref_view = DepthView(ref, read_colmap_array(depth_path(dense_dir, ref.name, "photometric")))
    src_views = [DepthView(s, read_colmap_array(depth_path(dense_dir, s.name, "photometric"))) for s in sources]
    depth = geometric_filter(ref_view, src_views, rel_tolerance=settings.rel_tolerance,
                             max_reprojection=settings.max_reprojection, min_consistent=settings.min_consistent)
    normals = read_colmap_array(normal_path(dense_dir, ref.name, "photometric"))
    _write_maps(dense_dir, ref, depth, np.where((depth > 0)[..., None], normals, 0.0), "geometric")
    _write_preview(dense_dir, ref.name, depth)
    return {"kept": float(np.mean(depth > 0)), "seconds": time.perf_counter() - t0,
            "cpu_seconds": time.process_time() - c0}


def _write_maps(dense_dir: Path, view: View, depth: np.ndarray, normals: np.ndarray, kind: str) -> None:
    for path, array in ((depth_path(dense_dir, view.name, kind), depth),
                        (normal_path(dense_dir, view.name, kind), normals)):
        path.parent.mkdir(parents=True, exist_ok=True)
        write_colmap_array(path, array)


def preview_path(dense_dir: Path, name: str, suffix: str = ".png") -> Path:
    return dense_dir / "previews" / f"{name}.depth{suffix}"


def _write_preview(dense_dir: Path, name: str, depth: np.ndarray) -> None:
    """A colour picture of the depth map (near warm, far cool, black without depth), and beside it the depth
    values as a PFM float map (Middlebury's format: `inf` without depth) for tools that read PFM, not COLMAP's
    arrays."""
    known = depth > 0
    inverse = np.zeros_like(depth)
    if known.any():
        q = 1.0 / depth[known]
        lo, hi = np.percentile(q, [1, 99])
        inverse[known] = np.clip((q - lo) / max(hi - lo, 1e-12), 0, 1)
    picture = cv2.applyColorMap((inverse * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    picture[~known] = 0
    path = preview_path(dense_dir, name)
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_whole(path, lambda tmp: write_image(tmp, picture))
    replace_whole(preview_path(dense_dir, name, ".pfm"), lambda tmp: write_pfm(tmp, np.where(known, depth, np.inf)))


def _model_key(model_dir: Path, image_dir: Path, max_image_size: int) -> str:
    files = sorted(p for p in model_dir.iterdir() if p.is_file())
    return digest([p.name for p in files], *[np.frombuffer(p.read_bytes(), np.uint8) for p in files],
                  str(image_dir.resolve()), max_image_size, code_digest("mvrecon.io.undistort"))


def run_dense(model_dir: Path | str, image_dir: Path | str, out_dir: Path | str, *, max_image_size: int = 1600,
              views: int = 8, workers: int | None = None, database: Path | str | None = None,
              mesh: bool = True, settings: DenseSettings | None = None) -> DenseSummary:
    """Dense reconstruction of the sparse model in `model_dir` (any COLMAP model; its images in `image_dir`)
    into `out_dir`, COLMAP's dense workspace: images/ and sparse/ undistorted to PINHOLE with the long side at
    most `max_image_size` (-1: full size), stereo/depth_maps/ and stereo/normal_maps/ (`NAME.photometric.bin`,
    `NAME.geometric.bin`, COLMAP's array format), previews/NAME.depth.png and .pfm, fused.ply (points, colours,
    normals, in the model's frame) and mesh.ply. Each view takes up to `views` source views. `workers`
    processes (default: all cores) make the depth maps. `database`: the database the model was mapped from
    (it tells the frame of EXIF-rotated images). A rerun reuses what was finished with the same inputs and
    settings. InputError (naming the path) for a folder without a model or images."""
    t_start = time.perf_counter()
    model_dir, image_dir, dense_dir = Path(model_dir), Path(image_dir), Path(out_dir)
    settings = replace(settings or DenseSettings(), views=views)  # the caller's settings left as they were
    load_reconstruction(model_dir)  # an InputError naming the folder when it holds no readable model
    dense_dir.mkdir(parents=True, exist_ok=True)
    record = Record(dense_dir, "dense.json")
    model_key = _model_key(model_dir, image_dir, max_image_size)
    if record.get("undistort", model_key, ["sparse/images.bin", "sparse/cameras.bin"]) is None:
        record.drop(*record.names())
        undistort_into(model_dir, image_dir, dense_dir, max_image_size,
                       None if database is None or not Path(database).is_file() else Path(database))
        record.put("undistort", model_key)
    all_views = read_views(dense_dir / "sparse")
    selections = select_sources(all_views, settings.views)
    summary = DenseSummary(dense_dir)
    code = code_digest("mvrecon.dense.sweep", "mvrecon.dense.patchmatch", "mvrecon.dense.tiles",
                       "mvrecon.dense.select", "mvrecon.dense.run", "mvrecon.dense.fuse")
    workers = default_workers() if workers is None else workers

    # photometric depth maps
    jobs, keys = {}, {}
    for view, sel in zip(all_views, selections):
        if sel.reason:
            summary.skipped[view.name] = sel.reason
            continue
        sources = [all_views[i] for i in sel.sources]
        keys[view.name] = digest(model_key, code, view.name, sel.sources, sel.depth_range, vars(settings))
        files = [path(dense_dir, view.name, "photometric").relative_to(dense_dir) for path in (depth_path, normal_path)]
        if record.get(f"photometric/{view.name}", keys[view.name], files) is None:
            record.drop(f"photometric/{view.name}")
            jobs[view.name] = (dense_dir, view, sources, sel.depth_range, settings)
    t_depth = time.perf_counter()
    photometric = {name: record.report(f"photometric/{name}") for name in keys if name not in jobs}
    if jobs:
        warm_up()  # the numba kernels compiled and cached once, before the workers load them
    processes = min(workers, max(len(jobs), 1))
    cores = default_workers()
    items = [(*job, view_threads(i, len(jobs), processes, cores)) for i, job in enumerate(jobs.values())]
    with WorkerPool(processes) as pool:
        results = pool.map(_photometric_job, items, name=lambda job: job[1].name)
        for name, report in progress(zip(jobs, results), total=len(jobs), desc="depth maps", unit="view"):
            record.put(f"photometric/{name}", keys[name], report)
            photometric[name] = report

    # geometric depth maps: each view against its sources that have photometric maps
    by_name = {v.name: v for v in all_views}
    geo_jobs, geo_keys = {}, {}
    for view, sel in zip(all_views, selections):
        if view.name not in photometric:
            continue
        sources = [all_views[i] for i in sel.sources if all_views[i].name in photometric]
        if len(sources) < settings.min_consistent:
            summary.skipped[view.name] = (f"{len(sources)} of its source views have depth maps, fewer than the "
                                          f"{settings.min_consistent} its depths must agree with")
            continue
        geo_keys[view.name] = digest(keys[view.name], [keys[s.name] for s in sources], vars(settings))
        files = [depth_path(dense_dir, view.name, "geometric").relative_to(dense_dir)]
        if record.get(f"geometric/{view.name}", geo_keys[view.name], files) is None:
            record.drop(f"geometric/{view.name}")
            geo_jobs[view.name] = (dense_dir, view, sources, settings)
    geometric = {name: record.report(f"geometric/{name}") for name in geo_keys if name not in geo_jobs}
    with WorkerPool(min(workers, max(len(geo_jobs), 1))) as pool:
        results = pool.map(_geometric_job, list(geo_jobs.values()), name=lambda job: job[1].name)
        for name, report in progress(zip(geo_jobs, results), total=len(geo_jobs), desc="consistency",
                                     unit="view"):
            record.put(f"geometric/{name}", geo_keys[name], report)
            geometric[name] = report
    summary.depth_seconds = time.perf_counter() - t_depth
    for name, report in geometric.items():
        view = by_name[name]
        summary.views[name] = {"sources": [all_views[i].name for i in selections[view.index].sources],
                               "valid": photometric[name]["valid"], "kept": report["kept"],
                               "seconds": photometric[name]["seconds"] + report["seconds"],
                               "cpu_seconds": photometric[name]["cpu_seconds"] + report["cpu_seconds"]}
        summary.megapixels += view.width * view.height / 1e6

    # fusion and mesh
    fused_key = digest([geo_keys[n] for n in sorted(geometric)], code_digest("mvrecon.dense.fuse"), mesh)
    report = record.get("fused", fused_key, ["fused.ply"] + (["mesh.ply"] if mesh else []))
    if report is None:
        record.drop("fused")
        report = _fuse_and_mesh(dense_dir, [by_name[n] for n in sorted(geometric)], selections, settings, mesh)
        record.put("fused", fused_key, report)
    summary.fused_points = report["points"]
    summary.mesh_vertices, summary.mesh_triangles = report.get("vertices", 0), report.get("triangles", 0)
    record.prune()
    summary.seconds = time.perf_counter() - t_start
    return summary


def dense_from_run(run_dir: Path | str, out_dir: Path | str | None = None, *, model_dir: Path | str | None = None,
                   image_dir: Path | str | None = None, **options) -> DenseSummary:
    """`run_dense` on the output folder of `mvrecon reconstruct`: its largest model (RUN/sparse/0 unless
    `model_dir`), the images it was made from (recorded by its features stage, unless `image_dir`), its
    database; into RUN/dense unless `out_dir`. `options` go to `run_dense`. InputError naming the folder when
    it is not a run with a model."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder (the output folder of `mvrecon reconstruct`)")
    model = Path(model_dir) if model_dir else run_dir / "sparse" / "0"
    if not (model / "images.bin").is_file() and not (model / "images.txt").is_file():
        raise InputError(f"{model}: no sparse model here (run `mvrecon reconstruct` first, or pass --model)")
    if image_dir is None:
        features = Workspace(run_dir).stage_config("features")
        if not features or "images" not in features:
            raise InputError(f"{run_dir}: cannot tell where its images are; pass --image-dir")
        image_dir = features["images"]
    out = Path(out_dir) if out_dir else run_dir / "dense"
    with Workspace(run_dir).lock():  # another run writing the folder (a `reconstruct --overwrite`) is refused
        return run_dense(model, image_dir, out, database=run_dir / "database.db", **options)


def _fuse_and_mesh(dense_dir: Path, views: list[View], selections, settings: DenseSettings, mesh: bool) -> dict:
    """Write fused.ply and mesh.ply; the report: points, mesh size, wall and CPU seconds of each."""
    t0, c0 = time.perf_counter(), time.process_time()
    depth_views = []
    for view in views:
        bgr = cv2.imdecode(np.fromfile(dense_dir / "images" / view.name, np.uint8), cv2.IMREAD_COLOR)
        depth_views.append(DepthView(view, read_colmap_array(depth_path(dense_dir, view.name, "geometric")),
                                     read_colmap_array(normal_path(dense_dir, view.name, "geometric")),
                                     bgr[:, :, ::-1], tuple(selections[view.index].sources)))
    xyz, rgb, normals = fuse(depth_views, rel_tolerance=settings.rel_tolerance,
                             max_reprojection=settings.max_reprojection)
    replace_whole(dense_dir / "fused.ply", lambda tmp: write_ply(tmp, xyz, rgb, normals))
    report = {"points": len(xyz), "fuse_seconds": time.perf_counter() - t0,
              "fuse_cpu_seconds": time.process_time() - c0}
    t0, c0 = time.perf_counter(), time.process_time()
    if mesh and len(xyz) >= 100:
        vertices, triangles = [], []

        def write_mesh(tmp: Path) -> None:
            v, t = poisson_mesh(xyz, rgb, normals, tmp)
            vertices.append(v)
            triangles.append(t)

        replace_whole(dense_dir / "mesh.ply", write_mesh)
        report.update(vertices=vertices[0], triangles=triangles[0], mesh_seconds=time.perf_counter() - t0,
                      mesh_cpu_seconds=time.process_time() - c0)
    elif mesh:
        log.warning("%s: %d fused points, too few for a mesh", dense_dir, len(xyz))
    return report
