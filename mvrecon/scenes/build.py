"""Turn a catalog entry (a parsed TOML table) into a scene folder: geometry, cameras, renders, ground truth.

One function per scene kind: `perspective` (images + COLMAP model + depth), `stereo` (adds Middlebury
disparity, occlusion mask and calib.txt), `sem_tilt` (orthographic tilt series + height map) and
`colmap_synthetic` (COLMAP's own synthetic generator). All randomness comes from the entry's seed.
"""

import inspect
import json
import logging
from pathlib import Path

import numpy as np
import pycolmap

from ..geometry.camera import PARAM_NAMES, default_params
from ..io.gps import from_enu, gps_exif
from ..io.images import to_gray
from ..progress import progress
from . import cameras, layouts, meshes
from .cameras import OrthographicCamera, PerspectiveCamera
from .render import Hits, Renderer, RenderSettings
from .textures import TextureSpec
from .writers import write_colmap_model, write_depth, write_disparity, write_image, write_middlebury_calib

log = logging.getLogger("mvrecon.scenes")

TRAJECTORIES = {
    "orbit": cameras.orbit,
    "handheld": cameras.handheld,
    "forward": cameras.forward,
    "hemisphere": cameras.hemisphere,
    "inward": cameras.inward,
    "stereo": cameras.stereo_pair,
    "tilt": cameras.tilt_series,
    "survey": cameras.survey,
    "loop": cameras.loop,
    "rings": cameras.rings,
}


OBJECT_KEYS = {
    "quad": {"origin", "u", "v", "texture", "uv_repeat"},
    "box": {"center", "size", "yaw_deg", "texture", "textures", "tile"},
    "room": {"center", "size", "yaw_deg", "texture", "textures"},
    "sphere": {"center", "radius", "texture", "segments"},
    "cylinder": {"base", "radius", "height", "texture", "segments"},
    "heightfield": {"origin", "u", "v", "resolution", "relief", "amplitude", "features", "texture",
                    "uv_repeat"},
    "mesh": {"path", "texture", "scale", "translate"},
    **{name: set(inspect.signature(site).parameters) - {"centres", "seed"}
       for name, site in layouts.SITES.items()},
}
REPEAT_KEYS = {"repeat", "step"}  # any object: copies in a row or grid (`repeat_offsets`)


# keys an [[objects]] table of each type cannot do without (the others have defaults)
OBJECT_REQUIRED = {
    "quad": ("origin", "u", "v", "texture"),
    "box": ("center", "size"),
    "room": ("center", "size"),
    "sphere": ("center", "radius", "texture"),
    "cylinder": ("base", "radius", "height", "texture"),
    "heightfield": ("origin", "u", "v", "texture"),
    "mesh": ("path",),
    **{name: () for name in layouts.SITES},
}
CAMERA_KEYS = {
    "perspective": {"model", "width", "height", "params", "focal", "distortion", "orthographic", "zoom",
                    "size_step"},
    "orthographic": {"width", "height", "pixel_size", "orthographic"},
}
GPS_KEYS = {"origin", "sigma_horizontal", "sigma_vertical"}
MIN_VIEWS = 2  # fewer views make no scene to reconstruct (two-view geometry, an SEM pair)


def _listing(names) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _table(entry: dict, name: str, kind: str, needs: str) -> dict:
    """entry[name] when it is a table; a ValueError naming the table and what it must hold otherwise."""
    if name not in entry:
        raise ValueError(f"no [{name}] table; a {kind} scene needs one with {needs}")
    if not isinstance(entry[name], dict):
        raise ValueError(f"{name} = {entry[name]!r}: must be a [{name}] table with {needs}")
    return entry[name]


def _check_keys(table: dict, required, accepted, what: str) -> None:
    missing = [k for k in required if k not in table]
    if missing:
        raise ValueError(f"{what} lacks {_listing(missing)}")
    unknown = set(table) - set(accepted)
    if unknown:
        raise ValueError(f"{what}: unknown keys {sorted(unknown)}; accepted: {', '.join(sorted(accepted))}")


