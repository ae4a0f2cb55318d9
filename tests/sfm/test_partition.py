"""Partitioned mapping: the view-graph partitioner, and a catalog scene mapped in parts and merged against the
same scene mapped whole."""

import json
import re
import shutil

import numpy as np
import pytest

from mvrecon.cli import main
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.io.record import Record
from mvrecon.scenes import make_scene
from mvrecon.scenes.catalog import entry_path
from mvrecon.sfm.config import MapperConfig
from mvrecon.sfm.partition import overlap_for, partition_view_graph
from mvrecon.stages.mapping import map_workspace
from tests.sfm.test_mapper import synthetic_database


def grid_graph(rows: int, cols: int, seed: int = 0) -> np.ndarray:
    """Inlier counts of a survey grid: neighbours along a line strongly matched, across lines less, diagonals
    weakly, with noise."""
    rng = np.random.default_rng(seed)
    n = rows * cols
    W = np.zeros((n, n))
    for r in range(rows):
        for c in range(cols):
            for dr, dc, w in ((0, 1, 400), (0, 2, 150), (1, 0, 250), (1, 1, 80), (1, -1, 80)):
                rr, cc = r + dr, c + dc
                if 0 <= rr < rows and 0 <= cc < cols:
                    a, b = r * cols + c, rr * cols + cc
                    W[a, b] = W[b, a] = w * rng.uniform(0.7, 1.3)
    return W


def shared_graph_connected(parts: list[np.ndarray], least: int) -> bool:
    """Whether the parts, linked where they share `least` images, form one connected graph."""
    seen, todo = {0}, [0]
    while todo:
        a = todo.pop()
        for b in range(len(parts)):
            if b not in seen and len(np.intersect1d(parts[a], parts[b])) >= least:
                seen.add(b)
                todo.append(b)
    return len(seen) == len(parts)


@pytest.mark.parametrize("rows, cols, size", [(5, 8, 15), (4, 25, 30), (1, 40, 12)])
def test_partition_covers_the_graph_with_overlapping_parts_of_at_most_p(rows, cols, size):
    W = grid_graph(rows, cols)
    n = len(W)
    partition = partition_view_graph(W, size)
    cores, parts = partition.cores, partition.parts
    assert len(parts) >= int(np.ceil(n / size)) and all(len(p) <= size for p in parts)
    assert np.array_equal(np.sort(np.concatenate(cores)), np.arange(n))  # cores: disjoint, every image once
    assert all(np.isin(c, p).all() for c, p in zip(cores, parts))
    # every core grew by at least the overlap (or by all its neighbours), and the parts are chained by shared
    # images into one graph
    for c, p in zip(cores, parts):
        neighbours = np.setdiff1d(np.flatnonzero(W[:, c].sum(axis=1) > 0), c)
        assert len(p) - len(c) >= min(overlap_for(size), len(neighbours))
    assert shared_graph_connected(parts, least=2)
    # the cut follows the graph: most of the inlier weight stays inside the cores
    label = np.empty(n, int)
    for k, c in enumerate(cores):
        label[c] = k
    inside = sum(W[np.ix_(c, c)].sum() for c in cores)
    assert inside / W.sum() > 0.6
    # a sequence (one line) is cut into contiguous runs
    if rows == 1:
        assert all(np.ptp(c) == len(c) - 1 for c in cores)


def test_partition_keeps_components_apart_and_small_graphs_whole():
    W = np.zeros((24, 24))
    W[:12, :12] = grid_graph(3, 4)
    W[12:, 12:] = grid_graph(3, 4, seed=1)
    partition = partition_view_graph(W, 10)
    for core in partition.cores:  # no core mixes the two components
        assert (core < 12).all() or (core >= 12).all()
    assert all(len(p) <= 10 for p in partition.parts)
    whole = partition_view_graph(grid_graph(2, 5), 10)
    assert len(whole.parts) == 1 and np.array_equal(whole.parts[0], np.arange(10))
    with pytest.raises(ValueError):
        partition_view_graph(W, 5)


