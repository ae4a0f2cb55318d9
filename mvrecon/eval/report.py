"""The comparison report: `index.html` (one self-contained file that opens offline), `metrics.json`, `metrics.csv`.

The page is built from the same metrics dict that metrics.json holds; `format_value` is the one way a number is
printed, so a test (or a reader) can match any cell of the page to the file.
"""

import base64
import csv
import html
from pathlib import Path

from ..io.files import printable_name, write_json
from . import figures
from .compare import ACCURACY_KEYS, Comparison

INTEGER_METRICS = {"registered", "components", "points", "verified_pairs", "alignment_inliers"}


def format_value(metric: str, value: object) -> str:
    """How a metric's value is printed in the page ("—" when there is none)."""
    if value is None:
        return "—"
    if metric in INTEGER_METRICS:
        return f"{int(round(value)):d}"
    if metric.startswith("auc@"):
        return f"{value:.3f}"
    if metric in ("registered_pct", "keypoints_per_image", "mean_inliers_per_pair", "peak_mem_mb"):
        return f"{value:.1f}"
    if metric == "time_ratio_vs_colmap":
        return f"{value:.2f}"
    if metric.endswith("wall_s"):
        return f"{value:.2f}"
    return f"{value:.4g}"


def other_models_text(summary: dict) -> str:
    """The images of a run's other models, shown after the largest model's count: " + 3" (none: "")."""
    return "".join(f" + {k}" for k in summary.get("registered_other_models") or ())


def write_report(comparison: Comparison, report_dir: Path | str) -> Path:
    """Write index.html, metrics.json and metrics.csv into REPORT_DIR; returns the page's path."""
    report_dir = Path(report_dir)
    report_dir.mkdir(parents=True, exist_ok=True)
    m = comparison.metrics
    write_json(report_dir / "metrics.json", m, indent=1, allow_nan=False)  # strict JSON: no NaN
    write_csv(m, report_dir / "metrics.csv")
    page = report_dir / "index.html"
    page.write_text(printable_name(render_html(comparison)), encoding="utf-8")  # a folder's name may not be UTF-8
    return page


