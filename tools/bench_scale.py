"""Scale benchmark: mvrecon and COLMAP (pycolmap) on 100, 300 and 1,000 images of each scale scene, by stage.

    python tools/bench_scale.py                                     # the scale scenes, 100, 300, 1,000 images
    python tools/bench_scale.py --scenes aerial_survey --sizes 100  # a subset (comma-separated)
    python tools/bench_scale.py --scenes object_orbit --sizes 24,100  # any scene whose views are counted
    python tools/bench_scale.py --mvrecon-args "--pairs retrieval:20"  # flags for `mvrecon reconstruct`
    python tools/bench_scale.py --out docs/scale.md                 # the page (default), the plot beside it

The scenes: aerial_survey (a drone survey, GPS in each image's EXIF), street_long (forward motion round a
block and back to the start) and dense_orbit (two rings of views around objects), rendered with N views
(`mvrecon scene make NAME -o DIR --count N`) into WORK/scenes/NAME-N, cached. Per scene and size, one run
after the other, each in its own subprocess (`eval.runners`: the wall time of the whole process, the peak
memory of its process tree, and per stage the wall time its report.json records):
(a) `mvrecon reconstruct`, default settings (the pairs `--pairs auto` chooses), plus --mvrecon-args;
(b) pycolmap: extract_features, matching, incremental_mapping, on the CPU, the same camera model and seed 0.
COLMAP's matching follows what the scene offers: `match_spatial` when the images carry GPS (pycolmap reads it
from EXIF into pose priors), `match_sequential` for views taken in order (a walk, a video, an orbit:
trajectories loop, forward, handheld, orbit, rings; without loop detection, which needs a vocabulary tree that
pycolmap has no offline copy of), else `match_exhaustive` (1,000 images are 500,000 pairs: days for pycolmap
on a CPU).

Per row (scene, size) it prints, mvrecon / COLMAP: the wall time of features, matching, mapping and the whole
run (start-up included), the peak memory, the images registered (the largest model's, counted as
tools/bench_mapper.py counts them: a model without 3D points, or with most of its pairs 5 deg off, counts 0)
and AUC@1/5 against the ground truth (`eval.metrics`, over all image pairs). Per scene and engine, the growth
exponent of each stage: the least-squares slope of log(wall time) against log(images) over the sizes run (1:
linear, 2: quadratic; "-" with one size).

The targets, stated for 1,000 images and checked on every row: registered >= COLMAP's; AUC@5 >= COLMAP's -
0.02; whole wall time <= 0.5 x COLMAP's; peak memory <= COLMAP's; and per scene
mvrecon's mapping exponent <= 1.3. Each is a pass/FAIL column.

It writes --out (default docs/scale.md, the whole file: what large sets need from the user, the tables and the
command) and beside it the log-log plot of wall time against images (the same name, .svg).

Cache and resume (WORK, default out/bench_scale): the scenes; mvrecon's runs in WORK/NAME-N/VERSION/mvrecon,
VERSION being mvrecon's code version (git HEAD, plus a hash of mvrecon/'s files when they differ from it) and the
hash of --mvrecon-args; COLMAP's in WORK/NAME-N/colmap-PAIRS, one per scene and size whatever mvrecon's version
(its result does not depend on mvrecon's code; at 1,000 images it takes hours). A finished run (or one that timed
out) is read back, so a second call only runs what is missing. An interrupted mvrecon run is started again from
nothing, so that its time is whole; an interrupted COLMAP run goes on from its database and newest mapping
snapshot, each stage's time counted once (mvrecon/eval/resumable.py): at 1,000 images it takes COLMAP longer than
the machine may be left to it. A failed run (a crash, no model, a timeout) is a row saying so. The exit code is 0
whatever the verdicts (a report; 2 on bad arguments, 130 after Ctrl-C, with the rows measured so far written).
Delete WORK/NAME-N to measure a row again.
"""

import argparse
import hashlib
import inspect
import logging
import math
import shlex
import shutil
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pycolmap
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(ROOT / "tools"))

from bench_mapper import (  # noqa: E402
    code_version,
    counted,
    engine_figures,
    failed_figures,
    failure,
    forget_other_run,
    say,
    scene_camera_model,
    wrap,
)

