"""Pair selection: exhaustive, sequential with loop closures, spatial by GPS EXIF, unions and a pairs file; `auto`
choosing among them; one-line errors for bad specs and names."""

import logging

import numpy as np
import pytest
from PIL import Image

from mvrecon.errors import InputError
from mvrecon.io.gps import from_enu, gps_exif, read_gps
from mvrecon.matching.pairs import AUTO_EXHAUSTIVE, check_spec, numbered_sequence, plan_pairs, select_pairs
from tests.helpers import orbit_descriptors


def test_pair_selection(tmp_path):
    names = [f"f{i:02d}.jpg" for i in range(6)]
    assert len(select_pairs("exhaustive", names)) == 15
    views = orbit_descriptors(views=6, name="f{:02d}.jpg")
    seq = select_pairs("sequential:2", names, descriptors=views.__getitem__)
    # the window, and the loop closures of frames 0, 2 and 4 with the frames their windows do not reach
    window = {(names[i], names[j]) for i in range(6) for j in range(i + 1, min(6, i + 3))}
    loops = {("f00.jpg", "f03.jpg"), ("f00.jpg", "f04.jpg"), ("f00.jpg", "f05.jpg"), ("f01.jpg", "f04.jpg"),
             ("f02.jpg", "f05.jpg")}
    assert seq == sorted(window | loops) and len(window) == 9
    assert select_pairs("sequential:5", names) == select_pairs("exhaustive", names)  # no frame beyond the window
    pairs_file = tmp_path / "pairs.txt"
    pairs_file.write_text("# my pairs\nf00.jpg f03.jpg\nf03.jpg f00.jpg\n\nf01.jpg f05.jpg  # comment\n")
    assert select_pairs(str(pairs_file), names) == [("f00.jpg", "f03.jpg"), ("f01.jpg", "f05.jpg")]
    pairs_file.write_text("f00.jpg f03.jpg\nf00.jpg nope.jpg\n")
    with pytest.raises(InputError, match=r"pairs.txt:2: unknown image 'nope.jpg'"):
        select_pairs(str(pairs_file), names)
    with pytest.raises(InputError, match="positive integer"):
        select_pairs("sequential:x", names)


@pytest.mark.parametrize("spec,reason", [
    ("spatial:0", "the number of nearest images must be a positive integer, e.g. spatial:10"),
    ("spatial:5:", "the radius must be a positive number of metres, e.g. spatial:10:50"),
    ("spatial:5:-1", "the radius must be a positive number of metres, e.g. spatial:10:50"),
    ("spatial:5:nan", "the radius must be a positive number of metres, e.g. spatial:10:50"),
    ("retrieval:5+", "expected auto, exhaustive, sequential:K, spatial:K[:R], retrieval:K, A+B or an existing "
                     "pairs file"),
    ("auto+retrieval:5", "expected auto, exhaustive, sequential:K, spatial:K[:R], retrieval:K, A+B or an "
                         "existing pairs file"),
])
def test_bad_specs_are_refused_in_one_line(spec, reason):
    with pytest.raises(InputError) as err:
        check_spec(spec)
    assert str(err.value) == f"--pairs {spec}: {reason}"


def test_a_union_is_the_union_of_its_parts():
    names = [f"f{i:02d}.jpg" for i in range(12)]
    views = orbit_descriptors(views=12, points=1200, seen=300, name="f{:02d}.jpg")
    assert check_spec("sequential:2+retrieval:3") == "sequential:2+retrieval:3"
    both = select_pairs("sequential:2+retrieval:3", names, descriptors=views.__getitem__)
    parts = [select_pairs(s, names, descriptors=views.__getitem__) for s in ("sequential:2", "retrieval:3")]
    assert both == sorted(set(parts[0]) | set(parts[1]))


def grid_positions(rows: int, cols: int, spacing: float) -> list[tuple[float, float, float]]:
    """WGS84 positions of a survey grid `spacing` metres apart at 100 m above a point near Zurich, row by row."""
    enu = np.array([[c * spacing, r * spacing, 100.0] for r in range(rows) for c in range(cols)])
    return [tuple(p) for p in from_enu(enu, np.array([47.37, 8.54, 400.0]))]


