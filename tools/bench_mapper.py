"""Mapper generalisation suite: mvrecon's mapper against COLMAP's on the same database, on every set.

    python tools/bench_mapper.py                                    # every set, seed 0, this tree's mvrecon
    python tools/bench_mapper.py --only middlebury_templeRing,room  # names as in the table (--skip too)
    python tools/bench_mapper.py --seeds 0,1,2 --markdown docs/benchmarks.md
    python tools/bench_mapper.py --code ../wt-base                  # another checkout's mvrecon
    python tools/bench_mapper.py --map-args "--optimizer sfm"       # flags for `mvrecon map` only

The sets: every multi-view catalog scene (kinds perspective and colmap_synthetic, read from the catalog at run
time and rendered into WORK/scenes/, cached) and every multi-view set of ../shared/data (tools/scoreboard.py's
rule: an images/ folder of one scene). Left out: superglue_scannet_pairs and superglue_phototourism_pairs,
independent image pairs of many scenes (15 ScanNet rooms, 4 landmarks) with ground truth per pair, so there is
no model of one scene to make; calib_stereo_chessboard_ximea, a chessboard moved in front of a fixed stereo
rig, so no static scene, a repeating pattern and no ground-truth poses. A set the suite expects but cannot
find is named, with the reason.

Per set, mvrecon's front end builds one database (`mvrecon features` + `mvrecon match`, default settings,
camera mode auto; the camera model is the scene's own where mvrecon has it, e.g. OPENCV for wide_orbit,
OPENCV_FISHEYE for fisheye_orbit_small, else the default SIMPLE_RADIAL left open, as the real sets use it, so
that mvrecon's mapper may choose the lens from the data; `--open-model`: the default, left open, for every
set); then on that same
database (a) mvrecon's mapper, `mvrecon map --seed S` in a subprocess, and (b) COLMAP's incremental mapper
(pycolmap, `eval.runners.run_colmap_on_database`) with the same seed. The front end and the mapper run from
the source tree --code (default: this one), so an earlier commit's checkout can be measured with this tool.

Per set and seed it prints, mvrecon / COLMAP: models, images in the largest model, relative-pose AUC@1 and
AUC@5 (over all image pairs; a pair with an unregistered image, or split across models, counts 180 deg:
`eval.metrics`), and the mapping wall time (the "mapping" stage of each run's report.json: reading the
database, mapping, writing the models; not the interpreter's start-up). AUC is against the set's ground truth
where it has one; where not (opensfm_lund, openmvg_sceaux_castle) mvrecon's AUC is measured against COLMAP's
largest model, an agreement figure (COLMAP's cell reads "ref"), and only the images part of the target
applies.

The target of a row: mvrecon's images in the largest model >= COLMAP's, and mvrecon's AUC@5 >= COLMAP's -
0.02. A model without a single 3D point (COLMAP's answer to a camera turning in place), or, against ground
truth, one where most of its own image pairs are more than 5 deg off, counts as no model: images registered at
wrong poses are no gain over images left out. The table has a pass/FAIL column and the count; the failing rows
are listed at the end with mvrecon's reasons for the images it left out. The exit code is 0 whatever the
verdicts (it is a report; 2 on bad arguments).

Cache and resume (WORK, default out/bench_mapper): a set's database is built once and reused by later runs and
by every seed (the front end's own check rebuilds it when its settings or images changed); COLMAP's run is
reused while the database is the same; mvrecon's rows are keyed on the code version (git HEAD of --code, plus
a hash of its sources when they differ from HEAD), the mapper config hash, the database and the seed, so a
rerun skips the rows already measured. A failed run (a crash, no model, a timeout) is a row saying so, not the
end of the suite. Delete WORK/<set> to redo a set. From an empty work folder the whole suite takes about an
hour on 2 cores, a third of it rendering the catalog scenes.
"""

import argparse
import hashlib
import json
import logging
import math
import shlex
import shutil
import subprocess
import sys
import textwrap
import time
from collections import Counter
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(ROOT / "tools"))

from scoreboard import DATA, catalog_scenes, pixels, render_scene, shared_sets  # noqa: E402

