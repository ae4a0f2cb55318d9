"""Scene cameras and trajectories: which rays each pixel casts, and where the cameras stand.

Poses are COLMAP's cam_from_world (R, t): x right, y down, z forward, centre -R^T t. Perspective cameras
cast rays through the distortion model (pixel -> undistorted normalised coordinates), so distortion in the
images is exactly the one stored in the ground-truth camera. Orthographic cameras (SEM) cast parallel rays;
their scale is the pixel size in scene units (micrometres for SEM).
"""

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..geometry import camera as camera_model
from ..geometry.rotation import angle_axis_to_rotmat


@dataclass(frozen=True)
class PerspectiveCamera:
    """A COLMAP camera: model name, image size and parameter tuple (COLMAP pixel convention)."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self):
        object.__setattr__(
            self, "params", tuple(float(p) for p in camera_model.check_model(self.model, self.params))
        )

    def ray_directions(self, pixels: np.ndarray) -> np.ndarray:
        """Camera-frame directions (N,3) with z = 1 through pixels (N,2): a hit's t is its z-depth."""
        xy = camera_model.pixels_to_normalized(self.model, self.params, pixels)
        return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)

    def ray_origins(self, pixels: np.ndarray) -> np.ndarray:
        return np.zeros((len(pixels), 3))

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        return camera_model.project(self.model, self.params, points_cam)


@dataclass(frozen=True)
class OrthographicCamera:
    """Parallel projection along the camera z axis; pixel (u, v) sees camera x = (u - w/2) * pixel_size."""

    width: int
    height: int
    pixel_size: float  # scene units (micrometres for SEM) per pixel

    def ray_directions(self, pixels: np.ndarray) -> np.ndarray:
        return np.tile([0.0, 0.0, 1.0], (len(pixels), 1))

    def ray_origins(self, pixels: np.ndarray) -> np.ndarray:
        xy = (np.asarray(pixels, float) - [self.width / 2, self.height / 2]) * self.pixel_size
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        return np.asarray(points_cam, float)[..., :2] / self.pixel_size + [self.width / 2, self.height / 2]


def pixel_grid(width: int, height: int, supersample: int = 1) -> np.ndarray:
    """Sample positions (H*s*W*s, 2), row-major, at the centres of an s x s split of each pixel (COLMAP)."""
    s = supersample
    offsets = (np.arange(s) + 0.5) / s
    u = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    U, V = np.meshgrid(u, v)
    return np.stack([U.ravel(), V.ravel()], axis=1)


@dataclass(frozen=True)
class CameraRays:
    """Camera-frame rays of every sample of one camera, computed once and reused for each pose."""

    cam: PerspectiveCamera | OrthographicCamera
    supersample: int

    @cached_property
    def samples(self) -> tuple[np.ndarray | None, np.ndarray]:
        """(origins or None when all rays start at the centre, directions), float32, camera frame."""
        return self._rays(pixel_grid(self.cam.width, self.cam.height, self.supersample))

    @cached_property
    def centres(self) -> tuple[np.ndarray | None, np.ndarray]:
        return self._rays(pixel_grid(self.cam.width, self.cam.height, 1))

    def _rays(self, px):
        origins = (
            None if isinstance(self.cam, PerspectiveCamera) else self.cam.ray_origins(px).astype(np.float32)
        )
        return origins, self.cam.ray_directions(px).astype(np.float32)