from mvrecon.commands._options import join_option_value  # noqa: E402
from mvrecon.errors import InputError  # noqa: E402
from mvrecon.eval.compare import machine_info  # noqa: E402
from mvrecon.eval.ground_truth import find_ground_truth, load_ground_truth_for  # noqa: E402
from mvrecon.eval.runners import RunOptions, run_colmap, run_meta, run_mvrecon  # noqa: E402
from mvrecon.io.gps import read_gps  # noqa: E402
from mvrecon.io.images import list_images  # noqa: E402
from mvrecon.progress import clear_line, progress  # noqa: E402
from mvrecon.scenes import list_scenes, make_scene  # noqa: E402
from mvrecon.scenes.catalog import load_entry  # noqa: E402

SCALE_SCENES = ("aerial_survey", "street_long", "dense_orbit")
SIZES = (100, 300, 1000)
STAGES = ("features", "matching", "mapping")
SEQUENCES = ("loop", "forward", "handheld", "orbit", "rings")  # views in capture order: COLMAP's sequential
AUC_MARGIN = 0.02  # mvrecon's AUC@5 may trail COLMAP's by this much and pass
TIME_RATIO = 0.5  # mvrecon's whole wall time at most this share of COLMAP's
MAPPING_EXPONENT = 1.3  # mvrecon's mapping time may grow at most as images ** 1.3
ENGINES = {"mvrecon": "mvrecon", "colmap": "COLMAP"}
log = logging.getLogger("mvrecon.bench_scale")


@dataclass(kw_only=True)
class Row:
    scene: str
    images: int
    matching: str  # COLMAP's
    mvrecon: dict
    colmap: dict
    notes: list


# --- the numbers -----------------------------------------------------------------------------------------

def growth_exponent(sizes, seconds) -> float | None:
    """The least-squares slope of log(seconds) against log(sizes): time grows as sizes ** slope. None with
    fewer than two distinct sizes (a time that is missing, zero or not finite is left out)."""
    pts = [(math.log(n), math.log(s)) for n, s in zip(sizes, seconds)
           if n and s is not None and math.isfinite(s) and s > 0]
    if len({x for x, _ in pts}) < 2:
        return None
    x, y = np.array(pts).T
    return float(np.polyfit(x, y, 1)[0])


def exponents(rows: list[Row]) -> dict[tuple[str, str], dict[str, float | None]]:
    """(scene, engine) -> stage (and "total") -> growth exponent over the rows whose run did not fail."""
    out = {}
    for scene in dict.fromkeys(r.scene for r in rows):
        for engine in ENGINES:
            ok = [r for r in rows if r.scene == scene and not getattr(r, engine)["error"]]
            out[scene, engine] = {
                stage: growth_exponent([r.images for r in ok], [getattr(r, engine)["stages_s"].get(stage)
                                                                for r in ok])
                for stage in (*STAGES, "total")}
    return out


def checks(row: Row) -> dict[str, bool | None]:
    """The targets of a row: name -> met (None when it cannot be judged: a figure is missing)."""
    mv, cm = row.mvrecon, row.colmap
    failed = bool(mv["error"])

    def at_most(a, b, factor=1.0):
        if failed:
            return False
        if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
            return None
        return a <= factor * b

    auc = None if mv["auc@5"] is None and cm["auc@5"] is None else \
        (mv["auc@5"] or 0.0) >= (cm["auc@5"] or 0.0) - AUC_MARGIN
    return {"registered": not failed and counted(mv) >= counted(cm),
            "auc@5": False if failed else auc,
            "time": at_most(mv["stages_s"].get("total"), cm["stages_s"].get("total"), TIME_RATIO),
            "memory": at_most(mv["peak_mem_mb"], cm["peak_mem_mb"])}


# --- one row ---------------------------------------------------------------------------------------------

def colmap_matching(name: str, images: Path) -> str:
    """COLMAP's matching for the scene (module doc): spatial with GPS, sequential for views taken in order,
    else exhaustive."""
    names = list_images(images)[0]
    if names and read_gps(images / names[0]) is not None:
        return "spatial"
    trajectory = load_entry(name)[0].get("trajectory", {})
    return "sequential" if trajectory.get("type") in SEQUENCES else "exhaustive"