from mvrecon.commands._options import join_option_value  # noqa: E402
from mvrecon.commands.reconstruct import _reason_kind  # noqa: E402
from mvrecon.errors import InputError  # noqa: E402
from mvrecon.eval.compare import machine_info  # noqa: E402
from mvrecon.eval.ground_truth import find_ground_truth, load_ground_truth_for  # noqa: E402
from mvrecon.eval.metrics import accuracy_summary, relative_pose_errors  # noqa: E402
from mvrecon.eval.models import load_reconstruction  # noqa: E402
from mvrecon.eval.runners import (  # noqa: E402
    RunOptions,
    code_environment,
    refuse_other_settings,
    run_colmap_on_database,
    run_mvrecon_map,
)
from mvrecon.geometry.camera import MODELS  # noqa: E402
from mvrecon.io.images import list_images  # noqa: E402
from mvrecon.progress import clear_line, progress  # noqa: E402
from mvrecon.workspace import Workspace  # noqa: E402

# the shared sets the suite is meant to cover: one missing on disk is named, not silently absent
EXPECTED_SETS = ("middlebury_templeRing", "middlebury_templeSparseRing", "strecha_fountain_P11",
                 "strecha_herzjesu_P8", "gtsfm_lund_door", "opensfm_lund", "openmvg_sceaux_castle",
                 "imc_reichstag")
DEFAULT_MODEL = "SIMPLE_RADIAL"
AUC_MARGIN = 0.02  # mvrecon's AUC@5 may trail COLMAP's mapper by this much and pass
ROW_FORMAT = 3  # a row kept in WORK with another format is measured again (from the runs kept there)
SECTION = "## Mapper suite"
log = logging.getLogger("mvrecon.bench_mapper")


@dataclass(kw_only=True)
class SuiteSet:
    name: str
    origin: str  # "catalog" or "../shared/data"
    images: Path
    gt: Path | None
    camera_model: str


def failure(exc: Exception) -> str:
    """An error as one line: bad input says what and where itself; anything else is named by its type."""
    return str(exc) if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"


def say(text: str = "") -> None:
    clear_line()  # the progress bar's line first
    print(text, flush=True)


# --- the sets --------------------------------------------------------------------------------------------

def scene_camera_model(gt: Path | None) -> str:
    """The camera model of a rendered scene's ground truth, when it has one model that mvrecon reconstructs
    with; else SIMPLE_RADIAL (the default of both engines)."""
    if gt is None:
        return DEFAULT_MODEL
    models = {cam.model.name for cam in load_reconstruction(gt).cameras.values()}
    return models.pop() if len(models) == 1 and next(iter(models)) in MODELS else DEFAULT_MODEL


def plan_sets(work: Path, wanted, open_model: bool = False) -> tuple[list[SuiteSet], list[str]]:
    """The sets to run (small ones first) and a line for each left out, with the reason; with `open_model`
    every set is mapped from the default camera model left open (no --camera-model)."""
    sets, skipped = [], []
    scenes = [n for n in catalog_scenes() if wanted(n)]
    for name in progress(scenes, desc="rendering scenes", unit="scene"):
        try:  # a scene the renderer fails on is a line of the report, not the end of the suite
            images, gt = render_scene(name, work)
            model = DEFAULT_MODEL if open_model else scene_camera_model(gt)
        except Exception as exc:
            skipped.append(f"{name}: not rendered ({failure(exc)})")
            continue
        sets.append(SuiteSet(name=name, origin="catalog", images=images, gt=gt, camera_model=model))
    found = set(shared_sets())
    on_disk = sorted(p.name for p in DATA.iterdir() if (p / "images").is_dir()) if DATA.is_dir() else []
    for name in sorted(set(EXPECTED_SETS) | set(on_disk)):
        if not wanted(name):
            continue
        if name not in on_disk:
            skipped.append(f"{name}: not in {DATA}" if DATA.is_dir() else f"{name}: {DATA} not found")
        elif name not in found:  # why shared_sets() leaves it out
            skipped.append(f"{name}: independent image pairs of several scenes, not one scene"
                           if any((DATA / name).glob("*pairs*.txt")) else
                           f"{name}: a chessboard moved before a fixed stereo rig, not a static scene")
        else:
            sets.append(SuiteSet(name=name, origin="../shared/data", images=DATA / name / "images",
                                 gt=find_ground_truth(DATA / name), camera_model=DEFAULT_MODEL))
    sets.sort(key=lambda s: math.prod(pixels(s.images)))
    return sets, skipped


# --- the code under test ---------------------------------------------------------------------------------