def _whole(value, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def check_entry(entry: dict) -> None:
    """Refuse an entry that lacks a table or key its kind needs, has keys nothing reads, or cannot make a usable
    scene (fewer than 2 views), before a folder is made or a view rendered. The ValueError names the table and
    key; `make_scene` puts the file in front."""
    kind = entry.get("kind", "perspective")
    if kind == "colmap_synthetic":
        _check_synthetic(entry)
        return
    ortho = kind == "sem_tilt"
    needs = ("orthographic = true, width, height and pixel_size" if ortho
             else "model, width, height and params (or focal)")
    cam = _table(entry, "camera", kind, needs)
    if bool(cam.get("orthographic", False)) != ortho:
        raise ValueError("an SEM tilt series needs an orthographic camera ([camera] orthographic = true)" if ortho
                         else f"a {kind} scene needs a perspective camera (orthographic ones are for sem_tilt)")
    if ortho:
        _check_keys(cam, ("width", "height", "pixel_size"), CAMERA_KEYS["orthographic"], "[camera]")
    else:
        required = ("model", "width", "height") + (() if "focal" in cam else ("params",))
        _check_keys(cam, required, CAMERA_KEYS["perspective"], "[camera]")
    if kind == "stereo" and cam["model"] not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError(f"[camera] model = {cam['model']!r}: a rectified stereo pair needs PINHOLE or "
                         "SIMPLE_PINHOLE")
    for key in ("width", "height"):
        if not _whole(cam[key], 1):
            raise ValueError(f"[camera] {key} = {cam[key]!r}: must be a whole number of pixels, 1 or more")
    _check_view_cameras(cam, kind)
    traj = _table(entry, "trajectory", kind, {"sem_tilt": 'type = "tilt", angles_deg and distance',
                                              "stereo": 'type = "stereo", center, target and baseline'}
                  .get(kind, f"type ({', '.join(TRAJECTORIES)}) and its keys"))
    ttype = traj.get("type")
    if ttype not in TRAJECTORIES:
        raise ValueError(f"[trajectory] type {ttype!r}: expected one of {', '.join(TRAJECTORIES)}")
    expected = {"sem_tilt": "tilt", "stereo": "stereo"}.get(kind)
    if expected and ttype != expected:
        raise ValueError(f'a {kind} scene needs [trajectory] type = "{expected}", got {ttype!r}')
    params = inspect.signature(TRAJECTORIES[ttype]).parameters
    required = [n for n, p in params.items() if p.default is p.empty]
    _check_keys(traj, required, {"type", *params}, f"[trajectory] ({ttype})")
    if "count" in params and not _whole(traj["count"], MIN_VIEWS):
        raise ValueError(f"[trajectory] count = {traj['count']!r}: a scene needs a whole number of views, "
                         f"{MIN_VIEWS} or more")
    if ttype == "tilt":
        _check_tilt_angles(traj["angles_deg"])
    if isinstance(entry.get("render"), dict) and entry["render"].get("alpha"):
        if ortho:
            raise ValueError("[render] alpha = true: SEM tilt series are grey images without alpha")
        if entry.get("image_format", "png") != "png":
            raise ValueError(f"[render] alpha = true needs image_format = \"png\": "
                             f"{entry['image_format']} has no alpha channel")
    if "gps" in entry:
        if kind != "perspective":
            raise ValueError(f"[gps]: GPS positions are for perspective scenes, not {kind}")
        gps = _table(entry, "gps", kind, "origin = [latitude, longitude, altitude]")
        _check_keys(gps, ("origin",), GPS_KEYS, "[gps]")
        origin = gps["origin"]
        numbers = isinstance(origin, list) and len(origin) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in origin)
        if not (numbers and abs(origin[0]) <= 90 and abs(origin[1]) <= 180):
            raise ValueError(f"[gps] origin = {origin!r}: must be [latitude, longitude, altitude] in "
                             "degrees, degrees and metres")
    objects = entry.get("objects")
    if not objects:
        raise ValueError("no [[objects]] table; a rendered scene needs at least one")
    if not isinstance(objects, list) or not all(isinstance(o, dict) for o in objects):
        raise ValueError("objects: must be [[objects]] tables")
    for k, spec in enumerate(objects, 1):
        otype = spec.get("type")
        if otype not in OBJECT_KEYS:
            raise ValueError(f"[[objects]] #{k}: unknown object type {otype!r}; expected one of "
                             f"{', '.join(OBJECT_KEYS)}")
        _check_keys(spec, OBJECT_REQUIRED[otype], {"type", *OBJECT_KEYS[otype], *REPEAT_KEYS},
                    f"[[objects]] #{k} {otype}")
        if REPEAT_KEYS & set(spec):
            repeat_offsets(spec, f"[[objects]] #{k} {otype}")


