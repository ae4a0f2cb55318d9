"""The features and matching stages on a Dask LocalCluster of 2 worker processes on loopback (mvrecon/cluster.py)
give the database and model of the local process pool, also when a worker is killed during matching, when the
workers do not see the image folder, and when the client stops mid-run and the run is continued."""

import os
import shutil
import signal
import sqlite3
import time

import dask
import pycolmap
import pytest
from distributed import LocalCluster, get_task_stream

from mvrecon.cli import main
from mvrecon.cluster import (
    QUIET_LOCAL_CLUSTER,
    Cluster,
    ClusterLost,
    ClusterSpec,
    load_security,
    open_cluster,
    parse_cluster,
)
from mvrecon.errors import InputError
from mvrecon.geometry.rotation import rotation_error_deg
from mvrecon.pipeline import ReconstructConfig, reconstruct
from mvrecon.sfm.config import MapperConfig
from mvrecon.stages import features
from mvrecon.stages.common import FrontendConfig
from mvrecon.stages.features import extract_features
from mvrecon.stages.mapping import map_workspace
from mvrecon.stages.matching import match

TABLES = {"cameras": "camera_id", "images": "image_id", "keypoints": "image_id", "descriptors": "image_id",
          "matches": "pair_id", "two_view_geometries": "pair_id"}


def table_rows(database, table: str) -> list[tuple]:
    with sqlite3.connect(database) as db:
        return db.execute(f"SELECT * FROM {table} ORDER BY {TABLES[table]}").fetchall()


def assert_same_database(a, b, tables=TABLES):
    for table in tables:
        rows_a, rows_b = table_rows(a, table), table_rows(b, table)
        assert len(rows_a) == len(rows_b), table
        assert rows_a == rows_b, f"{table} differs"


def assert_same_model(sparse_a, sparse_b, max_deg: float = 0.01):
    """The same registered images, each camera's rotation within `max_deg` (the models share their frame: both
    start from the same pair of the same matches)."""
    a, b = pycolmap.Reconstruction(str(sparse_a)), pycolmap.Reconstruction(str(sparse_b))
    rot_a = {i.name: i.cam_from_world().rotation.matrix() for i in a.images.values() if i.has_pose}
    rot_b = {i.name: i.cam_from_world().rotation.matrix() for i in b.images.values() if i.has_pose}
    assert sorted(rot_a) == sorted(rot_b)
    assert len(rot_a) >= 8
    worst = max(rotation_error_deg(rot_a[n], rot_b[n]) for n in rot_a)
    assert worst < max_deg


@pytest.fixture(scope="module")
def cluster():
    with open_cluster(ClusterSpec("local:2")) as c:
        assert c.workers == 2
        yield c


@pytest.fixture(scope="module")
def local_run(object_orbit_small, tmp_path_factory):
    """object_orbit_small reconstructed with the local process pool (the default)."""
    out = tmp_path_factory.mktemp("local") / "run"
    reconstruct(ReconstructConfig(), object_orbit_small / "images", out)
    return out


@pytest.mark.slow
def test_a_cluster_run_gives_the_local_database_and_model(object_orbit_small, local_run, cluster, tmp_path):
    sent = cluster.sent_bytes
    report = reconstruct(ReconstructConfig(), object_orbit_small / "images", tmp_path / "run", cluster=cluster)
    assert_same_database(local_run / "database.db", tmp_path / "run" / "database.db")
    assert_same_model(local_run / "sparse" / "0", tmp_path / "run" / "sparse" / "0")
    assert sum(s["status"] == "registered" for s in report["images"].values()) == 10
    # the workers read the images from the shared folder: the client sent paths and descriptors, not images
    # (10 images of 640x480 are 9 MB decoded), and each image's descriptors once, not once per pair
    descriptor_bytes = sum(len(row[-1]) for row in table_rows(local_run / "database.db", "descriptors"))
    assert descriptor_bytes < cluster.sent_bytes - sent < 2.5 * descriptor_bytes


