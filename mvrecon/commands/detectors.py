"""Compare keypoint detectors (the seed paper's Table 1, extended): SIFT, SURF, FAST, ORB, AKAZE, BRISK.

Examples:
  mvrecon detectors photos/ -o table.md
  mvrecon detectors im0.png im1.png other0.png other1.png --pairs -o table.md

For every image: keypoints per detector and detection time. Per detector: repeatability under a known warp of each
image (rotation by --angle degrees and zoom by --scale about the centre, keypoints within 2.5 px), and, with
--pairs (consecutive images form pairs A, B), the matches verified by a fundamental matrix between A and B.
Writes the markdown table to -o and the same figures as CSV next to it (table.csv).

A rerun into the same table continues: each image's (and pair's) figures per detector are kept as they are measured
(in .stages/detectors-TABLE.json next to the table, keyed on the image pixels, the settings and the code), so
only the missing ones are computed; reused figures keep the times measured then, and the log names them.
"""

ORDER = 64
ON_INTERRUPT = "the images done are kept next to the table (in .stages); rerun the same command to continue"


def add_arguments(parser) -> None:
    from ._options import finite_float, positive_float

    parser.add_argument("inputs", nargs="+", help="image files and/or folders of images")
    parser.add_argument("-o", "--output", required=True, help="markdown table to write (a .csv is written too)")
    parser.add_argument("--pairs", action="store_true", help="consecutive images form pairs (A, B)")
    parser.add_argument("--detectors", default="SIFT,SURF,FAST,ORB,AKAZE,BRISK",
                        help="comma-separated list (default: SIFT,SURF,FAST,ORB,AKAZE,BRISK)")
    parser.add_argument("--angle", type=finite_float, default=20.0,
                        help="rotation of the repeatability warp in degrees (default 20)")
    parser.add_argument("--scale", type=positive_float, default=0.8,
                        help="zoom of the repeatability warp (default 0.8)")


def _collect(inputs):
    from pathlib import Path

    from mvrecon.errors import InputError
    from mvrecon.io.images import list_images

    paths = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            names, _ = list_images(p)
            paths += [p / n for n in names]
        elif p.is_file():
            paths.append(p)
        else:
            raise InputError(f"{p}: no such file or folder")
    return paths


def _reused(done: dict, total: int, what: str, names) -> str:
    """'all 4 images' or '2 of 4 images: a.png, b.png (SIFT)': the detectors are named where not all of them were
    reused. `done`: image path or pair label -> the detectors reused."""
    if not done:
        return ""
    if len(done) == total and all(len(v) == len(names) for v in done.values()):
        return f"all {total} {what}"
    from pathlib import Path

    label = (lambda k: Path(k).name) if what == "images" else str
    items = [label(k) if len(v) == len(names) else f"{label(k)} ({', '.join(v)})" for k, v in done.items()]
    return f"{len(done)} of {total} {what}: {', '.join(items)}"