def _check_tilt_angles(angles) -> None:
    """At least 2 tilts, numbers, each with its own image name (tilt_<angle to 0.1 deg>.png)."""
    if not isinstance(angles, list) or not all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                               and np.isfinite(a) for a in angles):
        raise ValueError(f"[trajectory] angles_deg = {angles!r}: must be a list of numbers (degrees)")
    if len(angles) < MIN_VIEWS:
        raise ValueError(f"[trajectory] angles_deg = {angles!r}: a tilt series needs {MIN_VIEWS} tilts or more")
    seen = {}
    for a in angles:
        name = f"tilt_{float(a):+.1f}.png"
        if name in seen:
            raise ValueError(f"[trajectory] angles_deg: {seen[name]:g} and {a:g} deg both make {name}; tilts must "
                             "differ by 0.1 deg or more")
        seen[name] = a


def _check_synthetic(entry: dict) -> None:
    """COLMAP's generator makes rigs x cameras per rig x frames per rig images: 2 or more."""
    opts = entry.get("synthetic", {})
    if not isinstance(opts, dict):
        raise ValueError(f"synthetic = {opts!r}: must be a [synthetic] table")
    defaults = pycolmap.SyntheticDatasetOptions()
    counts = {}
    for key in ("num_rigs", "num_cameras_per_rig", "num_frames_per_rig"):
        counts[key] = opts.get(key, getattr(defaults, key))
        if not _whole(counts[key], 1):
            raise ValueError(f"[synthetic] {key} = {counts[key]!r}: must be a whole number, 1 or more")
    if int(np.prod(list(counts.values()))) < MIN_VIEWS:
        raise ValueError(f"[synthetic] {' x '.join(f'{k} {v}' for k, v in counts.items())} make fewer than "
                         f"{MIN_VIEWS} images")


def repeat_offsets(spec: dict, what: str = "object") -> np.ndarray:
    """The offsets (N,3) of an object's copies: `repeat = [n1, n2, ...]` copies along each of the vectors
    `step = [[x, y, z], ...]` (a row, a grid), the object itself first; one copy without `repeat`."""
    if not REPEAT_KEYS & set(spec):
        return np.zeros((1, 3))
    counts, steps = spec.get("repeat"), spec.get("step")
    if not (isinstance(counts, list) and counts and all(_whole(n, 1) for n in counts)):
        raise ValueError(f"{what}: repeat = {counts!r}: must be a list of whole numbers of copies, 1 or more")
    try:
        steps = np.asarray(steps, float)
    except (TypeError, ValueError):
        steps = None
    if steps is None or steps.shape != (len(counts), 3) or not np.all(np.isfinite(steps)):
        raise ValueError(f"{what}: step = {spec.get('step')!r}: must be {len(counts)} vector(s) [x, y, z], "
                         "one per repeat count")
    grids = np.meshgrid(*[np.arange(n) for n in counts], indexing="ij")
    return np.stack([g.ravel() for g in grids], 1) @ steps


def _call(func, kwargs: dict, what: str):
    """func(**kwargs) with a ValueError that names the entry and the accepted keys when a key is wrong."""
    params = inspect.signature(func).parameters
    unknown = set(kwargs) - set(params)
    if unknown:
        raise ValueError(f"{what}: unknown keys {sorted(unknown)}; accepted: {', '.join(params)}")
    return func(**kwargs)