def code_version(code: Path) -> str:
    """git HEAD of the tree (12 hex digits), plus "+" and a hash of mvrecon/'s files when they differ."""
    def git(*args) -> str:
        return subprocess.run(["git", "-C", str(code), *args], capture_output=True, text=True,
                              check=True).stdout

    try:
        head = git("rev-parse", "--short=12", "HEAD").strip()
        changed = git("status", "--porcelain", "--untracked-files=all", "--", "mvrecon").strip()
        files = git("ls-files", "--cached", "--others", "--exclude-standard", "--", "mvrecon").split("\n")
    except (OSError, subprocess.CalledProcessError):
        head, changed = "no-git", "all"
        files = [str(p.relative_to(code)) for p in (code / "mvrecon").rglob("*")]
    if not changed:
        return head
    digest = hashlib.sha256()
    for name in sorted(f for f in files if f and (code / f).is_file()):
        digest.update(name.encode() + b"\0" + (code / name).read_bytes())
    return f"{head}+{digest.hexdigest()[:8]}"


def mapper_config_hash(code: Path, seed: int, map_args: list[str]) -> str:
    """The hash of the MapperConfig that `mvrecon map --seed SEED MAP_ARGS` of the tree `code` maps with; a
    bad flag in MAP_ARGS fails here, before any run."""
    script = ("import sys; from mvrecon.cli import parse_args; from mvrecon.config import config_hash; "
              "from mvrecon.commands.reconstruct import mapper_config; "
              "print(config_hash(mapper_config(parse_args(sys.argv[1:]))))")
    env, cwd = code_environment(code)
    proc = subprocess.run([sys.executable, "-c", script, "map", "-w", ".", "--seed", str(seed), *map_args],
                          capture_output=True, text=True, env=env, cwd=cwd)
    if proc.returncode != 0:
        last = ((proc.stderr or proc.stdout).strip().splitlines() or ["no output"])[-1]
        raise InputError(f"--map-args {shlex.join(map_args)!r}: `mvrecon map` of {code} refuses it: {last}")
    return proc.stdout.strip().splitlines()[-1]


# --- one set ---------------------------------------------------------------------------------------------

def build_database(s: SuiteSet, folder: Path, code: Path, bar) -> tuple[Path | None, str | None]:
    """(FOLDER/database.db made by mvrecon's front end, None), or (None, why it failed): `features` and
    `match`, no-ops when done. A workspace the front end refuses (other settings, images changed) is made
    again from scratch."""
    env, cwd = code_environment(code)
    where = str(folder.resolve())
    # the default model is left open, as a user's run leaves it (the mapper may choose the lens: sfm/lens.py)
    named = [] if s.camera_model == DEFAULT_MODEL else ["--camera-model", s.camera_model]
    commands = [["features", str(s.images.resolve()), "-w", where, "-q", *named],
                ["match", "-w", where, "-q"]]
    logfile = folder.parent / "frontend.log"
    folder.parent.mkdir(parents=True, exist_ok=True)
    for attempt in (1, 2):
        for command in commands:
            bar.set_postfix_str(f"{s.name}: {command[0]}")
            with open(logfile, "a") as out:
                status = subprocess.run([sys.executable, "-m", "mvrecon.cli", *command], stdout=out,
                                        stderr=subprocess.STDOUT, env=env, cwd=cwd).returncode
            if status == 0:
                continue
            last = (logfile.read_text(errors="replace").strip().splitlines() or ["no output"])[-1]
            if status == 2 and attempt == 1:  # refused: other settings, or changed images
                log.info("%s: %s; building the database again", folder, last)
                shutil.rmtree(folder, ignore_errors=True)
                break
            return None, f"mvrecon {command[0]} failed (exit code {status}): {last}"
        else:
            return folder / "database.db", None
    return None, "the database could not be built"


def forget_other_run(engine: str, source: Path, out: Path, options: RunOptions) -> None:
    """Delete a run in OUT that the runners would refuse as made with other settings: in this tool's own work
    folder that is a run of another place (the folder moved: runs are named by their sources' paths)."""
    try:
        refuse_other_settings(engine, source, out, options)
    except InputError as exc:
        log.info("%s; running it again", exc)
        shutil.rmtree(out)