def survey_scene(folder):
    """aerial_survey_small at 40 views, rendered at 480 x 360 without supersampling (12 s of CPU instead of 40)."""
    text = entry_path("aerial_survey_small").read_text()
    for old, new in (("width = 640", "width = 480"), ("height = 480", "height = 360"),
                     ("params = [500.0, 320.0, 240.0, -0.02]", "params = [375.0, 240.0, 180.0, -0.02]"),
                     ("supersample = 2", "supersample = 1"), ("count = 24", "count = 40"),
                     ("points = 6000", "points = 10000")):
        assert re.search(re.escape(old), text), old
        text = text.replace(old, new)
    toml = folder / "aerial_survey_40.toml"
    toml.write_text(text.replace('name = "aerial_survey_small"', 'name = "aerial_survey_40"'))
    return make_scene(str(toml), folder / "scene")


@pytest.mark.slow
def test_partitioned_mapping_merges_all_images_as_accurately_as_one_mapping(tmp_path):
    scene = survey_scene(tmp_path)
    whole, parted = tmp_path / "whole", tmp_path / "parted"
    assert main(["-q", "reconstruct", str(scene / "images"), "-o", str(whole)]) == 0
    shutil.copytree(whole, parted)
    assert main(["-q", "map", "-o", str(parted), "--partition-size", "15", "--overwrite"]) == 0
    gt = load_ground_truth(scene / "gt" / "sparse")
    acc = {ws: accuracy_summary([poses(r) for r in sparse_models(ws / "sparse")], gt) for ws in (whole, parted)}
    assert acc[whole]["registered"] == 40 and acc[whole]["components"] == 1
    assert acc[parted]["registered"] == 40 and acc[parted]["components"] == 1  # all images, one merged model
    assert abs(acc[parted]["auc@5"] - acc[whole]["auc@5"]) <= 0.01
    record = Record(parted / "snapshots" / "parts")
    assert len(record.names()) >= 3 and all(record.report(n)["images"] <= 15 for n in record.names())
    report = json.loads((parted / "report.json").read_text())
    assert all(s["status"] == "registered" and s["model"] == 0 for s in report["images"].values())
    # a resumed run maps no part again: each part's result is the file written before
    stamps = {p: p.stat().st_mtime_ns for p in (parted / "snapshots" / "parts").glob("part-*.pkl")}
    assert main(["-q", "map", "-o", str(parted), "--partition-size", "15", "--resume"]) == 0
    assert stamps and all(p.stat().st_mtime_ns == t for p, t in stamps.items())
    assert len(sparse_models(parted / "sparse")[0].images) == 40


def test_parts_of_a_synthetic_database_merge_into_one_accurate_model(tmp_path):
    """24 views of pycolmap's synthetic scene in parts of at most 10: the merge links every part, and the merged
    model holds every image at the accuracy of the whole mapping."""
    gt = synthetic_database(tmp_path / "database.db", num_images=24, num_points=800)
    summary = map_workspace(MapperConfig(seed=3, partition_size=10), tmp_path)
    acc = accuracy_summary([{m.names[i]: (m.R[i], m.t[i]) for i in m.registered_images()}
                            for m in summary.models], gt)
    assert acc["registered"] == 24 and acc["components"] == 1
    assert acc["median_rotation_error_deg"] < 0.1 and acc["auc@1"] >= 0.9
    assert all(s["status"] == "registered" for s in summary.status.values())
    record = Record(tmp_path / "snapshots" / "parts")
    assert len(record.names()) >= 3


def test_a_partition_size_too_small_to_map_is_refused(tmp_path, capsys):
    assert main(["map", "-o", str(tmp_path), "--partition-size", "5"]) == 2
    assert "--partition-size: partition size must be 0 (no parts) or at least 10, not 5" in capsys.readouterr().err
