"""The detector table (the seed paper's Table 1, extended): keypoints, detection time and repeatability of
each detector on each image, and with pairs the matches a fundamental matrix verifies, as Markdown and CSV.

`measure_table(config, paths, out)` measures what earlier runs into the same table have not (their figures are
kept in .stages/detectors-TABLE.json next to it, keyed on the image pixels, the settings and the code), so a
rerun after an interruption computes only the missing ones; `write_table` writes the Markdown and the CSV.
"""

import csv
import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..io.files import replace_whole
from ..io.images import list_images, read_image
from ..io.record import Record, code_digest, digest
from ..progress import progress
from . import detectors

log = logging.getLogger("mvrecon.detectors")


@dataclass(frozen=True)
class DetectorTableConfig:
    """The settings of a detector table."""

    detectors: str = ",".join(detectors.DETECTORS)  # comma-separated names, case-insensitive
    angle: float = 20.0  # rotation of the repeatability warp (degrees)
    scale: float = 0.8  # zoom of the repeatability warp
    pairs: bool = False  # consecutive images form pairs (A, B), whose verified matches are counted

    @property
    def names(self) -> list[str]:
        """The detectors, upper case, in the order given."""
        return [d.strip().upper() for d in self.detectors.split(",") if d.strip()]

    def validate(self) -> None:
        """An InputError unless at least one detector is given and every one is known."""
        known = ", ".join(detectors.DETECTORS)
        if not self.names:
            raise InputError(f"--detectors {self.detectors!r}: no detector given; choose from {known}")
        unknown = [d for d in self.names if d not in detectors.DETECTORS]
        if unknown:
            raise InputError(f"--detectors: unknown {', '.join(unknown)}; choose from {known}")

    def check_images(self, paths: list[Path]) -> None:
        """An InputError when pairs are asked for and the images do not form them."""
        if self.pairs and len(paths) % 2:
            raise InputError(f"--pairs needs an even number of images, got {len(paths)}")


def collect_images(inputs: Iterable[Path | str]) -> list[Path]:
    """The image files given, each folder replaced by its images (name order); an InputError names a path that
    does not exist."""
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