def write_csv(m: dict, path: Path | str) -> None:
    """Long format, one number per line: section (summary, stage, image), engine, item, metric, value; and a
    "skipped" line per image file no engine could read, with the reason as its value."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["section", "engine", "item", "metric", "value"])
        for row in m["rows"]:
            for engine, value in row["values"].items():
                w.writerow(["summary", engine, "", row["metric"], "" if value is None else value])
        for engine, e in m["engines"].items():
            for stage, s in e["stages"].items():
                for key, value in s.items():
                    w.writerow(["stage", engine, stage, key, value])
            for name, v in e["per_image"].items():
                w.writerow(["image", engine, name, "registered", int(v["status"] == "registered")])
                if v.get("model") is not None:
                    w.writerow(["image", engine, name, "model", v["model"]])
                for key in ("rotation_error_deg", "center_error", "center_error_pct"):
                    if v.get(key) is not None:
                        w.writerow(["image", engine, name, key, v[key]])
        for name, reason in m.get("skipped_images", {}).items():
            w.writerow(["skipped", "", name, "reason", reason])


def _img(png: bytes | None, alt: str) -> str:
    if png is None:
        return f"<p class='muted'>{html.escape(alt)}: nothing to plot (no model could be compared).</p>"
    return f"<img alt='{html.escape(alt)}' src='data:image/png;base64,{base64.b64encode(png).decode()}'>"


def _summary_table(m: dict) -> str:
    engines = list(m["engines"])
    head = "".join(f"<th data-engine='{html.escape(n)}'>{html.escape(n)}"
                   f"<div class='role'>{m['engines'][n]['role']}</div></th>" for n in engines)
    body = []
    for row in m["rows"]:
        arrow = {"higher": " ↑", "lower": " ↓"}.get(row["better"], "")
        unit = f" ({html.escape(row['unit'])})" if row["unit"] else ""
        cells = []
        for n in engines:
            value = row["values"].get(n)
            text = format_value(row["metric"], value)
            if value is None and m["engines"][n]["role"] == "reference" and row["metric"] in ACCURACY_KEYS:
                text = "ref"
            win = n in row["winners"]
            others = other_models_text(m["engines"][n]["summary"]) if row["metric"] == "registered" else ""
            if others:
                others = f"<span class='others' title='images in the other models'>{others}</span>"
            cells.append(f"<td class='{'winner' if win else ''}' data-engine='{html.escape(n)}' "
                         f"data-metric='{html.escape(row['metric'])}'><span class='v'>{text}</span>{others}"
                         f"{'<span class=star title=winner> ★</span>' if win else ''}</td>")
        body.append(f"<tr data-metric='{html.escape(row['metric'])}'><th>{html.escape(row['label'])}{unit}"
                    f"<span class='muted'>{arrow}</span></th>{''.join(cells)}</tr>")
    return (f"<table id='summary' class='grid'><thead><tr><th>metric</th>{head}</tr></thead>"
            f"<tbody>{''.join(body)}</tbody></table>")


def _unregistered(m: dict) -> str:
    parts = []
    for n, e in m["engines"].items():
        missing = {img: v for img, v in e["per_image"].items() if v["status"] != "registered"}
        other = {img: v for img, v in e["per_image"].items() if v["status"] == "registered" and v.get("model")}
        head = f"<h3>{html.escape(n)}: {len(missing)} of {len(e['per_image'])} images not registered</h3>"
        if e["error"]:
            head += f"<p class='error'>The run failed: {html.escape(e['error'])}</p>"
        rows = "".join(f"<tr><td>{html.escape(img)}</td><td>{html.escape(v['reason'] or '')}</td></tr>"
                       for img, v in missing.items())
        rows += "".join(f"<tr><td>{html.escape(img)}</td><td>registered, but in model {v['model']} (not the "
                        f"largest): no absolute errors</td></tr>" for img, v in other.items())
        table = (f"<table class='grid unreg' data-engine='{html.escape(n)}'><tr><th>image</th><th>reason</th></tr>"
                 f"{rows}</table>") if rows else "<p class='muted'>every image is in the largest model.</p>"
        parts.append(head + table)
    return "".join(parts)


def _skipped(m: dict) -> str:
    """The image files of the folder that no engine could read, each with its reason (none: nothing)."""
    skipped = m.get("skipped_images") or {}
    if not skipped:
        return ""
    rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{html.escape(r)}</td></tr>" for n, r in skipped.items())
    return (f"<h2>Images skipped</h2><p class='meta'>{len(skipped)} image file(s) of the folder could not be read; "
            "no engine saw them, and they are not counted above.</p>"
            f"<table id='skipped' class='grid unreg'><tr><th>image</th><th>reason</th></tr>{rows}</table>")


def _dense(m: dict) -> str:
    """A section per engine whose run folder holds a dense workspace (`mvrecon dense`): its depth maps as
    thumbnails and its fused cloud seen by one of its cameras; nothing when no run has one."""
    parts = []
    for n, e in m["engines"].items():
        d = e.get("dense")
        if not d:
            continue
        points = "no fused.ply" if d["fused_points"] is None else f"{d['fused_points']:,} fused points"
        head = (f"<h3>{html.escape(n)}</h3><p class='meta'><code>{html.escape(d['folder'])}</code>: "
                f"{d['depth_maps']} depth maps, {points}{', mesh.ply' if d['mesh'] else ''}</p>")
        thumbs = "".join(f"<figure class='thumb'><img alt='depth map {html.escape(name)}' "
                         f"src='data:image/png;base64,{base64.b64encode(png).decode()}'>"
                         f"<figcaption>{html.escape(name)}</figcaption></figure>"
                         for name, png in figures.depth_thumbnails(d["folder"]))
        view = figures.fused_view_png(d["folder"])
        cloud = "" if view is None else (f"<p class='meta'>fused.ply seen by the camera of {html.escape(view[0])}"
                                         f":</p>{_img(view[1], 'fused cloud')}")
        parts.append(f"<div class='dense' data-engine='{html.escape(n)}'>{head}"
                     f"<div class='thumbs'>{thumbs}</div>{cloud}</div>")
    if not parts:
        return ""
    return ("<h2 id='dense'>Dense reconstruction</h2><p class='meta'>Depth maps near (yellow) to far (blue), "
            "white where a view has no depth.</p>" + "".join(parts))


def _per_image_table(m: dict) -> str:
    engines = [n for n, e in m["engines"].items() if e["role"] != "reference"]
    head = "".join(f"<th colspan=2>{html.escape(n)}</th>" for n in engines)
    sub = "".join("<th>rot (deg)</th><th>centre (%)</th>" for _ in engines)
    rows = []
    for img in m["images"]:
        cells = []
        for n in engines:
            v = m["engines"][n]["per_image"].get(img, {})
            if v.get("status") != "registered":
                cells.append("<td colspan=2 class='muted'>not registered</td>")
            else:
                cells.append(f"<td>{format_value('rotation_error_deg', v.get('rotation_error_deg'))}</td>"
                             f"<td>{format_value('center_error_pct', v.get('center_error_pct'))}</td>")
        rows.append(f"<tr><td>{html.escape(img)}</td>{''.join(cells)}</tr>")
    return (f"<table class='grid small'><tr><th rowspan=2>image</th>{head}</tr><tr>{sub}</tr>"
            f"{''.join(rows)}</table>")


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px auto;max-width:1280px;color:#222;
padding:0 16px}
h1{margin-bottom:4px} h2{margin-top:36px;border-bottom:1px solid #ddd;padding-bottom:4px}
.muted{color:#888;font-weight:normal} .error{color:#b00020}
table.grid{border-collapse:collapse;font-size:14px} table.grid td,table.grid th{border:1px solid #ddd;
padding:4px 10px;text-align:right} table.grid th:first-child,table.grid td:first-child{text-align:left}
table.grid thead th{background:#f4f4f4} .role{font-size:11px;color:#888;font-weight:normal}
td.winner{background:#e3f4e1;font-weight:600} .star{color:#2e7d32}
table.small{font-size:12px} table.unreg td{text-align:left}
img{max-width:100%;border:1px solid #eee;margin:8px 0}
.meta{color:#555;font-size:14px;line-height:1.5} #scene3d{border:1px solid #eee}
figure.thumb{display:inline-block;margin:4px;font-size:11px;color:#555;text-align:center} figure.thumb img{margin:0}
"""


