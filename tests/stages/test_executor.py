"""The process pool when workers die (the kernel's out-of-memory killer, a crash in native code), its memory
budget, and the peak memory a run reports. Each case runs in a fresh interpreter with a timeout, so that a pool
waiting for a dead worker fails the test instead of hanging it."""

import ast
import json
import multiprocessing
import os
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import psutil
import pytest
from PIL import Image

from mvrecon.executor import WorkerPool, in_background
from tests import helpers
from tests.helpers import textured_views

ROOT = str(helpers.ROOT)


def _run(args, tmp_path, env=None, timeout=180) -> subprocess.CompletedProcess:
    """`python ARGS` with this tree and tmp_path importable; a run past `timeout` fails the test (a hang)."""
    path = os.pathsep.join([str(tmp_path), ROOT, os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, **(env or {})}
    try:
        return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=timeout,
                              env=env, cwd=tmp_path)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"still running after {timeout} s (a pool waiting for a dead worker): {exc.stderr}")


# Jobs of the pool tests, in a module the workers import (forkserver workers do not inherit the parent's).
JOBS = '''
import os, signal, time
from pathlib import Path

def job(k):
    """k*k after a short sleep; 3 and 5 kill their worker every time (SIGKILL, SIGSEGV), 6 the first time."""
    marks = Path(os.environ["MARKS"])
    first = not (marks / str(k)).exists()
    (marks / str(k)).touch()
    if k == 3 or (k == 6 and first):
        os.kill(os.getpid(), signal.SIGKILL)
    if k == 5:
        os.kill(os.getpid(), signal.SIGSEGV)
    time.sleep(0.05)
    return k * k

def interval(k):
    """(start, end) of a 0.3 s job."""
    start = time.time()
    time.sleep(0.3)
    return start, time.time()

def sleepy(k):
    time.sleep(0.4)
    return k
'''


@pytest.fixture
def jobs(tmp_path):
    (tmp_path / "jobs.py").write_text(JOBS)
    (tmp_path / "marks").mkdir()
    return {"MARKS": str(tmp_path / "marks")}


@pytest.mark.parametrize("method", ["fork", "forkserver"])
def test_a_worker_that_dies_is_noticed_its_item_run_again_then_given_up(tmp_path, jobs, method):
    """SIGKILL (what the out-of-memory killer sends) or SIGSEGV (a native crash) in a worker must not leave the
    pool waiting forever: the item runs again in a fresh worker (6 dies once, then gives 36), and an item whose
    worker dies twice gets `died`'s result with the reason (3 and 5); the others are unharmed.
    Workers are forked from a parent without OpenCV, else they come from the forkserver: both are covered."""
    script = textwrap.dedent(f"""
        import logging, sys
        logging.basicConfig(level=logging.DEBUG, format="%(message)s")
        if {method == "forkserver"}:
            import cv2  # OpenCV loaded here: the workers come from the forkserver
        import jobs
        from mvrecon.executor import WorkerPool
        with WorkerPool(2) as pool:
            print(list(pool.map(jobs.job, range(10), name=lambda k: f"item {{k}}", died=lambda k, why: why)))
    """)
    done = _run(["-c", script], tmp_path, jobs)
    assert done.returncode == 0, done.stderr
    results = ast.literal_eval(done.stdout)
    assert results[3] == "signal 9 (SIGKILL), probably out of memory"
    assert results[5] == "signal 11 (SIGSEGV), a crash in native code"
    others = [k for k in range(10) if k not in (3, 5)]
    assert [results[k] for k in others] == [k * k for k in others]
    assert f"process pool: 2 {method} workers" in done.stderr
    for k, why in ((3, "signal 9 (SIGKILL)"), (5, "signal 11 (SIGSEGV)"), (6, "signal 9 (SIGKILL)")):
        assert f"the worker running item {k} died ({why}" in done.stderr and "again on its own" in done.stderr
    assert done.stderr.count("running it again") == 3  # 3 and 5 are given up after their second death


