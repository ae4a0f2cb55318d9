"""Print the SEM height-error table: every height source of `mvrecon sem` on the rendered sem_tilt scenes, with
known and estimated tilts, against their ground truth. Run by hand:

    .venv/bin/python tools/sem_accuracy.py [--scenes sem_tilt_small,sem_tilt] [--sources dense,stereo]
                                           [--work DIR]

Each (scene, tilts, source) is one `run_sem` with the scene's gt/height.npy as ground truth; a run scores every
map it makes on the way (the gridded joint and merged points, the stereo matching before refinement), so
`joint` and `merged` rows come from the dense run. Error: RMS over the covered pixels (those with an estimate),
after removing the median offset, in % of the true height range; coverage: covered share of the pixels with a
true height. Time: wall seconds of the whole run that made the row's map.
"""

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    from mvrecon import progress
    from mvrecon.scenes import make_scene
    from mvrecon.sem.pipeline import SemConfig, run_sem

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="sem_tilt_small,sem_tilt", help="catalog scenes (comma-separated)")
    parser.add_argument("--sources", default="dense,stereo", help="height sources to run (dense, stereo, joint, "
                                                                   "merged; joint and merged are scored in every run)")
    parser.add_argument("--work", help="folder for the rendered scenes and the runs (default: a temporary one); "
                                       "scenes already rendered there are reused")
    args = parser.parse_args(argv)
    progress.set_enabled(False)
    work = Path(args.work or tempfile.mkdtemp(prefix="sem_accuracy_"))
    print("| scene | tilts | map | RMS % of range | coverage % | 99th pct % of range | run (s) |")
    print("|---|---|---|---:|---:|---:|---:|")
    for scene in args.scenes.split(","):
        root = work / scene
        if not (root / "gt" / "height.json").is_file():
            make_scene(scene, root)
        meta = json.loads((root / "gt" / "height.json").read_text())
        truth = np.load(root / "gt" / "height.npy")
        order = np.argsort(meta["tilt_angles_deg"])
        images = sorted((root / "images").iterdir(), key=lambda p: float(p.stem.split("_")[1]))
        tilts = tuple(float(meta["tilt_angles_deg"][i]) for i in order)
        axis = 90.0 if meta["tilt_axis"] == "y" else 0.0
        for mode in ("known", "estimated"):
            shown = set()
            for source in args.sources.split(","):
                config = SemConfig(tilts_deg=tilts if mode == "known" else None,
                                   axis_deg=axis if mode == "known" else None,
                                   pixel_size_um=meta["pixel_size_um"], height_source=source)
                report = run_sem(images, work / "runs" / f"{scene}_{mode}_{source}", config, truth)
                for name, acc in report["accuracy"]["maps"].items():
                    if name in shown:
                        continue
                    shown.add(name)
                    print(f"| {scene} | {mode} | {name} | {acc['rms_percent_of_range']:.3f} | "
                          f"{100 * acc['coverage']:.1f} | {acc['p99_percent_of_range']:.2f} | "
                          f"{report['timings']['total_s']:.1f} |", flush=True)
    print(f"runs in {work}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