def build_object(
    spec: dict, seed: int, base_dir: Path, centres: np.ndarray | None = None
) -> meshes.TexturedMesh:
    """One `[[objects]]` table -> a textured mesh (with `repeat`, its copies: `repeat_offsets`). Texture seeds
    default to `seed` + face index. A site (`layouts.SITES`) is laid out around the camera `centres` (N,3)."""
    spec = dict(spec)
    kind = spec.pop("type", None)
    offsets = repeat_offsets(spec, kind)
    for key in REPEAT_KEYS:
        spec.pop(key, None)
    if kind in layouts.SITES:
        return _call(layouts.SITES[kind], {"centres": centres, "seed": seed, **spec}, kind)
    mesh = _build_one(kind, spec, seed, base_dir)
    return mesh if len(offsets) == 1 else meshes.tile(mesh, offsets)


def _build_one(kind, spec: dict, seed: int, base_dir: Path) -> meshes.TexturedMesh:
    if kind not in OBJECT_KEYS:
        raise ValueError(f"unknown object type {kind!r}; expected one of {', '.join(OBJECT_KEYS)}")
    unknown = set(spec) - OBJECT_KEYS[kind]
    if unknown:
        accepted = ", ".join(sorted(OBJECT_KEYS[kind]))
        raise ValueError(f"{kind}: unknown keys {sorted(unknown)}; accepted: {accepted}")

    def tex(value, k=0):
        return TextureSpec.parse(value, default_seed=seed + k)

    if kind == "quad":
        return meshes.quad(
            spec["origin"], spec["u"], spec["v"], tex(spec["texture"]), spec.get("uv_repeat", (1, 1))
        )
    if kind in ("box", "room"):
        textures = spec.get("textures", [spec.get("texture", "noise")])
        textures = [tex(t, k) for k, t in enumerate(textures)]
        if len(textures) == 1:
            textures = [TextureSpec(**{**textures[0].__dict__, "seed": seed + k}) for k in range(6)]
        return meshes.box(
            spec["center"], spec["size"], textures, spec.get("yaw_deg", 0.0), inward=kind == "room",
            tile=spec.get("tile"),
        )
    if kind == "sphere":
        return meshes.uv_sphere(
            spec["center"], spec["radius"], tex(spec["texture"]), spec.get("segments", 64)
        )
    if kind == "cylinder":
        return meshes.cylinder(
            spec["base"], spec["radius"], spec["height"], tex(spec["texture"]), spec.get("segments", 32)
        )
    if kind == "heightfield":
        u, v = np.asarray(spec["u"], float), np.asarray(spec["v"], float)
        nu, nv = spec.get("resolution", (200, 200))
        heights = meshes.relief(
            spec.get("relief", "bumps"),
            (nv, nu),
            (np.linalg.norm(u), np.linalg.norm(v)),
            spec.get("amplitude", 0.1),
            seed,
            spec.get("features", 40),
        )
        return meshes.grid(spec["origin"], u, v, heights, tex(spec["texture"]), spec.get("uv_repeat", (1, 1)))
    return meshes.load_mesh(  # kind == "mesh"
        base_dir / spec["path"],
        tex(spec.get("texture", "noise")),
        spec.get("scale", 1.0),
        spec.get("translate", (0, 0, 0)),
    )


def build_mesh(entry: dict, base_dir: Path, poses: list | None = None) -> meshes.TexturedMesh:
    """The entry's objects in one mesh; sites are laid out around the cameras of `poses` (default: the
    entry's trajectory)."""
    seed = int(entry.get("seed", 0))
    objects = entry.get("objects", [])
    if not objects:
        raise ValueError("a rendered scene needs at least one [[objects]] table")
    centres = None
    if any(o.get("type") in layouts.SITES for o in objects):
        centres = np.array([-R.T @ t for R, t in (build_poses(entry) if poses is None else poses)])
    return meshes.merge([build_object(o, seed * 1000 + 100 * k, base_dir, centres)
                         for k, o in enumerate(objects)])


def build_poses(entry: dict) -> list:
    traj = dict(entry.get("trajectory", {}))
    kind = traj.pop("type", None)
    if kind not in TRAJECTORIES:
        raise ValueError(f"trajectory type {kind!r}; expected one of {', '.join(TRAJECTORIES)}")
    if kind in ("hemisphere", "handheld", "survey"):
        traj.setdefault("seed", int(entry.get("seed", 0)))
    return _call(TRAJECTORIES[kind], traj, f"trajectory {kind}")