@dataclass(kw_only=True)
class DetectorTable:
    """The measured figures: one row per image ("image", then per detector "NAME keypoints", "NAME ms",
    "NAME repeatability %") and, with pairs, one per pair ("pair", then "NAME inliers")."""

    config: DetectorTableConfig
    paths: list[Path]  # the images asked for, decodable or not
    rows: list[dict] = field(default_factory=list)
    pair_rows: list[dict] = field(default_factory=list)
    implementation: dict[str, str] = field(default_factory=dict)  # detector -> whose implementation
    # image path or pair label -> the detectors whose figures an earlier run measured
    reused_images: dict[str, list[str]] = field(default_factory=dict)
    reused_pairs: dict[str, list[str]] = field(default_factory=dict)
    cache_path: Path | None = None  # where the figures are kept for a rerun

    def markdown(self) -> list[str]:
        """The table's Markdown lines."""
        names, rows, pair_rows, config = self.config.names, self.rows, self.pair_rows, self.config
        lines = ["# Keypoint detectors", "",
                 f"Repeatability: rotation {config.angle:g} deg, zoom {config.scale:g}, "
                 "keypoints within 2.5 px. Implementations: "
                 + ", ".join(f"{n} {self.implementation[n]}" for n in names), "",
                 "## Keypoints per image (the seed paper's Table 1, extended)", "",
                 "| image | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
        lines += [f"| {Path(r['image']).name} | " + " | ".join(str(r[f'{n} keypoints']) for n in names) + " |"
                  for r in rows]
        lines += ["", "## Per detector (mean over images)", "",
                  "| detector | keypoints | ms / image | repeatability % |"
                  + (" verified inliers / pair |" if pair_rows else ""),
                  "|---|---|---|---|" + ("---|" if pair_rows else "")]
        for n in names:
            cells = [f"{np.mean([r[f'{n} keypoints'] for r in rows]):.0f}",
                     f"{np.mean([r[f'{n} ms'] for r in rows]):.1f}",
                     f"{np.mean([r[f'{n} repeatability %'] for r in rows]):.1f}"]
            if pair_rows:
                cells.append(f"{np.mean([r[f'{n} inliers'] for r in pair_rows]):.0f}")
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
        if pair_rows:
            lines += ["", "## Verified matches per pair (F inliers, our eight-point RANSAC, 1 px)", "",
                      "| pair | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
            lines += [f"| {r['pair']} | " + " | ".join(str(r[f'{n} inliers']) for n in names) + " |"
                      for r in pair_rows]
        return lines

    def reused_text(self) -> str:
        """What was reused from an earlier run ('all 4 images; 1 of 2 pairs: a.png / b.png (SIFT)'), or ''."""
        names = self.config.names
        parts = (_reused(self.reused_images, len(self.rows), "images", names),
                 _reused(self.reused_pairs, len(self.pair_rows), "pairs", names))
        return "; ".join(part for part in parts if part)


def _reused(done: dict, total: int, what: str, names) -> str:
    """'all 4 images' or '2 of 4 images: a.png, b.png (SIFT)': the detectors are named where not all of them
    were reused. `done`: image path or pair label -> the detectors reused."""
    if not done:
        return ""
    if len(done) == total and all(len(v) == len(names) for v in done.values()):
        return f"all {total} {what}"
    label = (lambda k: Path(k).name) if what == "images" else str
    items = [label(k) if len(v) == len(names) else f"{label(k)} ({', '.join(v)})" for k, v in done.items()]
    return f"{len(done)} of {total} {what}: {', '.join(items)}"


def measure_table(config: DetectorTableConfig, paths: list[Path], out: Path) -> DetectorTable:
    """The figures of every image (and pair) of `paths` for the table `out`: those that earlier runs into
    `out` measured are reused, the others measured and kept as each is done. An image that cannot be decoded
    is skipped with a warning, except with pairs (they are given by position); none decoded is an
    InputError."""
    stages = Record(out.parent, f"detectors-{out.stem}.json")  # what earlier runs into this table finished
    settings = {"angle": config.angle, "scale": config.scale, "opencv": cv2.__version__,
                "code": code_digest(*detectors.CODE)}
    table = DetectorTable(config=config, paths=paths, cache_path=stages.path)
    keys = {}
    held, previous = {}, None  # the current pair's detections made in this run, and its first image
    for i, path in enumerate(progress(paths, desc="detectors", unit="img")):
        try:
            image = read_image(path)
        except InputError as exc:
            if config.pairs:  # the pairs are given by position: one missing image would shift the others
                raise
            log.warning("skipping %s", exc)
            continue
        keys[path] = digest(image, settings)
        table.rows.append(_image_row(config, stages, table, path, image, keys[path], held))
        if config.pairs and i % 2:
            first, second = (paths[i - 1], previous), (path, image)
            table.pair_rows.append(_pair_row(config, stages, table, first, second, keys, held))
            held.clear()
        previous = image
    if not table.rows:
        raise InputError(f"none of the {len(paths)} image(s) could be decoded")
    stages.prune()
    return table


def _image_row(config: DetectorTableConfig, stages: Record, table: DetectorTable, path: Path, image,
               key: str, held: dict) -> dict:
    """One image's row: each detector's figures, reused or measured (and kept); with pairs, the detections
    made are held for the pair."""
    H = detectors.synthetic_homography(image.shape, config.angle, config.scale)
    row = {"image": str(path)}
    for name in config.names:
        item, item_key = f"{name} {path}", digest(key, name)
        figures = stages.get(item, item_key)
        if figures is None:
            t0 = time.perf_counter()
            det, figures = detectors.measure(name, image, H)
            stages.put(item, item_key, figures, time.perf_counter() - t0)
            if config.pairs:
                held[(path, name)] = det
        else:
            table.reused_images.setdefault(str(path), []).append(name)
        table.implementation[name] = figures["implementation"]
        row[f"{name} keypoints"] = figures["keypoints"]
        row[f"{name} ms"] = round(1000 * figures["detect_s"], 1)
        row[f"{name} repeatability %"] = round(100 * figures["repeatability"], 1)
    return row


def _pair_row(config: DetectorTableConfig, stages: Record, table: DetectorTable, first: tuple,
              second: tuple, keys: dict, held: dict) -> dict:
    """One pair's row: each detector's verified inliers between its (path, image) `first` and `second`."""
    (a, image_a), (b, image_b) = first, second
    row = {"pair": f"{a.name} / {b.name}"}
    for name in config.names:
        item, key = f"{name} {a} / {b}", digest(keys[a], keys[b], name)
        result = stages.get(item, key)
        if result is None:  # an image measured in an earlier run is detected again for its descriptors
            t0 = time.perf_counter()
            dets = [held.get((p, name)) or detectors.detect(name, img)
                    for p, img in ((a, image_a), (b, image_b))]
            result = {"inliers": detectors.verified_inliers(*dets, name)}
            stages.put(item, key, result, time.perf_counter() - t0)
        else:
            table.reused_pairs.setdefault(row["pair"], []).append(name)
        row[f"{name} inliers"] = result["inliers"]
    return row


def write_table(table: DetectorTable, out: Path) -> list[str]:
    """`out` (Markdown) and the same figures as CSV next to it (.csv), each replaced whole; returns the
    Markdown lines."""
    lines = table.markdown()
    replace_whole(out, lambda tmp: tmp.write_text("\n".join(lines) + "\n"))
    rows, pair_rows = table.rows, table.pair_rows

    def write_csv(tmp):
        with open(tmp, "w", newline="") as f:
            fields = list(rows[0]) + (list(pair_rows[0])[1:] if pair_rows else []) + ["pair"]
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            pairs = {str(a): p for a, p in zip(table.paths[::2], pair_rows)} if pair_rows else {}
            for r in rows:
                writer.writerow({**r, **pairs.get(r["image"], {})})

    replace_whole(out.with_suffix(".csv"), write_csv)
    return lines
