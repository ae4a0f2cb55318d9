"""Georeferencing: models brought into the metric frame of their cameras' position priors (GPS or surveyed).

The priors (database pose priors, WGS84 or local CARTESIAN) become east/north/up metres about one origin
(`CenterPriors.of`); a model whose registered images with a prior are spread in two directions is moved into that
frame by a robust similarity (`georeference`), after which its bundle adjustments hold each camera centre to its
prior through a Cauchy loss (bundle.py): a fix tens of metres off pulls with a force that fades with its distance
instead of bending the model. `prior_residuals` tells each image's distance from its prior, in metres and in
sigmas, so that a wrong fix is named in the report. `triangulate_observed` places ground control markers seen in
the images in a finished model (commands/georef.py).
"""

import logging
from dataclasses import dataclass

import numpy as np

from ..geometry.camera import pixels_to_normalized, project
from ..geometry.rotation import angle_axis_to_rotmat
from ..geometry.sim3 import Sim3, ransac_umeyama
from ..geometry.triangulation import refine_points, triangulate_dlt
from ..io.gps import enu_to_ecef, from_enu, to_enu
from ..io.pose_priors import CARTESIAN, WGS84
from .model import Reconstruction

log = logging.getLogger("mvrecon.sfm")

# the spread the registered prior positions need (RMS along their second principal axis, in horizontal sigmas)
# before a similarity is fitted to them: along one line the roll about it is not determined
MIN_SPREAD_SIGMAS = 2.0
INLIER_SIGMAS = 3.0  # a prior within this many sigmas (of its norm) of the fitted similarity is an inlier


@dataclass
class CenterPriors:
    """Camera-centre priors in one metric frame: image id -> position (east, north, up metres about `origin`,
    or the CARTESIAN priors' own x, y, z when `origin` is None) and sigmas (metres, per axis)."""

    image_ids: np.ndarray
    positions: np.ndarray  # (N, 3)
    sigmas: np.ndarray  # (N, 3)
    origin: np.ndarray | None  # (lat, lon, alt) of the ENU origin; None: a local frame

    @classmethod
    def of(cls, priors: dict, origin: np.ndarray | None = None) -> "CenterPriors | None":
        """The priors (image id -> io.pose_priors.PosePrior) in one frame, or None without any. WGS84 priors
        become ENU about `origin` (default: their median position); when both kinds are present the more
        numerous is used and the others are left out with a warning."""
        if not priors:
            return None
        geo = {i: p for i, p in priors.items() if p.coordinate_system == WGS84}
        local = {i: p for i, p in priors.items() if p.coordinate_system == CARTESIAN}
        use = geo if len(geo) >= len(local) else local
        if geo and local:
            log.warning("pose priors in two coordinate systems (%d WGS84, %d CARTESIAN): only the %s ones are used",
                        len(geo), len(local), "WGS84" if use is geo else "CARTESIAN")
        ids = np.array(sorted(use), np.int64)
        pos = np.array([use[i].position for i in ids], float)
        sig = np.array([use[i].sigmas for i in ids], float)
        if use is geo:
            origin = np.median(pos, axis=0) if origin is None else np.asarray(origin, float)
            pos = to_enu(pos, origin)
        else:
            origin = None
        return cls(ids, pos, sig, origin)

    def in_model(self, model: Reconstruction, registered: bool = True) -> tuple[np.ndarray, np.ndarray,
                                                                                 np.ndarray]:
        """(model image indices, positions, sigmas) of the priors of the model's (registered) images."""
        index = {int(i): k for k, i in enumerate(model.image_ids)}
        rows = [(index[int(i)], k) for k, i in enumerate(self.image_ids) if int(i) in index]
        if registered:
            rows = [(j, k) for j, k in rows if model.registered[j]]
        if not rows:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        js, ks = np.array(rows, np.int64).T
        return js, self.positions[ks], self.sigmas[ks]


