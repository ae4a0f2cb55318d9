"""Are the catalog scenes usable? Run pycolmap's own pipeline on each; print accuracy vs ground truth.

    .venv/bin/python tools/check_scenes_colmap.py [NAME ...] [--out out/scenes]

For each perspective scene (default: all of them): make the scene (cached), then pycolmap extract ->
exhaustive match -> incremental mapping, and print registered images, components, AUC@0.5/1/5 deg, the
median and maximum rotation error after a Sim3 alignment (deg), the median centre error (% of extent),
and the wall time of each stage. The acceptance bar: every image in the largest model, max rotation
error < 0.5 deg and max centre error < 1 % of the scene extent (a frame registered one texture period off
fails here).
"""

import argparse
import json
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mvrecon.scenes import list_scenes, make_scene
from mvrecon.scenes.catalog import load_entry
from mvrecon.scenes.validate import colmap_reconstruct, compare_with_ground_truth


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("names", nargs="*", help="scene names (default: every perspective scene)")
    parser.add_argument("--out", default="out/scenes", help="folder for the scenes and the COLMAP runs")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("pycolmap").setLevel(logging.WARNING)
    names = args.names or [
        n for n in list_scenes() if load_entry(n)[0].get("kind", "perspective") == "perspective"
    ]
    rows = []
    for name in names:
        out = Path(args.out) / name
        start = time.perf_counter()
        make_scene(name, out)
        render_s = time.perf_counter() - start
        run = colmap_reconstruct(out, Path(args.out) / f"{name}_colmap")
        summary = compare_with_ground_truth(out, run["models"])
        summary.pop("rotation_errors_deg", None)
        row = {
            "scene": name,
            "make_s": round(render_s, 1),
            **{k: round(v, 4) if isinstance(v, float) else v for k, v in summary.items()},
            **{f"{k}_s": round(v, 1) for k, v in run["seconds"].items()},
        }
        ok = (row["registered_in_largest"] == row["images"] and row.get("max_rotation_error_deg", 180) < 0.5
              and row.get("max_center_error_pct", 100.0) < 1.0)
        row["acceptance"] = "pass" if ok else "FAIL"
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(
        f"{sum(r['acceptance'] == 'pass' for r in rows)}/{len(rows)} scenes pass "
        "(all images in the largest model, max rotation error < 0.5 deg, max centre error < 1 % of extent)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