def test_workers_killed_from_outside_cost_only_their_item_and_a_second_death_raises(tmp_path, jobs):
    """The out-of-memory killer picks any worker, busy or idle (an idle one keeps the memory it freed): after
    SIGKILL of a worker mid-item, the item runs again and every result comes; without `died`, an item whose
    workers die twice raises WorkerDied where its result is asked for, after the results before it."""
    script = textwrap.dedent("""
        import os, signal, time
        import jobs
        from mvrecon.executor import WorkerDied, WorkerPool
        with WorkerPool(2) as pool:
            results = pool.map(jobs.sleepy, range(6))
            time.sleep(0.2)  # both workers in their first item
            os.kill(pool.pids()[0], signal.SIGKILL)
            print(list(results))
        with WorkerPool(2) as pool:
            got = []
            try:
                for r in pool.map(jobs.job, [1, 2, 3, 4]):
                    got.append(r)
            except WorkerDied as exc:
                print(got, exc)
    """)
    done = _run(["-c", script], tmp_path, jobs)
    assert done.returncode == 0, done.stderr
    first, second = done.stdout.splitlines()
    assert first == "[0, 1, 2, 3, 4, 5]"
    assert second == "[1, 4] the workers running an item died: signal 9 (SIGKILL), probably out of memory"


def test_items_run_at_the_same_time_only_while_their_memory_fits(tmp_path, jobs):
    """Each worker needs memory for its item (SIFT's scale space: 1.5 GB for a 3072 x 2048 photo), and one
    worker per core ran out of memory on a small machine. With `cost`, items run together only while the
    workers' costs fit in the memory available (here 1,000 MB): items of 600 MB run one at a time, items of
    400 MB two at a time."""
    script = textwrap.dedent("""
        import sys
        import jobs
        from mvrecon import executor
        executor.available_mb = lambda: 1000.0
        for cost in (600, 400):
            with executor.WorkerPool(2) as pool:
                spans = sorted(pool.map(jobs.interval, range(4), cost=lambda k: cost))
            overlaps = sum(later[0] < earlier[1] for earlier, later in zip(spans, spans[1:]))
            print(cost, overlaps)
    """)
    done = _run(["-c", script], tmp_path, jobs)
    assert done.returncode == 0, done.stderr
    overlaps = dict(line.split() for line in done.stdout.splitlines())
    assert overlaps["600"] == "0" and int(overlaps["400"]) >= 1, overlaps


# Makes the worker reading an image kill itself: view02.png every time (SIGKILL), view04.png once (SIGSEGV).
# As sitecustomize it is loaded by every interpreter, the forkserver's included.
DYING_READER = '''
import os, signal
from pathlib import Path
import mvrecon.io.images as images

_real = images.read_image_for_detection

def _dying(path, detection_size):
    name, marks = Path(path).name, Path(os.environ["MARKS"])
    if name == "view02.png":
        os.kill(os.getpid(), signal.SIGKILL)
    if name == "view04.png" and not (marks / name).exists():
        (marks / name).touch()
        os.kill(os.getpid(), signal.SIGSEGV)
    return _real(path, detection_size)

images.read_image_for_detection = _dying
'''


def test_a_run_whose_worker_dies_skips_that_image_with_the_reason_and_goes_on(tmp_path, jobs):
    """`mvrecon reconstruct` with a worker killed while it extracts an image: the image whose workers die
    twice is skipped with the reason in report.json, the one whose worker died once is extracted again, and
    the run registers the other images."""
    images = textured_views(tmp_path / "images")
    (tmp_path / "sitecustomize.py").write_text(DYING_READER)
    out = tmp_path / "out"
    argv = ["-m", "mvrecon.cli", "reconstruct", str(images), "-o", str(out), "--workers", "2"]
    done = _run(argv, tmp_path, jobs)
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "report.json").read_text())
    status = {name: im["status"] for name, im in report["images"].items()}
    assert status == {f"view{i:02d}.png": "skipped" if i == 2 else "registered" for i in range(6)}
    assert report["images"]["view02.png"]["reason"] == f"{images / 'view02.png'}: the worker extracting it " \
        "died twice: signal 9 (SIGKILL), probably out of memory"
    assert f"the worker running {images / 'view04.png'} died (signal 11 (SIGSEGV)" in done.stderr