def run(args) -> int:
    import csv
    import logging
    import time
    from pathlib import Path

    import numpy as np

    from mvrecon.errors import InputError
    from mvrecon.features.detectors import CODE, DETECTORS, detect, measure, synthetic_homography, verified_inliers
    from mvrecon.io.files import replace_whole
    from mvrecon.io.stage_cache import Stages, code_digest, digest
    from mvrecon.io.images import read_image
    from mvrecon.progress import progress

    from ._options import check_output_file

    log = logging.getLogger("mvrecon.detectors")
    names = [d.strip().upper() for d in args.detectors.split(",") if d.strip()]
    if not names:
        raise InputError(f"--detectors {args.detectors!r}: no detector given; choose from {', '.join(DETECTORS)}")
    unknown = [d for d in names if d not in DETECTORS]
    if unknown:
        raise InputError(f"--detectors: unknown {', '.join(unknown)}; choose from {', '.join(DETECTORS)}")
    paths = _collect(args.inputs)
    if args.pairs and len(paths) % 2:
        raise InputError(f"--pairs needs an even number of images, got {len(paths)}")
    out = Path(args.output)
    for path in (out, out.with_suffix(".csv")):
        check_output_file(path, paths)
    import cv2

    stages = Stages(out.parent, f"detectors-{out.stem}.json")  # what earlier runs into this table finished
    settings = {"angle": args.angle, "scale": args.scale, "opencv": cv2.__version__, "code": code_digest(*CODE)}
    rows, pair_rows, impl, keys = [], [], {}, {}
    reused_images, reused_pairs = {}, {}  # name -> the detectors whose figures an earlier run measured
    held, previous = {}, None  # the current pair's detections made in this run, and its first image
    for i, path in enumerate(progress(paths, desc="detectors", unit="img")):
        try:
            image = read_image(path)
        except InputError as exc:
            if args.pairs:  # the pairs are given by position: one missing image would shift the others
                raise
            log.warning("skipping %s", exc)
            continue
        keys[path] = digest(image, settings)
        H = synthetic_homography(image.shape, args.angle, args.scale)
        row = {"image": str(path)}
        for name in names:
            item, key = f"{name} {path}", digest(keys[path], name)
            figures = stages.get(item, key)
            if figures is None:
                t0 = time.perf_counter()
                det, figures = measure(name, image, H)
                stages.put(item, key, figures, time.perf_counter() - t0)
                if args.pairs:
                    held[(path, name)] = det
            else:
                reused_images.setdefault(str(path), []).append(name)
            impl[name] = figures["implementation"]
            row[f"{name} keypoints"] = figures["keypoints"]
            row[f"{name} ms"] = round(1000 * figures["detect_s"], 1)
            row[f"{name} repeatability %"] = round(100 * figures["repeatability"], 1)
        rows.append(row)
        if args.pairs and i % 2:
            a, b = paths[i - 1], path
            row = {"pair": f"{a.name} / {b.name}"}
            for name in names:
                item, key = f"{name} {a} / {b}", digest(keys[a], keys[b], name)
                result = stages.get(item, key)
                if result is None:  # an image measured in an earlier run is detected again for its descriptors
                    t0 = time.perf_counter()
                    dets = [held.get((p, name)) or detect(name, img) for p, img in ((a, previous), (b, image))]
                    result = {"inliers": verified_inliers(*dets, name)}
                    stages.put(item, key, result, time.perf_counter() - t0)
                else:
                    reused_pairs.setdefault(row["pair"], []).append(name)
                row[f"{name} inliers"] = result["inliers"]
            pair_rows.append(row)
            held.clear()
        previous = image
    if not rows:
        raise InputError(f"none of the {len(paths)} image(s) could be decoded")
    lines = ["# Keypoint detectors", "", f"Repeatability: rotation {args.angle:g} deg, zoom {args.scale:g}, "
             "keypoints within 2.5 px. Implementations: " + ", ".join(f"{n} {impl[n]}" for n in names), "",
             "## Keypoints per image (the seed paper's Table 1, extended)", "",
             "| image | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    lines += [f"| {Path(r['image']).name} | " + " | ".join(str(r[f'{n} keypoints']) for n in names) + " |"
              for r in rows]
    lines += ["", "## Per detector (mean over images)", "",
              "| detector | keypoints | ms / image | repeatability % |" + (" verified inliers / pair |"
                                                                            if pair_rows else ""),
              "|---|---|---|---|" + ("---|" if pair_rows else "")]
    for n in names:
        cells = [f"{np.mean([r[f'{n} keypoints'] for r in rows]):.0f}", f"{np.mean([r[f'{n} ms'] for r in rows]):.1f}",
                 f"{np.mean([r[f'{n} repeatability %'] for r in rows]):.1f}"]
        if pair_rows:
            cells.append(f"{np.mean([r[f'{n} inliers'] for r in pair_rows]):.0f}")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    if pair_rows:
        lines += ["", "## Verified matches per pair (F inliers, our eight-point RANSAC, 1 px)", "",
                  "| pair | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        lines += [f"| {r['pair']} | " + " | ".join(str(r[f'{n} inliers']) for n in names) + " |" for r in pair_rows]
    replace_whole(out, lambda tmp: tmp.write_text("\n".join(lines) + "\n"))

    def write_csv(tmp):
        with open(tmp, "w", newline="") as f:
            fields = list(rows[0]) + (list(pair_rows[0])[1:] if pair_rows else []) + ["pair"]
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            pairs = {str(a): p for a, p in zip(paths[::2], pair_rows)} if pair_rows else {}
            for r in rows:
                writer.writerow({**r, **pairs.get(r["image"], {})})

    replace_whole(out.with_suffix(".csv"), write_csv)
    stages.prune()
    log.info("\n".join(lines))
    if reused_images or reused_pairs:
        log.info("reused from an earlier run into this table (%s), with the times measured then: %s", stages.path,
                 "; ".join(part for part in (_reused(reused_images, len(rows), "images", names),
                                             _reused(reused_pairs, len(pair_rows), "pairs", names)) if part))
    print(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0
