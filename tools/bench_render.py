"""How fast is the scene renderer? Frames of a catalog scene at full size, next to pycolmap's synthetic ones.

    .venv/bin/python tools/bench_render.py [--scene object_orbit] [--frames 5]

Prints, per frame of the scene (1024x768, 2x2 supersampling by default): wall time and CPU time of
`Renderer.render`, the share spent in Embree ray casting, and the one-off set-up (textures, rays through the
distortion model). For reference it times `pycolmap.synthesize_images` on a model of the same size, in the
same run and prints the ratio (ours / pycolmap per image). On a busy machine wall time exceeds CPU time; both
are printed so the figure can be read either way. Target: under 2 s per 1024x768 frame.
"""

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mvrecon.scenes.build import build_camera, build_mesh, build_poses, render_settings
from mvrecon.scenes.cameras import CameraRays
from mvrecon.scenes.catalog import load_entry
from mvrecon.scenes.render import Renderer


class Timed:
    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="object_orbit",
                        help="catalog scene to render (`mvrecon scene list`; default object_orbit)")
    parser.add_argument("--frames", type=int, default=5, help="frames of the scene to render (default 5)")
    args = parser.parse_args()

    entry, _, path = load_entry(args.scene)
    cam = build_camera(entry)
    settings, _ = render_settings(entry)
    poses = build_poses(entry)[: args.frames]
    with Timed() as setup:
        renderer = Renderer(build_mesh(entry, path.parent), settings)
    with Timed() as first:
        renderer.render(cam, poses[0])  # also computes the camera's rays once
    print(
        f"scene {args.scene}: {cam.width}x{cam.height}, supersample {settings.supersample}, "
        f"{renderer.mesh.num_triangles} triangles, {len(renderer.mesh.textures)} textures, "
        f"{os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    print(
        f"set-up (textures, Embree scene): {setup.wall:.2f} s wall; first frame incl. camera rays: "
        f"{first.wall:.2f} s wall"
    )
    cast_seconds = []
    _, sample_dirs = CameraRays(cam, settings.supersample).samples
    walls, cpus = [], []
    for k, pose in enumerate(poses):
        with Timed() as t:
            renderer.render(cam, pose, seed=k)
        walls.append(t.wall)
        cpus.append(t.cpu)
        dirs = sample_dirs @ pose[0].astype(np.float32)
        origins = np.broadcast_to((-pose[0].T @ pose[1]).astype(np.float32), dirs.shape)
        with Timed() as c:
            renderer.cast(origins, dirs)
        cast_seconds.append(c.wall)
        print(
            f"frame {k}: {t.wall:.2f} s wall, {t.cpu:.2f} s CPU "
            f"(Embree ray casting of the supersampled rays alone: {c.wall:.2f} s)"
        )
    ours = float(np.median(walls))

    import pycolmap

    opts = pycolmap.SyntheticDatasetOptions(
        num_rigs=1,
        num_frames_per_rig=len(poses),
        num_points3D=2000,
        camera_width=cam.width,
        camera_height=cam.height,
    )
    rec = pycolmap.synthesize_dataset(opts)
    with tempfile.TemporaryDirectory() as tmp, Timed() as ref:
        pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), rec, tmp)
    theirs = ref.wall / len(poses)
    print(
        f"median per frame: {ours:.2f} s wall, {float(np.median(cpus)):.2f} s CPU, "
        f"ray casting {float(np.median(cast_seconds)):.2f} s; target < 2 s: "
        f"{'met' if ours < 2 else 'NOT met'}"
    )
    print(
        f"pycolmap.synthesize_images, same size, same run: {theirs:.2f} s per image; "
        f"ratio ours/pycolmap = {ours / theirs:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
