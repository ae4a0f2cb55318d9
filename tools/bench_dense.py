"""Dense benchmark: `mvrecon dense` on rendered scenes scored against their truth, and on real photographs.

    python tools/bench_dense.py                                   # 3 catalog scenes, 2 Strecha sets
    python tools/bench_dense.py --scenes object_orbit_small --real none   # a subset (comma-separated)
    python tools/bench_dense.py --dense-args "--max-image-size 1024"       # flags for `mvrecon dense`
    python tools/bench_dense.py --figures docs                    # pictures: docs/dense_NAME.png
    python tools/bench_dense.py --code ../other-checkout          # the mvrecon source tree to run

Per catalog scene: the scene is rendered (`mvrecon scene make NAME`, cached in WORK/scenes/NAME), then, each
in its own subprocess, `mvrecon reconstruct` (eval.runners.run_mvrecon, cached in WORK/runs/NAME) and `mvrecon
dense OUT -o OUT/dense` (eval.runners.measured_process: the wall time of the whole process, the peak memory of
its process tree). The dense output is scored by eval.dense.score_workspace: the fused cloud, brought into the
truth's frame by the similarity of its cameras onto the true ones, against the surface the views see
(accuracy, completeness and F-score at 0.2%, 0.5% and 1% of the scene extent, ETH3D's definitions), and each
depth map (the share of the view's truth pixels whose depth it gives within 1%). Time per view and per
megapixel divide the dense wall time by the depth maps and by their pixels; CPU s/Mpx is the CPU time of the
dense process and its workers per megapixel, which a shared machine's load changes far less than wall time (on
an idle 2-core machine wall time is about half of it).

Per real set (Strecha fountain_P11 and herzjesu_P8 from --data, when present; else a line says why not):
reconstruct and dense as above, the sparse model's camera centres against the published cameras (median error,
% of their extent: how far the model can be trusted), the depth maps' agreement between views (the share of a
view's depths that another view's map confirms within 1%), and the fused cloud's and the mesh's sizes.

Targets (issue 60), a pass/FAIL column: on the orbit and room scenes F@1% >= 0.9 and F@0.5% >= 0.75; dense
under 10 s per 1-Mpx view. The table is printed (markdown) and, with --json, written with every per-view
number.

Cache (WORK, default out/bench_dense): scenes and sparse runs are reused; a dense run is reused when its
record (OUT/dense_run.json) holds the same command and code version and its fused.ply exists. Delete
WORK/runs/NAME to measure a row again. Exit code 0 whatever the verdicts; 2 on bad arguments.
"""

import argparse
import json
import resource
import shlex
import sys
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(ROOT / "tools"))

from bench_mapper import code_version, failure, say, scene_camera_model  # noqa: E402

from mvrecon.errors import InputError  # noqa: E402
from mvrecon.eval import dense as D  # noqa: E402
from mvrecon.eval import metrics as M  # noqa: E402
from mvrecon.eval.compare import machine_info  # noqa: E402
from mvrecon.eval.ground_truth import load_ground_truth  # noqa: E402
from mvrecon.eval.models import load_reconstruction, poses  # noqa: E402
from mvrecon.eval.runners import RunOptions, measured_process, run_mvrecon  # noqa: E402
from mvrecon.interrupts import import_open3d  # noqa: E402
from mvrecon.io.colmap_array import read_colmap_array  # noqa: E402
from mvrecon.io.images import read_image  # noqa: E402
from mvrecon.io.ply import read_ply_points  # noqa: E402
from mvrecon.io.record import Record  # noqa: E402
from mvrecon.scenes import make_scene  # noqa: E402

SCENES = ("object_orbit_small", "object_orbit", "room")
TARGET_SCENES = ("object_orbit_small", "object_orbit", "room")  # the orbit and room scenes
REAL = {"fountain": "strecha_fountain_P11", "herzjesu": "strecha_herzjesu_P8"}
F1_TARGET, F05_TARGET, S_PER_MPX_TARGET = 0.9, 0.75, 10.0


