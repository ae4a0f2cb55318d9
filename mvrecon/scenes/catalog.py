"""The scene catalog: TOML entries in the top-level `scenes/` folder, and `make_scene` that renders one.

A scene folder's record (`io.record.Record`, SCENE/.stages/record.json) keeps two pieces keyed on the hash of the
TOML (plus the generator version) they were made from: "views", recorded before the first view is rendered, and
"scene", once the scene is complete (its report is scene.json's content). Asking again for the same scene into the
same folder then returns at once, or, after an interruption, renders only the views still missing; `scene.json`
describes the scene (name, kind, units, views) and marks the folder as a scene's.
"""

import hashlib
import logging
import shutil
import time
import tomllib
from pathlib import Path

from ..errors import InputError
from ..io.files import made_folder, read_json_object, write_json
from ..io.record import Record


def _catalog_dir() -> Path:
    """The folder of the catalog's TOML files: `mvrecon/catalog/` in an installed package (pyproject.toml maps
    the top-level `scenes/` there), else `scenes/` beside the package in a checkout or an editable install."""
    package = Path(__file__).resolve().parents[1]
    installed = package / "catalog"
    return installed if installed.is_dir() else package.parent / "scenes"


CATALOG_DIR = _catalog_dir()
GENERATOR_VERSION = "4"  # bump when a scene's files change, so cached scenes are rebuilt (4: calib.txt in mm)
UNITS = {
    "perspective": "scene units (metres)",
    "stereo": "scene units (metres)",
    "sem_tilt": "micrometres",
    "colmap_synthetic": "COLMAP synthetic units",
}
_OWNED = ("images", "gt", "disp0GT.pfm", "mask0nocc.png", "calib.txt")

log = logging.getLogger("mvrecon.scenes")


def list_scenes() -> list[str]:
    """Names of the catalog's scenes, sorted."""
    return sorted(p.stem for p in CATALOG_DIR.glob("*.toml"))


def entry_path(name: str) -> Path:
    """The TOML of a catalog name, or a path to a TOML file outside the catalog."""
    if name.endswith(".toml"):
        path = Path(name)
        if not path.is_file():
            raise InputError(f"{name}: no such scene file")
        return path
    path = CATALOG_DIR / f"{name}.toml"
    if not path.is_file():
        raise InputError(f"{name}: no such scene; known scenes: {', '.join(list_scenes())}")
    return path


def load_entry(name: str) -> tuple[dict, str, Path]:
    """(parsed entry, hash of its bytes and the generator version, its path)."""
    path = entry_path(name)
    data = path.read_bytes()
    try:
        entry = tomllib.loads(data.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None
    digest = hashlib.sha256(data + GENERATOR_VERSION.encode()).hexdigest()
    return entry, digest, path


def read_scene_info(out_dir: Path | str) -> dict | None:
    """The scene.json of a folder, or None (none there, or one cut off by an interruption: only make_scene
    writes it, so such a folder is a scene of ours to render again)."""
    return read_json_object(Path(out_dir) / "scene.json")


def with_count(entry: dict, digest: str, count: int) -> tuple[dict, str]:
    """The entry with `count` views instead of its trajectory's own (the trajectory stretches or densifies:
    `cameras.survey`, `loop`, `rings`), its ground-truth points scaled alike so that each view keeps about as
    many, and the hash of both."""
    trajectory = entry.get("trajectory")
    if not isinstance(trajectory, dict) or "count" not in trajectory:
        raise InputError(f"{entry.get('name', 'this scene')}: --count needs a trajectory with a count "
                         "(this one has a fixed set of views)")
    entry = {**entry, "trajectory": {**trajectory, "count": count}}
    if isinstance(trajectory["count"], int) and trajectory["count"] > 0 and "points" in entry:
        entry["points"] = max(int(round(entry["points"] * count / trajectory["count"])), 1)
    return entry, hashlib.sha256(f"{digest} count={count}".encode()).hexdigest()


def make_scene(name: str, out_dir: Path | str, count: int | None = None) -> Path:
    """Render catalog scene `name` (or a .toml path) into out_dir and return out_dir; `count` replaces the
    number of views of its trajectory (`with_count`).

    Deterministic: the same TOML gives the same bytes. Cached: when out_dir already holds the complete scene
    made from the same TOML, nothing is recomputed; when it holds an interrupted one, the views rendered are
    kept and only the others rendered. A folder holding other files than a scene's is refused, and so is an
    entry that lacks a table or key or makes fewer than 2 views (`build.check_entry`), before the folder is
    touched; an error while building removes the folder when this call created it.
    """
    from .build import KINDS, check_entry  # noqa: PLC0415 - pycolmap and OpenCV: not for `scene list`

    entry, digest, path = load_entry(name)
    if count is not None:
        entry, digest = with_count(entry, digest, count)
    out = Path(out_dir)
    record = Record(out)
    if record.get("scene", digest, ["scene.json"]) is not None:
        log.info("%s: scene %s is up to date", out, entry.get("name", path.stem))
        return out
    if not (out / "scene.json").exists() and not record.path.exists() and out.is_dir() and any(out.iterdir()):
        raise InputError(f"{out}: holds files but no scene.json, so it is not a scene folder; refusing to "
                         "overwrite it (choose an empty or new folder)")
    kind = entry.get("kind", "perspective")
    if kind not in KINDS:
        raise InputError(f"{path}: unknown kind {kind!r}; expected one of {', '.join(KINDS)}")
    try:
        check_entry(entry)  # before anything is removed, made or rendered
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None
    # an interrupted run of the same entry: keep its views (each written whole)
    resume = record.key("views") == digest
    record.drop("scene", *(() if resume else ("views",)))
    for item in () if resume else _OWNED:  # remove what an older version of this scene left behind
        target = out / item
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    scene_name = entry.get("name", path.stem)
    meta = {
        "name": scene_name,
        "kind": kind,
        "hash": digest,
        "units": entry.get("units", UNITS[kind]),
        "description": entry.get("description", ""),
        "seed": int(entry.get("seed", 0)),
        "complete": False,
    }
    start = time.perf_counter()
    bad_entry = (ValueError, KeyError, TypeError)
    try:  # a folder this call made holds nothing a rerun of a corrected TOML reuses
        with made_folder(out, removed_on=bad_entry):
            _write_json(out / "scene.json", meta)
            record.put("views", digest)  # the views rendered from now on are of this entry
            details = KINDS[kind](entry, path.parent, out)
    except bad_entry as exc:
        raise InputError(f"{path}: {type(exc).__name__}: {exc}") from None
    meta.update(details)
    meta["complete"] = True
    _write_json(out / "scene.json", meta)
    record.put("scene", digest, meta, time.perf_counter() - start)
    log.info("%s: made scene %s (%s) in %.1f s", out, scene_name, kind, time.perf_counter() - start)
    return out


def _write_json(path: Path, data: dict) -> None:
    write_json(path, data, indent=1, sort_keys=True)