def test_report_json_gives_the_peak_memory_of_the_run_and_its_workers(tmp_path):
    """report.json's peak_mem_mb is the peak of the process and its workers, as measured from outside (the main
    process alone can be a fifth of it: 304 of 1,531 MB for castle), and the main process's own is
    peak_main_mem_mb."""
    images = textured_views(tmp_path / "images")
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "mvrecon.cli", "-q", "reconstruct", str(images), "-o",
                             str(out), "--workers", "2"], env=env, stderr=subprocess.PIPE, text=True)
    outside, root, deadline = 0.0, psutil.Process(proc.pid), time.monotonic() + 180
    while proc.poll() is None and time.monotonic() < deadline:
        rss = 0
        try:
            for p in [root, *root.children(recursive=True)]:
                try:
                    rss += p.memory_info().rss
                except psutil.Error:
                    pass
        except psutil.Error:
            pass
        outside = max(outside, rss / 2 ** 20)
        time.sleep(0.02)
    if proc.poll() is None:
        proc.kill()
        pytest.fail("reconstruct did not end in 180 s")
    assert proc.wait() == 0, proc.stderr.read()
    total = json.loads((out / "report.json").read_text())["total"]
    assert total["peak_mem_mb"] > 1.5 * total["peak_main_mem_mb"], total  # the workers count
    assert 0.85 * outside < total["peak_mem_mb"] < 1.15 * outside, (total, outside)