def run_dense(out: Path, dense_args: list[str], code: Path, version: str, timeout: float | None) -> dict:
    """`mvrecon dense OUT -o OUT/dense DENSE_ARGS` measured, or the record of the same run made before:
    {command, version, exit_code, wall_s, peak_mb, error}."""
    dense_dir = out / "dense"
    cmd = [sys.executable, "-m", "mvrecon.cli", "dense", str(out), "-o", str(dense_dir), *dense_args]
    record_path = out / "dense_run.json"
    if record_path.is_file() and (dense_dir / "fused.ply").is_file():
        record = json.loads(record_path.read_text())
        if record.get("command") == cmd[1:] and record.get("version") == version:
            return record
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    code_, peak, wall = measured_process(cmd, out / "dense.log", timeout, tree=code)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    error = None
    if code_ is None:
        error = f"timed out after {timeout:g} s"
    elif code_ != 0:
        lines = [ln for ln in (out / "dense.log").read_text(errors="replace").splitlines() if ln.strip()]
        error = f"exit code {code_}: {(lines or ['no output'])[-1][:300]}"
    record = {"command": cmd[1:], "version": version, "exit_code": code_, "wall_s": wall, "cpu_s": cpu,
              "peak_mb": peak, "error": error}
    if error is None:
        record_path.write_text(json.dumps(record, indent=1))
    return record


def depth_pixels(dense_dir: Path) -> tuple[int, float]:
    """(depth maps, their megapixels) of a dense workspace."""
    maps = sorted((dense_dir / "stereo" / "depth_maps").glob("*.geometric.bin"))
    return len(maps), sum(read_colmap_array(p).size for p in maps) / 1e6


def reconstruct(images: Path, out: Path, camera_model: str, code: Path, timeout: float | None):
    run = run_mvrecon(images, out, RunOptions(camera_model=camera_model), timeout, code=code)
    if run.error:
        raise RuntimeError(f"reconstruct failed: {run.error}")
    if not run.models:
        raise RuntimeError("reconstruct made no model")
    return run


def stage_cpu(dense_dir: Path) -> dict:
    """CPU seconds of the depth and consistency maps (summed over the views, as recorded by their workers), and
    wall and CPU seconds of fusion and of the mesh, from the dense workspace's record."""
    record = Record(dense_dir, "dense.json")
    depth = sum(record.report(n).get("cpu_seconds", 0.0) for n in record.names()
                if n.startswith(("photometric/", "geometric/")))
    fused = record.report("fused") or {}
    return {"depth_cpu_s": depth, **{k: fused.get(k, float("nan")) for k in
                                      ("fuse_seconds", "fuse_cpu_seconds", "mesh_seconds", "mesh_cpu_seconds")}}


def timing(row: dict, dense_dir: Path, record: dict) -> None:
    views, mpx = depth_pixels(dense_dir)
    row.update(stage_cpu(dense_dir))
    row["depth_cpu_s_per_mpx"] = row["depth_cpu_s"] / max(mpx, 1e-9)
    row.update({"depth_maps": views, "mpx_per_view": mpx / max(views, 1), "dense_wall_s": record["wall_s"],
                "s_per_view": record["wall_s"] / max(views, 1),
                "s_per_mpx": record["wall_s"] / max(mpx, 1e-9),
                "cpu_s_per_mpx": record.get("cpu_s", float("nan")) / max(mpx, 1e-9),
                "peak_mb": record["peak_mb"]})


def cached_truth(scene: Path, path: Path) -> D.DenseTruth:
    """`eval.dense.scene_truth` of the scene, kept in PATH for the scene made from the same TOML."""
    key = json.loads((scene / "scene.json").read_text())["hash"] + f" {D.SPACING_FRACTION}"
    if path.is_file():
        data = np.load(path)
        if str(data["key"]) == key:
            return D.DenseTruth(points=data["points"], views=data["views"], extent=float(data["extent"]),
                                spacing=float(data["spacing"]))
    truth = D.scene_truth(scene)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, key=key, points=truth.points, views=truth.views, extent=truth.extent,
             spacing=truth.spacing)
    return truth


