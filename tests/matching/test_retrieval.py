"""`--pairs retrieval:K`: each image matched with the K images nearest by a VLAD vector of its own SIFT
descriptors. Refusals, determinism, the fallbacks, the ranking of true neighbours, and on a ground-truth scene
fewer pairs with every image registered and the accuracy of exhaustive matching."""

import json
import logging

import numpy as np
import pytest

from mvrecon import database as dbmod
from mvrecon.cli import main
from mvrecon.errors import InputError
from mvrecon.eval.ground_truth import load_ground_truth
from mvrecon.eval.metrics import accuracy_summary
from mvrecon.eval.models import poses, sparse_models
from mvrecon.eval.overlap import overlapping_pairs, pair_recall
from mvrecon.matching.pairs import check_spec, select_pairs
from mvrecon.matching.retrieval import nearest, similarities
from mvrecon.stages.common import FrontendConfig
from mvrecon.stages.matching import match
from tests.helpers import orbit_descriptors


@pytest.mark.parametrize("spec,reason", [
    ("retrieval:0", "the number of nearest images must be a positive integer, e.g. retrieval:10"),
    ("retrieval:x", "the number of nearest images must be a positive integer, e.g. retrieval:10"),
    ("retrieval:-3", "the number of nearest images must be a positive integer, e.g. retrieval:10"),
    ("retrieval:", "the number of nearest images must be a positive integer, e.g. retrieval:10"),
    ("retrieval:²", "the number of nearest images must be a positive integer, e.g. retrieval:10"),
    ("retrieval", "expected auto, exhaustive, sequential:K, spatial:K[:R], retrieval:K, A+B or an existing "
                  "pairs file"),
])
def test_bad_retrieval_specs_are_refused_in_one_line(spec, reason, tmp_path, capsys):
    with pytest.raises(InputError) as err:
        check_spec(spec)
    assert str(err.value) == f"--pairs {spec}: {reason}"
    assert main(["match", "-w", str(tmp_path / "ws"), "--pairs", spec]) == 2
    assert capsys.readouterr().err == f"mvrecon: error: --pairs {spec}: {reason}\n"
    assert not (tmp_path / "ws").exists()


def test_retrieval_spec_is_accepted_from_flag_and_config_file(tmp_path, capsys):
    assert check_spec("retrieval:10") == "retrieval:10"
    toml = tmp_path / "c.toml"
    toml.write_text('pairs = "retrieval:0"\n')
    assert main(["match", "-w", str(tmp_path / "ws"), "--config", str(toml)]) == 2
    assert f"{toml}: pairs = 'retrieval:0': the number of nearest images" in capsys.readouterr().err


def test_retrieval_pairs_each_view_with_its_orbit_neighbours_deterministically(caplog):
    views = orbit_descriptors()
    names = sorted(views)
    reads = []

    def read(name):
        reads.append(name)
        return views[name]

    with caplog.at_level(logging.INFO, logger="mvrecon"):
        pairs = select_pairs("retrieval:2", names, descriptors=read)
    # each view's 2 nearest are its 2 orbit neighbours: the union is the ring, 16 of the 120 pairs
    ring = {tuple(sorted((names[i], names[(i + 1) % 16]))) for i in range(16)}
    assert set(pairs) == ring and len(pairs) == 16
    assert all(a < b for a, b in pairs) and pairs == sorted(pairs)
    assert "retrieval:2: 16 of the 120 pairs of 16 images selected in" in caplog.text
    assert sorted(reads) == sorted(names * 2)  # every image read twice: sample, then encode
    assert select_pairs("retrieval:2", list(reversed(names)), descriptors=views.__getitem__) == pairs
    # K = 4 reaches i +- 2 (400 shared points) before anything sharing less
    wider = select_pairs("retrieval:4", names, descriptors=views.__getitem__)
    assert {(a, b) for a, b in wider} >= ring and len(wider) < 120
    assert all(min(abs(int(a[1:3]) - int(b[1:3])), 16 - abs(int(a[1:3]) - int(b[1:3]))) <= 3 for a, b in wider)


def test_near_ties_after_query_expansion_are_ranked_by_the_raw_vectors():
    # rows 0 and 1 expanded to the same vector (the two ends of a chain of views), 1e-9 apart: row 2 is as
    # similar to both, and its raw vector is nearer row 1's
    expanded = similarities(np.array([[1.0, 0.0, 0.0], [1.0, 1e-9, 0.0], [0.5, 0.0, 0.75 ** 0.5]]))
    raw = similarities(np.array([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0], [0.0, 0.8, 0.6]]))
    assert nearest(expanded, 1)[2, 0] == 0  # by index alone
    assert nearest(expanded, 1, tiebreak=raw)[2, 0] == 1
    assert nearest(expanded, 2, tiebreak=raw).tolist() == [[1, 2], [0, 2], [1, 0]]
    # a real difference in the expanded similarity is not overruled by the raw vectors
    apart = np.array([[1.0, 0.0, 0.0], [1.0, 0.01, 0.0] / np.linalg.norm([1.0, 0.01, 0.0]), [0.5, 0.0, 0.75 ** 0.5]])
    assert nearest(similarities(apart), 1, tiebreak=raw)[2, 0] == 0  # row 2's similarity to row 1: 0.499975


