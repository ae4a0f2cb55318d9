"""The comparison report's figures: matplotlib PNGs (as bytes) drawn from the metrics dict, and the 3D view.

Each figure reads only `Comparison.metrics` (the numbers written to metrics.json), so what a plot shows is what the
files hold. The 3D view is a plotly figure with plotly.js inlined: a real WebGL viewer that works offline.
"""

import io
import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

from ..io.colmap_array import read_colmap_array
from ..io.ply import read_ply_points
from . import dense as D
from . import metrics as M

ENGINE_COLORS = {"mvrecon": "#1f77b4", "colmap": "#ff7f0e", "colmap-global": "#9467bd",
                 "colmap-same-matches": "#2ca02c", "ground truth": "#222222"}
_EXTRA_COLORS = ("#d62728", "#17becf", "#8c564b", "#e377c2", "#bcbd22", "#7f7f7f")


def engine_colors(names: Iterable[str]) -> dict:
    """A stable colour per engine: the usual engines keep theirs, others (e.g. --models labels) take the rest."""
    out, extra = {}, iter(_EXTRA_COLORS * 4)
    for n in names:
        out[n] = ENGINE_COLORS.get(n) or next(extra)
    return out


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - matplotlib: figures only

    plt.close(fig)
    return buf.getvalue()


def _pyplot():
    import matplotlib  # noqa: PLC0415 - matplotlib: figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415 - matplotlib: figures only

    return plt


def cumulative_errors_png(metrics: dict) -> bytes | None:
    """Cumulative curves: relative-pose error over all pairs (its area up to t is AUC@t), and per-image absolute
    rotation and centre errors after alignment. Unregistered images and split pairs never reach the curve's top."""
    engines = {n: e for n, e in metrics["engines"].items() if e["relative_pose_errors_deg"]}
    if not engines:
        return None
    plt = _pyplot()
    colors = engine_colors(metrics["engines"])
    n_images = max(len(metrics["images"]), 1)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for name, e in engines.items():
        err = np.sort(np.asarray(e["relative_pose_errors_deg"], dtype=float))
        recall = np.arange(1, len(err) + 1) / len(err)
        auc5 = e["summary"].get("auc@5")
        axes[0].step(np.r_[0, err], np.r_[0, recall], where="post", color=colors[name],
                     label=f"{name} (AUC@5 {auc5:.3f})" if auc5 is not None else name)
        for ax, key in ((axes[1], "rotation_error_deg"), (axes[2], "center_error_pct")):
            vals = np.sort([v[key] for v in e["per_image"].values() if v.get(key) is not None])
            if len(vals):
                ax.step(np.r_[0, vals], np.arange(len(vals) + 1) / n_images, where="post", color=colors[name],
                        label=name)
    failed = M.FAILED_DEG
    shown = [v for e in engines.values() for v in e["relative_pose_errors_deg"] if v is not None and v < failed]
    # over the pairs' errors (~0.05 deg ones sat on the y axis of a 0-10 range), at most to 10 deg, the last AUC
    # threshold: failed pairs (180 deg) stay off the plot, below the top
    top = min(max(max(shown, default=10.0) * 1.1, 0.01), max(M.AUC_THRESHOLDS))
    for t in M.AUC_THRESHOLDS:
        if t <= top:
            axes[0].axvline(t, color="#bbb", lw=0.8, ls=":")
    axes[0].set(xlim=(0, top), ylim=(0, 1.02), xlabel="relative-pose error (deg; dotted: the AUC thresholds)",
                ylabel="fraction of image pairs", title=f"Relative pose, all pairs (failed = {failed:g} deg)")
    axes[1].set(ylim=(0, 1.02), xlabel="rotation error (deg)", ylabel="fraction of images",
                title="Absolute rotation after Sim3")
    axes[2].set(ylim=(0, 1.02), xlabel="centre error (% of scene extent)",
                ylabel="fraction of images", title="Absolute camera centre after Sim3")
    for ax, key in ((axes[1], "rotation_error_deg"), (axes[2], "center_error_pct")):
        _log_axis(ax, [v[key] for e in engines.values() for v in e["per_image"].values() if v.get(key)])
    for ax in axes:
        ax.grid(alpha=0.3)
        _legend(ax, fontsize=8, loc="lower right")
    return _png(fig)