def render(name: str, count: int, work: Path) -> tuple[Path, Path | None]:
    """The scene with `count` views, rendered (or reused) into WORK/scenes/NAME-COUNT: its images and ground
    truth."""
    entry = load_entry(name)[0]
    own = entry.get("trajectory", {}).get("count")
    folder = work / "scenes" / f"{name}-{count}"
    if count == own:
        make_scene(name, folder)
    elif "count" in inspect.signature(make_scene).parameters:
        make_scene(name, folder, count=count)
    else:
        raise InputError(f"{name}: this mvrecon renders the scene's own {own} views only (no --count)")
    return folder / "images", find_ground_truth(folder)


def start_over_if_interrupted(out: Path) -> None:
    """Delete a run that started and never ended: run again, it would resume and time only its second part."""
    meta = run_meta(out)
    if meta and not meta.get("finished"):
        log.info("%s: an interrupted run; starting it again", out)
        shutil.rmtree(out)


def figures(result, gt: dict | None) -> dict:
    """What a row shows of one engine's run (engine_figures, plus stage times, memory and verified pairs)."""
    out = engine_figures(result, gt)
    stages = result.report.get("stages", {})
    out["stages_s"] = {s: (stages.get(s) or {}).get("wall_s") for s in STAGES}
    out["stages_s"]["total"] = out.pop("process_wall_s", None)
    out["peak_mem_mb"] = result.peak_mem_mb if math.isfinite(result.peak_mem_mb) else None
    out["verified_pairs"] = result.report.get("counts", {}).get("verified_pairs")
    return out


def measure(name: str, count: int, work: Path, mvrecon_args: list[str], version: str, timeout: float,
            bar) -> Row:
    """One row: the scene rendered, mvrecon's run and COLMAP's (each read back when finished), their
    figures."""
    bar.set_postfix_str(f"{name} {count}: rendering")
    images, gt_path = render(name, count, work)
    names = [Path(n).name for n in list_images(images)[0]]
    matching = colmap_matching(name, images)
    options = RunOptions(camera_model=scene_camera_model(gt_path), seed=0, colmap_matching=matching,
                         mvrecon_args=tuple(mvrecon_args))
    args_key = f"-{hashlib.sha256(shlex.join(mvrecon_args).encode()).hexdigest()[:8]}" if mvrecon_args else ""
    scene = work / f"{name}-{count}"
    results = {}
    outs = {"mvrecon": scene / f"{version}{args_key}" / "mvrecon", "colmap": scene / f"colmap-{matching}"}
    for engine, out in outs.items():
        forget_other_run(engine, images, out, options)
        if engine == "mvrecon":
            start_over_if_interrupted(out)
        bar.set_postfix_str(f"{name} {count}: {ENGINES[engine]}")
        run = run_mvrecon if engine == "mvrecon" else run_colmap
        results[engine] = run(images, out, options, timeout=timeout, code=ROOT)
    gt = load_ground_truth_for(gt_path, names) if gt_path else None
    notes = [] if gt is not None else ["no ground truth"]
    notes += [f"{ENGINES[e]}'s run failed: {r.error}" for e, r in results.items() if r.error]
    row = Row(scene=name, images=len(names), matching=matching, notes=notes,
              **{e: figures(r, gt) for e, r in results.items()})
    for engine in ENGINES:
        f = getattr(row, engine)
        if f["largest"] and not counted(f):
            row.notes.append(f"{ENGINES[engine]}'s largest model counts as none (no 3D point, or most of its "
                             "pairs off by more than 5 deg)")
    return row


def failed_row(name: str, count: int, why: str) -> Row:
    empty = {**failed_figures(why), "stages_s": {}, "peak_mem_mb": None, "verified_pairs": None}
    return Row(scene=name, images=count, matching="-", mvrecon=empty, colmap=dict(empty), notes=[why])


# --- the tables and the plot -----------------------------------------------------------------------------

