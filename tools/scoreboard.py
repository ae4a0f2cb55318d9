"""The standing scoreboard: `mvrecon compare` over the catalog scenes and every multi-view set in ../shared/data.

    python tools/scoreboard.py                      # everything it finds, small scenes first
    python tools/scoreboard.py --only object_orbit_small middlebury_templeRing
    python tools/scoreboard.py --max-pixels 1e6     # skip sets with larger images (the Strecha sets are 6 Mpx)
    python tools/scoreboard.py --cached-only        # rewrite the table from finished runs only (after Ctrl-C)
    python tools/scoreboard.py --global-mappers     # also both global mappers (mvrecon-global, COLMAP global)

Each scene's comparison goes to WORK/<scene>/ (index.html, metrics.json, runs/); finished runs are reused, so a
second call only runs what is missing (delete WORK/<scene> to redo one). docs/scoreboard.md is rewritten after
every scene with one row per scene: both engines' registered images, AUC@1/5, points, reprojection error, wall time
and the time ratio, plus the machine and the date. Scenes with ground truth are scored against it; the others
against COLMAP's model (then COLMAP's AUC is the reference and reads "ref"), unless it holds fewer images than
mvrecon's or under half of them (then the model with the most images is the reference, or none is: `compare`'s
`choose_reference`, whose note goes to the row). With --global-mappers each row has two more columns: the global
mappers' registered images and AUC@5 (`mvrecon --mapper global` / pycolmap's `global_mapping`), beside the
incremental ones.
"""

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
MULTI_VIEW_KINDS = ("perspective", "colmap_synthetic")


def catalog_scenes() -> list[str]:
    """The multi-view catalog scenes (perspective and pycolmap-synthetic; not stereo pairs or SEM tilts)."""
    from mvrecon.scenes import list_scenes
    from mvrecon.scenes.catalog import load_entry

    return [n for n in list_scenes() if load_entry(n)[0].get("kind", "perspective") in MULTI_VIEW_KINDS]


def render_scene(name: str, work: Path) -> tuple[Path, Path | None]:
    """Render (or reuse) a catalog scene into WORK/scenes/NAME; its image folder and ground truth."""
    from mvrecon.eval.ground_truth import find_ground_truth
    from mvrecon.scenes import make_scene

    folder = make_scene(name, work / "scenes" / name)
    return folder / "images", find_ground_truth(folder)


def shared_sets() -> list[str]:
    """Every multi-view set in ../shared/data: an images/ folder with 3+ images that is neither a collection of
    independent pairs (a *pairs*.txt next to it) nor a stereo calibration (intrinsics/extrinsics .yml)."""
    from mvrecon.io.images import list_images

    if not DATA.is_dir():
        return []
    out = []
    for d in sorted(p for p in DATA.iterdir() if (p / "images").is_dir()):
        if any(d.glob("*pairs*.txt")) or any(d.glob("*trinsics.yml")):
            continue
        if len(list_images(d / "images")[0]) >= 3:
            out.append(d.name)
    return out


def pixels(image_dir: Path) -> tuple[float, int]:
    """(pixels of the first image, number of images): how big a run will be."""
    from mvrecon.io.images import image_metadata, list_images

    names, _ = list_images(image_dir)
    meta = image_metadata(image_dir / names[0])
    return float(meta.width * meta.height), len(names)


def run_scene(name, images, gt, work: Path, timeout: float | None, global_mappers: bool = False) -> dict:
    from mvrecon.eval.compare import CompareConfig, compare_images
    from mvrecon.eval.report import write_report

    report_dir = work / name
    config = CompareConfig(timeout_s=timeout, colmap_global=global_mappers, mvrecon_global=global_mappers)
    comparison = compare_images(images, report_dir, gt=gt, config=config)
    write_report(comparison, report_dir)
    return comparison.metrics


_ENGINE_NAMES = {"colmap": "COLMAP"}


def _fmt(metric, value, role="engine"):
    from mvrecon.eval.report import format_value

    if value is None and role == "reference" and metric.startswith("auc@"):
        return "ref"
    return format_value(metric, value)


