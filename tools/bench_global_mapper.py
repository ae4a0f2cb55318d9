"""Global against incremental mapping on the same databases: mvrecon's two mappers and pycolmap's two.

    python tools/bench_global_mapper.py WORK                         # every set with a database in WORK
    python tools/bench_global_mapper.py WORK --only object_orbit_small,strecha_herzjesu_P8
    python tools/bench_global_mapper.py WORK --engines mvrecon-global,colmap-global
    python tools/bench_global_mapper.py WORK --engines mvrecon-global,mvrecon-global-pairs   # tracks vs pairs
    python tools/bench_global_mapper.py WORK --engines mvrecon-global --seed 1                # another seed

WORK is tools/bench_mapper.py's work folder: WORK/<set>/database/database.db (mvrecon's front end, default
settings), the catalog scenes' ground truth in WORK/scenes/<set>/gt/sparse, the shared sets' in
../shared/data/<set>. Per set and engine it prints the images registered (in all models, and in the largest),
the images of the largest model at a wrong pose (eval.metrics.misplaced_images: its relative poses to the model's
other images off by a median over 5 deg; the target counts the largest model's images less these), the relative-pose
AUC@1 and AUC@5 against the ground truth (eval.metrics: a pair with an unregistered image or split across models
counts 180 deg) and the mapping wall time: mvrecon's mappers called in this process on the
database's correspondences (the global one's view graph in one process per core; reading the database not
counted; mvrecon-global-pairs is the global mapper with
the final model's centres from translation averaging of the pairs' directions instead of global positioning
from the tracks), pycolmap's `global_mapping` and
`incremental_mapping` on a copy of the database, every mapper at `--seed` (default 0). Wall and CPU time (all
the process's threads) of each; each engine runs once per set: on a shared machine the wall times are noisy, the
CPU times less so.
"""

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mvrecon import database  # noqa: E402  (mvrecon before pycolmap: see the README)
from mvrecon.eval.ground_truth import find_ground_truth, load_ground_truth_for  # noqa: E402
from mvrecon.eval.metrics import accuracy_summary  # noqa: E402
from mvrecon.executor import cpu_seconds, default_workers  # noqa: E402
from mvrecon.sfm import global_mapper  # noqa: E402
from mvrecon.sfm.config import MapperConfig  # noqa: E402
from mvrecon.sfm.global_mapper import map_correspondences_globally  # noqa: E402
from mvrecon.sfm.incremental import map_correspondences  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
ENGINES = ("mvrecon-global", "mvrecon-incremental", "colmap-global", "colmap-incremental")
OTHER_ENGINES = ("mvrecon-global-pairs",)  # only when named in --engines


def ground_truth(work: Path, name: str):
    for folder in (work / "scenes" / name, DATA / name, work / name):
        found = find_ground_truth(folder) if folder.is_dir() else None
        if found is not None:
            return found
    return None


def run_mvrecon(db: Path, engine: str, seed: int = 0) -> tuple[list[dict], float, float]:
    corr = database.read_correspondences(db)
    start, cpu = time.perf_counter(), cpu_seconds()
    if engine.startswith("mvrecon-global"):
        global_mapper.POSITIONS = "pairs" if engine == "mvrecon-global-pairs" else "tracks"
        result = map_correspondences_globally(corr, MapperConfig(mapper="global", seed=seed), default_workers())
    else:
        result = map_correspondences(corr, MapperConfig(seed=seed))
    seconds, cpu = time.perf_counter() - start, cpu_seconds() - cpu
    return [{m.names[i]: (m.R[i], m.t[i]) for i in m.registered_images()} for m in result.models], seconds, cpu


def run_colmap(db: Path, engine: str, seed: int = 0) -> tuple[list[dict], float, float]:
    import pycolmap

    from mvrecon.eval.models import poses

    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "database.db"
        shutil.copyfile(db, copy)
        out = Path(tmp) / "out"
        out.mkdir()
        pycolmap.set_random_seed(seed)
        start, cpu = time.perf_counter(), time.process_time()
        if engine == "colmap-global":
            opts = pycolmap.GlobalPipelineOptions()
            opts.random_seed = seed
            found = pycolmap.global_mapping(copy, tmp, out, opts)
        else:
            opts = pycolmap.IncrementalPipelineOptions()
            opts.random_seed = seed
            found = pycolmap.incremental_mapping(copy, tmp, out, opts)
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        models = sorted(found.values(), key=lambda r: r.num_reg_images(), reverse=True)
        return [poses(r) for r in models], seconds, cpu


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("work", type=Path, help="tools/bench_mapper.py's work folder")
    parser.add_argument("--only", default="", help="comma-separated set names")
    parser.add_argument("--engines", default=",".join(ENGINES),
                        help=f"comma-separated, of {', '.join(ENGINES + OTHER_ENGINES)}")
    parser.add_argument("--seed", type=int, default=0,
                        help="the mappers' random seed: a change is judged over several (0, 1, 2)")
    args = parser.parse_args(argv)
    names = [n for n in args.only.split(",") if n] or sorted(
        p.parent.parent.name for p in args.work.glob("*/database/database.db"))
    engines = [e for e in args.engines.split(",") if e]
    print("| set | engine | registered | largest | misplaced | AUC@1 | AUC@5 | mapping s | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in names:
        db = args.work / name / "database" / "database.db"
        gt_path = ground_truth(args.work, name)
        if not db.is_file() or gt_path is None:
            print(f"| {name} | - | no {'database' if not db.is_file() else 'ground truth'} | | | | | | |")
            continue
        corr = database.read_correspondences(db)
        gt = load_ground_truth_for(gt_path, [im.name for im in corr.images.values()])
        for engine in engines:
            try:
                run = run_mvrecon if engine.startswith("mvrecon") else run_colmap
                models, seconds, cpu = run(db, engine, args.seed)
            except Exception as exc:  # a failed engine is a row saying so, not the end of the table
                print(f"| {name} | {engine} | failed: {type(exc).__name__}: {exc} | | | | | | |", flush=True)
                continue
            acc = accuracy_summary(models, gt)
            largest = len(models[0]) if models else 0
            print(f"| {name} | {engine} | {acc['registered']}/{len(corr.images)} | {largest} | {acc['misplaced']} | "
                  f"{acc['auc@1']:.3f} | {acc['auc@5']:.3f} | {seconds:.1f} | {cpu:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
