"""Benchmark GTSAM bundle adjustment: gtsam.SfmLevenbergMarquardtOptimizer (Schur) against plain LM.

Two measurements on a workspace database (or a pycolmap synthetic scene when none is given), or a third on a
finished run (--final):
1. the whole incremental mapper with each optimizer: total BA time, number of BA calls, mapping time,
registered
   images, points and mean reprojection error;
2. one global BA of the finished model after perturbing poses (0.5 deg, 1% of the scene) and points: time,
   iterations, initial and final cost.

3. with --final RUN: the final BA of the run's model (every image and point, intrinsics refined; read from
   RUN/snapshots/mapper.pkl and RUN/database.db) under each linear solver, and with today's solver eliminating
   the poses in image order instead of `bundle._pose_order`'s, each in a process of its own: wall time, LM
   iterations, cost, and the process's peak memory above what it held before the BA.

Usage:
  python tools/bench_ba.py --database out/database.db
  python tools/bench_ba.py --synthetic 20
  python tools/bench_ba.py --final out/run
  python tools/bench_ba.py --final out/run --solvers sequential,image-order
"""

import argparse
import json
import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import gtsam
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mvrecon import database  # noqa: E402
from mvrecon.geometry.rotation import angle_axis_to_rotmat  # noqa: E402
from mvrecon.memory import main_peak_mb, rss_mb  # noqa: E402
from mvrecon.sfm import bundle  # noqa: E402
from mvrecon.sfm.bundle import bundle_adjust  # noqa: E402
from mvrecon.sfm.config import MapperConfig  # noqa: E402
from mvrecon.sfm.incremental import IncrementalMapper  # noqa: E402
from mvrecon.sfm.model import Reconstruction  # noqa: E402


def synthetic_database(path: Path, images: int) -> None:
    import pycolmap

    opts = pycolmap.SyntheticDatasetOptions(num_rigs=1, num_cameras_per_rig=1, num_frames_per_rig=images,
                                            num_points3D=2000, camera_width=1024, camera_height=768)
    with pycolmap.Database.open(str(path)) as db:
        rec = pycolmap.synthesize_dataset(opts, db)
        pycolmap.synthesize_noise(pycolmap.SyntheticNoiseOptions(point2D_stddev=0.5), rec, db)


def perturbed(model: Reconstruction, mapper: IncrementalMapper, seed: int = 0) -> Reconstruction:
    m = Reconstruction.from_state(model.state(), mapper.keypoints)
    rng = np.random.default_rng(seed)
    extent = np.ptp(m.centers()[m.registered], axis=0).max()
    for i in m.registration_order[1:]:
        dR = angle_axis_to_rotmat(rng.normal(scale=np.radians(0.5) / np.sqrt(3), size=3))
        c = m.centers()[i] + rng.normal(scale=0.01 * extent / np.sqrt(3), size=3)
        m.R[i] = dR @ m.R[i]
        m.t[i] = -m.R[i] @ c
    pts = m.alive_points()
    m.xyz.data[pts] += rng.normal(scale=0.002 * extent, size=(len(pts), 3))
    return m


# the final BA's linear solvers: today's (LM, sequential Cholesky, points first), the same with the poses in image
# order, GTSAM's multifrontal one with today's ordering, GTSAM's Sfm optimizer (Schur), and conjugate gradients
# with a block-Jacobi preconditioner
SOLVERS = ("sequential", "image-order", "multifrontal", "sfm", "pcg")


def _multifrontal(gtsam_, graph, values, kind, iterations, relative_tolerance, ordering, initial_lambda):
    """bundle._optimize running LM with GTSAM's multifrontal Cholesky (the same Ceres-style settings)."""
    params = gtsam.LevenbergMarquardtParams.CeresDefaults()
    params.setLinearSolverType("MULTIFRONTAL_CHOLESKY")
    params.setOrdering(ordering)
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setlambdaInitial(initial_lambda)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    initial = opt.error()
    result = opt.optimize()
    return result, int(opt.iterations()), initial, opt.error()


def final_ba(run: Path, solver: str) -> dict:
    """The final BA of `run`'s first model under `solver`, in this process: its figures."""
    corr = database.read_correspondences(run / "database.db")
    mapper = IncrementalMapper(corr, MapperConfig())
    with open(run / "snapshots" / "mapper.pkl", "rb") as f:
        state = pickle.load(f)["state"]
    m = Reconstruction.from_state((state["finished"] or [state["current"]])[0], mapper.keypoints)
    if solver == "multifrontal":
        bundle._optimize = _multifrontal
    if solver == "image-order":
        bundle.ORDERED_POSES = sys.maxsize
    before = rss_mb([os.getpid()])
    # each solver by itself: the mapper's own choice of conjugate gradients where the factorisation fills in is off
    out = bundle_adjust(m, m.registered_images(), MapperConfig(ba_iterative_fill=0), point_ids=m.alive_points(),
                        refine_intrinsics=True, optimizer=solver if solver in ("sfm", "pcg") else "lm")
    return {"solver": solver, "seconds": out.seconds, "iterations": out.iterations, "final_cost": out.final_error,
            "peak_above_mb": main_peak_mb() - before, "observations": out.num_observations,
            "images": int(m.registered.sum()), "points": len(m.alive_points()),
            "reprojection_px": m.stats()["mean_reprojection_error_px"]}


