"""Stereo figures (PNG, matplotlib Agg): matches with epipolar lines and epipoles, the rectified pair, colour-scaled
disparity and depth maps with their scale bar, and the error map against ground truth."""

from pathlib import Path

import numpy as np

from ..geometry.fundamental import epipolar_lines, epipoles


def _plt():
    import matplotlib  # noqa: PLC0415 - figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - figures only

    return plt


def _show(ax, image):
    ax.imshow(image, cmap="gray" if np.asarray(image).ndim == 2 else None)
    ax.set_axis_off()


def _draw_line(ax, line, width, height, **style):
    a, b, c = line
    if abs(b) > abs(a):
        xs = np.array([0, width])
        ys = -(a * xs + c) / b
    else:
        ys = np.array([0, height])
        xs = -(b * ys + c) / a
    ax.plot(xs, ys, **style)


def matches_epipolar_figure(path: Path | str, left: np.ndarray, right: np.ndarray, x1: np.ndarray,
                            x2: np.ndarray, F: np.ndarray, inliers: np.ndarray, max_lines: int = 20,
                            seed: int = 0) -> None:
    """Top: the two images side by side with inlier matches (green) and outliers (red).
    Bottom: a sample of inliers with their epipolar lines in both images and the epipoles (if in view)."""
    plt = _plt()
    h, w = left.shape[:2]
    fig, axes = plt.subplots(2, 2, figsize=(12, 9), gridspec_kw={"height_ratios": [1, 1]})
    gs = axes[0, 0].get_gridspec()
    for ax in axes[0]:
        ax.remove()
    top = fig.add_subplot(gs[0, :])
    canvas = np.concatenate([left, right], axis=1)
    _show(top, canvas)
    x1, x2 = np.asarray(x1), np.asarray(x2)
    rng = np.random.default_rng(seed)
    out_idx = np.flatnonzero(~inliers)
    in_idx = np.flatnonzero(inliers)
    from matplotlib.collections import LineCollection  # noqa: PLC0415 - figures only

    for idx, colour in ((rng.permutation(out_idx)[:100], "r"), (rng.permutation(in_idx)[:300], "lime")):
        segments = np.stack([x1[idx], x2[idx] + [w, 0]], axis=1)
        top.add_collection(LineCollection(segments, colors=colour, linewidths=0.5, alpha=0.7))
    top.set_title(f"{inliers.sum()} inlier matches (green) of {len(inliers)}; outliers in red (sample)")
    sample = rng.permutation(in_idx)[:max_lines]
    e1, e2 = epipoles(F)
    colours = plt.cm.tab20(np.linspace(0, 1, max(len(sample), 1)))
    for ax, pts, lines, e, name in ((axes[1, 0], x1[sample], epipolar_lines(F, x2[sample], 1), e1, "left"),
                                    (axes[1, 1], x2[sample], epipolar_lines(F, x1[sample], 2), e2, "right")):
        _show(ax, left if name == "left" else right)
        for line, p, col in zip(lines, pts, colours):
            _draw_line(ax, line, w, h, color=col, lw=0.8)
            ax.plot(*p, "o", color=col, ms=4)
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        if abs(e[2]) > 1e-9 and np.all(np.abs(e[:2] / e[2]) < 1e7):
            ex, ey = e[:2] / e[2]
            where = f"({ex:.0f}, {ey:.0f})"
            if 0 <= ex <= w and 0 <= ey <= h:
                ax.plot(ex, ey, "y*", ms=14)
        else:
            where = "at infinity"
        ax.set_title(f"{name} epipolar lines; epipole {where}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def rectified_figure(path: Path | str, left: np.ndarray, right: np.ndarray, step: int = 40) -> None:
    """Rectified pair side by side with horizontal lines every `step` rows: matches must sit on the same line."""
    plt = _plt()
    h, w = left.shape[:2]
    fig, ax = plt.subplots(figsize=(12, 12 * h / (2 * w) + 0.6))
    _show(ax, np.concatenate([left, right], axis=1))
    for y in range(step // 2, h, step):
        ax.axhline(y, color="lime", lw=0.5)
    ax.set_title("rectified left | right (corresponding points share a row)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def scalar_map_figure(path: Path | str, values: np.ndarray, title: str, label: str, cmap: str = "turbo",
                      vmin: float | None = None, vmax: float | None = None) -> None:
    """A float map with a colour scale; NaN (holes) drawn black."""
    plt = _plt()
    v = np.asarray(values, dtype=float)
    finite = v[np.isfinite(v)]
    lo = vmin if vmin is not None else (np.percentile(finite, 1) if finite.size else 0)
    hi = vmax if vmax is not None else (np.percentile(finite, 99) if finite.size else 1)
    h, w = v.shape
    fig, ax = plt.subplots(figsize=(8, 8 * h / w + 0.5))
    colormap = plt.get_cmap(cmap).with_extremes(bad="black")
    im = ax.imshow(np.ma.masked_invalid(v), cmap=colormap, vmin=lo, vmax=hi)
    ax.set_axis_off()
    ax.set_title(title)
    fig.colorbar(im, ax=ax, fraction=0.035, pad=0.02, label=label)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def error_map_figure(path: Path | str, error: np.ndarray, title: str, cap: float = 4.0) -> None:
    """|d - d_gt| capped at `cap` px (hot colours = wrong), holes magenta, unknown ground truth grey."""
    plt = _plt()
    err = np.asarray(error, dtype=float)
    h, w = err.shape
    rgb = plt.get_cmap("inferno")(np.clip(np.nan_to_num(err, nan=0, posinf=cap) / cap, 0, 1))[..., :3]
    rgb[np.isinf(err)] = (1.0, 0.0, 1.0)
    rgb[np.isnan(err)] = (0.5, 0.5, 0.5)
    fig, ax = plt.subplots(figsize=(8, 8 * h / w + 0.5))
    ax.imshow(rgb)
    ax.set_axis_off()
    ax.set_title(title)
    sm = plt.cm.ScalarMappable(cmap="inferno", norm=plt.Normalize(0, cap))
    fig.colorbar(sm, ax=ax, fraction=0.035, pad=0.02, label=f"|error| px (capped at {cap:g}); magenta = hole")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
