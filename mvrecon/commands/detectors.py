"""Compare keypoint detectors (the seed paper's Table 1, extended): SIFT, SURF, FAST, ORB, AKAZE, BRISK.

Examples:
  mvrecon detectors photos/ -o table.md
  mvrecon detectors im0.png im1.png other0.png other1.png --pairs -o table.md

For every image: keypoints per detector and detection time. Per detector: repeatability under a known warp of each
image (rotation by --angle degrees and zoom by --scale about the centre, keypoints within 2.5 px), and, with
--pairs (consecutive images form pairs A, B), the matches verified by a fundamental matrix between A and B.
Writes the markdown table to -o and the same figures as CSV next to it (table.csv).
"""

ORDER = 64


def add_arguments(parser) -> None:
    from ._options import finite_float, positive_float

    parser.add_argument("inputs", nargs="+", help="image files and/or folders of images")
    parser.add_argument("-o", "--output", required=True, help="markdown table to write (a .csv is written too)")
    parser.add_argument("--pairs", action="store_true", help="consecutive images form pairs (A, B)")
    parser.add_argument("--detectors", default="SIFT,SURF,FAST,ORB,AKAZE,BRISK", help="comma-separated list")
    parser.add_argument("--angle", type=finite_float, default=20.0, help="rotation of the repeatability warp (degrees)")
    parser.add_argument("--scale", type=positive_float, default=0.8, help="zoom of the repeatability warp")


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


def run(args) -> int:
    import csv
    import logging
    from pathlib import Path

    import numpy as np

    from mvrecon.errors import InputError
    from mvrecon.features.detectors import (DETECTORS, detect, synthetic_homography, verified_inliers,
                                            warp_repeatability)
    from mvrecon.io.files import replace_whole
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
    rows, detections = [], {}
    impl = {}
    for path in progress(paths, desc="detectors", unit="img"):
        try:
            image = read_image(path)
        except InputError as exc:
            if args.pairs:  # the pairs are given by position: one missing image would shift the others
                raise
            log.warning("skipping %s", exc)
            continue
        H = synthetic_homography(image.shape, args.angle, args.scale)
        row = {"image": str(path)}
        for name in names:
            det = detect(name, image)
            impl[name] = det.implementation
            detections[(str(path), name)] = det
            row[f"{name} keypoints"] = len(det.keypoints)
            row[f"{name} ms"] = round(1000 * det.seconds, 1)
            row[f"{name} repeatability %"] = round(100 * warp_repeatability(name, image, H), 1)
        rows.append(row)
    if not rows:
        raise InputError(f"none of the {len(paths)} image(s) could be decoded")
    pair_rows = []
    if args.pairs:
        for a, b in zip(paths[::2], paths[1::2]):
            row = {"pair": f"{a.name} / {b.name}"}
            for name in names:
                row[f"{name} inliers"] = verified_inliers(detections[(str(a), name)], detections[(str(b), name)],
                                                          name)
            pair_rows.append(row)
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
    log.info("\n".join(lines))
    print(f"wrote {out} and {out.with_suffix('.csv')}")
    return 0