def _cell(v, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def _verdict(ok: bool | None) -> str:
    return "-" if ok is None else "pass" if ok else "FAIL"


def rows_table(rows: list[Row]) -> str:
    """One line per scene and size: each cell `mvrecon / COLMAP`, then the targets' verdicts."""
    def pair(r, fmt, get):
        return " / ".join(_cell(get(getattr(r, e)), fmt) for e in ENGINES)

    lines = ["| scene | images | COLMAP pairs | verified pairs | features s | matching s | mapping s "
             "| whole s | peak MB "
             "| registered | AUC@1 | AUC@5 | registered >= | AUC@5 >= -0.02 | time <= 0.5x | memory <= "
             "| notes |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = checks(r)
        stages = [pair(r, "{:.1f}", lambda f, s=s: f["stages_s"].get(s)) for s in (*STAGES, "total")]
        lines.append(
            f"| {r.scene} | {r.images} | {r.matching} | {pair(r, '{:d}', lambda f: f['verified_pairs'])} | "
            f"{' | '.join(stages)} | "
            f"{pair(r, '{:.0f}', lambda f: f['peak_mem_mb'])} | {pair(r, '{:d}', counted)} | "
            f"{pair(r, '{:.3f}', lambda f: f['auc@1'])} | {pair(r, '{:.3f}', lambda f: f['auc@5'])} | "
            f"{_verdict(c['registered'])} | {_verdict(c['auc@5'])} | {_verdict(c['time'])} | "
            f"{_verdict(c['memory'])} | {'; '.join(r.notes) or '-'} |")
    return "\n".join(lines)


def exponents_table(rows: list[Row], exps: dict) -> str:
    """Per scene: the sizes measured and each stage's growth exponent, `mvrecon / COLMAP`; the mapping
    target."""
    lines = ["| scene | sizes | features | matching | mapping | whole run | mapping <= 1.3 |",
             "|---|---|---|---|---|---|---|"]
    for scene in dict.fromkeys(r.scene for r in rows):
        sizes = ", ".join(str(r.images) for r in rows if r.scene == scene)
        cells = [" / ".join(_cell(exps[scene, e][s], "{:.2f}") for e in ENGINES) for s in (*STAGES, "total")]
        exponent = exps[scene, "mvrecon"]["mapping"]
        lines.append(f"| {scene} | {sizes} | {' | '.join(cells)} | "
                     f"{_verdict(None if exponent is None else exponent <= MAPPING_EXPONENT)} |")
    return "\n".join(lines)


def plot(rows: list[Row], path: Path) -> None:
    """Wall time against images on log-log axes, a panel per scene: each stage and the whole run, both engines
    (mvrecon solid, COLMAP dashed). Written without a date, so the same figures give the same file."""
    scenes = list(dict.fromkeys(r.scene for r in rows))
    fig = Figure(figsize=(4.2 * len(scenes) + 0.8, 3.8))
    colors = {"features": "tab:blue", "matching": "tab:orange", "mapping": "tab:green", "total": "black"}
    for k, scene in enumerate(scenes):
        ax = fig.add_subplot(1, len(scenes), k + 1)
        for engine, style in (("mvrecon", "-"), ("colmap", "--")):
            ok = [r for r in rows if r.scene == scene and not getattr(r, engine)["error"]]
            for stage, color in colors.items():
                pts = [(r.images, getattr(r, engine)["stages_s"].get(stage)) for r in ok]
                pts = [(n, s) for n, s in pts if s is not None and s > 0]
                if pts:
                    ax.plot(*zip(*pts), style, marker="o", markersize=3, color=color,
                            label=f"{ENGINES[engine]} {'whole run' if stage == 'total' else stage}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        sizes = sorted({r.images for r in rows if r.scene == scene})
        ax.set_xticks(sizes, [str(n) for n in sizes])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(scene, fontsize=10)
        ax.set_xlabel("images")
        ax.grid(True, which="both", alpha=0.3)
        if k == 0:
            ax.set_ylabel("wall time, s")
    if scenes:
        fig.axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.tight_layout()
    fig.savefig(path, format="svg", metadata={"Date": None})


INTRO = """# Scale: 100 to 1,000 images

What a large image set asks of you, and how mvrecon's time and memory grow with the images, measured against
COLMAP (pycolmap) on the same rendered scenes.

- **Pairs.** `--pairs auto` (the default) picks pairs by GPS, capture order or retrieval above 50 images; give
  `sequential:K`, `spatial:K` or `retrieval:K` when you know better ([pairs.md](pairs.md)).
- **Memory.** *peak MB* below includes the worker processes, one per core: `--workers N` runs fewer. An
  interrupted run keeps its features and matches; `--resume` continues its mapping.
- **Time.** Multiply the 1,000-image time by (N / 1,000) ** exponent (table below) for a first guess at N images.
- **Mapping.** Past 100 registered images, a global bundle adjustment during growth moves 100 images (those
  registered since the last one and the images sharing the most points with them) and holds the others;
  `growth_ba_max_images` in the `[mapper]` table of `--config` sets the number (0: every image). The model's
  last refinement moves every image; from 100 registered images (`final_ba_subset_min_images`, 0: never) it
  optimises 300 well-spread points per image, as the BAs during growth, and re-fits the other points to its
  poses one by one. A BA over every point holds the run's peak memory in a smaller model: GTSAM's solver
  keeps, per 3D point, a dense block over the cameras that see it, so that memory grows with points x views
  per point squared (a 150-view orbit, 29,000 points seen 10 times on average: 0.8 GB). On a 300-image survey
  the final refinement now peaks 0.34 GB above the model (0.88 GB before) for the same AUC, in the subset BAs
  (docs/benchmarks.md, "The final refinement of a large model"). GTSAM's other linear solvers hold more or
  stop at a higher cost (`tools/bench_ba.py --final RUN`).
"""

HOW = """
Each cell is `mvrecon / COLMAP`. Both ran in subprocesses on the same images: mvrecon
`reconstruct` with its default settings, COLMAP (pycolmap {pycolmap}, CPU) extract_features, the matching of
the *COLMAP pairs* column (spatial: by the EXIF GPS positions; sequential: each image with the next ones, no
loop detection, which needs a vocabulary tree; exhaustive: every pair) and incremental_mapping; the same
camera model, seed 0. *whole s*: the whole process, start-up included; *peak MB*: the largest summed resident
memory of the run's process tree; *registered*: images in the largest model (a model without 3D points, or
with most of its image pairs more than 5 deg off, counts 0); *verified pairs*: image pairs with a two-view
geometry in the run's database; AUC@t: relative-pose AUC over all image pairs against the ground truth (a pair
with an unregistered image, or split across models, counts 180 deg). COLMAP's run of a scene and size is made
once and read back by later calls; one cut off goes on from where it stopped, each stage's time counted once,
the work repeated after its last snapshot left out. The targets, stated for 1,000 images:
registered >= COLMAP's, AUC@5 >= COLMAP's - {margin}, whole wall time <= {ratio} x COLMAP's, peak memory <=
COLMAP's, and mapping time growing at most as images ** {exponent}. On a machine shared with other work, wall
times drift by a third between calls, so a ratio between the engines holds to about that.
"""


def write_page(path: Path, rows: list[Row], skipped: list[str], command: str, version: str,
               seconds: float) -> None:
    """The whole page: the intro, the run's description, both tables, the plot and what was not run."""
    exps = exponents(rows)
    machine = machine_info()
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    run = (f"Measured with `{command}`, finished {when} (this call {seconds / 60:.0f} min; finished runs are "
           f"read back). mvrecon at {version}; {machine['cpu']}, {machine['cores']} cores, "
           f"{machine['memory_gb']} GB RAM, {machine['system']}, Python {machine['python']}.")
    how = HOW.format(pycolmap=pycolmap.__version__, margin=AUC_MARGIN, ratio=TIME_RATIO,
                     exponent=MAPPING_EXPONENT)
    text = (f"{INTRO}\n## Measured\n\n{wrap(run)}\n\n{wrap(how)}\n\n{rows_table(rows)}\n\n"
            f"Growth exponents (slope of log wall time against log images, over the sizes run; `mvrecon / "
            f"COLMAP`):\n\n{exponents_table(rows, exps)}\n\n![wall time against images]({path.stem}.svg)\n")
    if skipped:
        text += f"\n{wrap('Not run: ' + '; '.join(skipped) + '.')}\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    plot(rows, path.with_suffix(".svg"))


# --- main ------------------------------------------------------------------------------------------------

def names_list(text: str) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()]


def sizes_list(text: str) -> list[int]:
    try:
        sizes = sorted({int(v) for v in names_list(text)})
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected image counts such as 100,300,1000") from None
    if not sizes or sizes[0] < 2:
        raise argparse.ArgumentTypeError(f"{text!r}: expected image counts of 2 or more, as 100,300,1000")
    return sizes


def published_command(args: argparse.Namespace) -> str:
    """The call as the page shows it: the flags that decide what ran, not this machine's folders."""
    flags = [f"--scenes {','.join(args.scenes)}", f"--sizes {','.join(map(str, args.sizes))}"]
    if args.mvrecon_args:
        flags.append(f"--mvrecon-args={shlex.quote(args.mvrecon_args)}")
    return "python tools/bench_scale.py " + " ".join(flags)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--scenes", type=names_list, default=list(SCALE_SCENES),
                        help=f"catalog scenes, comma-separated (default {','.join(SCALE_SCENES)})")
    parser.add_argument("--sizes", type=sizes_list, default=list(SIZES),
                        help=f"numbers of images, comma-separated (default {','.join(map(str, SIZES))})")
    parser.add_argument("--mvrecon-args", default="",
                        help="extra flags for `mvrecon reconstruct`, in one string")
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "bench_scale",
                        help="scenes and runs, kept across calls (default out/bench_scale)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "scale.md",
                        help="the page to write, the plot beside it as .svg (default docs/scale.md)")
    parser.add_argument("--timeout", type=float, default=8 * 3600,
                        help="seconds per engine run (default 28800: COLMAP's matching of 1,000 images can "
                             "take hours on 2 cores)")
    raw = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(join_option_value(raw, "--mvrecon-args"))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for handler in logging.getLogger().handlers:
        handler.addFilter(clear_line)
    unknown = [n for n in args.scenes if n not in SCALE_SCENES and n not in list_scenes()]
    if unknown:
        parser.error(f"no such catalog scene: {', '.join(unknown)}")
    try:
        mvrecon_args = shlex.split(args.mvrecon_args)
    except ValueError as exc:
        parser.error(f"--mvrecon-args: {exc}")
    start = time.perf_counter()
    version = code_version(ROOT)
    command = published_command(args)
    say(f"scale benchmark: mvrecon {version}, pycolmap {pycolmap.__version__}, "
        f"scenes {','.join(args.scenes)}, sizes {','.join(map(str, args.sizes))}, work folder {args.work}")
    plan, skipped = [], []
    for name in args.scenes:
        if name not in list_scenes():
            skipped.append(f"{name} (not in this catalog)")
        elif "count" not in load_entry(name)[0].get("trajectory", {}):
            skipped.append(f"{name} (a fixed set of views: its number cannot be chosen)")
        else:
            plan += [(name, n) for n in args.sizes]
    for line in skipped:
        say(f"not run: {line}")
    rows = []
    bar = progress(total=len(plan), desc="scale benchmark", unit="row")
    try:
        for name, count in plan:
            try:
                row = measure(name, count, args.work, mvrecon_args, version, args.timeout, bar)
            except Exception as exc:  # a scene that does not render, unreadable ground truth: a row saying so
                row = failed_row(name, count, failure(exc))
            rows.append(row)
            bar.update(1)
            say(rows_table([row]).splitlines()[-1])
    except KeyboardInterrupt:
        bar.close()
        skipped += [f"{n} at {c} images (interrupted)" for n, c in plan[len(rows):]]
        write_page(args.out, rows, skipped, command, version, time.perf_counter() - start)
        say(f"interrupted; wrote {args.out} with the {len(rows)} row(s) measured")
        return 130
    bar.close()
    exps = exponents(rows)
    say()
    say(rows_table(rows))
    say()
    say(exponents_table(rows, exps))
    write_page(args.out, rows, skipped, command, version, time.perf_counter() - start)
    minutes = (time.perf_counter() - start) / 60
    say(f"\nwrote {args.out} and {args.out.with_suffix('.svg')} ({minutes:.1f} min; work folder {args.work})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