def test_few_images_or_images_without_descriptors_fall_back_to_exhaustive(caplog):
    views = orbit_descriptors(views=6)
    names = sorted(views)

    def never(name):
        raise AssertionError(f"read {name}: with N <= K + 1 no descriptor is needed")

    with caplog.at_level(logging.INFO, logger="mvrecon"):
        assert select_pairs("retrieval:5", names, descriptors=never) == select_pairs("exhaustive", names)
    assert "retrieval:5 on 6 images: each has at most 5 others, so all 15 pairs are matched" in caplog.text
    caplog.clear()
    views["v02.png"] = np.zeros((0, 128), np.uint8)
    with caplog.at_level(logging.INFO, logger="mvrecon"):
        pairs = select_pairs("retrieval:1", names, descriptors=views.__getitem__)
    with_empty = [p for p in pairs if "v02.png" in p]
    assert len(with_empty) == 5  # paired with every other image
    assert "retrieval:1: 1 image(s) without descriptors (v02.png) are paired with every other image" in caplog.text
    assert len(pairs) < 15


@pytest.fixture(scope="module")
def orbit_runs(object_orbit_small, tmp_path_factory):
    root, scene = tmp_path_factory.mktemp("retrieval"), object_orbit_small
    runs = {}
    for spec in ("exhaustive", "retrieval:3"):
        out = root / spec.replace(":", "")
        assert main(["-q", "reconstruct", str(scene / "images"), "-o", str(out), "--pairs", spec]) == 0
        runs[spec] = out
    return scene, runs


def test_retrieval_on_an_orbit_matches_fewer_pairs_with_the_accuracy_of_exhaustive(orbit_runs):
    scene, runs = orbit_runs
    gt = load_ground_truth(scene / "gt" / "sparse")
    acc = {spec: accuracy_summary([poses(m) for m in sparse_models(out / "sparse")], gt)
           for spec, out in runs.items()}
    # a rerun of the matching stage selects the same pairs and finds them all done (the same database gives
    # the same pairs)
    selected = {spec: match(FrontendConfig(pairs=spec), out) for spec, out in runs.items()}
    assert all(summary.num_matched == 0 for summary in selected.values())
    assert selected["exhaustive"].num_pairs == 45
    assert 10 <= selected["retrieval:3"].num_pairs <= 30  # the union of 10 lists of 3
    assert acc["retrieval:3"]["registered"] == acc["exhaustive"]["registered"] == 10
    assert acc["retrieval:3"]["auc@5"] >= acc["exhaustive"]["auc@5"] - 0.02
    report = json.loads((runs["retrieval:3"] / "report.json").read_text())
    assert report["pairs"] == {"strategy": "retrieval:3", "reason": "given",
                               "pairs": selected["retrieval:3"].num_pairs}


def test_retrieval_finds_the_overlapping_pairs(orbit_runs):
    scene, runs = orbit_runs
    with dbmod.open_database(runs["retrieval:3"] / "database.db") as db:
        ids = {i.name: i.image_id for i in dbmod.read_images(db).values()}
        pairs = select_pairs("retrieval:3", sorted(ids), descriptors=lambda n: dbmod.read_descriptors(db, ids[n]))
    # every view of this half orbit sees the object, so every pair shares some ground-truth points; those that
    # share the most are all found, in fewer than half of the 45 pairs
    gt = scene / "gt" / "sparse"
    assert pair_recall(pairs, overlapping_pairs(gt, min_fraction=0.6)) >= 0.9
    assert pair_recall(pairs, overlapping_pairs(gt, min_fraction=0.7)) == 1.0 and len(pairs) < 45 / 2


def test_retrieval_ranks_the_orbit_neighbours_first_and_another_k_is_another_config(orbit_runs):
    _, runs = orbit_runs
    ws = runs["retrieval:3"]
    with dbmod.open_database(ws / "database.db") as db:
        ids = {i.name: i.image_id for i in dbmod.read_images(db).values()}
        pairs = select_pairs("retrieval:1", sorted(ids),
                             descriptors=lambda name: dbmod.read_features(db, ids[name])[1])
    # 10 views 20 deg apart on a half orbit (names in orbit order): each one's nearest is a next view (at the
    # ends only through the raw vectors' tie-break: 0000 and 0001 expand to the same vector, which 0002 is as
    # near to)
    assert pairs and all(abs(int(a[:4]) - int(b[:4])) == 1 for a, b in pairs)
    with pytest.raises(InputError, match=r"different matching config \(pairs: retrieval:3 -> retrieval:4\)"):
        match(FrontendConfig(pairs="retrieval:4"), ws)