def look_at(
    center: Sequence[float] | np.ndarray,
    target: Sequence[float] | np.ndarray,
    up: Sequence[float] | np.ndarray = (0.0, 0.0, 1.0),
    roll_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at `center` looking at `target`, world `up` up in the image."""
    center, target, up = (np.asarray(a, dtype=float) for a in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: any right vector will do
        x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    if roll_deg:
        c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ R
    return R, -R @ center


def orbit(
    count: int,
    radius: float,
    height: float,
    target: Sequence[float] | np.ndarray = (0, 0, 0),
    start_deg: float = 0.0,
    arc_deg: float = 360.0,
    height_wobble: float = 0.0,
    roll_wobble_deg: float = 0.0,
) -> list:
    """Cameras on a horizontal circle around `target`, all looking at it (a turntable seen from outside).

    A full circle spaces `count` views evenly; a partial arc includes both ends. The wobbles vary height, roll
    sinusoidally so that the centres are not coplanar and rotations are not all about one axis.
    """
    target = np.asarray(target, float)
    full = abs(arc_deg - 360.0) < 1e-9
    angles = start_deg + arc_deg * np.arange(count) / (count if full else max(count - 1, 1))
    poses = []
    for k, a in enumerate(np.radians(angles)):
        phase = 2 * np.pi * k / max(count, 1) * 2
        c = target + [radius * np.cos(a), radius * np.sin(a), height + height_wobble * np.sin(phase)]
        poses.append(look_at(c, target, roll_deg=roll_wobble_deg * np.cos(phase)))
    return poses


def handheld(
    count: int,
    radius: float,
    height: float,
    target: Sequence[float] | np.ndarray = (0, 0, 0),
    start_deg: float = 0.0,
    arc_deg: float = 90.0,
    jitter: float = 0.0,
    jitter_deg: float = 0.0,
    pace: float = 0.0,
    shake_deg: float = 0.0,
    seed: int = 0,
) -> list:
    """Frames of a phone video walked around `target` along an arc (both ends included), with a hand's sway.

    The centre wanders off the arc by about `jitter` (scene units, per axis) and the view turns off the target
    by about `jitter_deg` in pan, tilt and roll: seeded smooth noise, three sinusoids per axis with periods of
    6-40 frames and random phases, so that neighbouring frames stay close as a video's do while the path is
    no circle and the rotations are about every axis. `pace` varies the walking speed the same way (relative
    standard deviation; the speed never falls below a tenth of the mean): frames sampled at a fixed rate are
    then unevenly spaced, bunched where the walker slows down. `shake_deg` adds a hand's shake, a rotation
    drawn anew for each frame (standard deviation per axis): frames taken a good fraction of a second apart
    from a video do not share it.
    """
    rng = np.random.default_rng(seed)
    k = np.arange(count)[:, None]
    periods = rng.uniform(6.0, 40.0, (7, 3))
    phases = rng.uniform(0.0, 2 * np.pi, (7, 3))
    # (count, 7) smooth noise with a standard deviation about 1 per axis (3 sinusoids of variance 1/2 each):
    # position x, y, z, rotation about the camera's x, y, z, speed
    wander = np.stack([np.sin(2 * np.pi * k / periods[a] + phases[a]).sum(1) for a in range(7)], 1)
    wander *= np.sqrt(2.0 / 3.0)
    target = np.asarray(target, float)
    steps = np.maximum(1.0 + pace * wander[:-1, 6], 0.1)  # the walk from each frame to the next
    progress = np.concatenate([[0.0], np.cumsum(steps)]) / max(steps.sum(), 1e-12)
    angles = np.radians(start_deg + arc_deg * progress)
    shake = rng.normal(0.0, 1.0, (count, 3))
    poses = []
    for j, a in enumerate(angles):
        c = target + [radius * np.cos(a), radius * np.sin(a), height] + jitter * wander[j, :3]
        R, _ = look_at(c, target)
        turn = np.radians(jitter_deg) * wander[j, 3:6] + np.radians(shake_deg) * shake[j]
        R = angle_axis_to_rotmat(turn) @ R  # tilt, pan, roll (camera x, y, z)
        poses.append((R, -R @ c))
    return poses


def forward(
    count: int,
    start: Sequence[float] | np.ndarray,
    direction: Sequence[float] | np.ndarray,
    step: float,
    look_distance: float = 10.0,
    sway: float = 0.0,
    yaw_wobble_deg: float = 0.0,
) -> list:
    """A camera moving along `direction` (a street or a video): `step` apart, sideways `sway` wobble."""
    start, direction = np.asarray(start, float), np.asarray(direction, float)
    direction /= np.linalg.norm(direction)
    side = np.cross(direction, [0.0, 0.0, 1.0])
    poses = []
    for k in range(count):
        phase = 2 * np.pi * k / 20.0
        c = start + k * step * direction + sway * np.sin(phase) * side
        yaw = np.radians(yaw_wobble_deg * np.sin(phase + 1.0))
        look = np.cos(yaw) * direction + np.sin(yaw) * side
        poses.append(look_at(c, c + look_distance * look))
    return poses


def hemisphere(
    count: int,
    radius_min: float,
    radius_max: float,
    target: Sequence[float] | np.ndarray = (0, 0, 0),
    elevation_min_deg: float = 15.0,
    elevation_max_deg: float = 70.0,
    seed: int = 0,
) -> list:
    """Random (seeded) views on a shell above `target`, all looking at it."""
    rng = np.random.default_rng(seed)
    target = np.asarray(target, float)
    poses = []
    for _ in range(count):
        az = rng.uniform(0, 2 * np.pi)
        el = np.radians(rng.uniform(elevation_min_deg, elevation_max_deg))
        r = rng.uniform(radius_min, radius_max)
        c = target + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        poses.append(look_at(c, target))
    return poses


def inward(
    count: int,
    radius: float,
    height: float,
    center: Sequence[float] | np.ndarray = (0, 0, 0),
    look_height: float | None = None,
    across: float = 3.0,
) -> list:
    """Cameras inside a room on a circle of `radius`, each looking across the centre at the opposite wall."""
    center = np.asarray(center, float)
    poses = []
    for a in 2 * np.pi * np.arange(count) / count:
        d = np.array([np.cos(a), np.sin(a), 0.0])
        c = center + radius * d + [0, 0, height]
        t = center - across * d + [0, 0, height if look_height is None else look_height]
        poses.append(look_at(c, t))
    return poses


def stereo_pair(
    center: Sequence[float] | np.ndarray, target: Sequence[float] | np.ndarray, baseline: float
) -> list:
    """A rectified pair: the same rotation, the right camera `baseline` along the left camera's x axis."""
    R, t = look_at(center, target)
    c1 = np.asarray(center, float) + baseline * R[0]
    return [(R, t), (R.copy(), -R @ c1)]


def tilt_series(
    angles_deg: Sequence[float],
    distance: float,
    axis: str = "y",
    eucentric: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
) -> list:
    """Orthographic views of a specimen in the world x-y plane, tilted about a world axis through `eucentric`.

    At 0 degrees the camera looks straight down (-z) with image x along world x and image y along world -y,
    so the 0-degree image grid is the specimen's top view. `distance` puts the ray origins above the specimen.
    """
    axis_vec = {"x": [1.0, 0, 0], "y": [0, 1.0, 0]}[axis]
    R0 = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    p = np.asarray(eucentric, float)
    poses = []
    for a in angles_deg:
        R = R0 @ angle_axis_to_rotmat(np.radians(a) * np.asarray(axis_vec)).T  # the specimen turns by +a
        t = -R @ p + [0.0, 0.0, distance]
        poses.append((R, t))
    return poses


def survey(
    count: int,
    altitude: float,
    along: float,
    across: float,
    oblique_every: int = 0,
    oblique_deg: float = 0.0,
    jitter: float = 0.0,
    jitter_deg: float = 0.0,
    seed: int = 0,
) -> list:
    """A drone's lawn-mower survey at `altitude` over the x-y plane, centred on the origin.

    Flight lines run along y (north), `across` apart, flown alternately north and south; the views on a line
    are `along` apart, the image's vertical axis along the flight (the short side of a landscape frame, as
    survey drones fly). The grid is about square in metres, so more views cover a larger area at the same
    overlap (forward overlap = 1 - along / footprint). Every `oblique_every`-th view is pitched `oblique_deg`
    forward from nadir (0: all nadir). `jitter` (metres, per axis) and `jitter_deg` (yaw, roll, pitch) are a
    seeded wind's offsets from the plan.
    """
    rng = np.random.default_rng(seed)
    per_line = max(2, int(round(np.sqrt(count * across / along))))
    lines = max(1, int(np.ceil(count / per_line)))
    sizes = [count // lines + (k < count % lines) for k in range(lines)]
    poses = []
    for line, n in enumerate(sizes):
        x = (line - (lines - 1) / 2) * across
        heading = 1.0 if line % 2 == 0 else -1.0
        ys = (np.arange(n) - (n - 1) / 2) * along * heading
        for y in ys:
            k = len(poses)
            c = np.array([x, y, altitude]) + jitter * rng.normal(size=3)
            pitch = oblique_deg if oblique_every and k % oblique_every == oblique_every - 1 else 0.0
            pitch = np.radians(pitch)
            ahead = np.array([0.0, heading, 0.0])
            look = np.cos(pitch) * np.array([0.0, 0.0, -1.0]) + np.sin(pitch) * ahead
            R, _ = look_at(c, c + look, up=ahead)  # the image top points along the flight
            R = angle_axis_to_rotmat(np.radians(jitter_deg) * rng.normal(size=3)) @ R
            poses.append((R, -R @ c))
    return poses


def loop(
    count: int,
    step: float,
    height: float,
    aspect: float = 1.5,
    corner_radius: float = 4.0,
    look_distance: float = 10.0,
    sway: float = 0.0,
    yaw_wobble_deg: float = 0.0,
) -> list:
    """Forward motion once around a block: a rounded rectangle (corners of `corner_radius`, sides in the ratio
    `aspect`) centred on the origin, `count` views `step` apart, whose length is count * step: the last view
    stands one step before the first, so the loop closes. Starts in the middle of the south side heading east
    (counter-clockwise); each camera looks along the path, with a sideways `sway` and a yaw wobble.
    """
    r = corner_radius
    perimeter = count * step
    ly = (perimeter + 8 * r - 2 * np.pi * r) / (2 * (aspect + 1))
    lx = aspect * ly
    if min(lx, ly) <= 2 * r:
        raise ValueError(f"loop: {count} views {step} apart make a loop too short for corners of radius {r}")
    sx, sy = lx - 2 * r, ly - 2 * r  # straight parts
    # the path from the middle of the south side: straights and left-turning quarter circles, as
    # (straight length or None for a turn, start point, heading at the start)
    pieces, pos, angle = [], np.array([0.0, -ly / 2]), 0.0
    for straight in (sx / 2, sy, sx, sy, sx / 2):
        pieces.append((straight, pos, angle))
        pos = pos + straight * np.array([np.cos(angle), np.sin(angle)])
        pieces.append((None, pos, angle))
        pos = pos + r * np.array([np.cos(angle) - np.sin(angle), np.sin(angle) + np.cos(angle)])
        angle += np.pi / 2
    pieces.pop()  # back at the start
    poses = []
    for k in range(count):
        s = k * step
        for straight, start, a0 in pieces:
            length = np.pi / 2 * r if straight is None else straight
            if s <= length:
                break
            s -= length
        if straight is None:
            a = a0 + s / r
            centre = start + r * np.array([-np.sin(a0), np.cos(a0)])
            p = centre + r * np.array([np.sin(a), -np.cos(a)])
        else:
            a = a0
            p = start + s * np.array([np.cos(a0), np.sin(a0)])
        phase = 2 * np.pi * k / 20.0
        direction = np.array([np.cos(a), np.sin(a), 0.0])
        side = np.array([np.sin(a), -np.cos(a), 0.0])
        c = np.array([p[0], p[1], height]) + sway * np.sin(phase) * side
        yaw = np.radians(yaw_wobble_deg * np.sin(phase + 1.0))
        look = np.cos(yaw) * direction + np.sin(yaw) * side
        poses.append(look_at(c, c + look_distance * look))
    return poses


def rings(
    count: int,
    radius: float,
    heights: Sequence[float],
    target: Sequence[float] = (0, 0, 0),
) -> list:
    """Cameras on horizontal rings around `target`, one per entry of `heights` (above the target), all looking
    at it: `count` views shared out evenly (a dense capture of an object), each ring turned half a step from
    the one below so that no two views stand above one another."""
    heights = list(heights)
    sizes = [count // len(heights) + (k < count % len(heights)) for k in range(len(heights))]
    poses = []
    for k, (n, h) in enumerate(zip(sizes, heights)):
        poses += orbit(n, radius, h, target, start_deg=180.0 / n * k)
    return poses