_NO_ZOOM, _NO_STEP = [1.0, 1.0], [0, 0]  # `view_cameras` without `zoom` or `size_step`: every view the same camera


def _check_view_cameras(cam: dict, kind: str) -> None:
    """Refuse a `zoom` or `size_step` (`view_cameras`) that is malformed, or on a scene kind of one camera."""
    if ("zoom" in cam or "size_step" in cam) and kind != "perspective":
        raise ValueError(f"[camera] zoom and size_step: a {kind} scene has one camera; they are for perspective "
                         "scenes")
    zoom = cam.get("zoom", _NO_ZOOM)
    if not (isinstance(zoom, list) and len(zoom) == 2 and all(isinstance(z, int | float) for z in zoom)
            and 0 < zoom[0] <= zoom[1]):
        raise ValueError(f"[camera] zoom = {zoom!r}: must be [low, high] with 0 < low <= high")
    step = cam.get("size_step", _NO_STEP)
    if not (isinstance(step, list) and len(step) == 2 and all(_whole(v, 0) for v in step)):
        raise ValueError(f"[camera] size_step = {step!r}: must be [width, height] steps of 0 or more pixels")


def view_cameras(entry: dict, count: int) -> list[PerspectiveCamera]:
    """The camera of each of `count` views: the entry's [camera] for all of them, or one camera per view with
    `zoom = [low, high]` (each view's focal times its own seeded factor, log-uniform between the two) and
    `size_step = [dw, dh]` (view k's image (width + k dw) x (height + k dh), its principal point moved with the
    image's centre): photos of one place from many cameras, each image its own camera, as in a collection of
    visitors' photos."""
    cam = build_camera(entry)
    spec = entry.get("camera", {})
    low, high = spec.get("zoom", _NO_ZOOM)
    dw, dh = spec.get("size_step", _NO_STEP)
    rng = np.random.default_rng([int(entry.get("seed", 0)), 0x200D])
    factors = np.exp(rng.uniform(np.log(low), np.log(high), count))
    names = PARAM_NAMES[cam.model]
    out = []
    for k, factor in enumerate(factors):
        params = np.array(cam.params, float)
        for i, name in enumerate(names):
            if name.startswith("f"):
                params[i] *= factor
            elif name in ("cx", "cy"):
                params[i] += k * (dw if name == "cx" else dh) / 2
        out.append(PerspectiveCamera(cam.model, cam.width + k * dw, cam.height + k * dh, tuple(params)))
    return out


def build_camera(entry: dict) -> PerspectiveCamera | OrthographicCamera:
    """The entry's [camera] (without the per-view variation of `view_cameras`)."""
    c = {k: v for k, v in entry.get("camera", {}).items() if k not in ("zoom", "size_step")}
    if c.pop("orthographic", False):
        return _call(cameras.OrthographicCamera, c, "camera")
    if "focal" in c:
        params = default_params(c["model"], c.pop("focal"), c["width"], c["height"])
        for name, value in c.pop("distortion", {}).items():
            params[PARAM_NAMES[c["model"]].index(name)] = value
        c["params"] = tuple(params)
    return _call(cameras.PerspectiveCamera, c, "camera")


def render_settings(entry: dict) -> tuple[RenderSettings, float]:
    r = dict(entry.get("render", {}))
    jitter = float(r.pop("exposure_jitter", 0.0))
    for key in ("light", "background"):
        if key in r:
            r[key] = tuple(float(x) for x in r[key])
    return _call(RenderSettings, r, "render"), jitter