@pytest.mark.slow
def test_a_worker_killed_during_matching_loses_no_pair(object_orbit_small, local_run, cluster, tmp_path):
    ws, config = tmp_path / "ws", FrontendConfig()
    ws.mkdir()  # the local run's features, its matching not yet done
    shutil.copytree(local_run / ".stages", ws / ".stages")
    shutil.copy(local_run / "database.db", ws)
    with sqlite3.connect(ws / "database.db") as db:
        db.execute("DELETE FROM matches")
        db.execute("DELETE FROM two_view_geometries")
    killed, progress = [], []

    def kill_a_worker(done: int):
        progress.append(done)
        if not killed:  # after the first batch is written, one of the two workers is ended
            pid = max(cluster.worker_pids().values())
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    summary = match(config, ws, cluster=cluster, batch_size=2, on_batch=kill_a_worker)
    assert killed and progress[0] < 45  # killed while 40+ pairs were left
    assert summary.num_pairs == summary.num_matched == 45
    assert progress == sorted(progress) and progress[-1] == 45  # every pair written once
    assert_same_database(local_run / "database.db", ws / "database.db")
    map_workspace(MapperConfig(), ws)
    assert_same_model(local_run / "sparse" / "0", ws / "sparse" / "0")
    assert killed[0] not in cluster.worker_pids().values()  # gone (its nanny starts another, in its own time)


def test_workers_that_do_not_see_the_folder_get_the_images(object_orbit_small, local_run, cluster, tmp_path,
                                                           monkeypatch):
    """The client sends the images' bytes, here in tasks of 3 images (a larger set's batches): the database is the
    local pool's, row for row."""
    monkeypatch.setattr(Cluster, "workers_see", lambda self, folder: False)
    monkeypatch.setattr(features, "images_per_task", lambda count, workers: 3)
    sent = cluster.sent_bytes
    extract_features(FrontendConfig(), object_orbit_small / "images", tmp_path / "ws", cluster=cluster)
    image_bytes = sum(p.stat().st_size for p in (object_orbit_small / "images").iterdir())
    assert cluster.sent_bytes - sent >= image_bytes
    assert_same_database(local_run / "database.db", tmp_path / "ws" / "database.db",
                         ["cameras", "images", "keypoints", "descriptors"])


def test_a_run_whose_client_stopped_continues_where_it_was(object_orbit_small, local_run, cluster, tmp_path):
    ws, images, written = tmp_path / "ws", object_orbit_small / "images", []

    def stop_after_three(name: str):
        written.append(name)
        if len(written) == 3:
            raise KeyboardInterrupt  # Ctrl-C, or a client whose machine went away, after 3 commits

    with pytest.raises(KeyboardInterrupt):
        extract_features(FrontendConfig(), images, ws, cluster=cluster, on_image=stop_after_three)
    assert len(table_rows(ws / "database.db", "keypoints")) == 3
    summary = extract_features(FrontendConfig(), images, ws, cluster=cluster)
    assert (summary.num_images, summary.num_extracted) == (10, 7)
    assert_same_database(local_run / "database.db", ws / "database.db", ["images", "keypoints", "descriptors"])


def test_the_cluster_option_refuses_an_open_remote_scheduler(tmp_path, capsys):
    assert parse_cluster("local:2").local_workers == 2
    assert parse_cluster("tcp://127.0.0.1:8786").local_workers is None
    assert parse_cluster("tcp://localhost:8786").address == "tcp://localhost:8786"
    assert parse_cluster("tcp://10.1.2.3:8786", "none").security == "none"
    for address, security, why in [("local:0", None, "at least 1 worker"),
                                   ("10.1.2.3:8786", None, "expected local:N"),
                                   ("tcp://10.1.2.3:8786", None, "needs --cluster-security"),
                                   ("tls://10.1.2.3:8786", "none", "needs --cluster-security FILE"),
                                   ("tcp://10.1.2.3:8786", str(tmp_path / "no.yaml"), "cannot read")]:
        with pytest.raises(InputError, match=why):
            parse_cluster(address, security)
    # the refusal comes before any work, as a one-line error
    assert main(["features", str(tmp_path), "-o", str(tmp_path / "ws"), "--cluster", "tcp://10.1.2.3:8786"]) == 2
    assert "needs --cluster-security" in capsys.readouterr().err


def test_a_security_file_names_existing_certificates(tmp_path):
    for name in ("ca.pem", "cert.pem", "key.pem"):
        (tmp_path / name).write_text("-----BEGIN CERTIFICATE-----\n")
    good = tmp_path / "tls.toml"
    good.write_text('ca-file = "ca.pem"\ncert = "cert.pem"\nkey = "key.pem"\n')
    spec = parse_cluster("tls://10.1.2.3:8786", str(good))
    security = load_security(spec.security)
    assert security.require_encryption and security.tls_client_key == str(tmp_path / "key.pem")
    yaml_file = tmp_path / "tls.yaml"
    yaml_file.write_text("ca-file: ca.pem\ncert: cert.pem\nkey: missing.pem\n")
    with pytest.raises(InputError, match="key = missing.pem: no such file"):
        load_security(yaml_file)
    yaml_file.write_text("ca-file: ca.pem\ncert: cert.pem\n")
    with pytest.raises(InputError, match="missing key"):
        load_security(yaml_file)


