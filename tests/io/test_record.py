"""The record of finished work (io/record.py) and the workspace built on it: a changed key or a missing file
redoes a piece, a piece cut off mid-write is never taken for a finished one, and a refused config names the
fields that differ."""

import json

import pytest

from mvrecon.config import config_hash
from mvrecon.errors import InputError
from mvrecon.io.record import Record
from mvrecon.workspace import Workspace


def _piece(folder, text: str, calls: list):
    """make() of a piece that writes `text` to folder/out.txt and reports its length."""
    def make():
        calls.append(text)
        (folder / "out.txt").write_text(text)
        return {"chars": len(text)}
    return make


def test_a_piece_is_reused_under_its_key_and_redone_when_the_key_differs_or_a_file_is_missing(tmp_path):
    calls = []
    assert Record(tmp_path).run("piece", "k1", ["out.txt"], _piece(tmp_path, "one", calls)) == {"chars": 3}
    again = Record(tmp_path)  # a rerun: reads what the first one wrote
    assert again.run("piece", "k1", ["out.txt"], _piece(tmp_path, "one", calls)) == {"chars": 3}
    assert calls == ["one"] and again.reused == ["piece"]
    changed = Record(tmp_path)
    assert changed.run("piece", "k2", ["out.txt"], _piece(tmp_path, "three", calls)) == {"chars": 5}
    assert calls == ["one", "three"] and changed.reused == [] and Record(tmp_path).key("piece") == "k2"
    (tmp_path / "out.txt").unlink()
    assert Record(tmp_path).run("piece", "k2", ["out.txt"], _piece(tmp_path, "three", calls)) == {"chars": 5}
    assert calls == ["one", "three", "three"]
    assert Record(tmp_path).seconds("piece") >= 0


def test_a_piece_cut_off_mid_write_is_not_taken_for_finished(tmp_path):
    calls = []
    Record(tmp_path).run("piece", "k1", ["out.txt"], _piece(tmp_path, "one", calls))

    def cut_off():  # the rewrite with other settings starts, then Ctrl-C
        (tmp_path / "out.txt").write_text("tw")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Record(tmp_path).run("piece", "k2", ["out.txt"], cut_off)
    # the entry was dropped before the file was rewritten: neither key takes the half-written file
    rerun = Record(tmp_path)
    assert rerun.get("piece", "k1", ["out.txt"]) is None and rerun.get("piece", "k2", ["out.txt"]) is None
    # a record file cut off (by hand, or by another writer) is damaged: nothing in it counts as finished
    text = rerun.path.read_text()
    Record(tmp_path).put("other", "k", {"n": 1})
    rerun.path.write_text(rerun.path.read_text()[:20])
    damaged = Record(tmp_path)
    assert damaged.damaged and damaged.names() == [] and damaged.get("other", "k") is None
    assert not list(rerun.path.parent.glob(".*partial*"))  # written whole: no partial file left behind
    assert json.loads(text) == {}


def test_prune_keeps_only_the_pieces_asked_for(tmp_path):
    record = Record(tmp_path, "table.json")
    for name in ("a", "b", "c"):
        record.put(name, name)
    rerun = Record(tmp_path, "table.json")
    assert rerun.get("b", "b") == {} and rerun.get("c", "other") is None
    rerun.prune()
    assert Record(tmp_path, "table.json").names() == ["b", "c"]


def test_differences_name_the_fields_that_differ(tmp_path):
    config = {"sift": {"peak_threshold": 0.01, "max_num_features": 8192}, "images": "/a"}
    Record(tmp_path).put("features", config_hash(config), config=config)
    changed = {"sift": {"peak_threshold": 0.02, "max_num_features": 8192}, "images": "/a"}
    record = Record(tmp_path)
    assert record.differences("features", config) == []
    assert record.differences("features", changed) == ["sift.peak_threshold: 0.01 -> 0.02"]
    assert record.differences("matching", changed) == []  # not recorded: nothing to refuse
    record.put("bare", "some key")
    assert record.differences("bare", changed) == ["(settings not recorded)"]


def test_the_workspace_refuses_a_changed_config_and_overwrite_drops_the_later_stages(tmp_path):
    ws = Workspace(tmp_path / "ws")
    features, matching = {"sift": {"peak_threshold": 0.01}}, {"pairs": "exhaustive"}
    assert ws.begin_stage("features", features) == []
    assert ws.begin_stage("matching", matching) == []
    assert ws.begin_stage("mapping", {"seed": 0}) == []
    assert ws.begin_stage("features", features) == []  # the same config resumes
    changed = {"sift": {"peak_threshold": 0.02}}
    with pytest.raises(InputError, match=r"made with a different features config \(sift.peak_threshold: "
                                         r"0.01 -> 0.02\); rerun with --overwrite"):
        ws.check_stage("features", changed)
    assert ws.check_stage("matching", {"pairs": "exhaustive"}) == []
    assert ws.begin_stage("matching", {"pairs": "sequential:5"}, overwrite=True) == ["matching", "mapping"]
    assert list(ws.stages()) == ["features", "matching"]
    assert ws.stage_config("matching") == {"pairs": "sequential:5"}
    assert ws.stages()["features"]["hash"] == config_hash(features)
    assert ws.begin_stage("features", changed, overwrite=True) == ["features", "matching"]
    assert list(ws.stages()) == ["features"]


def test_a_workspace_of_the_older_record_is_refused_then_started_over(tmp_path):
    ws = Workspace(tmp_path / "ws").create()
    (ws.path / "config.json").write_text(json.dumps({"stages": {"features": {"hash": "0", "config": {}}}}))
    with pytest.raises(InputError, match="config.json: a workspace of an older mvrecon version.*--overwrite"):
        ws.begin_stage("features", {"sift": {}})
    with pytest.raises(InputError, match="older mvrecon version"):
        ws.stage_config("features")
    assert ws.begin_stage("features", {"sift": {}}, overwrite=True) == ["features"]
    assert not (ws.path / "config.json").exists() and ws.stage_config("features") == {"sift": {}}