INCREMENTAL = ("mvrecon", "colmap", "colmap-same-matches")
GLOBAL = ("mvrecon-global", "colmap-global")


def finished(report_dir: Path, global_mappers: bool = False) -> bool:
    """Whether every engine run of a scene's comparison finished (or timed out) earlier."""
    from mvrecon.eval.runners import run_meta

    engines = INCREMENTAL + (GLOBAL if global_mappers else ())
    return all(run_meta(report_dir / "runs" / e).get("finished") for e in engines)


def table_row(name: str, origin: str, m: dict, work: Path, global_mappers: bool = False) -> tuple[str, str]:
    """The scene's markdown row, and the path of its HTML report."""
    from mvrecon.eval.report import other_models_text

    def pair(metric, engines=("mvrecon", "colmap")):
        return " / ".join(_fmt(metric, e.get("summary", {}).get(metric), e.get("role", "engine"))
                          + (other_models_text(e.get("summary", {})) if metric == "registered" else "")
                          for e in (m["engines"].get(k, {}) for k in engines))

    mv = m["engines"].get("mvrecon", {})

    n = len(m["images"])
    reference = m["reference"]["name"]
    gt = "GT" if reference == "ground truth" else f"vs {_ENGINE_NAMES.get(reference, reference)}" if reference \
        else "none"
    ratio = _fmt("time_ratio_vs_colmap", mv.get("summary", {}).get("time_ratio_vs_colmap"))
    notes = [f"{k} failed: {e['error']}" for k, e in m["engines"].items() if e.get("error")]
    if m["reference"].get("note"):
        notes.append(m["reference"]["note"])
    failed = "; ".join(notes)
    link = Path(work / name / "index.html").resolve()
    extra = f"{pair('registered', GLOBAL)} | {pair('auc@5', GLOBAL)} | " if global_mappers else ""
    return (f"| {name} | {origin} | {n} | {gt} | {pair('registered')} | {pair('auc@1')} | {pair('auc@5')} | "
            f"{pair('points')} | {pair('mean_reprojection_error_px')} | {pair('wall_s')} | {ratio} | {extra}"
            f"{failed or '—'} |"), str(link)


def write_scoreboard(path: Path, rows: list[str], skipped: list[str], machine: dict, command: str,
                     global_mappers: bool = False) -> None:
    extra = "global registered (mvrecon / COLMAP) | global AUC@5 | " if global_mappers else ""
    header = ("| scene | source | images | scored | registered (mvrecon / COLMAP) | AUC@1 | AUC@5 | points | "
              f"reproj. error px | wall s | time ratio | {extra}notes |\n"
              f"|---|---|---|---|---|---|---|---|---|---|---|{'---|---|' if global_mappers else ''}---|\n")
    text = f"""# Scoreboard: mvrecon vs COLMAP (pycolmap), measured

Generated by `{command}` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.
Machine: {machine['cpu']}, {machine['cores']} cores, {machine['memory_gb']} GB RAM, {machine['system']},
Python {machine['python']}; pycolmap on the CPU. Both engines ran in the same process tree on the same images with
their default camera settings (`--camera-mode auto`, seed 0; COLMAP SIMPLE_RADIAL, mvrecon the model left open,
SIMPLE_RADIAL unless its mapper finds the lens needs OPENCV or OPENCV_FISHEYE), one after the other.

Each cell is `mvrecon / COLMAP`. *scored*: GT = against the data set's ground truth; vs COLMAP = no ground truth, so
AUC is measured against COLMAP's model (COLMAP's own reads "ref"); vs mvrecon = no ground truth, and COLMAP's model
holds fewer images than mvrecon's or under half of them, so mvrecon's is the reference (the note says why); none =
no model holds half the images. Registered images are those of the largest model, the other models' after a "+".
AUC@t is the relative-pose AUC over all image pairs (a pair with an unregistered image, or split across models,
counts 180 deg); points and reprojection error are of the largest model; wall time is the whole run (start-up,
features, matching, mapping); time ratio = mvrecon / COLMAP (below 1: mvrecon is faster). The per-scene HTML
reports (`mvrecon compare`) hold every other number.

{header}{chr(10).join(rows)}
"""
    if skipped:
        text += "\nNot run this time: " + "; ".join(skipped) + "\n"
    path.write_text(text)