def _spread(positions: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """The positions' RMS extent along their principal directions, largest first, in units of their median
    horizontal sigma."""
    s = np.linalg.svd(positions - positions.mean(axis=0), compute_uv=False) / np.sqrt(len(positions))
    return s / float(np.median(sigmas[:, :2]))


def _inlier_threshold(sigmas: np.ndarray) -> float:
    """The distance within which a camera agrees with its prior: INLIER_SIGMAS of its sigmas' norm (median)."""
    return INLIER_SIGMAS * float(np.median(np.linalg.norm(sigmas, axis=1)))


def spread_enough(positions: np.ndarray, sigmas: np.ndarray) -> bool:
    """Whether positions span two directions well beyond their noise (see MIN_SPREAD_SIGMAS)."""
    return len(positions) >= 3 and bool(_spread(positions, sigmas)[1] >= MIN_SPREAD_SIGMAS)


def align_centres(centres: np.ndarray, positions: np.ndarray, sigmas: np.ndarray,
                  seed: int = 0) -> tuple[Sim3, np.ndarray] | None:
    """The similarity taking camera `centres` onto their known `positions` (RANSAC, inliers within
    INLIER_SIGMAS of their sigmas' norm), with the inlier mask; None when the positions do not span two
    directions (`spread_enough`)."""
    if not spread_enough(positions, sigmas):
        return None
    threshold = _inlier_threshold(sigmas)
    try:
        return ransac_umeyama(centres, positions, threshold=threshold, seed=seed)
    except (ValueError, np.linalg.LinAlgError):
        return None


def upright_alignment(centres: np.ndarray, ups: np.ndarray, positions: np.ndarray, sigmas: np.ndarray,
                      seed: int = 0) -> tuple[Sim3, np.ndarray] | None:
    """The similarity taking camera `centres` onto `positions` that lie along one line (a street), where the
    roll about the line is not determined by them: the cameras' mean up direction (`ups`, the image's -y axis
    in the model) is taken as the vertical, as photos are mostly taken upright, and heading, scale and
    offset are fitted (RANSAC over pairs, inliers within INLIER_SIGMAS). None when the cameras do not agree on
    an up direction or the positions are not spread along their line."""
    up = ups.mean(axis=0)
    if np.linalg.norm(up) < 0.7 or len(positions) < 3:
        return None
    up /= np.linalg.norm(up)
    if _spread(positions, sigmas)[0] < MIN_SPREAD_SIGMAS:
        return None
    axis = np.cross(up, [0.0, 0.0, 1.0])
    angle = np.arctan2(np.linalg.norm(axis), up[2])
    if np.linalg.norm(axis) < 1e-12:  # up already along +z, or along -z: a half turn about x
        level = np.eye(3) if angle < np.pi / 2 else np.diag([1.0, -1.0, -1.0])
    else:  # the model's up onto +z
        level = angle_axis_to_rotmat(axis / np.linalg.norm(axis) * angle)
    c = centres @ level.T
    zm, zp = c[:, 0] + 1j * c[:, 1], positions[:, 0] + 1j * positions[:, 1]
    threshold = _inlier_threshold(sigmas)
    rng = np.random.default_rng(seed)

    def fit(mask):
        am, ap = zm[mask].mean(), zp[mask].mean()
        a = np.vdot(zm[mask] - am, zp[mask] - ap) / max(float(np.sum(np.abs(zm[mask] - am) ** 2)), 1e-300)
        yaw = np.array([[a.real, -a.imag, 0.0], [a.imag, a.real, 0.0], [0.0, 0.0, abs(a)]]) / max(abs(a), 1e-300)
        rot = yaw @ level
        scale = abs(a)
        t = positions[mask].mean(axis=0) - scale * centres[mask].mean(axis=0) @ rot.T
        return Sim3(scale, rot, t)

    best, best_count = np.ones(len(zm), bool), -1
    for _ in range(200):
        pair = rng.choice(len(zm), 2, replace=False)
        if abs(zm[pair[0]] - zm[pair[1]]) < 1e-12:
            continue
        mask = np.zeros(len(zm), bool)
        mask[pair] = True
        T = fit(mask)
        inl = np.linalg.norm(T.apply(centres) - positions, axis=1) < threshold
        if inl.sum() > best_count:
            best, best_count = inl, int(inl.sum())
    if best_count < 3:
        return None
    T = fit(best)
    inliers = np.linalg.norm(T.apply(centres) - positions, axis=1) < threshold
    return (fit(inliers), inliers) if inliers.sum() >= 3 else (T, best)


def fit_similarity(model: Reconstruction, priors: CenterPriors, seed: int = 0) -> tuple[Sim3, np.ndarray] | None:
    """`align_centres` of the model's registered images with a prior."""
    js, pos, sig = priors.in_model(model)
    return align_centres(model.centers()[js], pos, sig, seed)


def triangulate_observed(views: list[list[tuple[np.ndarray, np.ndarray, str, np.ndarray, np.ndarray]]]
                         ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Points seen in images (ground control markers), each from its views (R, t cam_from_world, camera model,
    its parameters, the pixel): the multi-view DLT refined on the reprojection error (geometry.triangulation),
    as the mapper triangulates. Returns the points (n, 3; NaN where the rays meet behind a camera or not at all)
    and each point's reprojection error per view, in pixels."""
    k = max(len(v) for v in views)
    R, t = np.tile(np.eye(3), (len(views), k, 1, 1)), np.zeros((len(views), k, 3))
    x, mask = np.zeros((len(views), k, 2)), np.zeros((len(views), k), bool)
    for i, obs in enumerate(views):
        for j, (Rj, tj, model, params, uv) in enumerate(obs):
            R[i, j], t[i, j], mask[i, j] = Rj, tj, True
            x[i, j] = pixels_to_normalized(model, params, np.asarray(uv, float)[None])[0]
    X = refine_points(triangulate_dlt(R, t, x, mask), R, t, x, mask)
    errors = []
    for i, obs in enumerate(views):
        cam = np.einsum("kij,j->ki", R[i, :len(obs)], X[i]) + t[i, :len(obs)]
        if not (np.isfinite(X[i]).all() and (cam[:, 2] > 0).all()):
            X[i] = np.nan
        errors.append(np.array([np.linalg.norm(project(m, p, c[None])[0] - np.asarray(uv, float))
                                for c, (_, _, m, p, uv) in zip(cam, obs)]))
    return X, errors


def transform_model(model: Reconstruction, T: Sim3) -> None:
    """Move the model (poses and points) by the similarity T: x' = s R x + t."""
    centers = T.apply(model.centers())
    model.R = model.R @ T.R.T
    model.t = -np.einsum("nij,nj->ni", model.R, centers)
    n = model.xyz.n
    model.xyz.data[:n] = T.apply(model.xyz.data[:n])


def georeference(model: Reconstruction, seed: int = 0) -> Sim3 | None:
    """Move a model with priors (`model.priors`) into their frame once its registered images with a prior
    span two directions; then `model.georeferenced` is set and the bundle adjustments hold the centres to
    their priors. Returns the similarity applied, or None (no priors, already done, or not yet spread)."""
    priors = getattr(model, "priors", None)
    if priors is None or model.georeferenced:
        return None
    fit = fit_similarity(model, priors, seed)
    if fit is None:
        return None
    T, inliers = fit
    transform_model(model, T)
    model.georeferenced = True
    log.info("model georeferenced at %d registered images (%d of %d priors inliers, scale %.4g)",
             int(model.registered.sum()), int(inliers.sum()), len(inliers), T.scale)
    return T


def prior_residuals(model: Reconstruction, priors: CenterPriors) -> dict[str, tuple[np.ndarray, float]]:
    """name -> (centre minus prior, metres per axis; that difference in sigmas, as a norm) for every registered
    image with a prior."""
    js, pos, sig = priors.in_model(model)
    diff = model.centers()[js] - pos
    return {model.names[j]: (d, float(np.linalg.norm(d / s))) for j, d, s in zip(js.tolist(), diff, sig)}


def georeference_models(models: list, priors: CenterPriors | None, *, frame: str = "enu", max_sigmas: float = 4.0,
                        seed: int = 0) -> dict | None:
    """Bring each model into the priors' frame (the incremental mapper has done so while growing; the global
    mapper's models are moved here), name the images whose centre is more than `max_sigmas` from its prior, and
    with `frame` "ecef" move georeferenced models to earth-centred metres. Returns the report's `georef` entry
    (frame, origin, per model its fit to the priors and flagged images, per image its position and latitude,
    longitude, altitude), or None without priors."""
    if priors is None:
        return None
    frame = frame if priors.origin is not None else "local"
    out = {"frame": frame, "origin": None if priors.origin is None else [float(v) for v in priors.origin],
           "models": [], "images": {}}
    for m in models:
        m.priors = priors
        if m.georeferenced:
            # held by the priors in its BAs as it grew; their share of a BA's cost is small, so LM stops before
            # the gauge settles (street_long, 100 views: 3.2 m RMS from the truth, 0.8 m after this refit)
            fit = fit_similarity(m, priors, seed)
            if fit is not None:
                transform_model(m, fit[0])
        georeference(m, seed)
        if not m.georeferenced:  # priors along one line (a street): the cameras' up fixes the roll
            js, pos, sig = priors.in_model(m)
            fit = upright_alignment(m.centers()[js], -m.R[js, 1, :], pos, sig, seed)
            if fit is not None:
                transform_model(m, fit[0])
                m.georeferenced = True
                log.info("model georeferenced by its cameras' up direction and %d priors along a line "
                         "(scale %.4g)", len(pos), fit[0].scale)
        entry = {"georeferenced": bool(m.georeferenced), "priors": 0}
        out["models"].append(entry)
        if not m.georeferenced:
            entry["reason"] = ("its registered images with a position prior do not span two directions (fewer "
                               "than 3, or along one line with cameras that are not upright): the model stays "
                               "in its own frame")
            log.warning("a model of %d images is not georeferenced: %s", int(m.registered.sum()), entry["reason"])
            continue
        residuals = prior_residuals(m, priors)
        flagged = sorted(n for n, (_, z) in residuals.items() if z > max_sigmas)
        good = np.array([d for n, (d, _) in residuals.items() if n not in flagged]).reshape(-1, 3)
        entry.update({"priors": len(residuals), "flagged": flagged,
                      "prior_rms_m": float(np.sqrt(np.mean(np.sum(good**2, axis=1)))) if len(good) else None})
        if flagged:
            log.warning("%d image(s) lie more than %g sigmas from their position prior (a wrong GPS fix?): %s",
                        len(flagged), max_sigmas, ", ".join(f"{n} ({residuals[n][1]:.1f})" for n in flagged[:10]))
        regs = m.registered_images()
        centers = m.centers()[regs]
        lla = from_enu(centers, priors.origin) if priors.origin is not None else None
        for k, j in enumerate(regs.tolist()):
            name = m.names[j]
            info = {"enu" if lla is not None else "xyz": [round(float(v), 4) for v in centers[k]]}
            if lla is not None:
                info.update({"lat": float(lla[k, 0]), "lon": float(lla[k, 1]), "alt": round(float(lla[k, 2]), 4)})
            if name in residuals:
                d, z = residuals[name]
                info.update({"prior_residual_m": [round(float(v), 4) for v in d], "prior_sigmas": round(z, 3),
                             "flagged": name in flagged})
            out["images"][name] = info
        if frame == "ecef":
            R, t = enu_to_ecef(priors.origin)
            transform_model(m, Sim3(1.0, R, t))
    return out