def _render_all(
    renderer: Renderer, cams: list, poses, names, out: Path, seed: int, jitter: float, grey: bool = False,
    exifs: list | None = None,
) -> None:
    """Render each view k with its camera cams[k] into images/ and gt/depth/, skipping views whose two files are
    there: make_scene leaves only those of an interrupted run of the same entry, and both are written whole
    (seeded per view, so the views rendered now are the bytes an uninterrupted run gives). exifs[k]: view k's
    EXIF block."""
    rng = np.random.default_rng(seed)
    exposures = 1.0 + jitter * rng.uniform(-1.0, 1.0, len(poses))
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "gt" / "depth").mkdir(parents=True, exist_ok=True)
    files = [(out / "images" / n, out / "gt" / "depth" / (Path(n).stem + ".npy")) for n in names]
    todo = [k for k, (image, depth) in enumerate(files) if not (image.is_file() and depth.is_file())]
    if len(todo) < len(poses):
        log.info("%s: %d of %d views already rendered, rendering the other %d", out, len(poses) - len(todo),
                 len(poses), len(todo))
    for k in progress(todo, desc="render", unit="image"):
        image, depth = renderer.render(cams[k], poses[k], exposure=float(exposures[k]), seed=seed * 7919 + k)
        if grey:
            image = np.round(to_gray(image, np.float32))
            image = np.clip(image, 0, 255).astype(np.uint8)
        write_image(files[k][0], image, exif=None if exifs is None else exifs[k])
        write_depth(files[k][1], depth)