def test_spatial_pairs_from_exif_gps_are_the_nearest_in_metres_and_within_the_radius(tmp_path):
    names = [f"img{i:02d}.jpg" for i in range(12)]
    for name, lla in zip(names, grid_positions(3, 4, 30.0)):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / name, exif=gps_exif(*lla))

    def gps(name):
        return read_gps(tmp_path / name)

    near = select_pairs("spatial:4", names, positions=gps)
    index = {n: i for i, n in enumerate(names)}
    grid = {n: np.array(divmod(i, 4)) for n, i in index.items()}  # (row, col)
    # the 4 nearest on a 30 m grid: the 2-4 at 30 m, then those at 42 m (diagonal) or 60 m; never farther
    assert max(np.hypot(*(grid[a] - grid[b])) for a, b in near) <= 2.0 + 1e-9
    assert all(any(index[b] in (i + 1, i + 4) for a, b in near if index[a] == i) for i in range(11))
    assert 12 * 4 // 2 <= len(near) <= 12 * 4
    within = select_pairs("spatial:4:31", names, positions=gps)  # only the 4-neighbours at 30 m
    assert set(within) <= set(near) and all(s == 1 for s in [np.abs(grid[a] - grid[b]).sum() for a, b in within])
    assert len(within) == 3 * 3 + 2 * 4  # the grid's 17 edges


def test_spatial_pairs_fall_back_to_retrieval_for_images_without_gps(caplog):
    names = [f"v{i:02d}.png" for i in range(16)]
    views = orbit_descriptors()
    positions = dict(zip(names, grid_positions(4, 4, 30.0)))
    positions["v05.png"] = None
    with caplog.at_level(logging.INFO, logger="mvrecon.matching.pairs"):
        pairs = select_pairs("spatial:2", names, descriptors=views.__getitem__, positions=positions.get)
    assert "spatial:2: 1 of 16 images have no GPS position: paired by retrieval" in caplog.text
    partners = {b if a == "v05.png" else a for a, b in pairs if "v05.png" in (a, b)}
    assert partners == {"v04.png", "v06.png"}  # its orbit neighbours, by appearance


def test_numbered_names_read_as_frames_of_a_video():
    assert numbered_sequence([f"frame_{i:05d}.jpg" for i in range(1, 61)]) == 1.0
    assert numbered_sequence([f"frame_{i:05d}.jpg" for i in range(0, 300, 5)]) == 1.0  # every 5th frame
    assert numbered_sequence([f"{i:08x}_{i * 7919 % 1000:04d}x.jpg" for i in range(60)]) < 0.5
    assert numbered_sequence(["a.jpg", "b.jpg"]) == 0.0


def test_auto_chooses_from_what_the_images_offer(caplog):
    n = AUTO_EXHAUSTIVE + 10
    small = [f"frame_{i:05d}.jpg" for i in range(AUTO_EXHAUSTIVE - 1)]
    plan = plan_pairs("auto", small)  # no descriptors read, no positions needed
    assert plan.spec == "exhaustive" and plan.pairs == select_pairs("exhaustive", small)

    # 300 descriptors a view, 100 more each step: a view shares 200 with the next, 100 with the one after
    frames = orbit_descriptors(views=n, points=100 * n, seen=300, name="frame_{:05d}.jpg")
    names = sorted(frames)
    with caplog.at_level(logging.INFO, logger="mvrecon.matching.pairs"):
        video = plan_pairs("auto", names, descriptors=frames.__getitem__)
    assert video.spec == "sequential:10" and "numbered frames" in video.reason
    assert "pairs auto: sequential:10 (" in caplog.text
    # the closed orbit's loop: the last frames are paired with the first ones
    assert any(a == names[0] and b in names[-3:] for a, b in video.pairs)
    assert len(video.pairs) <= n * 10 + n // 2 * 5

    shuffled = dict(zip(names, (frames[k] for k in np.random.default_rng(0).permutation(names))))
    photos = plan_pairs("auto", names, descriptors=shuffled.__getitem__)  # numbered, but not in visiting order
    assert photos.spec == "retrieval:20" and "not a video" in photos.reason

    lla = dict(zip(names, grid_positions(6, 10, 30.0)))
    survey = plan_pairs("auto", names, descriptors=frames.__getitem__, positions=lla.get)
    assert survey.spec == "spatial:20+retrieval:20" and survey.reason == f"{n} of {n} images have a GPS position"
    assert len(survey.pairs) <= n * 40

    unnamed = {f"{k:03d}_{k * 37 % 101:03d}.jpg": v for k, v in enumerate(frames.values())}  # not one sequence
    plan = plan_pairs("auto", sorted(unnamed), descriptors=unnamed.__getitem__)
    assert plan.spec == "retrieval:20" and len(plan.pairs) < n * (n - 1) // 2
