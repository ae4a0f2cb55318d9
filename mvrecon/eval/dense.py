"""Dense reconstructions scored against ground truth: depth maps per view, and the fused cloud ETH3D's way.

Ground truth (`scene_truth`) is what a rendered scene's cameras see: every view's exact depth map (the scene
folder's gt/depth/, cast through the pixel centres) back-projected with its true camera and pose, thinned to one
sample per cell of a grid of `spacing_fraction` of the scene extent, each sample counting the views that see it
(its projection's true depth agrees within 1%: not hidden, in the frame). It is computed from a scene folder's
own files, so any rendered scene (one made before, a read-only shared one) can be scored without rendering it
again, and the samples are exactly the surface the cameras see: unlike samples of the scene's meshes, none lies
on a face no view sees, which no reconstruction could recover. Samples seen by two or more views are the
`reconstructable` surface, that completeness is measured against (a face one view sees cannot be triangulated);
accuracy is measured against every sample, as a point on a face only one view sees is still a right one.

Scores (`score_cloud`) follow ETH3D: at a tolerance tau, accuracy (precision) is the share of reconstructed points
within tau of the truth, completeness (recall) the share of truth samples within tau of the reconstruction, and F
their harmonic mean; tau is 0.2%, 0.5% and 1% of the scene extent (the diagonal of the bounding box of what the
views see). The reconstruction is first brought into the truth's frame by the similarity that takes its cameras'
centres onto the true ones (`frame_alignment`, the robust Sim3 of `metrics.align_and_compare`).

`depth_scores` scores each depth map (COLMAP's `.bin`): the share of a view's valid truth pixels whose depth the
map gives within 1%. `depth_agreement` needs no truth (real photographs): the share of a view's depths that
another view's depth map confirms within 1%.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from ..errors import InputError
from ..geometry import camera as cammodel
from ..geometry.sim3 import Sim3
from ..interrupts import import_open3d
from ..io.colmap_array import read_colmap_array
from ..io.ply import read_ply_points
from . import metrics as M
from .models import load_reconstruction, poses

TOLERANCES = (0.002, 0.005, 0.01)  # of the scene extent: ETH3D-style thresholds
DEPTH_TOLERANCE = 0.01  # relative depth error a depth map's pixel may have and count as right
SPACING_FRACTION = 0.001  # truth sample spacing: half the finest tolerance


@dataclass(frozen=True)
class View:
    """One camera of a model: name, COLMAP model name and params, size, cam_from_world (R, t)."""

    name: str
    model: str
    params: np.ndarray
    width: int
    height: int
    R: np.ndarray
    t: np.ndarray

    @property
    def corner_radius(self) -> float:
        """The largest normalised radius (tan of the angle off the axis) the image's corners see."""
        corners = np.array([[0, 0], [self.width, 0], [0, self.height], [self.width, self.height]], float)
        return float(np.max(np.hypot(*cammodel.pixels_to_normalized(self.model, self.params, corners).T)))

    def world_points(self, depth: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) of the pixels (every `stride`-th row and column) with a positive finite z-depth,
        and their flat pixel indices into `depth` (whose size may differ from the camera's: it is scaled)."""
        h, w = depth.shape
        rows, cols = np.mgrid[0:h:stride, 0:w:stride]
        z = depth[rows, cols].ravel().astype(np.float64)
        ok = np.isfinite(z) & (z > 0)
        rows, cols, z = rows.ravel()[ok], cols.ravel()[ok], z[ok]
        sx, sy = self.width / w, self.height / h
        uv = np.stack([(cols + 0.5) * sx, (rows + 0.5) * sy], 1)
        xy = cammodel.pixels_to_normalized(self.model, self.params, uv)
        X_cam = np.concatenate([xy * z[:, None], z[:, None]], 1)
        return (X_cam - self.t) @ self.R, rows * w + cols

    def project(self, points: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(flat index of the nearest pixel of an array of `shape` (-1 outside it or behind the camera),
        camera z) of world points (N,3)."""
        X_cam = points @ self.R.T + self.t
        z = X_cam[:, 2]
        uv = cammodel.project(self.model, self.params, X_cam)
        h, w = shape
        col = np.floor(uv[:, 0] * w / self.width)
        row = np.floor(uv[:, 1] * h / self.height)
        inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)  # NaN compares False
        with np.errstate(invalid="ignore", divide="ignore"):  # distortion folds far-off-axis points back in
            inside &= np.hypot(X_cam[:, 0] / z, X_cam[:, 1] / z) <= 1.05 * self.corner_radius
        index = np.full(len(points), -1, np.int64)
        index[inside] = row[inside].astype(np.int64) * w + col[inside].astype(np.int64)
        return index, z


def model_views(rec: pycolmap.Reconstruction) -> dict[str, View]:
    """The registered images of a pycolmap model as `View`s, by image name."""
    out = {}
    for name, (R, t) in poses(rec).items():
        cam = rec.cameras[rec.find_image_with_name(name).camera_id]  # the model's own camera, not a copy's
        out[name] = View(name, cam.model.name, np.array(cam.params, float), int(cam.width), int(cam.height),
                         R, t)
    return out


@dataclass(frozen=True)
class DenseTruth:
    """Surface samples of a scene (N,3), how many views see each (N,), the scene extent and the sample spacing
    (scene units)."""

    points: np.ndarray
    views: np.ndarray
    extent: float
    spacing: float

    @property
    def reconstructable(self) -> np.ndarray:
        """The samples two or more views see: what a multi-view reconstruction can recover."""
        return self.points[self.views >= 2]


def scene_truth(scene_dir: Path | str, spacing_fraction: float = SPACING_FRACTION) -> DenseTruth:
    """The dense ground truth of a rendered scene folder (gt/sparse and gt/depth/*.npy; see the module's text).

    Each view's pixels are thinned into the samples before the next view's are added, so memory holds the
    depth maps, one view's points and the samples.
    """
    scene_dir = Path(scene_dir)
    model_dir, depth_dir = scene_dir / "gt" / "sparse", scene_dir / "gt" / "depth"
    if not model_dir.is_dir() or not depth_dir.is_dir():
        raise InputError(f"{scene_dir}: no gt/sparse and gt/depth (not a rendered perspective scene)")
    views = model_views(load_reconstruction(model_dir))
    depths = {}
    for name in views:
        path = depth_dir / f"{Path(name).stem}.npy"
        if not path.is_file():
            raise InputError(f"{path}: ground-truth depth of {name} missing")
        depths[name] = path
    return truth_from_depths({n: (views[n], np.load(p)) for n, p in depths.items()}, spacing_fraction)


def truth_from_depths(depths: dict, spacing_fraction: float = SPACING_FRACTION) -> DenseTruth:
    """`scene_truth` from name -> (View, z-depth (H,W) in the view's scene units, inf or 0 where no
    surface)."""
    lows, highs = [], []
    for view, depth in depths.values():  # the extent first: it sets the sample spacing
        X, _ = view.world_points(np.asarray(depth), stride=4)
        if len(X):
            lows.append(X.min(0))
            highs.append(X.max(0))
    if not lows:
        raise InputError("the ground-truth depth maps hold no surface")
    low, high = np.min(lows, 0), np.max(highs, 0)
    extent = float(np.linalg.norm(high - low))
    spacing = spacing_fraction * extent
    cells = np.ceil((high - low) / spacing).astype(np.int64) + 3
    keys, points = np.zeros(0, np.int64), np.zeros((0, 3))
    for view, depth in depths.values():
        X, _ = view.world_points(np.asarray(depth))
        cell = np.floor((X - low) / spacing).astype(np.int64) + 1
        k = (cell[:, 0] * cells[1] + cell[:, 1]) * cells[2] + cell[:, 2]
        # one sample per cell: the first pixel that fell in it, a point exactly on the surface
        keys, first = np.unique(np.r_[keys, k], return_index=True)
        points = np.r_[points, X][first]
    seen = np.zeros(len(points), np.int32)
    for view, depth in depths.values():
        depth = np.asarray(depth)
        index, z = view.project(points, depth.shape)
        inside = index >= 0
        d = np.full(len(points), np.nan)
        d[inside] = depth.ravel()[index[inside]]
        seen += np.abs(d - z) <= DEPTH_TOLERANCE * np.abs(z)  # NaN and inf compare False
    return DenseTruth(points=points, views=seen, extent=extent, spacing=spacing)


@dataclass(frozen=True)
class DenseScore:
    """ETH3D-style scores of a cloud at each tolerance (a fraction of the extent): accuracy (precision),
    completeness (recall), F-score; and the counts they were computed from."""

    accuracy: dict[float, float]
    completeness: dict[float, float]
    fscore: dict[float, float]
    points: int
    truth_points: int
    extent: float

    def as_dict(self) -> dict:
        out = {"points": self.points, "truth_points": self.truth_points, "extent": self.extent}
        for tau in self.accuracy:
            out.update({f"accuracy@{100 * tau:g}%": self.accuracy[tau],
                        f"completeness@{100 * tau:g}%": self.completeness[tau],
                        f"fscore@{100 * tau:g}%": self.fscore[tau]})
        return out


def score_cloud(points: np.ndarray, truth: DenseTruth, tolerances: tuple[float, ...] = TOLERANCES) -> DenseScore:
    """Accuracy, completeness and F of `points` (N,3, already in the truth's frame) at each tolerance of the
    extent: accuracy against every truth sample, completeness of the samples two or more views see."""
    points = np.asarray(points, float).reshape(-1, 3)
    target = truth.reconstructable
    largest = max(tolerances) * truth.extent
    if len(points):
        to_truth = cKDTree(truth.points).query(points, distance_upper_bound=largest, workers=-1)[0]
        to_cloud = cKDTree(points).query(target, distance_upper_bound=largest, workers=-1)[0]
    else:
        to_truth, to_cloud = np.zeros(0), np.full(len(target), np.inf)
    acc, comp, f = {}, {}, {}
    for tau in tolerances:
        d = tau * truth.extent
        acc[tau] = float(np.mean(to_truth <= d)) if len(points) else 0.0
        comp[tau] = float(np.mean(to_cloud <= d)) if len(target) else 0.0
        f[tau] = 2 * acc[tau] * comp[tau] / (acc[tau] + comp[tau]) if acc[tau] + comp[tau] > 0 else 0.0
    return DenseScore(accuracy=acc, completeness=comp, fscore=f, points=len(points), truth_points=len(target),
                      extent=truth.extent)


def frame_alignment(est: dict, truth: dict, inlier_fraction: float = 0.05) -> Sim3:
    """The similarity taking the estimated world frame onto the truth's (name -> (R, t) world-to-camera each),
    from the camera centres of the images both hold (robust Umeyama, `metrics.align_and_compare`)."""
    al = M.align_and_compare(est, truth, inlier_fraction)
    if al is None:
        raise InputError(f"{len(set(est) & set(truth))} image(s) shared with the ground truth: 3 are needed to "
                         "align the reconstruction to it")
    return al.sim3


def dense_model(dense_dir: Path | str) -> pycolmap.Reconstruction:
    """The undistorted model of a dense workspace (DENSE/sparse), the cameras its depth maps were made with."""
    sparse = Path(dense_dir) / "sparse"
    if not sparse.is_dir():
        raise InputError(f"{dense_dir}: no sparse/ (not a dense workspace of `mvrecon dense`)")
    return load_reconstruction(sparse)


def depth_map_path(dense_dir: Path | str, name: str) -> Path | None:
    """The geometric depth map of image `name` (the photometric one when there is no geometric), or None."""
    folder = Path(dense_dir) / "stereo" / "depth_maps"
    for kind in ("geometric", "photometric"):
        path = folder / f"{name}.{kind}.bin"
        if path.is_file():
            return path
    return None


def depth_scores(dense_dir: Path | str, scene_dir: Path | str, to_truth: Sim3,
                 tolerance: float = DEPTH_TOLERANCE) -> dict[str, float]:
    """Per image of the dense workspace: the share of its truth pixels (a finite true depth, inside the
    undistorted view) whose depth the view's depth map gives within `tolerance` (relative); a pixel without an
    estimate counts as wrong, and a view without a depth map scores 0. `to_truth` takes the reconstruction's
    frame onto the truth's (`frame_alignment`)."""
    scene_dir = Path(scene_dir)
    truth = model_views(load_reconstruction(scene_dir / "gt" / "sparse"))
    from_truth = to_truth.inverse()
    out = {}
    for name, view in model_views(dense_model(dense_dir)).items():
        gt_path = scene_dir / "gt" / "depth" / f"{Path(name).stem}.npy"
        if name not in truth or not gt_path.is_file():
            continue
        X, _ = truth[name].world_points(np.load(gt_path))
        path = depth_map_path(dense_dir, name)
        if path is None:
            out[name] = 0.0
            continue
        depth = read_colmap_array(path)
        index, z = view.project(from_truth.apply(X), depth.shape)
        inside = index >= 0
        if not inside.any():
            out[name] = 0.0
            continue
        d = depth.ravel()[index[inside]]
        out[name] = float(np.mean((d > 0) & (np.abs(d - z[inside]) <= tolerance * z[inside])))
    return out


def depth_agreement(dense_dir: Path | str, tolerance: float = DEPTH_TOLERANCE,
                    stride: int = 2) -> dict[str, dict[str, float]]:
    """Per image with a depth map, without ground truth: `valid`, the share of its pixels with a depth, and
    `confirmed`, the share of those (every `stride`-th row and column) whose point another view's depth map
    gives within `tolerance` of its depth there."""
    views = model_views(dense_model(dense_dir))
    maps = {n: read_colmap_array(p) for n in views if (p := depth_map_path(dense_dir, n)) is not None}
    out = {}
    for name, depth in maps.items():
        X, _ = views[name].world_points(depth, stride)
        confirmed = np.zeros(len(X), bool)
        for other, other_depth in maps.items():
            if other == name:
                continue
            index, z = views[other].project(X, other_depth.shape)
            inside = np.flatnonzero(index >= 0)
            d = other_depth.ravel()[index[inside]]
            confirmed[inside] |= (d > 0) & (np.abs(d - z[inside]) <= tolerance * z[inside])
        out[name] = {"valid": float(np.mean(np.isfinite(depth) & (depth > 0))),
                     "confirmed": float(confirmed.mean()) if len(X) else 0.0}
    return out


def score_workspace(dense_dir: Path | str, scene_dir: Path | str, truth: DenseTruth | None = None) -> dict:
    """Everything a dense workspace (DENSE: sparse/, stereo/depth_maps/, fused.ply) scores against the rendered
    scene SCENE_DIR: the alignment's scale and inliers, the fused cloud's `DenseScore`, each view's depth
    score and their mean. `truth`: `scene_truth(scene_dir)`, when the caller has it already."""
    dense_dir, scene_dir = Path(dense_dir), Path(scene_dir)
    fused = dense_dir / "fused.ply"
    if not fused.is_file():
        raise InputError(f"{dense_dir}: no fused.ply")
    truth = truth if truth is not None else scene_truth(scene_dir)
    gt = poses(load_reconstruction(scene_dir / "gt" / "sparse"))
    est = poses(dense_model(dense_dir))
    to_truth = frame_alignment(est, gt)
    points, _ = read_ply_points(fused)
    depth = depth_scores(dense_dir, scene_dir, to_truth)
    return {"alignment_scale": to_truth.scale, "views": len(est),
            "fused": score_cloud(to_truth.apply(points), truth).as_dict(),
            "depth_within_1pct": float(np.mean(list(depth.values()))) if depth else 0.0,
            "depth_per_view": depth}


def render_points(view: View, points: np.ndarray, colors: np.ndarray, shape: tuple[int, int],
                  background: int = 255) -> np.ndarray:
    """An (H,W,3) uint8 picture of coloured points (N,3) seen by `view` at `shape` (a view's size scaled: half
    size closes the gaps between a dense cloud's points), the nearest point winning each pixel."""
    h, w = shape
    image = np.full((h * w, 3), background, np.uint8)
    index, z = view.project(np.asarray(points, float).reshape(-1, 3), shape)
    ok = np.flatnonzero(index >= 0)
    order = ok[np.argsort(-z[ok], kind="stable")]  # far to near: the nearest is written last
    image[index[order]] = np.asarray(colors)[order]
    return image.reshape(h, w, 3)


def render_mesh(view: View, vertices: np.ndarray, triangles: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """An (H,W) grey picture in [0, 1] of a mesh seen by `view` at `shape`, lit from the camera (1: no
    surface), for a mesh's figure without a display (ray-cast, as the scene renderer draws)."""
    o3d = import_open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(triangles, np.uint32)))
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w]
    uv = np.stack([(cols.ravel() + 0.5) * view.width / w, (rows.ravel() + 0.5) * view.height / h], 1)
    xy = cammodel.pixels_to_normalized(view.model, view.params, uv)
    directions = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ view.R  # camera to world: R^T d
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = np.broadcast_to(-view.R.T @ view.t, directions.shape)
    hits = scene.cast_rays(o3d.core.Tensor(np.concatenate([origins, directions], 1).astype(np.float32)))
    normals = hits["primitive_normals"].numpy()
    shade = 0.25 + 0.75 * np.abs(np.sum(normals * directions, axis=1))
    return np.where(np.isfinite(hits["t_hit"].numpy()), shade, 1.0).reshape(h, w)


def ply_vertex_count(path: Path | str) -> int | None:
    """The vertex count a PLY file's header declares (its points, without reading them), or None."""
    try:
        with open(path, "rb") as f:
            for _ in range(64):
                line = f.readline().decode("ascii", "replace").split()
                if line[:2] == ["element", "vertex"] and len(line) == 3:
                    return int(line[2])
                if line[:1] == ["end_header"]:
                    return None
    except (OSError, ValueError):
        return None
    return None


def workspace_summary(dense_dir: Path | str) -> dict | None:
    """What a dense workspace holds, for a report: its folder, depth maps, fused points (None: no fused.ply)
    and whether it has a mesh; None when DENSE_DIR is no dense workspace (no sparse/, or no depth map and no
    fused.ply)."""
    dense_dir = Path(dense_dir)
    if not (dense_dir / "sparse").is_dir():
        return None
    names = {p.name.rsplit(".", 2)[0] for p in (dense_dir / "stereo" / "depth_maps").glob("*.bin")}
    fused = dense_dir / "fused.ply"
    if not names and not fused.is_file():
        return None
    return {"folder": str(dense_dir), "depth_maps": len(names),
            "fused_points": ply_vertex_count(fused) if fused.is_file() else None,
            "mesh": (dense_dir / "mesh.ply").is_file()}