def measure_scene(name: str, work: Path, args, code: Path, version: str, figures: Path | None) -> dict:
    scene = make_scene(name, work / "scenes" / name)
    out = work / "runs" / name
    row = {"scene": name}
    reconstruct(scene / "images", out, scene_camera_model(scene / "gt" / "sparse"), code, args.timeout)
    record = run_dense(out, args.dense_args, code, version, args.timeout)
    if record["error"]:
        return {**row, "error": record["error"]}
    timing(row, out / "dense", record)
    truth = cached_truth(scene, work / "truth" / f"{name}.npz")
    scores = D.score_workspace(out / "dense", scene, truth)
    row.update({"depth_within_1pct": scores["depth_within_1pct"], **scores["fused"],
                "depth_per_view": scores["depth_per_view"]})
    if figures is not None:
        row["figure"] = str(scene_figure(name, scene, out / "dense", truth, figures))
    return row


def measure_real(key: str, data: Path, work: Path, args, code: Path, version: str,
                 figures: Path | None) -> dict:
    folder = data / REAL[key]
    row = {"scene": key}
    if not (folder / "images").is_dir():
        return {**row, "skipped": f"{folder}: not present"}
    out = work / "runs" / key
    run = reconstruct(folder / "images", out, "SIMPLE_RADIAL", code, args.timeout)
    gt = load_ground_truth(folder / "gt_dense_cameras")
    al = M.align_and_compare(run.poses[0], gt)
    if al is not None:
        errors = list(al.center_errors.values())
        row["sparse_centre_error_pct"] = float(100 * np.median(errors) / al.scene_extent)
    row["registered"] = f"{len(run.poses[0])}/{len(gt)}"
    record = run_dense(out, args.dense_args, code, version, args.timeout)
    if record["error"]:
        return {**row, "error": record["error"]}
    timing(row, out / "dense", record)
    agreement = D.depth_agreement(out / "dense")
    row.update({"depth_valid": float(np.mean([a["valid"] for a in agreement.values()])),
                "depth_confirmed": float(np.mean([a["confirmed"] for a in agreement.values()])),
                "agreement_per_view": agreement,
                "points": D.ply_vertex_count(out / "dense" / "fused.ply")})
    mesh = out / "dense" / "mesh.ply"
    if mesh.is_file():
        m = import_open3d().io.read_triangle_mesh(str(mesh))
        row.update({"mesh_vertices": len(m.vertices), "mesh_triangles": len(m.triangles)})
    if figures is not None:
        row["figure"] = str(real_figure(key, out / "dense", figures))
    return row


# --- pictures -----------------------------------------------------------------------------------------------

def _depth_colours(view: D.View, points: np.ndarray, low: float, high: float) -> np.ndarray:
    from matplotlib import colormaps  # noqa: PLC0415 - pictures only

    z = (points - (-view.R.T @ view.t)) @ view.R[2]
    return (colormaps["viridis"](np.clip((z - low) / (high - low), 0, 1))[:, :3] * 255).astype(np.uint8)


def _mesh_arrays(path: Path, transform=None) -> tuple[np.ndarray, np.ndarray] | None:
    if not path.is_file():
        return None
    m = import_open3d().io.read_triangle_mesh(str(path))
    vertices = np.asarray(m.vertices)
    return (transform.apply(vertices) if transform is not None else vertices), np.asarray(m.triangles)


def _save(panels: list[tuple[str, np.ndarray]], path: Path) -> Path:
    import matplotlib  # noqa: PLC0415 - pictures only

    matplotlib.use("Agg")
    from matplotlib.figure import Figure  # noqa: PLC0415 - pictures only

    cols = 2 if len(panels) == 4 else len(panels)
    rows = (len(panels) + cols - 1) // cols
    h, w = panels[0][1].shape[:2]
    fig = Figure(figsize=(cols * 5.0, rows * 5.0 * h / w + 0.3 * rows))
    for k, (title, image) in enumerate(panels):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.imshow(image, cmap="gray", vmin=0, vmax=1) if image.ndim == 2 else ax.imshow(image)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=72)
    Image.open(path).convert("RGB").quantize(256).save(path, optimize=True)  # a third of the bytes
    return path