def render_html(comparison: Comparison) -> str:
    m = comparison.metrics
    ref = m["reference"]
    machine = m["machine"]
    extent = next((e["alignment"]["scene_extent"] for e in m["engines"].values() if e.get("alignment")), None)
    scene = figures.scene_3d_html(comparison.geometry, extent) if comparison.geometry else \
        "<p class='muted'>no model to draw.</p>"
    reference_line = (f"ground truth ({html.escape(str(ref['source']))}, {ref['images']} images)"
                      if ref["name"] == "ground truth" else
                      "none that can be trusted (no ground truth given): accuracy is not scored"
                      if ref["name"] is None else
                      f"the <b>{html.escape(str(ref['name']))}</b> model ({ref['images']} images; no ground truth "
                      "given): its own accuracy cells read 'ref', and images it did not register cannot be scored")
    note = f"<p class='error' id='reference-note'>{html.escape(ref['note'])}</p>" if ref.get("note") else ""
    folders = ", ".join(html.escape(e["out_dir"]) for e in m["engines"].values())
    n_skipped = len(m.get("skipped_images") or {})
    skipped_note = (f" ({n_skipped} more skipped: <a href='#skipped'>unreadable</a>)" if n_skipped else "")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>mvrecon compare: {html.escape(m['title'])}</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{CSS}</style></head>
<body>
<h1>mvrecon vs COLMAP: {html.escape(m['title'])}</h1>{note}
<div class="meta">{len(m['images'])} images from <code>{html.escape(m['source'])}</code>{skipped_note}<br>
Reference: {reference_line}<br>
Run {html.escape(m['created'])} on {html.escape(str(machine['cpu']))}, {machine['cores']} cores,
{machine['memory_gb']} GB, {html.escape(machine['system'])}, Python {html.escape(machine['python'])}</div>

<h2>Summary</h2>
<p class="meta">★ marks the best value of a row among the end-to-end engines (↑ higher is better, ↓ lower);
ties and rows without a direction have no star. <i>colmap-same-matches</i> is COLMAP's mapper on mvrecon's own
matches: where it beats mvrecon the mapper is to blame, where it matches mvrecon the front end is.
Accuracy: relative-pose AUC over all image pairs (a pair with an unregistered image or split across models counts
180 deg); absolute errors after a robust Sim3 of the largest model's camera centres onto the reference, checked
against pycolmap's own alignment ("our Sim3 vs pycolmap's": largest disagreement of the placed centres).</p>
{_summary_table(m)}

<h2>Cumulative errors</h2>
{_img(figures.cumulative_errors_png(m), "cumulative error curves")}

<h2>Per-image errors</h2>
{_img(figures.per_image_errors_png(m), "per-image errors")}
<details><summary>the numbers</summary>{_per_image_table(m)}</details>

<h2>Time and memory</h2>
{_img(figures.timing_png(m), "per-stage timing")}

<h2>Images not registered</h2>
{_unregistered(m)}
{_skipped(m)}
{_dense(m)}

<h2>3D view (aligned to the reference)</h2>
<p class="meta">Drag to rotate, scroll to zoom; click a legend entry to hide or show a model's cameras or points.</p>
{scene}

<p class="meta">Every number on this page is in <a href="metrics.json">metrics.json</a> and
<a href="metrics.csv">metrics.csv</a>. Engine folders: {folders}.</p>
</body></html>
"""
