"""Calibrate the ximea stereo chessboard set with `mvrecon.stereo.calibrate` and print it next to the author's
OpenCV result (intrinsics.yml / extrinsics.yml). Run by hand: .venv/bin/python tools/calib_ximea.py

The principal points are printed in OpenCV pixels (top-left pixel centre at (0, 0)), as the author's files
hold them; the camera.toml of `mvrecon calibrate` is in COLMAP pixels, 0.5 px more in cx and cy."""

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
XIMEA = ROOT.parent / "shared" / "data" / "calib_stereo_chessboard_ximea"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[1],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args(argv)  # no options: --help must not start the calibration
    import cv2

    from mvrecon.geometry.rotation import rotation_error_deg, vector_angle_deg
    from mvrecon.stereo.calibrate import CalibrationConfig, calibrate_stereo, stereo_pairs

    if not XIMEA.is_dir():
        print(f"ximea set not found at {XIMEA}", file=sys.stderr)
        return 1
    names = sorted(p.name for p in (XIMEA / "images").glob("*.jpg"))
    lefts, rights, pairs = stereo_pairs(names)
    read = {n: cv2.imread(str(XIMEA / "images" / n), cv2.IMREAD_GRAYSCALE) for n in names}
    res = calibrate_stereo({n: read[n] for n in lefts}, {n: read[n] for n in rights}, pairs, CalibrationConfig())
    fs = cv2.FileStorage(str(XIMEA / "intrinsics.yml"), cv2.FILE_STORAGE_READ)
    fe = cv2.FileStorage(str(XIMEA / "extrinsics.yml"), cv2.FILE_STORAGE_READ)
    ref = {"M1": fs.getNode("M1").mat(), "M2": fs.getNode("M2").mat(), "R": fe.getNode("R").mat(),
           "T": fe.getNode("T").mat().ravel()}
    print(f"board {res.left.board[0]}x{res.left.board[1]}; {len(pairs)} pairs; dropped views "
          f"{res.left.dropped + res.right.dropped}; dropped pairs {res.dropped_pairs}")
    print("| camera | quantity | ours | author | difference |\n|---|---|---|---|---|")
    for label, mono, M in (("left", res.left, ref["M1"]), ("right", res.right, ref["M2"])):
        K, dist = mono.camera.opencv()
        for q, ours, theirs in (("fx", K[0, 0], M[0, 0]), ("fy", K[1, 1], M[1, 1]), ("cx", K[0, 2], M[0, 2]),
                                ("cy", K[1, 2], M[1, 2])):
            print(f"| {label} | {q} (px, OpenCV pixels) | {ours:.2f} | {theirs:.2f} | "
                  f"{ours - theirs:+.2f} ({100 * (ours - theirs) / theirs:+.2f} %) |")
        print(f"| {label} | RMS reprojection (px) | {mono.rms_px:.3f} | - | - |")
    print(f"| rig | rotation difference (deg) | - | - | {rotation_error_deg(res.R, ref['R']):.3f} |")
    print(f"| rig | baseline direction difference (deg) | - | - | {vector_angle_deg(res.t, ref['T']):.3f} |")
    scale = np.linalg.norm(ref["T"]) / np.linalg.norm(res.t)
    print(f"| rig | baseline (squares; author's units) | {np.linalg.norm(res.t):.4f} | {np.linalg.norm(ref['T']):.3f} "
          f"| implied square size {scale:.2f} author units |")
    print(f"| rig | stereo RMS (px) | {res.rms_px:.3f} | - | - |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
