"""Run the engines under comparison on the same images, each in its own subprocess, into one `report.json` schema.

- `run_mvrecon`: our `mvrecon reconstruct` CLI, exactly as a user runs it.
- `run_colmap`: pycolmap's extract_features + match_exhaustive (or match_sequential, match_spatial) +
  incremental_mapping (or global_mapping), CPU, with the same camera mode and model; engine "colmap" (or
  "colmap-global").
- `run_colmap_on_database`: COLMAP's incremental mapper on mvrecon's own database ("same matches"), which separates
  front-end differences from mapper differences.
- `run_mvrecon_map`: mvrecon's mapper alone (`mvrecon map`) on a database, the other side of that comparison; it can
  run another source tree of mvrecon (an earlier commit's checkout) than the one imported here.

Each run happens in a subprocess so its wall time and peak memory are its own and a crash cannot take the caller
down. Each OUT keeps the record of its run (`io.record.Record`, OUT/.stages/runner.json: the run's identity as
its config, and a report of whether it finished, its wall time, peak memory, error and command; `run_meta`). A
finished OUT is read back instead of rerun, and so is a run that timed out (rerunning would only time out again);
a run that failed otherwise is retried next time. A COLMAP run cut off part way (Ctrl-C, a killed process)
goes on from its database and newest mapping snapshot next time, each stage's time counted once (resumable.py).
OUT with a run made with other options is refused, so numbers from different settings never mix; the options
that count are those the engine's result depends on (`RunOptions.identity`: COLMAP's own runs ignore
`mvrecon_args`). Delete OUT to rerun after changing an engine.
"""

import argparse
import compileall
import hashlib
import json
import logging
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import closing
from dataclasses import asdict, dataclass, field
from pathlib import Path

import pycolmap

from .. import __version__
from ..cameras import CameraConfig, focal_prior, group_cameras, report_entry
from ..config import config_hash, diff
from ..database import (
    COLMAP_FISHEYE_NOTE,
    colmap_blind_cameras,
    colmap_needs_focal,
    database_counts,
    read_correspondences,
)
from ..errors import InputError
from ..executor import describe_death, user_environment
from ..io.files import read_json_object, some_names
from ..io.images import image_metadata, list_images
from ..io.masks import check_masks, find_masks
from ..io.record import Record
from ..memory import INTERVAL_S, PeakSampler, process_tree
from .models import model_stats, poses, sparse_models
from .resumable import SNAPSHOT_FRAMES, StageProgress, counted_before

log = logging.getLogger("mvrecon.eval.runners")

CAMERA_MODES = ("auto", "single", "per-folder", "per-image")
COLMAP_ENGINES = ("colmap", "colmap-global")  # COLMAP end to end: never sees mvrecon's extra flags
RUN = "run"  # the piece of work a run folder's record holds
RECORD = "runner.json"  # the record of a run, in OUT/.stages (an older mvrecon kept it in OUT itself)
# COLMAP's pairs in its own runs: every pair; each image with the next ones in name order (its
# SequentialPairingOptions: 10 and 2, 4, 8... further, no loop detection, which needs a vocabulary tree); or
# each with its nearest images by the GPS positions that its feature extraction reads from EXIF into pose priors
# (SpatialPairingOptions: up to 50 within 100 m, heights ignored)
COLMAP_MATCHING = ("exhaustive", "sequential", "spatial")