def _legend(ax, **kwargs) -> None:
    """A legend when the axes have labelled lines: an engine that failed leaves some empty, and matplotlib warns
    on the console ("No artists with labels found") for an empty one."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kwargs)


def _log_axis(ax, values) -> None:
    """A log x axis over the data (errors of 0.01-0.1 deg sit in a tenth of a decade, invisible on a fixed
    range), ticked at 1-2-5 per decade (or per decade, over many) as plain numbers: matplotlib's own minor
    labels ("2x10^-2 3x10^-2 ...") ran into each other."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: PLC0415 - figures only

    ax.set_xscale("log")
    positive = [v for v in values if v is not None and v > 0 and math.isfinite(v)]
    if not positive:
        return
    lo, hi = min(positive) / 1.5, max(positive) * 1.5
    ax.set_xlim(lo, hi)
    decades = math.log10(hi / lo)
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if decades <= 2 else (1.0,)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def per_image_errors_png(metrics: dict) -> bytes | None:
    """Per-image rotation and centre errors, one bar per engine; an x marks an image the engine did not register
    (or registered outside its largest model)."""
    engines = {n: e for n, e in metrics["engines"].items()
               if e["role"] != "reference" and e["relative_pose_errors_deg"]}
    if not engines:
        return None
    plt = _pyplot()
    colors = engine_colors(metrics["engines"])
    names = metrics["images"]
    x = np.arange(len(names))
    width = 0.8 / len(engines)
    fig, axes = plt.subplots(2, 1, figsize=(max(8.0, 0.45 * len(names) + 2), 6.5), sharex=True)
    for ax, key, label in ((axes[0], "rotation_error_deg", "rotation error (deg)"),
                           (axes[1], "center_error_pct", "centre error (% extent)")):
        top = max([v.get(key) or 0 for e in engines.values() for v in e["per_image"].values()] + [1e-9])
        for k, (name, e) in enumerate(engines.items()):
            vals = np.array([e["per_image"][n].get(key) if e["per_image"][n].get(key) is not None else np.nan
                             for n in names], dtype=float)
            pos = x - 0.4 + width * (k + 0.5)
            ax.bar(pos, np.nan_to_num(vals), width, color=colors[name], label=name)
            missing = np.isnan(vals)
            if missing.any():
                ax.plot(pos[missing], np.full(missing.sum(), top * 0.05), "x", color=colors[name], ms=8, mew=2)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    _legend(axes[0], fontsize=8, ncol=len(engines))
    axes[0].set_title("Per-image errors after Sim3 alignment (x: not in the largest model)")
    axes[1].set_xticks(x, names, rotation=70, fontsize=7, ha="right")
    return _png(fig)


def timing_png(metrics: dict) -> bytes | None:
    """Per-stage wall time (stacked) and peak memory of each engine."""
    engines = {n: e for n, e in metrics["engines"].items() if e["stages"] or e["summary"].get("wall_s") is not None}
    if not engines:
        return None
    plt = _pyplot()
    stage_names = []
    for e in engines.values():
        stage_names += [s for s in e["stages"] if s not in stage_names]
    stage_colors = dict(zip(stage_names, ("#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860")))
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 0.6 * len(engines) + 1.8),
                                  gridspec_kw={"width_ratios": [2, 1]})
    labels = list(engines)
    y = np.arange(len(labels))
    left = np.zeros(len(labels))
    for stage in stage_names:
        vals = np.array([engines[n]["stages"].get(stage, {}).get("wall_s") or 0.0 for n in labels])
        ax.barh(y, vals, left=left, color=stage_colors[stage], label=stage)
        left += vals
    for k, n in enumerate(labels):
        wall = engines[n]["summary"].get("wall_s")
        if wall is not None:
            ax.plot([wall], [k], "k|", ms=18, mew=2)
            ax.annotate(f" {wall:.1f} s", (max(wall, left[k]), k), va="center", fontsize=8)
    ax.set_yticks(y, labels)
    ax.invert_yaxis()
    ax.set(xlabel="wall time (s); bar = stages, | = whole run incl. start-up", title="Time per stage")
    _legend(ax, fontsize=8, loc="lower right")
    ax.grid(axis="x", alpha=0.3)
    mem = [engines[n]["summary"].get("peak_mem_mb") or 0.0 for n in labels]
    colors = engine_colors(metrics["engines"])
    ax2.barh(y, mem, color=[colors[n] for n in labels])
    for k, m in enumerate(mem):
        ax2.annotate(f" {m:.0f}", (m, k), va="center", fontsize=8)
    ax2.set_yticks(y, [])
    ax2.invert_yaxis()
    ax2.set(xlabel="peak memory (MB, RSS summed over the process tree)", title="Peak memory")
    ax2.grid(axis="x", alpha=0.3)
    return _png(fig)


def _frustum_lines(cameras: dict, size: float):
    """Line segments (with None breaks, plotly's way) of a pyramid per camera: apex at the centre, image plane at
    `size` along the optical axis, and a tick marking the image's top edge."""
    xs, ys, zs, names = [], [], [], []
    for name, (R, C, aspect, fov) in cameras.items():
        half_w = size * math.tan(fov / 2)
        half_h = half_w / aspect
        corners_cam = np.array([[-half_w, -half_h, size], [half_w, -half_h, size], [half_w, half_h, size],
                                [-half_w, half_h, size], [0, -1.4 * half_h, size]])
        R = np.asarray(R)
        corners = corners_cam @ R + np.asarray(C)  # camera to world: R^T x + C
        a, b, c, d, top = corners
        for seg in ((C, a), (C, b), (C, c), (C, d), (a, b), (b, c), (c, d), (d, a), (a, top), (top, b)):
            for p in seg:
                xs.append(p[0]), ys.append(p[1]), zs.append(p[2]), names.append(name)
            xs.append(None), ys.append(None), zs.append(None), names.append(None)
    return xs, ys, zs, names


