"""The detector comparison: one interface for six detectors, repeatability under a known warp, verified matches on
a real pair, and the `detectors` command's tables."""

from pathlib import Path

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.features.detectors import (
    DETECTORS,
    detect,
    repeatability,
    synthetic_homography,
    verified_inliers,
    warp_repeatability,
)
from tests.helpers import DATA

CONES = DATA / "stereo_middlebury2003_cones_gray"


def test_repeatability_counts_reappearing_points():
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(50, 350, 200), rng.uniform(50, 250, 200)])
    H = synthetic_homography((300, 400), 15, 0.9)
    moved = np.column_stack([pts, np.ones(len(pts))]) @ H.T
    moved = moved[:, :2] / moved[:, 2:]
    assert repeatability(pts, moved, H, (300, 400), (300, 400)) == pytest.approx(1.0)
    half = moved.copy()
    half[::2] += 10.0  # half the points move away
    assert repeatability(pts, half, H, (300, 400), (300, 400)) == pytest.approx(0.5, abs=0.05)


@pytest.fixture(scope="module")
def cones():
    from mvrecon.io.images import read_image

    if not CONES.is_dir():
        pytest.skip(f"Cones pair not found at {CONES}")
    return read_image(CONES / "left.png"), read_image(CONES / "right.png")


def _chance_repeatability(n1, n2, H, shape, rng) -> float:
    """Repeatability of uniformly random points in the same numbers: dense detectors (FAST, ORB) score 0.5-0.6
    by chance alone within the 2.5 px tolerance."""
    h, w = shape[:2]
    draws = [repeatability(rng.uniform((0, 0), (w, h), (n1, 2)), rng.uniform((0, 0), (w, h), (n2, 2)), H, shape,
                           shape) for _ in range(3)]
    return float(np.mean(draws))


def test_every_detector_finds_repeatable_keypoints(cones):
    import cv2

    left, right = cones
    H = synthetic_homography(left.shape, 20, 0.8)
    gray = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY) if left.ndim == 3 else left
    warped = cv2.warpPerspective(gray, H, (gray.shape[1], gray.shape[0]))
    rng = np.random.default_rng(0)
    for name in DETECTORS:
        det = detect(name, left)
        assert len(det.keypoints) > 100, name
        assert det.descriptors is not None and len(det.descriptors) == len(det.keypoints), name
        rep = warp_repeatability(name, left, H)
        chance = _chance_repeatability(len(det.keypoints), len(detect(name, warped).keypoints), H, gray.shape, rng)
        # the share of what chance leaves that the detector repeats (measured 0.51 for ORB to 0.77 for BRISK)
        assert rep > 0.5 and (rep - chance) / (1 - chance) > 0.4, (name, rep, chance)
    a, b = detect("SIFT", left), detect("SIFT", right)
    assert verified_inliers(a, b, "SIFT") > 300
    with pytest.raises(ValueError, match="unknown detector"):
        detect("HARRIS", left)


def test_detectors_command_writes_tables(tmp_path, cones, capsys):
    import cv2

    left, right = cones
    for name, img in (("a0.png", left), ("a1.png", right)):
        cv2.imwrite(str(tmp_path / name), img[:200, :300])
    out = tmp_path / "table.md"
    assert main(["detectors", str(tmp_path / "a0.png"), str(tmp_path / "a1.png"), "--pairs", "-o", str(out),
                 "--detectors", "SIFT,FAST,ORB", "-q"]) == 0
    text = out.read_text()
    assert "| a0.png |" in text and "verified inliers" in text
    rows = (tmp_path / "table.csv").read_text().splitlines()
    assert rows[0].startswith("image,SIFT keypoints") and len(rows) == 3
    import csv

    table = list(csv.DictReader(rows))  # the numbers themselves (measured 555-1959 keypoints, 72-81 %)
    for row in table:
        for name in ("SIFT", "FAST", "ORB"):
            assert int(row[f"{name} keypoints"]) > 300 and float(row[f"{name} repeatability %"]) > 50, row
    # the pair's verified inliers (measured SIFT 244, FAST 701, ORB 653); the second row holds none
    assert int(table[0]["SIFT inliers"]) > 120 and min(int(table[0][f"{n} inliers"]) for n in ("FAST", "ORB")) > 300
    assert table[0]["pair"] == "a0.png / a1.png" and table[1]["SIFT inliers"] == ""
    (tmp_path / "b.png").write_bytes((tmp_path / "a0.png").read_bytes()[:500])  # cut off: left out
    assert main(["detectors", str(tmp_path), "-o", str(out), "--detectors", "SIFT", "-q"]) == 0
    assert len((tmp_path / "table.csv").read_text().splitlines()) == 3
    (tmp_path / "b.png").unlink()
    capsys.readouterr()
    assert main(["detectors", str(tmp_path / "a0.png"), "--pairs", "-o", str(out)]) == 2
    assert "even number" in capsys.readouterr().err
    assert main(["detectors", str(tmp_path / "a0.png"), "--detectors", "HARRIS", "-o", str(out)]) == 2