@dataclass(frozen=True)
class RunOptions:
    """Settings both engines get, so a comparison differs only in the engine."""

    camera_mode: str = "auto"  # auto: images of one size and EXIF camera share intrinsics (mvrecon's rule, both)
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP's model name; both engines' default
    camera_params: tuple[float, ...] = ()  # known intrinsics in camera_model's layout (trusted); empty: estimate
    seed: int = 0  # random seed of both engines (COLMAP's RANSAC and mapper, mvrecon's --seed)
    mvrecon_args: tuple[str, ...] = ()  # extra flags for `mvrecon reconstruct` only (e.g. matcher settings)
    masks: str = ""  # folder of image masks for both engines (io/masks.py, COLMAP's mask_path); "" = none
    colmap_matching: str = "exhaustive"  # COLMAP's pairs in its own runs (COLMAP_MATCHING); mvrecon's: its flags

    def __post_init__(self):
        if self.camera_mode not in CAMERA_MODES:
            raise InputError(f"camera mode {self.camera_mode!r}: expected one of {', '.join(CAMERA_MODES)}")
        if self.colmap_matching not in COLMAP_MATCHING:
            raise InputError(f"COLMAP matching {self.colmap_matching!r}: expected one of "
                             f"{', '.join(COLMAP_MATCHING)}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["camera_params"], d["mvrecon_args"] = list(self.camera_params), list(self.mvrecon_args)
        if not self.masks:  # runs made before masks existed keep their identity
            del d["masks"]
        if self.colmap_matching == "exhaustive":  # and those made before COLMAP could match otherwise
            del d["colmap_matching"]
        return d

    def identity(self, engine: str) -> dict:
        """The options `engine`'s result depends on, which a finished run must have been made with to be reused.
        COLMAP's own runs never see mvrecon's extra flags, so other flags for mvrecon must not make them stale;
        the same-matches run maps mvrecon's database, which those flags shaped, so it keeps them. COLMAP's
        matching only counts for COLMAP's own runs."""
        d = self.to_dict()
        if engine in COLMAP_ENGINES:
            del d["mvrecon_args"]
        else:
            d.pop("colmap_matching", None)
        return d


@dataclass(kw_only=True)
class RunResult:
    """One engine's run: its folder, its report.json, its models (largest first), and what it cost."""

    engine: str
    out_dir: Path
    report: dict = field(default_factory=dict)
    models: list = field(default_factory=list)  # pycolmap.Reconstruction, largest first
    wall_s: float = float("nan")  # wall time of the whole subprocess, measured the same way for every engine
    peak_mem_mb: float = float("nan")  # the run's peak memory, its process tree's (memory.py)
    error: str | None = None  # why the run produced no report (crash, timeout, bad input), else None

    @property
    def poses(self) -> list[dict]:
        """name -> (R, t) per model, largest first: what `eval.metrics` takes."""
        return [poses(m) for m in self.models]


def check_run_masks(options: RunOptions, image_dir: Path | str, names: list[str]) -> str | None:
    """Refuse, before any run, a mask that does not fit its image (io/masks.py); the line saying which images have
    no mask, or None: pycolmap 4.2 leaves such an image out of its runs, where mvrecon takes its features
    everywhere."""
    if not options.masks:
        return None
    masks, missing = find_masks(options.masks, names)
    check_masks(masks, Path(image_dir), {n: image_metadata(Path(image_dir) / n) for n in masks})
    if not missing:
        return None
    return (f"{options.masks}: no mask for {len(missing)} image(s) ({some_names(missing)}): COLMAP leaves them out "
            "of its runs, mvrecon takes their features everywhere")


def colmap_fisheye_warning(options: RunOptions, image_dir: Path | str, names: list[str]) -> str | None:
    """The line saying that COLMAP's runs will register no image, said before any run: COLMAP marks every pair
    of a fisheye camera without a focal-length prior DEGENERATE, and gets a prior only from --camera-params or an
    image's EXIF focal length; None when it has one for every image, or the model is not one of its fisheyes."""
    if options.camera_params or not colmap_needs_focal(options.camera_model):
        return None
    if all(focal_prior(image_metadata(Path(image_dir) / name))[1] for name in names):
        return None
    return (f"--camera-model {options.camera_model} without --camera-params: {COLMAP_FISHEYE_NOTE}, so COLMAP's "
            "runs will register no image; give --camera-params to compare with it")


def run_mvrecon(image_dir: Path | str, out_dir: Path | str, options: RunOptions = RunOptions(),
                timeout: float | None = None, code: Path | str | None = None,
                global_mapper: bool = False) -> RunResult:
    """`mvrecon reconstruct IMAGE_DIR -o OUT_DIR` with the options' camera settings and seed; engine "mvrecon",
    or "mvrecon-global" with `global_mapper` (`--mapper global`, after the options' extra flags).

    Known intrinsics (`camera_params`) are held fixed, as `run_colmap` holds them in COLMAP's bundle adjustment.
    `code`: the mvrecon source tree to run (`code_environment`), else the one installed."""
    cmd = [sys.executable, "-m", "mvrecon.cli", *reconstruct_args(image_dir, out_dir, options)]
    if global_mapper:
        cmd += ["--mapper", "global"]
    return _run("mvrecon-global" if global_mapper else "mvrecon", cmd, Path(image_dir), Path(out_dir), options,
                timeout, tree=code)


def reconstruct_args(image_dir: Path | str, out_dir: Path | str, options: RunOptions) -> list[str]:
    """The `mvrecon` arguments of `run_mvrecon` (`reconstruct IMAGES -o OUT ...`, the extra flags last): one
    place, so that `--mvrecon-args` can be checked against the very command that will run."""
    args = ["reconstruct", str(image_dir), "-o", str(out_dir), "-q", "--seed", str(options.seed),
            "--camera-mode", options.camera_mode]
    if options.camera_model != RunOptions.camera_model:  # the default stays open, as in a user's run:
        args += ["--camera-model", options.camera_model]  # mvrecon's mapper chooses the lens (sfm/lens.py)
    if options.camera_params:  # known intrinsics stay fixed, in both engines
        args += ["--camera-params", ",".join(f"{p:.17g}" for p in options.camera_params), "--fix-intrinsics"]
    if options.masks:
        args += ["--masks", options.masks]
    return args + list(options.mvrecon_args)


def run_colmap(image_dir: Path | str, out_dir: Path | str, options: RunOptions = RunOptions(),
               global_mapper: bool = False, timeout: float | None = None, code: Path | str | None = None) -> RunResult:
    """pycolmap end to end on the CPU: extract_features, the options' matching (`colmap_matching`), incremental
    (or global) mapping. `code`: the mvrecon source tree whose runner starts it, else the one installed."""
    engine = "colmap-global" if global_mapper else "colmap"
    cmd = [sys.executable, "-m", "mvrecon.eval.runners", "colmap", str(image_dir), str(out_dir),
           "--options", json.dumps(options.identity(engine))] + (["--global-mapper"] if global_mapper else [])
    return _run(engine, cmd, Path(image_dir), Path(out_dir), options, timeout, tree=code)


def run_colmap_on_database(database_path: Path | str, out_dir: Path | str,
                           image_dir: Path | str | None = None,
                           options: RunOptions = RunOptions(), timeout: float | None = None) -> RunResult:
    """COLMAP's incremental mapper on a copy of another engine's database (the original is left untouched).

    `image_dir` only serves to colour the points.
    """
    database_path, out_dir = Path(database_path), Path(out_dir)
    if not database_path.is_file():
        raise InputError(f"{database_path}: no such database")
    content = _drop_if_database_changed(database_path, out_dir, options)
    cmd = [sys.executable, "-m", "mvrecon.eval.runners", "colmap-db", str(database_path), str(out_dir),
           "--options", json.dumps(options.identity("colmap-same-matches"))] \
        + (["--image-dir", str(image_dir)] if image_dir else [])
    return _run("colmap-same-matches", cmd, database_path, out_dir, options, timeout, {"database_sha256": content})


def run_mvrecon_map(workspace: Path | str, options: RunOptions = RunOptions(),
                    image_dir: Path | str | None = None,
                    code: Path | str | None = None, timeout: float | None = None) -> RunResult:
    """`mvrecon map -w WORKSPACE` on the database.db already in it, with the options' seed and extra flags
    (`mvrecon_args`, here `map`'s mapper flags): mvrecon's mapper alone, as `run_colmap_on_database` runs COLMAP's.

    `code`: the mvrecon source tree to run (a folder holding `mvrecon/`), else the one installed; `image_dir`
    only serves to colour the points. A finished run in WORKSPACE is read back, as every runner's is."""
    workspace = Path(workspace).resolve()  # the run's working directory may be `code`
    cmd = [sys.executable, "-m", "mvrecon.cli", "map", "-w", str(workspace), "-q", "--seed", str(options.seed)]
    if image_dir is not None:
        cmd += ["--image-dir", str(Path(image_dir).resolve())]
    cmd += list(options.mvrecon_args)
    return _run("mvrecon-map", cmd, workspace / "database.db", workspace, options, timeout,
                {"code": str(Path(code).resolve()) if code else ""}, tree=code)


def code_environment(code: Path | str | None) -> tuple[dict[str, str], str | None]:
    """(environment, working directory) that make `python -m mvrecon...` import mvrecon from the source tree
    `code`, or the user's environment and the caller's directory when `code` is None: `-m` puts the working
    directory first on the path, before PYTHONPATH, so a run started from another checkout would import that one."""
    env = {**user_environment(), "PYTHONUNBUFFERED": "1"}
    if code is None:
        return env, None
    code = str(Path(code).resolve())
    env["PYTHONPATH"] = os.pathsep.join(p for p in (code, env.get("PYTHONPATH", "")) if p)
    return env, code


def _drop_if_database_changed(database_path: Path, out_dir: Path, options: RunOptions) -> str:
    """The database's sha256, after deleting a finished run of COLMAP on an earlier content of it (mvrecon's run
    redone after its folder was deleted, say): the run's identity holds the database's path, so its record
    keeps the content's hash too (the copy it mapped is no witness: COLMAP writes to it). A run with other options
    is refused first, as always; one from before the hash was kept cannot be judged and is kept."""
    meta = refuse_other_settings("colmap-same-matches", database_path, out_dir, options)
    with open(database_path, "rb") as fh:
        content = hashlib.file_digest(fh, "sha256").hexdigest()
    if meta.get("finished") and meta.get("database_sha256", content) != content:
        log.info("%s: %s changed since this run mapped it; mapping it again", out_dir, database_path)
        shutil.rmtree(out_dir)
    return content


def load_run(out_dir: str | Path, engine: str | None = None) -> RunResult:
    """A finished engine folder (ours or any OUT with report.json and sparse/), without running anything."""
    out_dir = Path(out_dir)
    report_path = out_dir / "report.json"
    if not report_path.is_file():
        raise InputError(f"{out_dir}: no report.json (not a finished mvrecon/colmap run)")
    try:
        report = json.loads(report_path.read_text())
    except ValueError as exc:
        raise InputError(f"{report_path}: not valid JSON ({exc})") from None
    if not isinstance(report, dict):
        raise InputError(f"{report_path}: not a run report (a JSON object)")
    meta = run_meta(out_dir)
    total = report.get("total", {})
    return RunResult(engine=engine or report.get("engine", "unknown"), out_dir=out_dir, report=report,
                     models=sparse_models(out_dir / "sparse"),
                     wall_s=float(meta.get("wall_s", total.get("wall_s", float("nan")))),
                     # sampling the tree can miss a short spike that the main process's own max RSS saw
                     peak_mem_mb=max(float(meta.get("peak_tree_mem_mb") or 0.0),
                                     float(total.get("peak_mem_mb") or 0.0)) or float("nan"))


def forget_if_failed(out_dir: str | Path) -> bool:
    """Delete a run folder whose run failed (a crash, a timeout), so that the next call runs it again; True if
    it did. Failed runs are otherwise results like any other (`--retry-failed` of compare and study)."""
    out_dir = Path(out_dir)
    if not run_meta(out_dir).get("error"):
        return False
    shutil.rmtree(out_dir)
    return True


def _read_json(path) -> dict:
    """The JSON object in `path`, or {} when it is missing, cut off or not an object."""
    return read_json_object(path) or {}


def run_meta(out_dir: str | Path) -> dict:
    """What the record of the run in OUT_DIR says: its identity (engine, source, options) and report (finished,
    wall_s, peak_tree_mem_mb, error, command, attempts, ...); {} when OUT_DIR holds no record of a run."""
    record = Record(out_dir, RECORD)
    identity = record.config(RUN)
    return {} if identity is None else {**identity, **record.report(RUN)}


def refuse_other_settings(engine: str, source: str | Path, out_dir: str | Path, options: RunOptions) -> dict:
    """`run_meta(out_dir)`, after refusing a run in it made with settings other than what `engine` on `source`
    with `options` would run: a caller running several engines checks every folder this way before the first one
    starts. Options an earlier run recorded that no longer count for `engine` are ignored. A run recorded by an
    older mvrecon version (OUT/runner.json) is refused too: what it was made with is not read any more."""
    identity = _identity(engine, Path(source), options)
    meta = run_meta(out_dir)
    if not meta and (Path(out_dir) / RECORD).is_file():
        raise InputError(f"{out_dir}: holds a run recorded by an older mvrecon version ({RECORD}); delete it to "
                         "run it again, or use another folder")
    if meta:
        old = {k: meta.get(k) for k in identity}
        if isinstance(old["options"], dict):
            old["options"] = {k: v for k, v in old["options"].items() if k in identity["options"]}
        differing = diff(old, identity)
        if differing:
            raise InputError(f"{out_dir}: holds a run of {meta.get('engine')} made with other settings "
                             f"({'; '.join(differing)}); use another folder or delete it")
    return meta


def _identity(engine: str, source: Path, options: RunOptions) -> dict:
    return {"engine": engine, "source": str(source.resolve()), "options": options.identity(engine)}


def _run(engine, cmd, source: Path, out_dir: Path, options: RunOptions, timeout, record: dict | None = None,
         tree=None) -> RunResult:
    """Run `cmd` into OUT_DIR unless a finished run is there; `record` is kept in runner.json beside the identity;
    `tree`: the mvrecon source tree the command imports (`code_environment`), else the installed one."""
    if not source.exists():
        raise InputError(f"{source}: not found")
    identity = _identity(engine, source, options)
    meta = refuse_other_settings(engine, source, out_dir, options)
    if meta.get("finished"):
        return _result(engine, out_dir, meta)
    out_dir.mkdir(parents=True, exist_ok=True)
    run_record = Record(out_dir, RECORD)  # started, not finished: a rerun with other settings is refused
    run_record.put(RUN, config_hash(identity), {**(record or {}), "finished": False}, config=identity)
    _cache_bytecode()
    log.debug("running %s on %s -> %s", engine, source, out_dir)
    wall, before_mb = counted_before(out_dir)  # a COLMAP run cut off earlier resumes: its counted part
    peaks = [before_mb] if before_mb else []
    for attempt in (1, 2):
        error = None
        code, peak_mb, wall_s = measured_process(cmd, out_dir / "run.log", timeout, tree)
        if code is None:
            error = f"timed out after {timeout:g} s"
        else:
            peaks.append(peak_mb)
            if code != 0 and not _ran_without_model(out_dir, code):
                error = _failure_line(out_dir / "run.log", code)
        wall += wall_s
        if code is None or code >= 0:
            break
        # killed (the out-of-memory killer, a crash): once more, as the feature pool does with an image; an
        # mvrecon run resumes from what it had written, so the time is that of both attempts
        if attempt == 1:
            log.warning("%s on %s: the process running it died (%s); running it again", engine, source,
                        describe_death(code))
        else:
            error = f"the process running it died twice: {describe_death(code)}"
    timed_out = error is not None and error.startswith("timed out")
    report = {**(record or {}), "finished": error is None or timed_out, "wall_s": wall,
              "peak_tree_mem_mb": max(peaks) if peaks else None, "error": error, "command": cmd,
              "attempts": attempt}
    run_record.put(RUN, config_hash(identity), report, wall, config=identity)
    return _result(engine, out_dir, {**identity, **report})


def measured_process(cmd: list[str], log_path: Path | str, timeout: float | None = None,
                     tree: Path | str | None = None) -> tuple[int | None, float, float]:
    """Run `cmd` in its own session, its output into `log_path`, and return (exit code, or None when it ran
    over `timeout` seconds and was killed; peak memory of its process tree in MB; wall time in s). `tree`: the
    mvrecon source tree it imports (`code_environment`). Ctrl-C kills the whole tree before it propagates."""
    start, end = time.perf_counter(), None
    with open(log_path, "w") as logf:
        env, cwd = code_environment(tree)
        proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True, env=env,
                                cwd=cwd)
        try:
            code, peak_mb, end = _wait_measuring_memory(proc, timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            code, peak_mb = None, float("nan")
        except BaseException:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            raise
    return code, peak_mb, (end if end is not None else time.perf_counter()) - start


def _ran_without_model(out_dir: Path, code: int) -> bool:
    """`mvrecon reconstruct` exits 1 when it ran to the end but made no model (its report.json says so, with
    every image's reason): a result, 0 images registered, as a COLMAP run without a model is, not a failure."""
    return code == 1 and _read_json(out_dir / "report.json").get("models") == []


def _cache_bytecode() -> None:
    """Byte-compile mvrecon's sources (a no-op when they are up to date), so that both engines' processes start
    as an installed application does. Python caches byte code itself on a first run, unless
    PYTHONDONTWRITEBYTECODE is set (as on the machines here): then every run compiled the ~60 modules it imports
    again, 0.1-0.2 s of each timed run of mvrecon and some of each pycolmap run (its runner is mvrecon code)."""
    compileall.compile_dir(Path(__file__).resolve().parents[1], quiet=2)


def _wait_measuring_memory(proc, timeout, interval: float = INTERVAL_S) -> tuple[int, float, float]:
    """Wait for the run; return its exit code, its peak memory (MB) and the `time.perf_counter()` of its end.

    The peak is the largest summed RSS of the run's whole process tree, sampled by the parent (memory.py's
    definition, which report.json's peak_mem_mb follows too): the same way for every engine, so worker
    processes (mvrecon's feature pool) count as much as threads (COLMAP's) do. The end is taken by a thread
    blocked in `waitpid`: `Popen.wait` with a timeout polls with sleeps growing to 50 ms, and noticed the end
    of a run 3-48 ms late (10-29 ms for 2 s runs), adding to both engines' times and to their spread; the
    thread notices it in 2-7 ms, the child's own exit included. Raises subprocess.TimeoutExpired after
    `timeout` seconds.
    """
    ended = []
    waiter = threading.Thread(target=lambda: ended.append((proc.wait(), time.perf_counter())), daemon=True,
                              name="run-waiter")
    sampler = PeakSampler(lambda: process_tree(proc.pid), interval)
    waiter.start()
    sampler.start()
    waiter.join(timeout)
    peak = sampler.stop()
    if not ended:
        raise subprocess.TimeoutExpired(proc.args, timeout)
    return ended[0][0], peak, ended[0][1]


def _failure_line(log_path: Path, code: int) -> str:
    lines = [ln.strip() for ln in log_path.read_text(errors="replace").splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower()]
    return f"exit code {code}: {(errors or lines or ['no output'])[-1][:300]}"


def _result(engine, out_dir: Path, meta: dict) -> RunResult:
    if meta.get("error") or not (out_dir / "report.json").is_file():
        return RunResult(engine=engine, out_dir=out_dir, wall_s=float(meta.get("wall_s", float("nan"))),
                         error=meta.get("error") or "the run wrote no report.json")
    result = load_run(out_dir, engine)
    result.error = None
    return result


# --- the COLMAP side, run inside the subprocess ---------------------------------------------------------------

def _colmap_main(image_dir: Path, out_dir: Path, options: dict, global_mapper: bool) -> None:
    """COLMAP end to end into OUT, resuming an attempt that was cut off (resumable.py)."""
    pycolmap.set_random_seed(int(options["seed"]))
    db = out_dir / "database.db"
    progress = StageProgress(out_dir)
    if not progress.resumed and db.exists():
        db.unlink()  # an attempt of a version that did not resume: start clean
    if not progress.done("features"):
        with progress.stage("features"):
            _extract_features(db, image_dir, options)
    if not progress.done("matching"):
        with progress.stage("matching"):
            _match(db, options)
    models = _mapped(db, image_dir, out_dir, options, global_mapper, progress)
    _write_outputs(out_dir, "colmap-global" if global_mapper else "colmap", options, models, db, progress)


def _extract_features(db: Path, image_dir: Path, options: dict) -> None:
    """pycolmap's SIFT into `db` with the run's camera mode and model; the images already there are skipped, and
    the images of a camera some of whose images are there join that camera."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options["camera_model"]
    if options["camera_params"]:
        reader.camera_params = ",".join(f"{p:.17g}" for p in options["camera_params"])
    if options.get("masks"):
        reader.mask_path = options["masks"]
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    done = _camera_of_images(db)
    auto = _camera_groups(image_dir)
    names = sorted(sum(auto, []))  # mvrecon's listing (no hidden files such as degrade's)
    if options["camera_mode"] == "auto":  # one SINGLE-camera extraction per group of mvrecon's auto rule
        groups = [(pycolmap.CameraMode.SINGLE, group) for group in auto]
    elif options["camera_mode"] == "single":
        groups = [(pycolmap.CameraMode.SINGLE, names)]
    elif options["camera_mode"] == "per-image":
        groups = [(pycolmap.CameraMode.PER_IMAGE, names)]
    else:  # per folder: one camera per subfolder, which a resumed extraction would split; it starts again
        if done:
            db.unlink()
            done = {}
        groups = [(pycolmap.CameraMode.PER_FOLDER, names)]
    for mode, group in groups:
        if all(n in done for n in group):
            continue
        reader.existing_camera_id = next((done[n] for n in group if n in done), -1) \
            if mode == pycolmap.CameraMode.SINGLE else -1
        pycolmap.extract_features(db, image_dir, image_names=group, camera_mode=mode, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)


def _camera_of_images(db: Path) -> dict[str, int]:
    """Image name -> camera id of the images in `db` that have their features, {} without a database."""
    if not db.is_file():
        return {}
    with closing(sqlite3.connect(db)) as con:
        return dict(con.execute("SELECT images.name, images.camera_id FROM images JOIN descriptors "
                                "ON descriptors.image_id = images.image_id WHERE descriptors.rows > 0"))


def _match(db: Path, options: dict) -> None:
    """The run's pairs matched and verified (the pairs already in `db` are skipped)."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = int(options["seed"])
    how = options.get("colmap_matching", "exhaustive")
    if how == "sequential":
        pycolmap.match_sequential(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    elif how == "spatial":  # the pose priors extract_features wrote from the images' EXIF GPS
        pycolmap.match_spatial(db, matching_options=matching, verification_options=verification,
                               device=pycolmap.Device.cpu)
    else:
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)


def _colmap_db_main(database: Path, out_dir: Path, options: dict, image_dir: Path | None) -> None:
    """COLMAP's incremental mapper on a copy of `database`, resuming an attempt that was cut off."""
    pycolmap.set_random_seed(int(options["seed"]))
    db = out_dir / "database.db"
    progress = StageProgress(out_dir)
    if not progress.resumed or not db.exists():
        shutil.copyfile(database, db)
    models = _mapped(db, image_dir, out_dir, options, False, progress)
    _write_outputs(out_dir, "colmap-same-matches", options, models, db, progress)


def _mapped(db: Path, image_dir, out_dir: Path, options: dict, global_mapper: bool,
            progress: StageProgress) -> list:
    """`_map` as the run's mapping stage, its models written to OUT/sparse (read back from there once mapped):
    incremental mapping snapshots its model into OUT/snapshots and resumes from the newest whole one."""
    if progress.done("mapping"):
        return sparse_models(out_dir / "sparse")
    snapshots = out_dir / "snapshots"
    start = None if global_mapper else progress.snapshot("mapping")
    with progress.stage("mapping", snapshots=None if global_mapper else snapshots):
        models = _map(db, image_dir, out_dir, options, global_mapper, snapshots, start)
        _write_models(out_dir / "sparse", models)
    shutil.rmtree(snapshots, ignore_errors=True)
    return models


def _camera_groups(image_dir: Path) -> list[list[str]]:
    """Images that share a camera under mvrecon's `auto` rule (same size and EXIF make/model/focal).

    COLMAP's own CameraMode.AUTO gives every image without EXIF focal length a camera of its own (19 cameras for
    templeRing's 19 PNGs), while mvrecon shares one; grouping the same way keeps "same camera settings" true.
    """
    names, _ = list_images(image_dir)
    metas = {n: image_metadata(image_dir / n) for n in names}
    return [members for _, members in group_cameras(names, metas, CameraConfig(mode="auto"))]


def _map(db: Path, image_dir, out_dir: Path, options: dict, global_mapper: bool, snapshots: Path,
         start: Path | None = None) -> list:
    """COLMAP's models of `db`, largest first; incremental mapping writes a snapshot of its model into
    `snapshots` every SNAPSHOT_FRAMES images, and starts from the model in `start` when given. The scratch
    folders of attempts that were cut off (a killed process leaves its temporary folder) are removed first."""
    for stale in out_dir.glob("mapper-*"):
        shutil.rmtree(stale, ignore_errors=True)
    with tempfile.TemporaryDirectory(dir=out_dir, prefix="mapper-") as tmp:
        if global_mapper:
            opts = pycolmap.GlobalPipelineOptions()
            opts.random_seed = int(options["seed"])
            found = pycolmap.global_mapping(db, image_dir or "", tmp, opts)
        else:
            opts = pycolmap.IncrementalPipelineOptions()
            opts.random_seed = int(options["seed"])
            if options["camera_params"]:
                opts.ba_refine_focal_length = False
                opts.ba_refine_extra_params = False
            snapshots.mkdir(exist_ok=True)
            opts.snapshot_path = str(snapshots)
            opts.snapshot_frames_freq = SNAPSHOT_FRAMES
            if start is not None:
                log.info("mapping resumes from the snapshot %s", start)
            found = pycolmap.incremental_mapping(db, image_dir or "", tmp, opts, input_path=start or "")
        return sorted(found.values(), key=lambda r: r.num_reg_images(), reverse=True)


def _write_models(sparse: Path, models: list) -> None:
    """The models into sparse/0, sparse/1, ..., largest first (an earlier attempt's replaced)."""
    if sparse.exists():
        shutil.rmtree(sparse)
    for k, rec in enumerate(models):
        (sparse / str(k)).mkdir(parents=True)
        rec.write(str(sparse / str(k)))


def _write_outputs(out_dir: Path, engine: str, options: dict, models: list, db: Path,
                   progress: StageProgress) -> None:
    """points.ply of the largest model and report.json (every image's status, the stages' counted times)."""
    if models:
        models[0].export_PLY(str(out_dir / "points.ply"))
    corr = read_correspondences(db, mapped=False)  # COLMAP's own run: any of its camera models
    model_of = {}
    for k, rec in enumerate(models):
        for im in rec.images.values():
            if im.has_pose:
                model_of.setdefault(im.name, k)
    paired = corr.paired_images()
    blind = _fisheye_without_focal(corr.cameras)
    images = {}
    for image_id, info in sorted(corr.images.items(), key=lambda kv: kv[1].name):
        if info.name in model_of:
            images[info.name] = {"status": "registered", "model": model_of[info.name], "reason": None}
            continue
        if len(corr.keypoints.get(image_id, ())) == 0:
            reason = "no keypoints"
        elif info.camera_id in blind:
            reason = blind[info.camera_id]
        elif image_id not in paired:
            reason = "no verified pairs"
        else:
            reason = "COLMAP's mapper did not register it (it gives no reason)"
        images[info.name] = {"status": "unregistered", "model": None, "reason": reason}
    report = {
        "engine": engine, "version": f"pycolmap {_pycolmap_version()} via mvrecon {__version__}",
        "config_hash": "", "seed": int(options["seed"]), "images": images,
        "models": [{"index": k, **model_stats(rec), "cameras": _cameras(rec)} for k, rec in enumerate(models)],
        "stages": progress.stages(), "total": progress.total(), "counts": database_counts(db),
    }
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))