@pytest.mark.slow
def test_a_lost_scheduler_ends_the_run_in_one_line_and_the_rerun_continues(object_orbit_small, local_run, cluster,
                                                                           tmp_path):
    ws, images, written = tmp_path / "ws", object_orbit_small / "images", []
    # a scheduler of its own, reached by its tcp:// address on loopback as a remote one is
    other = LocalCluster(n_workers=1, threads_per_worker=1, host="127.0.0.1", dashboard_address=None)
    with open_cluster(parse_cluster(other.scheduler_address)) as remote:
        assert remote.workers == 1 and remote.workers_see(images)

        def lose_the_scheduler(name: str):
            written.append(name)
            if len(written) == 3:
                other.close()

        with pytest.raises(ClusterLost, match="connection to the scheduler was lost.*rerun"):
            extract_features(FrontendConfig(), images, ws, cluster=remote, on_image=lose_the_scheduler)
    assert 3 <= len(table_rows(ws / "database.db", "keypoints")) < 10
    summary = extract_features(FrontendConfig(), images, ws, cluster=cluster)
    assert summary.num_images == 10 and summary.num_extracted == 10 - len(written)
    assert_same_database(local_run / "database.db", ws / "database.db", ["images", "keypoints", "descriptors"])


def test_the_parts_of_a_partitioned_mapping_run_on_the_cluster_as_on_the_pool(cluster, tmp_path):
    """24 views of pycolmap's synthetic scene in parts of at most 10, mapped once by the process pool and once on
    the cluster: the same registered images and rotations, every part a task of the cluster."""
    from tests.sfm.test_mapper import synthetic_database

    pool_ws, cluster_ws = tmp_path / "pool", tmp_path / "cluster"
    for ws in (pool_ws, cluster_ws):
        ws.mkdir()
        synthetic_database(ws / "database.db", num_images=24, num_points=800)
    config = MapperConfig(seed=3, partition_size=10)
    map_workspace(config, pool_ws)
    sent = cluster.sent_bytes
    on_cluster = map_workspace(config, cluster_ws, cluster=cluster)
    assert cluster.sent_bytes > sent  # the parts went to the cluster's workers
    assert sum(s["status"] == "registered" for s in on_cluster.status.values()) == 24
    assert_same_model(pool_ws / "sparse" / "0", cluster_ws / "sparse" / "0")


def test_a_local_cluster_runs_its_workers_with_little_periodic_work(cluster):
    """local:N's workers run with QUIET_LOCAL_CLUSTER (no profiler, rare health ticks and memory checks), also a
    worker its nanny starts again after a death; the caller's Dask settings are as they were once the cluster is
    closed."""
    def settings(**_):
        return {key: dask.config.get(key) for key in QUIET_LOCAL_CLUSTER}

    assert list(cluster.client.run(settings).values()) == [QUIET_LOCAL_CLUSTER] * 2
    with dask.config.set({"distributed.admin.tick.interval": "7ms"}):  # the caller's own setting
        with open_cluster(ClusterSpec("local:1")) as one:
            [pid] = one.worker_pids().values()
            os.kill(pid, signal.SIGKILL)
            deadline = time.monotonic() + 60
            while pid in (pids := one.client.run(os.getpid, on_error="ignore").values()) or not pids:
                assert time.monotonic() < deadline, "the nanny did not start its worker again"
                time.sleep(0.2)
            assert list(one.client.run(settings).values()) == [QUIET_LOCAL_CLUSTER]
        assert dask.config.get("distributed.admin.tick.interval") == "7ms"


def test_a_task_is_named_by_its_function(cluster):
    """The task stream (and the dashboard) tell the stages' tasks apart by their keys' function names."""
    with get_task_stream(cluster.client) as stream:
        assert list(cluster.map(abs, [-1, 2, -3])) == [1, 2, 3]
    assert sorted(str(record["key"]).rsplit("-", 1)[0] for record in stream.data) == ["abs"] * 3
    with get_task_stream(cluster.client) as stream:  # several items a task: still in order, one task per batch
        assert list(cluster.map(abs, range(-3, 4), per_task=3)) == [3, 2, 1, 0, 1, 2, 3]
    assert sorted(str(record["key"]).rsplit("-", 1)[0] for record in stream.data) == ["abs"] * 3
