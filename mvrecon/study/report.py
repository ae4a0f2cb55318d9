"""`study.html`: one self-contained page (PNGs embedded) with the breaking points, the plots and the table."""

import base64
import html
import math
from datetime import datetime, timezone
from pathlib import Path

from ..io.files import printable_name
from .config import StudyConfig
from .grid import AXES, Grid

TABLE_COLUMNS = (("engine", "engine"), ("degradation", "degradation"), ("level", "level"),
                 ("registered_pct", "registered %"), ("auc@1", "AUC@1"), ("auc@5", "AUC@5"), ("points", "points"),
                 ("mean_track_length", "track length"), ("mean_reprojection_error_px", "reproj. error (px)"),
                 ("keypoints_per_image", "keypoints / image"), ("mean_inliers_per_pair", "inliers / pair"),
                 ("wall_s", "wall (s)"), ("error", "error"))

STYLE = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1400px;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:13px}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f0f0f0}td.t{text-align:left}.broke{color:#b00;font-weight:600}.held{color:#070}
img{max-width:100%;border:1px solid #ddd;margin:0.5em 0}code{background:#f4f4f4;padding:1px 4px}"""


def _png(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


def _fmt(value) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return "-"
        return f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"
    return html.escape(str(value))


def describe_breaking_point(verdict: dict, axis: str) -> tuple[str, str]:
    """(text, css class) for one engine x degradation."""
    if verdict["metric"] == "clean run failed":
        return "clean run failed", "broke"
    if verdict["level"] is None:
        tested = verdict["tested"]
        return (f"held to {AXES[axis].name} {tested[-1]:g}" if tested else "no degraded level"), "held"
    return f"{AXES[axis].name} {verdict['level']:g} ({verdict['metric']})", "broke"


def write_report(path: Path | str, config: StudyConfig, grid: Grid, rows: list[dict], verdicts: dict,
                 plots: list, sheet: Path, command: str | None = None, skipped: dict | None = None) -> Path:
    """`skipped`: the files of IMAGES left out of the study (name -> why), from `io.images.list_images`."""
    engines = list(dict.fromkeys(r["engine"] for r in rows))
    reference = ("ground truth " + html.escape(str(config.gt))) if config.gt else \
        "each engine's own reconstruction of the clean images (no ground truth given)"
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>mvrecon degradation study</title>"
           f"<style>{STYLE}</style></head><body>",
           "<h1>Degradation study</h1>",
           f"<p>Images: <code>{html.escape(str(config.images))}</code> ({rows[0]['images'] if rows else 0} images). "
           f"Accuracy measured against {reference}. Seed {config.seed}. "
           f"Generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC.</p>"]
    if skipped:
        out.append(f"<p>{len(skipped)} file(s) in the image folder left out (not given to any engine, not "
                   "counted in registered %):</p><ul>" + "".join(
                       f"<li><code>{html.escape(name)}</code>: {html.escape(why)}</li>"
                       for name, why in skipped.items()) + "</ul>")
    if command:
        out.append(f"<p>Command: <code>{html.escape(command)}</code></p>")
    out.append("<h2>Breaking points</h2><p>The first level (mild to severe, as listed) where registered % or "
               "relative-pose AUC@5 drops below half of the engine's value on the clean images.</p>")
    out.append("<table><tr><th>degradation</th>" + "".join(f"<th>{html.escape(e)}</th>" for e in engines) + "</tr>")
    clean = {e: next(r for r in rows if r["engine"] == e) for e in engines}
    out.append("<tr><td class='t'>clean images: registered %, AUC@5</td>" + "".join(
        f"<td class='t'>{_fmt(clean[e]['registered_pct'])} %, {_fmt(clean[e]['auc@5'])}</td>" for e in engines)
        + "</tr>")
    for axis in grid.axes():
        cells = []
        for engine in engines:
            text, css = describe_breaking_point(verdicts[(engine, axis)], axis)
            cells.append(f"<td class='t {css}'>{html.escape(text)}</td>")
        out.append(f"<tr><td class='t'>{html.escape(AXES[axis].label)}</td>{''.join(cells)}</tr>")
    out.append("</table>")
    out.append("<h2>Example crops</h2><p>The same region of one image at each level.</p>"
               f"<img src='{_png(sheet)}' alt='contact sheet'>")
    out.append("<h2>Metrics</h2><p>One plot per metric, a panel per degradation, a line per engine; "
               "levels run from clean (left) to most severe (right).</p>")
    for title, png in plots:
        out.append(f"<h3>{html.escape(title)}</h3><img src='{_png(png)}' alt='{html.escape(title)}'>")
    out.append("<h2>All cells (study.csv)</h2><table><tr>" +
               "".join(f"<th>{html.escape(label)}</th>" for _, label in TABLE_COLUMNS) + "</tr>")
    for row in rows:
        shown = {**row, "level": "clean" if row["level"] == AXES[row["degradation"]].identity else f"{row['level']:g}"}
        out.append("<tr>" + "".join(f"<td class='{'t' if isinstance(shown[k], str) else ''}'>{_fmt(shown[k])}</td>"
                                    for k, _ in TABLE_COLUMNS) + "</tr>")
    out.append("</table><p>Degradations are applied in the fixed order downscale, blur, motion blur, brightness, "
               "Poisson noise, Gaussian noise, gamma, sharpen, JPEG (see <code>mvrecon degrade --help</code>).</p>"
               "</body></html>")
    path = Path(path)
    path.write_text(printable_name("\n".join(out)), encoding="utf-8")  # a folder's name may not be UTF-8
    return path