def _fisheye_without_focal(cameras: dict) -> dict[int, str]:
    """camera_id -> the reason none of its images registers, for the cameras COLMAP verifies no pair of."""
    return {cid: f"{COLMAP_FISHEYE_NOTE} (camera {cid} is {cameras[cid].model} without one); give --camera-params "
                 "to compare with it" for cid in colmap_blind_cameras(cameras)}


def _cameras(rec) -> list[dict]:
    """The cameras of a pycolmap model's registered images, as mvrecon's report.json lists them
    (`stages.mapping.camera_entries`)."""
    cams = [(cid, rec.cameras[cid]) for cid in sorted({im.camera_id for im in rec.images.values() if im.has_pose})]
    return [report_entry(cid, cam.model.name, cam.width, cam.height, cam.params) for cid, cam in cams]


def _pycolmap_version() -> str:
    return pycolmap.__version__


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mvrecon.eval.runners",
                                     description="The COLMAP side of a comparison (used by run_colmap*).")
    parser.add_argument("mode", choices=("colmap", "colmap-db"))
    parser.add_argument("source", type=Path, help="image folder (colmap) or database (colmap-db)")
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--options", required=True, help="RunOptions as JSON")
    parser.add_argument("--global-mapper", action="store_true")
    parser.add_argument("--image-dir", type=Path)
    args = parser.parse_args(argv)
    options = json.loads(args.options)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if args.mode == "colmap":
        _colmap_main(args.source, args.out_dir, options, args.global_mapper)
    else:
        _colmap_db_main(args.source, args.out_dir, options, args.image_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