def test_detectors_command_checks_its_output_and_options_before_the_work(tmp_path, capsys, monkeypatch):
    import cv2

    import mvrecon.features.detectors as detectors

    def no_work(*args, **kwargs):
        raise AssertionError("detected before the output was checked")

    monkeypatch.setattr(detectors, "detect", no_work)
    rng = np.random.default_rng(0)
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    for path in (a, b):
        cv2.imwrite(str(path), rng.integers(0, 255, (64, 64), dtype=np.uint8))
    original = b.read_bytes()
    (tmp_path / "folder").mkdir()
    (tmp_path / "b.csv").write_bytes(b"x")  # given as an input: the CSV written next to b.md would replace it
    for inputs, output, culprit, reason in (
            ([a, b], b, b, "is one of the input images"),
            ([a, tmp_path / "b.csv"], tmp_path / "b.md", tmp_path / "b.csv", "is one of the input images"),
            ([a, b], tmp_path / "folder", tmp_path / "folder", "is a folder"),
            ([a, b], Path("/proc/d.md"), Path("/proc/d.md"), "cannot write in /proc")):
        capsys.readouterr()
        assert main(["detectors", *map(str, inputs), "-o", str(output), "-q"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"mvrecon: error: {culprit}: {reason}") and err.count("\n") == 1, err
    assert b.read_bytes() == original and (tmp_path / "b.csv").read_bytes() == b"x"
    assert main(["detectors", str(a), "-o", str(tmp_path / "t.md"), "--detectors", " ,", "-q"]) == 2
    assert "--detectors ' ,': no detector given" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["detectors", str(a), "-o", str(tmp_path / "t.md"), "--angle", "nan"])
    assert exc.value.code == 2 and "--angle: must be a finite number" in capsys.readouterr().err
    assert not (tmp_path / "t.md").exists()


def test_detectors_command_resumes_after_ctrl_c(tmp_path, cones, monkeypatch, capsys, caplog):
    """Ctrl-C while the third image is measured, then the same command: only the missing images (and the pair they
    form) are computed, and the tables are byte for byte those of an uninterrupted run. Reused figures keep the time
    measured when they were computed, and the log names them."""
    import types

    import cv2

    import mvrecon.features.detectors as detectors

    left, right = cones
    crops = {"a0.png": left[:160, :240], "a1.png": right[:160, :240], "b0.png": left[150:310, 100:340],
             "b1.png": right[150:310, 100:340]}
    for name, img in crops.items():
        cv2.imwrite(str(tmp_path / name), img)
    which = {img.tobytes(): name for name, img in crops.items()}
    clock = {"now": 0.0, "step": 0.001}  # detection times that do not depend on the machine: one step each

    def perf_counter():
        clock["now"] += clock["step"]
        return clock["now"]

    monkeypatch.setattr(detectors, "time", types.SimpleNamespace(perf_counter=perf_counter))
    measured, verified = [], []  # (image, detector) measured; pairs verified
    warp_repeatability, verified_inliers = detectors.warp_repeatability, detectors.verified_inliers

    def counted(name, image, H, **kwargs):  # once per image and detector
        measured.append((which[image.tobytes()], name))
        if len(measured) == stop_at:
            raise KeyboardInterrupt
        return warp_repeatability(name, image, H, **kwargs)

    monkeypatch.setattr(detectors, "warp_repeatability", counted)
    monkeypatch.setattr(detectors, "verified_inliers", lambda *a, **k: verified.append(1) or verified_inliers(*a, **k))

    def run(out, *extra):
        measured.clear()
        verified.clear()
        return main(["detectors", *(str(tmp_path / n) for n in crops), "--pairs", "-o", str(tmp_path / out),
                     "--detectors", "SIFT,FAST,ORB", *extra])

    stop_at = None
    assert run("ref/t.md", "-q") == 0 and len(measured) == 12 and len(verified) == 6
    stop_at = 8  # b0.png: SIFT measured, FAST cut off
    capsys.readouterr()
    assert run("cut/t.md", "-q") == 130
    interrupted = capsys.readouterr().err
    assert not (tmp_path / "cut" / "t.md").exists() and not (tmp_path / "cut" / "t.csv").exists()
    stop_at = None
    with caplog.at_level("INFO", logger="mvrecon"):
        assert run("cut/t.md") == 0
    assert measured == [("b0.png", "FAST"), ("b0.png", "ORB"), ("b1.png", "SIFT"), ("b1.png", "FAST"),
                        ("b1.png", "ORB")]
    assert len(verified) == 3  # the pair b0 / b1 only
    assert interrupted == ("mvrecon: interrupted; the images done are kept next to the table (in .stages); rerun "
                           "the same command to continue\n")
    for table in ("t.md", "t.csv"):
        assert (tmp_path / "cut" / table).read_bytes() == (tmp_path / "ref" / table).read_bytes(), table
    assert ("with the times measured then: 3 of 4 images: a0.png, a1.png, b0.png (SIFT); "
            "1 of 2 pairs: a0.png / a1.png") in caplog.text
    # everything reused: the slower clock shows nowhere (the times are those measured then)
    clock["step"] = 0.005
    caplog.clear()
    with caplog.at_level("INFO", logger="mvrecon"):
        assert run("cut/t.md") == 0 and measured == [] and verified == []
    assert "with the times measured then: all 4 images; all 2 pairs" in caplog.text
    assert (tmp_path / "cut" / "t.md").read_bytes() == (tmp_path / "ref" / "t.md").read_bytes()
    # another setting: every image again; another pixel in b1.png: that image and its pair only
    assert run("cut/t.md", "--angle", "25", "-q") == 0 and len(measured) == 12
    img = crops["b1.png"].copy()
    img[0, 0] = 255 - img[0, 0]
    cv2.imwrite(str(tmp_path / "b1.png"), img)
    which[img.tobytes()] = "b1.png"
    assert run("cut/t.md", "--angle", "25", "-q") == 0
    assert measured == [("b1.png", n) for n in ("SIFT", "FAST", "ORB")] and len(verified) == 3