def scene_figure(name: str, scene: Path, dense_dir: Path, truth: D.DenseTruth, folder: Path) -> Path:
    """Seen by the scene's middle camera: its photo, the truth's samples and the fused cloud (both coloured by
    depth on one scale, white where there is nothing), and the mesh, all in the truth's frame."""
    views = D.model_views(load_reconstruction(scene / "gt" / "sparse"))
    name_view = sorted(views)[len(views) // 2]
    view = views[name_view]
    to_truth = D.frame_alignment(poses(D.dense_model(dense_dir)), {n: (v.R, v.t) for n, v in views.items()})
    shape = (view.height // 3, view.width // 3)
    fused, _ = read_ply_points(dense_dir / "fused.ply")
    fused = to_truth.apply(fused)
    z = (truth.points - (-view.R.T @ view.t)) @ view.R[2]
    low, high = np.quantile(z[z > 0], [0.01, 0.99])
    panels = [(f"{name}: image {name_view}", read_image(scene / "images" / name_view)[::3, ::3]),
              ("ground truth samples (colour: depth)",
               D.render_points(view, truth.points, _depth_colours(view, truth.points, low, high), shape)),
              ("fused.ply (same colours; white: nothing)",
               D.render_points(view, fused, _depth_colours(view, fused, low, high), shape))]
    mesh = _mesh_arrays(dense_dir / "mesh.ply", to_truth)
    if mesh is not None:
        panels.append(("mesh.ply", D.render_mesh(view, *mesh, shape)))
    return _save(panels, folder / f"dense_{name}.png")


def real_figure(key: str, dense_dir: Path, folder: Path) -> Path:
    """Seen by the middle camera of the dense workspace: its undistorted image, the fused cloud in its own
    colours, and the mesh."""
    views = D.model_views(D.dense_model(dense_dir))
    name_view = sorted(views)[len(views) // 2]
    view = views[name_view]
    shape = (view.height // 3, view.width // 3)
    points, colors = read_ply_points(dense_dir / "fused.ply")
    colors = colors if colors is not None else np.full((len(points), 3), 80, np.uint8)
    panels = [(f"{key}: image {name_view}", read_image(dense_dir / "images" / name_view)[::3, ::3]),
              ("fused.ply", D.render_points(view, points, colors, shape))]
    mesh = _mesh_arrays(dense_dir / "mesh.ply")
    if mesh is not None:
        panels.append(("mesh.ply", D.render_mesh(view, *mesh, shape)))
    return _save(panels, folder / f"dense_{key}.png")


# --- the table ----------------------------------------------------------------------------------------------

def _f(v, fmt: str) -> str:
    return "-" if v is None else format(v, fmt)


def verdict(row: dict) -> str:
    if row.get("error") or row.get("skipped"):
        return "-"
    misses = []
    if row["scene"] in TARGET_SCENES:
        if row["fscore@1%"] < F1_TARGET:
            misses.append(f"F@1% < {F1_TARGET}")
        if row["fscore@0.5%"] < F05_TARGET:
            misses.append(f"F@0.5% < {F05_TARGET}")
    if row["s_per_mpx"] >= S_PER_MPX_TARGET:
        misses.append(f"{S_PER_MPX_TARGET:g} s/Mpx or more")
    return "pass" if not misses else "FAIL: " + ", ".join(misses)


def scene_table(rows: list[dict]) -> str:
    head = ("| scene | views | Mpx/view | depth within 1% | acc/comp/F @0.2% | acc/comp/F @0.5% "
            "| acc/comp/F @1% | fused points | dense s | s/view | s/Mpx | CPU s/Mpx | depth CPU s/Mpx "
            "| fuse s (CPU) | mesh s (CPU) | peak MB | targets |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        if r.get("error"):
            lines.append(f"| {r['scene']} | failed: {r['error']} |")
            continue

        def trio(p):
            return "/".join(f"{r[f'{k}@{p}%']:.3f}" for k in ("accuracy", "completeness", "fscore"))

        lines.append(f"| {r['scene']} | {r['depth_maps']} | {r['mpx_per_view']:.2f} "
                     f"| {r['depth_within_1pct']:.3f} | {trio('0.2')} | {trio('0.5')} | {trio('1')} "
                     f"| {r['points']} | {r['dense_wall_s']:.0f} "
                     f"| {r['s_per_view']:.1f} | {r['s_per_mpx']:.1f} | {r['cpu_s_per_mpx']:.1f} "
                     f"| {r['depth_cpu_s_per_mpx']:.1f} | {r['fuse_seconds']:.0f} ({r['fuse_cpu_seconds']:.0f}) "
                     f"| {r['mesh_seconds']:.0f} ({r['mesh_cpu_seconds']:.0f}) | {r['peak_mb']:.0f} | {verdict(r)} |")
    return "\n".join(lines)


def real_table(rows: list[dict]) -> str:
    head = ("| set | registered | sparse centre error (% extent) | views | Mpx/view | depth valid "
            "| depth confirmed | fused points | mesh vertices | dense s | s/Mpx | CPU s/Mpx | peak MB |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        if r.get("skipped") or r.get("error"):
            lines.append(f"| {r['scene']} | {r.get('skipped') or 'failed: ' + r['error']} |")
            continue
        lines.append(f"| {r['scene']} | {r['registered']} | {_f(r.get('sparse_centre_error_pct'), '.3f')} "
                     f"| {r['depth_maps']} | {r['mpx_per_view']:.2f} | {r['depth_valid']:.3f} "
                     f"| {r['depth_confirmed']:.3f} | {r['points']} | {r.get('mesh_vertices', '-')} "
                     f"| {r['dense_wall_s']:.0f} | {r['s_per_mpx']:.1f} | {r['cpu_s_per_mpx']:.1f} "
                     f"| {r['peak_mb']:.0f} |")
    return "\n".join(lines)


def names(text: str, known) -> list[str]:
    out = [] if text.strip() in ("", "none") else [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in out if known is not None and n not in known]
    if unknown:
        raise InputError(f"unknown name(s) {', '.join(unknown)}; known: {', '.join(known)}")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default=",".join(SCENES),
                   help="catalog scenes, comma-separated ('none': none)")
    p.add_argument("--real", default=",".join(REAL), help=f"real sets of {', '.join(REAL)} ('none': none)")
    p.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data",
                   help="folder of the real sets")
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench_dense", help="scenes and runs (cached)")
    p.add_argument("--code", type=Path, default=ROOT, help="the mvrecon source tree to run")
    p.add_argument("--dense-args", default="", help="extra flags for `mvrecon dense` (one string)")
    p.add_argument("--timeout", type=float, default=None, help="seconds per run")
    p.add_argument("--figures", type=Path, default=None, help="folder for the pictures dense_NAME.png")
    p.add_argument("--json", type=Path, default=None, help="write every number here")
    args = p.parse_args(argv)
    try:
        scenes, real = names(args.scenes, None), names(args.real, list(REAL))
    except InputError as exc:
        p.error(str(exc))
    args.dense_args = shlex.split(args.dense_args)
    version = code_version(args.code)
    rows, real_rows = [], []
    for name in scenes:
        say(f"{name} ...")
        try:
            rows.append(measure_scene(name, args.work, args, args.code, version, args.figures))
        except (InputError, RuntimeError, ValueError, OSError) as exc:
            rows.append({"scene": name, "error": failure(exc)})
    for key in real:
        say(f"{key} ...")
        try:
            real_rows.append(measure_real(key, args.data, args.work, args, args.code, version, args.figures))
        except (InputError, RuntimeError, ValueError, OSError) as exc:
            real_rows.append({"scene": key, "error": failure(exc)})
    command = "python tools/bench_dense.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    machine = machine_info()
    say(f"\n{datetime.now(timezone.utc):%Y-%m-%d}, code {version}, {machine['cpu']}, "
        f"{machine['cores']} cores: `{command.strip()}`\n")
    if rows:
        say(scene_table(rows) + "\n")
    if real_rows:
        say(real_table(real_rows))
    if args.json:
        args.json.write_text(json.dumps({"command": command, "version": version, "machine": machine,
                                         "scenes": rows, "real": real_rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