def _without_far_outliers(points) -> np.ndarray:
    """Points within twice the 95th-percentile distance from their median: a few stray points far away would
    otherwise shrink the whole scene to a corner of the view."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 20:
        return points
    d = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    return points[d <= 2 * np.quantile(d, 0.95)]


def scene_3d_html(geometry: dict, extent: float | None = None) -> str:
    """A plotly 3D view of the aligned models: a frustum per camera and the points, one legend entry per model
    (click to hide or show; ground-truth points start hidden), with plotly.js inlined so the page works offline."""
    import plotly.graph_objects as go  # noqa: PLC0415 - plotly: the 3D view only
    import plotly.io as pio  # noqa: PLC0415 - plotly: the 3D view only

    colors = engine_colors(geometry)
    centres = np.array([c[1] for g in geometry.values() for c in g.cameras.values()]).reshape(-1, 3)
    if extent is None or not extent > 0:
        extent = float(np.max(np.linalg.norm(centres - np.median(centres, axis=0), axis=1))) if len(centres) else 1.0
    size = 0.08 * max(extent, 1e-9)
    fig = go.Figure()
    for name, g in geometry.items():
        color = colors[name]
        points = _without_far_outliers(g.points)
        if len(points):  # engine colours, not image colours: the point is to see where models disagree
            fig.add_trace(go.Scatter3d(x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers",
                                       marker={"size": 1.5, "color": color, "opacity": 0.6},
                                       name=f"{name} points", legendgroup=name, hoverinfo="skip",
                                       visible="legendonly" if name == "ground truth" else True))
        if g.cameras:  # ground truth a little larger, so an estimate drawn exactly on it stays visible inside
            xs, ys, zs, names = _frustum_lines(g.cameras, size * (1.25 if name == "ground truth" else 1.0))
            fig.add_trace(go.Scatter3d(x=xs, y=ys, z=zs, mode="lines", line={"color": color, "width": 3},
                                       name=f"{name} cameras", legendgroup=name, text=names,
                                       hovertemplate="%{text}<extra>" + name + "</extra>"))
    fig.update_layout(height=640, margin={"l": 0, "r": 0, "t": 30, "b": 0},
                      scene={"aspectmode": "data", "xaxis_title": "x", "yaxis_title": "y", "zaxis_title": "z"},
                      legend={"itemsizing": "constant", "title": {"text": "click to show/hide"}},
                      paper_bgcolor="white")
    return pio.to_html(fig, include_plotlyjs=True, full_html=False, div_id="scene3d",
                       config={"displaylogo": False, "responsive": True})


def _png_of(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def depth_thumbnails(dense_dir: Path | str, limit: int = 24, width: int = 160) -> list[tuple[str, bytes]]:
    """(image name, PNG) of a dense workspace's depth maps (the first `limit` by name), `width` pixels wide,
    near yellow to far blue over each map's 2nd-98th percentile, white where there is no depth."""
    from matplotlib import colormaps  # noqa: PLC0415 - matplotlib: figures only

    out = []
    names = sorted({p.name.rsplit(".", 2)[0] for p in (Path(dense_dir) / "stereo" / "depth_maps").glob("*.bin")})
    for name in names[:limit]:
        depth = read_colmap_array(D.depth_map_path(dense_dir, name))
        step = max(1, int(math.ceil(depth.shape[1] / width)))
        small = depth[::step, ::step]
        valid = np.isfinite(small) & (small > 0)
        low, high = np.quantile(small[valid], [0.02, 0.98]) if valid.any() else (0.0, 1.0)
        rgb = colormaps["viridis_r"](np.clip((small - low) / max(high - low, 1e-12), 0, 1))[..., :3]
        rgb[~valid] = 1.0
        out.append((name, _png_of(np.round(rgb * 255).astype(np.uint8))))
    return out


def fused_view_png(dense_dir: Path | str, width: int = 640) -> tuple[str, bytes] | None:
    """(image name, PNG) of the fused cloud in its own colours, seen by the middle camera of the dense
    workspace at about `width` pixels; None without fused.ply or cameras."""
    dense_dir = Path(dense_dir)
    if not (dense_dir / "fused.ply").is_file():
        return None
    views = D.model_views(D.dense_model(dense_dir))
    if not views:
        return None
    name = sorted(views)[len(views) // 2]
    view = views[name]
    scale = min(1.0, width / view.width)
    points, colors = read_ply_points(dense_dir / "fused.ply")
    colors = colors if colors is not None else np.full((len(points), 3), 90, np.uint8)
    shape = (max(1, round(view.height * scale)), max(1, round(view.width * scale)))
    return name, _png_of(D.render_points(view, points, colors, shape))