def surface_points(renderer: Renderer, count: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seeded surface samples: positions (N,3), unit normals (N,3), colours (N,3) uint8 from the texture."""
    pts, tri, bary = meshes.sample_surface(renderer.mesh, count, seed)
    v = renderer.mesh.vertices[renderer.mesh.triangles[tri]]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    hits = Hits(np.ones(len(pts), np.float32), tri, bary.astype(np.float32), normals.astype(np.float32))
    colors = np.clip(np.round(renderer.albedo(hits) * 255), 0, 255).astype(np.uint8)
    return pts, normals, colors


def observations(
    renderer: Renderer,
    cam: PerspectiveCamera,
    pose: tuple[np.ndarray, np.ndarray],
    points: np.ndarray,
    normals: np.ndarray,
    min_cos: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Which points a perspective camera sees, and where: (indices, pixels (N,2)).

    Seen = in front, inside the image, on the pixel's rendered ray, not at a grazing angle (|cos| >= min_cos
    between the viewing ray and the surface normal) and nothing between the camera centre and the point
    (ray cast).
    """
    R, t = pose
    X_cam = points @ R.T + t
    uv = cam.project(X_cam)
    ok = (X_cam[:, 2] > 0) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    # Distortion polynomials fold far-off-axis points back into the image; keep a point only when the
    # renderer's ray through its pixel (the inverse distortion) really points at it.
    with np.errstate(invalid="ignore", divide="ignore"):
        xy = X_cam[:, :2] / X_cam[:, 2:3]
    idx = np.flatnonzero(ok)
    ok[idx] = np.linalg.norm(cam.ray_directions(uv[idx])[:, :2] - xy[idx], axis=1) < 1e-7 * (
        1 + np.abs(xy[idx]).max(1)
    )
    centre = -R.T @ t
    view = points - centre
    cos = np.abs(np.sum(view * normals, axis=1)) / np.linalg.norm(view, axis=1)
    ok &= cos >= min_cos
    idx = np.flatnonzero(ok)
    visible = ~renderer.occluded(np.tile(centre, (len(idx), 1)), points[idx])
    idx = idx[visible]
    return idx, uv[idx]


def perspective(entry: dict, base_dir: Path, out: Path) -> dict:
    """Images, per-image depth and the ground-truth COLMAP model of a perspective scene."""
    return _perspective(entry, base_dir, out)[0]


def _perspective(entry: dict, base_dir: Path, out: Path, names: list[str] | None = None):
    seed = int(entry.get("seed", 0))
    poses = build_poses(entry)
    cams = view_cameras(entry, len(poses))
    cam = cams[0]
    settings, jitter = render_settings(entry)
    renderer = Renderer(build_mesh(entry, base_dir, poses), settings)
    ext = "jpg" if entry.get("image_format", "png") in ("jpg", "jpeg") else "png"
    names = names or [f"{k:04d}.{ext}" for k in range(len(poses))]
    gps = gps_positions(entry, poses, names)
    exifs = None
    if gps is not None:
        (out / "gt").mkdir(parents=True, exist_ok=True)
        (out / "gt" / "gps.json").write_text(json.dumps(gps, indent=1))
        exifs = [gps_exif(*gps["images"][n]["noisy_lla"]) for n in names]
    _render_all(renderer, cams, poses, names, out, seed, jitter, exifs=exifs)
    pts, normals, colors = surface_points(renderer, int(entry.get("points", 4000)), seed + 1)
    obs = [observations(renderer, c, p, pts, normals) for c, p in zip(cams, poses)]
    write_colmap_model(out / "gt" / "sparse", cams, names, poses, pts, colors, obs)
    info = {
        "images": len(poses),
        "camera": {"model": cam.model, "width": cam.width, "height": cam.height, "params": list(cam.params)},
    }
    if len(set(cams)) > 1:
        info["camera_per_image"] = True  # "camera" is the first image's; gt/sparse has each image's
    return info, renderer, cam, poses


def gps_positions(entry: dict, poses: list, names: list[str]) -> dict | None:
    """A drone's GPS fixes of the views of an entry with a [gps] table, or None: the scene's x, y, z are
    metres east, north and up of `origin` (latitude, longitude, altitude), and each fix is the camera centre
    plus seeded Gaussian noise of `sigma_horizontal` (per horizontal axis) and `sigma_vertical` metres,
    independent from view to view. Per image name: the true and the noisy position, in east/north/up metres
    and in WGS84 (degrees, degrees, metres); the noisy one is what the image's EXIF says."""
    gps = entry.get("gps")
    if gps is None:
        return None
    origin = np.asarray(gps["origin"], float)
    sigma = np.array([gps.get("sigma_horizontal", 2.5)] * 2 + [gps.get("sigma_vertical", 5.0)], float)
    centres = np.array([-R.T @ t for R, t in poses])
    rng = np.random.default_rng([int(entry.get("seed", 0)), 0x6795])
    noisy = centres + rng.normal(size=centres.shape) * sigma
    true_lla, noisy_lla = from_enu(centres, origin), from_enu(noisy, origin)
    images = {
        name: {"true_enu": centres[k].round(6).tolist(), "noisy_enu": noisy[k].round(6).tolist(),
               "true_lla": true_lla[k].round(9).tolist(), "noisy_lla": noisy_lla[k].round(9).tolist()}
        for k, name in enumerate(names)
    }
    return {"origin": origin.tolist(), "sigma_horizontal_m": float(sigma[0]),
            "sigma_vertical_m": float(sigma[2]),
            "frame": "scene x, y, z = metres east, north, up of origin (latitude, longitude, altitude)",
            "images": images}


def stereo(entry: dict, base_dir: Path, out: Path) -> dict:
    """A rectified pair im0/im1 plus Middlebury ground truth: disp0GT.pfm, mask0nocc.png, calib.txt."""
    if entry.get("camera", {}).get("model") not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError("a rectified stereo pair needs a PINHOLE or SIMPLE_PINHOLE camera")
    info, renderer, cam, poses = _perspective(entry, base_dir, out, names=["im0.png", "im1.png"])
    fx, cx, cy = cam.params[0], cam.params[-2], cam.params[-1]
    (R0, t0), (_, t1) = poses
    c0, c1 = -R0.T @ t0, -R0.T @ t1
    baseline = float(np.linalg.norm(c1 - c0))
    depth = np.load(out / "gt" / "depth" / "im0.npy").astype(np.float64)
    disparity, mask = disparity_from_depth(renderer, cam, (R0, t0), c1, depth, baseline)
    write_disparity(out / "disp0GT.pfm", disparity)
    write_image(out / "mask0nocc.png", mask)
    finite = disparity[np.isfinite(disparity)]
    ndisp = int(16 * np.ceil((finite.max() + 1) / 16)) if finite.size else 16
    write_middlebury_calib(out / "calib.txt", fx, cx, cy, baseline, cam.width, cam.height, ndisp)
    info.update({"baseline": baseline, "ndisp": ndisp})
    return info


def disparity_from_depth(
    renderer: Renderer,
    cam: PerspectiveCamera,
    pose0: tuple[np.ndarray, np.ndarray],
    c1: np.ndarray,
    depth: np.ndarray,
    baseline: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Left disparity fx*B/Z (inf without surface) and the Middlebury mask: 255 visible in the right image,
    128 occluded there (or outside it), 0 unknown."""
    R, t = pose0
    h, w = depth.shape
    disparity = np.where(np.isfinite(depth), cam.params[0] * baseline / depth, np.inf)
    px = cameras.pixel_grid(w, h)
    rays = cam.ray_directions(px)
    valid = np.isfinite(depth.ravel())
    X = ((rays[valid] * depth.ravel()[valid, None]) - t) @ R  # world points of the left pixel centres
    u_right = px[valid, 0] - disparity.ravel()[valid]
    seen = (u_right >= 0) & ~renderer.occluded(np.tile(c1, (len(X), 1)), X, rel_tol=1e-3)
    mask = np.zeros(h * w, np.uint8)
    mask[np.flatnonzero(valid)] = np.where(seen, 255, 128)
    return disparity.astype(np.float32), mask.reshape(h, w)


def sem_tilt(entry: dict, base_dir: Path, out: Path) -> dict:
    """Orthographic grey tilt series tilt_<angle>.png, per-tilt depth, the height map on the 0-degree grid."""
    seed = int(entry.get("seed", 0))
    cam = build_camera(entry)
    if not isinstance(cam, cameras.OrthographicCamera):
        raise ValueError("an SEM tilt series needs an orthographic camera (camera.orthographic = true)")
    traj = dict(entry["trajectory"])
    poses = build_poses(entry)
    angles = [float(a) for a in traj["angles_deg"]]
    settings, jitter = render_settings(entry)
    renderer = Renderer(build_mesh(entry, base_dir), settings)
    names = [f"tilt_{a:+.1f}.png" for a in angles]
    _render_all(renderer, [cam] * len(poses), poses, names, out, seed, jitter, grey=True)
    zero = cameras.tilt_series(
        [0.0], traj["distance"], traj.get("axis", "y"), traj.get("eucentric", (0, 0, 0))
    )[0]
    R, t = zero
    origins, dirs = cameras.CameraRays(cam, 1).centres
    centre = -R.T @ t
    hits = renderer.cast(origins @ R + centre, dirs @ R)
    height = np.where(hits.valid, (centre @ [0, 0, 1.0]) - hits.t, np.nan).reshape(cam.height, cam.width)
    np.save(out / "gt" / "height.npy", height.astype(np.float32))
    projections = {
        name: {
            "cam_from_world_R": np.asarray(R_, float).round(12).tolist(),
            "cam_from_world_t": np.asarray(t_, float).round(12).tolist(),
        }
        for name, (R_, t_) in zip(names, poses)
    }
    meta = {
        "pixel_size_um": cam.pixel_size,
        "tilt_angles_deg": angles,
        "tilt_axis": traj.get("axis", "y"),
        "tilt_axis_in_image": "vertical (image y)"
        if traj.get("axis", "y") == "y"
        else "horizontal (image x)",
        "units": "micrometres",
        "width": cam.width,
        "height": cam.height,
        "height_map": "world z of the surface seen by each pixel of the 0-degree image (NaN: no surface)",
        "projection": "orthographic: pixel = (R X + t)[:2] / pixel_size_um + (width/2, height/2)",
        "images": projections,
    }
    (out / "gt" / "height.json").write_text(json.dumps(meta, indent=1))
    return {"images": len(poses), "pixel_size_um": cam.pixel_size, "tilt_angles_deg": angles}


def colmap_synthetic(entry: dict, base_dir: Path, out: Path) -> dict:
    """COLMAP's own synthetic generator: random cameras and points, images with COLMAP's feature patches."""
    opts = dict(entry.get("synthetic", {}))
    if "camera_model" in opts:
        opts["camera_model_id"] = pycolmap.CameraModelId.__members__[opts.pop("camera_model")]
    image_opts = opts.pop("images", {})
    pycolmap.set_random_seed(int(entry.get("seed", 0)))
    rec = pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(**opts))
    (out / "images").mkdir(parents=True, exist_ok=True)
    pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(**image_opts), rec, str(out / "images"))
    (out / "gt" / "sparse").mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(out / "gt" / "sparse"))
    return {"images": rec.num_images(), "points": rec.num_points3D()}


KINDS = {
    "perspective": perspective,
    "stereo": stereo,
    "sem_tilt": sem_tilt,
    "colmap_synthetic": colmap_synthetic,
}