def sha256(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def failed_figures(error: str) -> dict:
    return {"error": error, "models": 0, "largest": 0, "points": 0, "auc@1": None, "auc@5": None,
            "mapping_s": None, "model_sizes": [], "unregistered_reasons": {}}


def engine_figures(result, reference: dict | None, ground_truth: bool = True) -> dict:
    """What the table shows of one engine's run: models, the largest model's images and points, AUC@1/5
    against `reference` (name -> pose), mapping seconds, and the reasons for the images it left out; when the
    reference is the ground truth, also the share of the largest model's own pairs within 5 deg (`counted`)."""
    stages = result.report.get("stages", {})
    figures = {**failed_figures(result.error), "models": len(result.models),
               "mapping_s": (stages.get("mapping") or {}).get("wall_s"),
               "mapping_cpu_s": (stages.get("mapping") or {}).get("cpu_s"),
               "process_wall_s": result.wall_s if math.isfinite(result.wall_s) else None,
               "model_sizes": [m.num_reg_images() for m in result.models]}
    if result.models:
        figures.update(largest=result.models[0].num_reg_images(), points=result.models[0].num_points3D())
    if reference is not None and len(reference) >= 2:
        poses = [{Path(k).name: v for k, v in p.items()} for p in result.poses]  # references name files
        summary = accuracy_summary(poses, reference)
        figures.update({"auc@1": summary["auc@1"], "auc@5": summary["auc@5"]})
        own = {name: reference[name] for name in poses[0] if name in reference} if poses else {}
        if ground_truth and len(own) >= 2:
            errors = relative_pose_errors(poses[:1], own)
            figures["largest_pairs_within_5deg"] = float(np.mean(np.nan_to_num(errors, nan=180.0) < 5.0))
    reasons = Counter(v.get("reason") or v.get("status") for v in result.report.get("images", {}).values()
                      if v.get("status") != "registered")
    figures["unregistered_reasons"] = dict(reasons.most_common())
    return figures


def published_command(raw: list[str]) -> str:
    """The call as the table shows it: without the folders of this machine (--work, --markdown), and with
    --code's tree as CHECKOUT, a checkout of the commit the section names."""
    shown, skip = [], False
    for arg in raw:
        if skip:
            skip = False
            continue
        name = arg.split("=", 1)[0]
        if name in ("--work", "--markdown"):
            skip = "=" not in arg
            continue
        if name == "--code":
            shown += ["--code", "CHECKOUT"]
            skip = "=" not in arg
            continue
        shown.append(arg)
    return "python tools/bench_mapper.py" + (" " + shlex.join(shown) if shown else "")


def counted(figures: dict) -> int:
    """Images in the largest model; 0 when it holds no 3D point (`compare.summary_rows`' rule too), or when
    against ground truth most of its own image pairs are more than 5 deg off: registering images at wrong poses
    is no gain over leaving them out (COLMAP's model of a camera turning in place)."""
    if not figures.get("points"):
        return 0
    if figures.get("largest_pairs_within_5deg", 1.0) < 0.5:
        return 0
    return figures["largest"]


def verdict(row: dict) -> tuple[bool, list[str]]:
    """Whether the row meets the target, and the parts it misses."""
    mv, cm = row["mvrecon"], row["colmap"]
    misses = []
    if mv["error"]:
        misses.append(f"mvrecon's run failed: {mv['error']}")
    if counted(mv) < counted(cm):
        misses.append(f"largest model {counted(mv)} < COLMAP's {counted(cm)}")
    if row["scored"] == "GT":
        a, b = mv["auc@5"] or 0.0, cm["auc@5"] or 0.0
        if a < b - AUC_MARGIN:
            misses.append(f"AUC@5 {a:.3f} < COLMAP's {b:.3f} - {AUC_MARGIN}")
    return not misses, misses


def measure_set(s: SuiteSet, seed: int, work: Path, code: Path, key: str, map_args: list[str],
                timeout: float, bar) -> dict:
    """One row: the database (built or reused), both mappers on it, their figures and the verdict."""
    folder = work / s.name
    names = [Path(n).name for n in list_images(s.images)[0]]
    row = {"format": ROW_FORMAT, "set": s.name, "origin": s.origin, "images": len(names), "seed": seed,
           "camera_model": s.camera_model, "code": key, "notes": []}
    db, error = build_database(s, folder / "database", code, bar)
    if db is None:
        row.update(scored="-", mvrecon=failed_figures(error), colmap=failed_figures(error), database=None,
                   passed=False, misses=[error])
        return row
    row["database"] = sha256(db)
    run_name = f"{key}-db{row['database'][:12]}-seed{seed}"
    kept = folder / "rows" / f"{run_name}.json"
    if kept.is_file():
        earlier = json.loads(kept.read_text())
        if earlier.get("format") == ROW_FORMAT:
            return {**earlier, "cached": True}

    options = RunOptions(camera_model=s.camera_model, seed=seed)
    ours = replace(options, mvrecon_args=tuple(map_args))
    workspace = folder / "mvrecon" / run_name
    forget_other_run("mvrecon-map", workspace / "database.db", workspace, ours)
    workspace.mkdir(parents=True, exist_ok=True)
    # the map run's own copy of the database and the workspace's record: a workspace holds one database
    shutil.copyfile(db, workspace / "database.db")
    Workspace(workspace).record_path.parent.mkdir(exist_ok=True)
    shutil.copyfile(Workspace(db.parent).record_path, Workspace(workspace).record_path)
    bar.set_postfix_str(f"{s.name} seed {seed}: mvrecon map")
    mv = run_mvrecon_map(workspace, ours, image_dir=s.images, code=code, timeout=timeout)
    (workspace / "database.db").unlink(missing_ok=True)
    bar.set_postfix_str(f"{s.name} seed {seed}: COLMAP mapper")
    theirs = folder / f"colmap-seed{seed}"
    forget_other_run("colmap-same-matches", db, theirs, options)
    cm = run_colmap_on_database(db, theirs, s.images, options, timeout)

    gt = load_ground_truth_for(s.gt, names) if s.gt else None
    if gt is not None:
        row["scored"], reference = "GT", gt
    elif cm.models and cm.models[0].num_reg_images() >= 2:
        row["scored"] = "vs COLMAP"
        reference = {Path(k).name: v for k, v in cm.poses[0].items()}
    else:
        row["scored"], reference = "-", None
        row["notes"].append("no ground truth and no COLMAP model to score against")
    row["mvrecon"], row["colmap"] = engine_figures(mv, reference, gt is not None), engine_figures(cm, gt)
    row["config_hash"] = mv.report.get("config_hash")
    if cm.error:
        row["notes"].append(f"COLMAP's run failed: {cm.error}")
    elif not cm.models and row["colmap"]["unregistered_reasons"]:
        row["notes"].append("COLMAP made no model: " + next(iter(row["colmap"]["unregistered_reasons"])))
    for engine in ("mvrecon", "colmap"):
        figures = row[engine]
        if figures["largest"] and not figures["points"]:
            row["notes"].append(f"{'COLMAP' if engine == 'colmap' else 'mvrecon'}'s largest model has no 3D "
                                "point: it counts as none")
    if row["scored"] == "vs COLMAP" and row["colmap"]["largest"] < 0.5 * len(names):
        row["notes"].append(f"COLMAP's model, the reference, holds {row['colmap']['largest']} of "
                            f"{len(names)} images: the AUC says little")
    row["passed"], row["misses"] = verdict(row)
    if not (mv.error or cm.error) or all(r.error.startswith("timed out") for r in (mv, cm) if r.error):
        kept.parent.mkdir(parents=True, exist_ok=True)  # a crash is tried again by the next call
        kept.write_text(json.dumps(row, indent=1) + "\n")
    return row


# --- the table -------------------------------------------------------------------------------------------

def _cell(v, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def table(rows: list[dict]) -> str:
    def pair(key, fmt, colmap_ref=False):
        theirs = "ref" if colmap_ref else _cell(r["colmap"].get(key), fmt)
        return f"{_cell(r['mvrecon'].get(key), fmt)} / {theirs}"

    lines = ["| set | images | seed | camera | scored | models | largest model | AUC@1 | AUC@5 | mapping s "
             "| target | notes |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ref = r["scored"] == "vs COLMAP"
        lines.append(f"| {r['set']} | {r['images']} | {r['seed']} | {r['camera_model']} | {r['scored']} | "
                     f"{pair('models', '{:d}')} | {pair('largest', '{:d}')} | "
                     f"{pair('auc@1', '{:.3f}', ref)} | {pair('auc@5', '{:.3f}', ref)} | "
                     f"{pair('mapping_s', '{:.1f}')} | {'pass' if r['passed'] else 'FAIL'} | "
                     f"{'; '.join(r['notes']) or '-'} |")
    return "\n".join(lines)


def failing_lines(rows: list[dict]) -> list[str]:
    out = []
    for r in rows:
        if r["passed"]:
            continue
        mv = r["mvrecon"]
        kinds, example = Counter(), {}
        for why, n in mv["unregistered_reasons"].items():  # counted by kind: each names its own images
            kinds[_reason_kind(why)] += n
            example.setdefault(_reason_kind(why), why)
        reasons = "; ".join(f"{n} like '{example[kind]}'" for kind, n in kinds.most_common(3))
        sizes = " + ".join(str(n) for n in mv["model_sizes"]) or "none"
        out.append(f"- {r['set']} (seed {r['seed']}): {'; '.join(r['misses'])}. mvrecon's models: {sizes} "
                   f"of {r['images']} images" + (f"; not registered: {reasons}" if reasons else ""))
    return out


TITLE = """# Benchmarks

Figures measured by the benchmark tools in `tools/`, each with the command that made them, the machine, the
date and the mvrecon commit measured. Wall times on a shared 2-core machine drift by a third between runs:
compare the figures of one run with each other.
"""


def write_markdown(path: Path, heading: str, body: str, replaces: str) -> None:
    """Put the section `heading` into the markdown file: in place of the section whose heading starts with
    `replaces` (the same code measured again), else first after the file's title."""
    text = path.read_text() if path.is_file() else TITLE
    parts = text.split("\n## ")
    head, sections = parts[0], ["## " + p for p in parts[1:]]
    same = [k for k, p in enumerate(sections) if p.splitlines()[0].split(" (")[0].strip() == replaces]
    kept = [p for k, p in enumerate(sections) if k not in same]
    kept.insert(same[0] if same else 0, f"{heading}\n\n{body.strip()}\n")
    path.write_text("\n".join([head.rstrip() + "\n", *(p.rstrip() + "\n" for p in kept)]))


HOW = """Each set's database is made once by mvrecon's front end (`mvrecon features` + `mvrecon match`,
default settings, camera mode auto, the camera model of the column); mvrecon's mapper (`mvrecon map`) and
COLMAP's incremental mapper (pycolmap) then map that same database with the same seed. Each cell is `mvrecon /
COLMAP`. *largest model*: images in the largest model; *scored*: GT = AUC against the set's ground truth; vs
COLMAP = no ground truth, mvrecon's AUC against COLMAP's largest model (COLMAP's reads "ref"). AUC@t:
relative-pose AUC over all image pairs, a pair with an unregistered image or split across models counting 180
deg. *mapping s*: the wall time of the mapping stage (reading the database, mapping, writing the models).
*target*: mvrecon's largest model holds at least as many images as COLMAP's (a model without 3D points, or
with ground truth one where most of its own image pairs are more than 5 deg off, counting as none), and with
ground truth its AUC@5 is at least COLMAP's - {margin}."""


def wrap(text: str) -> str:
    return textwrap.fill(" ".join(text.split()), width=110, break_on_hyphens=False, break_long_words=False)


def markdown_body(rows, skipped, command, version, seconds, machine) -> str:
    import pycolmap

    passed, earlier = sum(r["passed"] for r in rows), sum(bool(r.get("cached")) for r in rows)
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    read_back = f" ({earlier} of the {len(rows)} rows measured earlier, read back)" if earlier else ""
    checkout = " (CHECKOUT: a checkout of that commit)" if "--code CHECKOUT" in command else ""
    run = (f"`{command}`, finished {when}; this call took {seconds / 60:.0f} min{read_back}. mvrecon at "
           f"{version}{checkout}; pycolmap {pycolmap.__version__}; {machine['cpu']}, {machine['cores']} cores, "
           f"{machine['memory_gb']} GB RAM, {machine['system']}, Python {machine['python']}.")
    text = (f"{wrap(run)}\n\n{wrap(HOW.format(margin=AUC_MARGIN))}\n\n{table(rows)}\n\n"
            f"{passed} of {len(rows)} rows pass.\n")
    failing = failing_lines(rows)
    if failing:
        text += "\nFailing rows:\n\n" + "\n".join(failing) + "\n"
    if skipped:
        by_reason = {}
        for line in skipped:
            name, reason = line.split(": ", 1)
            by_reason.setdefault(reason, []).append(name)
        groups = "; ".join(f"{', '.join(names)} ({reason})" for reason, names in by_reason.items())
        text += f"\n{wrap(f'Not run: {groups}.')}\n"
    return text


# --- main ------------------------------------------------------------------------------------------------

def names_list(text: str) -> list[str]:
    return [n.strip() for n in text.split(",") if n.strip()]


def seeds_list(text: str) -> list[int]:
    try:
        seeds = [int(v) for v in names_list(text)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected seeds such as 0 or 0,1,2") from None
    if not seeds or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected non-negative seeds such as 0 or 0,1,2")
    return seeds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--only", type=names_list, default=[], help="only these sets, comma-separated")
    parser.add_argument("--skip", type=names_list, default=[], help="leave these sets out, comma-separated")
    parser.add_argument("--seeds", type=seeds_list, default=[0],
                        help="seeds of both mappers, comma-separated (default 0)")
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "bench_mapper",
                        help="scenes, databases, runs and rows, kept across runs (default out/bench_mapper)")
    parser.add_argument("--markdown", type=Path, default=None,
                        help="also write the table as a section of this markdown file (docs/benchmarks.md)")
    parser.add_argument("--label", default="", help="words added to the markdown section's heading")
    parser.add_argument("--code", type=Path, default=ROOT,
                        help="the mvrecon source tree whose front end and mapper run (default: this one)")
    parser.add_argument("--map-args", default="", help="extra flags for `mvrecon map`, in one string")
    parser.add_argument("--open-model", action="store_true",
                        help="map every set from the default camera model left open, the lens chosen from "
                             "the data (default: a rendered scene's own model where mvrecon has it)")
    parser.add_argument("--timeout", type=float, default=3600, help="seconds per mapper run (default 3600)")
    raw = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(join_option_value(raw, "--map-args"))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for handler in logging.getLogger().handlers:
        handler.addFilter(clear_line)
    start = time.perf_counter()
    code = args.code.resolve()
    if not (code / "mvrecon" / "__init__.py").is_file():
        parser.error(f"--code {args.code}: no mvrecon package there")
    try:
        map_args = shlex.split(args.map_args)
        version = code_version(code)
        configs = {seed: mapper_config_hash(code, seed, map_args) for seed in args.seeds}
    except (ValueError, InputError) as exc:
        parser.error(str(exc))
    on_disk = {p.name for p in DATA.iterdir() if (p / "images").is_dir()} if DATA.is_dir() else set()
    known = set(catalog_scenes()) | set(EXPECTED_SETS) | on_disk
    unknown = [n for n in args.only + args.skip if n not in known]
    if unknown:
        parser.error(f"no such set: {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    wanted = lambda n: (not args.only or n in args.only) and n not in args.skip  # noqa: E731

    say(f"mapper suite: mvrecon {version} from {code}, seeds {','.join(map(str, args.seeds))}, "
        f"work folder {args.work}")
    sets, skipped = plan_sets(args.work, wanted, args.open_model)
    for line in skipped:
        say(f"not run: {line}")
    rows = []
    bar = progress(total=len(sets) * len(args.seeds), desc="mapper suite", unit="row")
    for s in sets:
        for seed in args.seeds:
            key = f"{version}-{configs[seed][:12]}"
            try:
                row = measure_set(s, seed, args.work, code, key, map_args, args.timeout, bar)
            except Exception as exc:  # unreadable ground truth, a damaged model: a row saying so
                why = failure(exc)
                row = {"set": s.name, "origin": s.origin, "images": len(list_images(s.images)[0]),
                       "seed": seed, "camera_model": s.camera_model, "scored": "-",
                       "mvrecon": failed_figures(why), "colmap": failed_figures(why), "notes": [why],
                       "passed": False, "misses": [why]}
            rows.append(row)
            bar.update(1)
            say(table([row]).splitlines()[-1] + (" (measured earlier)" if row.get("cached") else ""))
    bar.close()
    seconds = time.perf_counter() - start
    passed = sum(r["passed"] for r in rows)
    say()
    say(table(rows))
    say(f"\n{passed} of {len(rows)} rows pass (mvrecon's largest model >= COLMAP's mapper's, and AUC@5 >= "
        f"COLMAP's - {AUC_MARGIN} where there is ground truth); {seconds / 60:.1f} min; work folder "
        f"{args.work}")
    failing = failing_lines(rows)
    if failing:
        say("failing rows:\n" + "\n".join(failing))
    if args.markdown:
        command = published_command(raw)
        replaces = f"{SECTION}: mvrecon {version}"
        heading = replaces + (f" ({args.label})" if args.label else "")
        body = markdown_body(rows, skipped, command, version, seconds, machine_info())
        write_markdown(args.markdown, heading, body, replaces)
        say(f"wrote the section '{heading}' of {args.markdown}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