def shown_command(args: argparse.Namespace) -> str:
    """The command as the scoreboard's header shows it: the flags that decide what ran and how long a run may
    take, not the folders it wrote to (--work, --out), which say nothing about the figures."""
    flags = [f"--max-pixels {args.max_pixels:g}"] if args.max_pixels else []
    flags.append(f"--timeout {args.timeout:g}")
    flags += [f"{flag} {' '.join(names)}" for flag, names in (("--only", args.only), ("--skip", args.skip)) if names]
    flags += ["--cached-only"] if args.cached_only else []
    flags += ["--global-mappers"] if args.global_mappers else []
    return "python tools/scoreboard.py " + " ".join(flags)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--work", type=Path, default=REPO / "out" / "scoreboard",
                        help="where scenes, runs, reports and scoreboard.json go (default: out/scoreboard)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "scoreboard.md",
                        help="the markdown table to rewrite (default: the repository's docs/scoreboard.md)")
    parser.add_argument("--only", nargs="+", help="only these scenes / data sets")
    parser.add_argument("--skip", nargs="+", default=[], help="leave these out")
    parser.add_argument("--max-pixels", type=float, help="skip sets whose images have more pixels than this")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per engine run (default 1800)")
    parser.add_argument("--cached-only", action="store_true",
                        help="only report scenes whose runs all finished earlier; run nothing new")
    parser.add_argument("--global-mappers", action="store_true",
                        help="also run both global mappers and show their registered images and AUC@5")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from mvrecon.eval.compare import machine_info
    from mvrecon.eval.ground_truth import find_ground_truth

    wanted = lambda n: (not args.only or n in args.only) and n not in args.skip  # noqa: E731
    catalog = [n for n in catalog_scenes() if wanted(n)]
    shared = sorted((n for n in shared_sets() if wanted(n)), key=lambda n: math.prod(pixels(DATA / n / "images")))
    # small catalog scenes, then the data sets from small to big, then the full-size catalog scenes
    quick = [n for n in catalog if "small" in n or "synthetic" in n]
    plan = [(n, "catalog") for n in quick] + [(n, "public set") for n in shared] \
        + [(n, "catalog") for n in catalog if n not in quick]
    rows, skipped = [], []
    command = shown_command(args)
    for k, (name, origin) in enumerate(plan):
        try:
            if origin == "catalog":
                images, gt = render_scene(name, args.work)
            else:
                images, gt = DATA / name / "images", find_ground_truth(DATA / name)
            size, count = pixels(images)
            if args.max_pixels and size > args.max_pixels:
                skipped.append(f"{name} ({count} images of {size / 1e6:.1f} Mpx > --max-pixels)")
                write_scoreboard(args.out, rows, skipped, machine_info(), command, args.global_mappers)
                continue
            if args.cached_only and not finished(args.work / name, args.global_mappers):
                skipped.append(f"{name} (not run yet)")
                continue
            print(f"== {name}: {count} images, {size / 1e6:.1f} Mpx, ground truth: {gt or 'none'}", flush=True)
            start = time.perf_counter()
            metrics = run_scene(name, images, gt, args.work, args.timeout, args.global_mappers)
        except KeyboardInterrupt:
            skipped += [f"{n} (interrupted before it finished)" for n, _ in plan[k:]]
            write_scoreboard(args.out, rows, skipped, machine_info(), command, args.global_mappers)
            print(f"interrupted; wrote {args.out} with the {len(rows)} scene(s) that finished")
            return 130
        row, link = table_row(name, origin, metrics, args.work, args.global_mappers)
        rows.append(row)
        print(row, f"({time.perf_counter() - start:.0f} s; report {link})", flush=True)
        write_scoreboard(args.out, rows, skipped, machine_info(), command, args.global_mappers)
    (args.work / "scoreboard.json").write_text(json.dumps({"rows": rows, "skipped": skipped}, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
