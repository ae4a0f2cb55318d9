"""Figures of a study: one plot per metric (a panel per degradation, a line per engine) and a contact sheet.

Levels are placed side by side in the order the user gave them (mild to severe), with the clean images first,
so every panel reads left to right as "worse", whether the level grows (noise sigma) or shrinks (JPEG quality).
"""

from pathlib import Path

import cv2
import numpy as np

from ..io.images import list_images, read_image, to_gray
from .grid import AXES, CLEAN, Cell, Grid

PLOTTED = (("registered_pct", "registered images (%)"), ("auc@1", "relative-pose AUC@1"),
           ("auc@5", "relative-pose AUC@5"), ("points", "3D points (largest model)"),
           ("mean_track_length", "mean track length"), ("mean_reprojection_error_px", "mean reprojection error (px)"),
           ("keypoints_per_image", "keypoints per image"), ("mean_inliers_per_pair", "verified inliers per pair"),
           ("wall_s", "wall time (s)"))
BREAKING_METRICS = ("registered_pct", "auc@5")
PANELS_PER_ROW = 4


def _level_label(axis: str, level: float) -> str:
    return "clean" if level == AXES[axis].identity else f"{level:g}"


def metric_plots(rows: list[dict], grid: Grid, out_dir: Path | str) -> list[tuple[str, Path]]:
    """Write `<metric>.png` per metric into out_dir; returns (title, path) pairs in PLOTTED order."""
    import matplotlib  # noqa: PLC0415 - figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - figures only

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    engines = list(dict.fromkeys(r["engine"] for r in rows))
    axes_names = grid.axes()
    written = []
    for metric, title in PLOTTED:
        ncols = min(PANELS_PER_ROW, len(axes_names))
        nrows = -(-len(axes_names) // ncols)
        fig, panels = plt.subplots(nrows, ncols, figsize=(3.6 * ncols + 0.6, 3.0 * nrows + 0.4), squeeze=False,
                                   sharey=True)
        panels = panels.ravel()
        for panel in panels[len(axes_names):]:
            panel.axis("off")
        for panel, axis in zip(panels, axes_names):
            for k, engine in enumerate(engines):
                series = [r for r in rows if r["engine"] == engine and r["degradation"] == axis]
                y = [r[metric] for r in series]
                panel.plot(range(len(series)), y, marker="o", color=f"C{k}", label=engine)
                if metric in BREAKING_METRICS and series:  # the breaking threshold: half of the clean value
                    panel.axhline(0.5 * series[0][metric], color=f"C{k}", linestyle=":", linewidth=1,
                                  label=f"{engine}: half of clean")
            labels = [_level_label(axis, r["level"]) for r in rows if r["engine"] == engines[0]
                      and r["degradation"] == axis]
            panel.set_xticks(range(len(labels)), labels)
            panel.set_xlabel(AXES[axis].label)
            panel.grid(alpha=0.3)
        for row in range(nrows):
            panels[row * ncols].set_ylabel(title)
        panels[len(axes_names) - 1].legend(fontsize=7)
        fig.suptitle(title)
        fig.tight_layout()
        path = out_dir / f"{metric.replace('@', '_at_')}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append((title, path))
    return written


def _display(path) -> np.ndarray:
    """An image file as 8-bit RGB for display, whatever its depth and channels."""
    img = read_image(path)
    if img.dtype == np.uint16:
        img = (img / 257.0).round().astype(np.uint8)
    return np.dstack([img] * 3) if img.ndim == 2 else img


def detailed_window(img: np.ndarray, size: int) -> tuple[int, int]:
    """Top-left corner of the size x size window with the most gradient energy (where degradations show)."""
    grey = to_gray(img, np.float32)
    energy = cv2.Sobel(grey, cv2.CV_32F, 1, 0) ** 2 + cv2.Sobel(grey, cv2.CV_32F, 0, 1) ** 2
    summed = cv2.boxFilter(energy, -1, (size, size), normalize=False, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)
    h, w = grey.shape
    valid = summed[: max(h - size + 1, 1), : max(w - size + 1, 1)]
    y, x = np.unravel_index(int(np.argmax(valid)), valid.shape)
    return int(x), int(y)


def contact_sheet(folders: dict, grid: Grid, path: Path | str, crop: int = 160, example: str | None = None,
                  names: list[str] | None = None) -> Path:
    """A grid of crops of one example image: a row per degradation, a column per level (clean first).

    The crop is the same scene region in every cell (scaled for downscaled cells, then shown enlarged).
    `names`: the study's images (default: `io.images.list_images` of the clean folder); the example is one that
    every cell has (a cell leaves out an image its decoder refused).
    """
    import matplotlib  # noqa: PLC0415 - figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - figures only


    if names is None:
        names, _ = list_images(folders[CLEAN])
    names = [n for n in names if all((Path(f) / n).is_file() for f in folders.values())] or list(names)
    name = example if example in names else names[len(names) // 2]
    clean = _display(Path(folders[CLEAN]) / name)
    crop = min(crop, *clean.shape[:2])
    x0, y0 = detailed_window(clean, crop)
    rows = grid.axes()
    cols = 1 + max(len(grid.degraded_levels(a)) for a in rows)
    fig, panels = plt.subplots(len(rows), cols, figsize=(1.9 * cols, 2.0 * len(rows)), squeeze=False)
    for r, axis in enumerate(rows):
        cells = [Cell(None, None)] + [Cell(axis, lv) for lv in grid.degraded_levels(axis)]
        for c in range(cols):
            panel = panels[r][c]
            panel.axis("off")
            if c >= len(cells):
                continue
            img = _display(Path(folders[cells[c].key]) / name)
            sx, sy = img.shape[1] / clean.shape[1], img.shape[0] / clean.shape[0]
            x, y = int(round(x0 * sx)), int(round(y0 * sy))
            w, h = max(1, int(round(crop * sx))), max(1, int(round(crop * sy)))
            tile = cv2.resize(img[y:y + h, x:x + w], (crop, crop), interpolation=cv2.INTER_NEAREST)
            panel.imshow(tile, interpolation="nearest")
            level = "clean" if cells[c].is_clean else f"{AXES[axis].name} {cells[c].level:g}"
            panel.set_title(level, fontsize=9)
    fig.suptitle(f"{name}: {crop}x{crop} px crop at each level", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path