def compare_final_ba(run: Path, solvers: tuple[str, ...] = SOLVERS) -> int:
    """Each solver's final BA of `run`, each in a fresh process so that its peak memory is its own."""
    print(f"{'solver':13s} {'seconds':>8s} {'iterations':>11s} {'final cost':>11s} {'reproj px':>10s} "
          f"{'peak MB above':>14s}")
    for solver in solvers:
        done = subprocess.run([sys.executable, __file__, "--final", str(run), "--solver", solver],
                              capture_output=True, text=True)
        if done.returncode:
            print(f"{solver:13s} failed: {(done.stderr.strip().splitlines() or ['?'])[-1]}")
            continue
        r = json.loads(done.stdout.strip().splitlines()[-1])
        print(f"{solver:13s} {r['seconds']:8.2f} {r['iterations']:11d} {r['final_cost']:11.1f} "
              f"{r['reprojection_px']:10.4f} {r['peak_above_mb']:14.0f}")
    print(f"({r['images']} images, {r['points']} points, {r['observations']} observations)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--database", default=None,
                    help="a COLMAP database.db with verified matches, e.g. a run's (default: a synthetic "
                         "scene)")
    ap.add_argument("--synthetic", type=int, default=15, help="images of the synthetic scene (no --database)")
    ap.add_argument("--final", type=Path, default=None,
                    help="a finished run's folder: its final BA under each linear solver (see above)")
    ap.add_argument("--solvers", default=",".join(SOLVERS),
                    help=f"with --final: these of {', '.join(SOLVERS)}, comma-separated (default: all)")
    ap.add_argument("--solver", choices=SOLVERS, default=None, help=argparse.SUPPRESS)  # one, in this process
    args = ap.parse_args(argv)
    if args.final and args.solver:
        print(json.dumps(final_ba(args.final, args.solver)))
        return 0
    if args.final:
        solvers = tuple(args.solvers.split(","))
        unknown = sorted(set(solvers) - set(SOLVERS))
        if unknown:
            ap.error(f"--solvers: unknown {', '.join(unknown)} (choose from {', '.join(SOLVERS)})")
        return compare_final_ba(args.final, solvers)
    db = Path(args.database) if args.database else Path(tempfile.mkdtemp()) / "database.db"
    if not args.database:
        synthetic_database(db, args.synthetic)
    corr = database.read_correspondences(db)
    print(f"database: {db} ({len(corr.images)} images, {len(corr.pairs)} verified pairs)")
    finals = {}
    print(f"{'optimizer':10s} {'mapping s':>10s} {'BA s':>8s} {'BA calls':>9s} {'registered':>11s} "
          f"{'points':>8s} {'reproj px':>10s}")
    for kind in ("lm", "sfm"):
        config = MapperConfig(optimizer=kind, ba_iterative_fill=0)
        mapper = IncrementalMapper(corr, config)
        start = time.perf_counter()
        result = mapper.run()
        wall = time.perf_counter() - start
        s = result.models[0].stats() if result.models else {"registered": 0, "points": 0,
                                                            "mean_reprojection_error_px": float("nan")}
        print(f"{kind:10s} {wall:10.2f} {result.stats['ba_seconds']:8.2f} {result.stats['ba_calls']:9d} "
              f"{s['registered']:11d} {s['points']:8d} {s['mean_reprojection_error_px']:10.3f}")
        finals[kind] = (mapper, result)
    mapper, result = finals["lm"]
    if not result.models:
        return 1
    print("\none global BA of the finished model after a perturbation:")
    print(f"{'optimizer':10s} {'seconds':>8s} {'iterations':>11s} {'initial cost':>13s} {'final cost':>11s}")
    times = {}
    for kind in ("lm", "sfm"):
        m = perturbed(result.models[0], mapper)
        out = bundle_adjust(m, m.registered_images(), MapperConfig(optimizer=kind),
                            point_ids=m.alive_points(), refine_intrinsics=True, max_iterations=100)
        times[kind] = out.seconds
        print(f"{kind:10s} {out.seconds:8.2f} {out.iterations:11d} {out.initial_error:13.1f} "
              f"{out.final_error:11.1f}")
    print(f"\nratio sfm / lm (single global BA time): {times['sfm'] / times['lm']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
