"""KD-tree vs brute-force ICP (the seed paper's comparison): time, iterations and final RMS on the same inputs.

Usage: OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python tools/bench_icp.py [--sizes 1000,10000,30000,100000]
       [--max-iterations 30] [--brute-cap N]
Each size samples a target of N points on a smooth height field (pixel units, like the SEM pair point sets) and a
source made of the same points plus 0.1 px noise (two pair sets share their SIFT keypoints), moved by a small
rigid motion (0.5 deg, about a pixel). Both variants
run `mvrecon.sem.icp.icp` with the same config and start; only the nearest-neighbour search differs. Prints a
markdown table; the last column is brute-force time / KD-tree time measured in this run.
"""

import argparse
import sys

import numpy as np

from mvrecon.geometry.rotation import angle_axis_to_rotmat
from mvrecon.sem.icp import IcpConfig, icp


def surface_points(n: int, seed: int) -> np.ndarray:
    """n points at a fixed density (one per 4 px^2, like dense SEM pair sets): more points cover a larger area."""
    rng = np.random.default_rng(seed)
    half = np.sqrt(n)
    xy = rng.uniform(-half, half, size=(n, 2))
    z = 20 * np.exp(-((xy[:, 0] - 0.2 * half) ** 2 + (xy[:, 1] + 0.1 * half) ** 2) / (0.4 * half) ** 2) \
        + 8 * np.sin(xy[:, 0] / 25) * np.cos(xy[:, 1] / 40)
    return np.column_stack([xy, z])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1000,10000,30000,100000",
                        help="comma-separated point counts, two table rows each (default "
                             "1000,10000,30000,100000)")
    parser.add_argument("--max-iterations", type=int, default=30,
                        help="ICP iteration cap of both variants (default 30)")
    parser.add_argument("--brute-cap", type=int, default=None,
                        help="above this many points brute force runs only --brute-iterations iterations (compare "
                             "the s / iteration column there); default: no cap, every run goes to convergence")
    parser.add_argument("--brute-iterations", type=int, default=2,
                        help="iterations of brute force above --brute-cap (default 2)")
    args = parser.parse_args(argv)
    config = IcpConfig(max_iterations=args.max_iterations, tolerance=1e-6)
    axis = np.array([0.2, -0.4, 0.9]) / np.linalg.norm([0.2, -0.4, 0.9])
    R = angle_axis_to_rotmat(np.radians(0.5) * axis)
    t = np.array([1.0, -0.8, 0.5])
    icp(surface_points(100, 1), surface_points(100, 1), "kdtree")  # import Open3D before timing
    print("| points | method | time (s) | iterations | s / iteration | final RMS (px) | rotation err (deg) "
          "| brute / KD-tree time |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    for n in (int(s) for s in args.sizes.split(",")):
        target = surface_points(n, seed=1)
        noise = np.random.default_rng(2).normal(0, 0.1, size=(n, 3))
        source = (target + noise - t) @ R  # target frame = R source + t
        kd = None
        for method in ("kdtree", "brute"):
            capped = method == "brute" and args.brute_cap is not None and n > args.brute_cap
            run_config = IcpConfig(max_iterations=args.brute_iterations, tolerance=1e-6) if capped else config
            result = icp(source, target, method, run_config)
            dR = result.matrix[:3, :3] @ R.T
            err = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
            per_iteration = result.seconds / result.iterations
            if method == "kdtree":
                kd, ratio = result, ""
            elif capped:
                ratio = f"{per_iteration / (kd.seconds / kd.iterations):.0f}x per iteration"
            else:
                ratio = f"{result.seconds / kd.seconds:.1f}x"
            label = f"{method} (capped)" if capped else method
            print(f"| {n} | {label} | {result.seconds:.3f} | {result.iterations} | {per_iteration:.4f} | "
                  f"{result.rms:.4f} | {err:.4f} | {ratio} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