def test_the_main_peak_is_the_run_s_own_not_that_of_the_process_that_started_it(tmp_path):
    """Linux carries ru_maxrss over an exec: mvrecon started from a process holding 400 MB (a notebook, a test
    run) reported 400 MB as its own peak, and the tree's peak with it. The main peak is the run's own."""
    held = np.ones(50_000_000)  # 400 MB resident in the process that starts the run
    done = _run(["-c", "from mvrecon.memory import main_peak_mb; print(main_peak_mb())"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert float(done.stdout) < 150 < held.nbytes / 2 ** 20, done.stdout


def test_a_large_jpeg_is_decoded_reduced_and_its_keypoints_stay_in_full_size_pixels(tmp_path):
    """A photo the detector shrinks anyway is decoded at 1/2-1/8 of its size (memory per worker: 12000 x 9000
    at 1,816 MB instead of 2,108). libjpeg's reduced decode is a sharper low-pass than the detector's area
    average, so not every keypoint is the same; most are, at the same place in full-size pixels."""
    from scipy.spatial import cKDTree

    from mvrecon.features.sift import SiftConfig, extract_sift
    from mvrecon.io.images import read_image, read_image_for_detection

    rng = np.random.default_rng(1)
    texture = (rng.random((96, 128, 3)) * 255).astype(np.uint8)
    photo = np.asarray(Image.fromarray(texture).resize((1024, 768), Image.BICUBIC))
    path = tmp_path / "photo.jpg"
    Image.fromarray(photo).save(path, quality=95)
    config = SiftConfig(max_image_size=300)
    reduced, factor = read_image_for_detection(path, config.max_image_size)
    assert factor == 2 and reduced.shape == (384, 512, 3)  # at 1/4 the long side, 256, is under 300
    assert read_image_for_detection(path, 250)[1] == 4 and read_image_for_detection(path, 600)[1] == 1
    whole = read_image(path)
    k_whole, _ = extract_sift(whole, config)
    k_reduced, _ = extract_sift(reduced, config, factor)
    assert 0.8 < len(k_reduced) / len(k_whole) < 1.25
    distance, _ = cKDTree(k_whole[:, :2]).query(k_reduced[:, :2])
    detection_px = 1024 / 300  # full-size pixels per pixel the detector sees
    assert np.mean(distance < 0.5 * detection_px) > 0.7, np.mean(distance < 0.5 * detection_px)
    assert np.median(distance) < 0.1 * detection_px


def test_the_memory_estimate_of_an_image_is_what_a_worker_uses(tmp_path):
    """The pool's budget rests on `extraction_memory_mb`: a process extracting a 1024 x 768 image grows by
    what it says, within a fifth."""
    rng = np.random.default_rng(2)
    Image.fromarray((rng.random((768, 1024, 3)) * 255).astype(np.uint8)).save(tmp_path / "photo.png")
    script = textwrap.dedent("""
        import resource
        from mvrecon.executor import _init_worker
        _init_worker()
        from mvrecon.features.sift import SiftConfig, extraction_memory_mb
        from mvrecon.memory import main_peak_mb, rss_mb
        from mvrecon.stages.features import _extract_job
        import os
        before = rss_mb([os.getpid()])
        name, result = _extract_job(("photo.png", "photo.png", SiftConfig(), None, 1))
        print(main_peak_mb() - before, extraction_memory_mb(1024, 768))
    """)
    done = _run(["-c", script], tmp_path)
    assert done.returncode == 0, done.stderr
    used, estimate = map(float, done.stdout.split())
    assert 0.8 * used < estimate < 1.2 * used, (used, estimate)


# Kills the `mvrecon reconstruct` process itself as it starts its run, the first DEATHS times.
DYING_RUN = '''
import os, signal
from pathlib import Path
import mvrecon.pipeline as pipeline

_real = pipeline.reconstruct

def _dying(*args, **kwargs):
    marks = Path(os.environ["MARKS"])
    runs = len(list(marks.iterdir()))
    (marks / f"run{runs}").touch()
    if runs < int(os.environ["DEATHS"]):
        os.kill(os.getpid(), signal.SIGKILL)
    return _real(*args, **kwargs)

pipeline.reconstruct = _dying
'''


def test_an_engine_run_that_is_killed_runs_once_more_then_fails_with_the_reason(tmp_path, jobs, monkeypatch):
    """The runs of `compare` and `study` are processes of their own: one killed (by the out-of-memory killer,
    say) is run once more, as the feature pool does with an image, and after a second death the run fails with
    the reason, where it said "exit code -9" and the last line of its log."""
    from mvrecon.eval.runners import run_meta, run_mvrecon

    images = textured_views(tmp_path / "images")
    (tmp_path / "sitecustomize.py").write_text(DYING_RUN)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), ROOT, os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("MARKS", jobs["MARKS"])
    monkeypatch.setenv("DEATHS", "1")
    once = run_mvrecon(images, tmp_path / "once", timeout=180)
    assert once.error is None and len(once.models[0].images) == 6
    assert run_meta(tmp_path / "once")["attempts"] == 2
    monkeypatch.setenv("DEATHS", "4")  # two marks are there already: the next two runs die
    twice = run_mvrecon(images, tmp_path / "twice", timeout=180)
    assert twice.error == "the process running it died twice: signal 9 (SIGKILL), probably out of memory"


def _pool_in_daemon(queue) -> None:
    with WorkerPool(2) as pool:
        queue.put((pool.workers, pool.pids(), list(pool.map(abs, [-1, 2, -3])), os.getpid()))


def test_a_pool_made_in_a_daemon_process_runs_its_items_there():
    """A daemon process (another pool's worker) may not start processes: a pool made there runs in-process."""
    ctx = multiprocessing.get_context("spawn")
    queue = ctx.Queue()
    process = ctx.Process(target=_pool_in_daemon, args=(queue,), daemon=True)
    process.start()
    workers, pids, results, pid = queue.get(timeout=120)
    process.join(30)
    assert (workers, pids, results) == (1, [], [1, 2, 3]) and pid == process.pid and process.exitcode == 0


def test_work_in_background_runs_beside_the_caller_and_hands_back_its_result_or_its_error():
    """`in_background` runs a function in a thread of its own while the caller goes on: the caller sees the
    thread start and finish, gets its result, or the exception it raised."""
    started, go = threading.Event(), threading.Event()

    def work():
        started.set()
        assert go.wait(10)
        return 42

    future = in_background(work)
    assert started.wait(10) and not future.done()  # it runs while the caller waits for nothing
    go.set()
    assert future.result(timeout=10) == 42
    failing = in_background(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        failing.result(timeout=10)
