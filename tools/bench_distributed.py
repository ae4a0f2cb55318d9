"""Distributed benchmark: the features and matching stages on the local process pool and on a Dask cluster.

    python tools/bench_distributed.py SCENE/images                       # local pool vs local:2, 3 rounds
    python tools/bench_distributed.py SCENE/images --repeats 2 --map     # and the mapping stage, timed once
    python tools/bench_distributed.py SCENE/images --partition-size 200  # and mapping in parts on the cluster
    python tools/bench_distributed.py SCENE/images --out docs/distributed.md  # the measured section of the page

(1) Overhead: the features and matching stages (default settings, `--pairs auto`) in a fresh workspace, as
`mvrecon reconstruct` runs them (one process; with a cluster, one cluster for both, its start counted in the
features stage), without the mapping, which is the same in both: a subprocess timed whole, once with the local
process pool and once on `--cluster` (default local:2), alternated --repeats times; the medians per stage and
their ratio (target: local:2 within 1.2x of the pool on a 2-core machine); and the CPU seconds per stage of the
process and its workers, which on a machine shared with other jobs is what the wall time follows.
(2) Cost model: in the last cluster run, under `distributed.get_task_stream`: per stage the tasks, the worker
compute per task, the bytes the client sent and received (`Cluster.sent_bytes`, dask's sizeof), the bytes the
workers sent one another, the images the workers read from the shared folder, and the client's (and, on a
LocalCluster, the scheduler's) CPU per task: the part that does not shrink with more machines (it writes every
result into the one database).
(3) Prediction of each stage's wall time on N machines of --cores cores each:
    T(N) = max(compute / (N x cores), client CPU, client bytes / bandwidth, image bytes / bandwidth)
the bandwidth being --bandwidth MB/s (default 110: one 1 Gbit/s link into the client and into the file server
holding the images; assumed, not measured: a LocalCluster moves its bytes over loopback). The stage whose
non-shrinking term first exceeds its compute term stops scaling first. With --map, the mapping stage is timed
once on the client (the features and matching's workspace copied, the model scored against SCENE/gt/sparse when
there is one) and added as a serial term: it runs on the client whatever the cluster. With --partition-size P it
is also mapped in parts of at most P images on the cluster (`map --partition-size P --cluster`, each part one
task): the parts' compute shrinks with the machines down to the largest part; what runs on the client (reading
the database, splitting the view graph, merging the parts and the final bundle adjustment) does not.

It prints the tables and, with --out, writes them into that markdown page between the markers
`<!-- bench_distributed -->` and `<!-- /bench_distributed -->` (the rest of the page is left as it is).
"""

import argparse
import contextlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from multiprocessing import forkserver
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from distributed import get_task_stream  # noqa: E402

from mvrecon.cluster import ClusterSpec, open_cluster  # noqa: E402
from mvrecon.eval.ground_truth import load_ground_truth  # noqa: E402
from mvrecon.eval.metrics import accuracy_summary  # noqa: E402
from mvrecon.eval.models import poses, sparse_models  # noqa: E402
from mvrecon.executor import cpu_seconds as pool_cpu_seconds  # noqa: E402
from mvrecon.executor import process_cpu_seconds  # noqa: E402
from mvrecon.memory import main_peak_mb  # noqa: E402
from mvrecon.sfm.config import MapperConfig  # noqa: E402
from mvrecon.stages.common import FrontendConfig  # noqa: E402
from mvrecon.stages.features import extract_features  # noqa: E402
from mvrecon.stages.mapping import map_workspace  # noqa: E402
from mvrecon.stages.matching import match  # noqa: E402
from mvrecon.workspace import Workspace  # noqa: E402

MARK, END = "<!-- bench_distributed -->", "<!-- /bench_distributed -->"
# task key prefix -> stage (client.submit names a task by its function)
STAGE_OF_TASK = {"_extract_job": "features", "_extract_sent": "features", "_match_batch": "matching",
                 "mvrecon-image": "matching", "map_part_item": "mapping"}


def mapping_times(images: Path, source: Path, ws: Path, address: str | None, partition_size: int) -> dict:
    """The mapping of `source`'s database (a finished front end's workspace) in a copy `ws`, in a subprocess
    (`run_mapping`): on the client without `address`, else in parts of at most `partition_size` images on the
    cluster. Returns run_mapping's figures."""
    shutil.rmtree(ws, ignore_errors=True)
    shutil.copytree(source, ws, ignore=shutil.ignore_patterns("sparse", "snapshots", "points.ply"))
    cmd = [sys.executable, __file__, "--mapping", str(images), "--work", str(ws)]
    if address:
        cmd += ["--cluster", address, "--partition-size", str(partition_size)]
    out = subprocess.run(cmd, check=True, env=code_env(), stdout=subprocess.PIPE, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def run_mapping(images: Path, ws: Path, address: str | None, partition_size: int) -> None:
    """The subprocess of `mapping_times`: maps `ws` with default settings (in parts on the cluster of `address`
    when given, its start not counted) and prints, as its last line, {"mapping": wall s, "cpu": CPU s of this
    process and its workers, "peak_mb": the largest resident memory of this process and of any worker,
    "registered", "models", "auc@1", "auc@5" (against images/../gt/sparse, None without it), and with a cluster
    "costs": {"mapping": the costs of `stage_costs`}}."""
    config = MapperConfig(partition_size=partition_size if address else 0)
    out = {"costs": {}}
    with open_cluster(ClusterSpec(address)) if address else contextlib.nullcontext() as cluster:
        start, cpu = time.perf_counter(), all_cpu_seconds(cluster)
        with stage_costs(cluster, "mapping", images, out) if cluster else contextlib.nullcontext():
            map_workspace(config, ws, image_dir=images, overwrite=True, cluster=cluster)
        out["mapping"] = time.perf_counter() - start
        out["cpu"] = all_cpu_seconds(cluster) - cpu
        if cluster:  # the parts' results, as kept in the workspace (Dask's sizeof does not see into them)
            kept = sum(f.stat().st_size for f in (ws / "snapshots" / "parts").glob("part-*.pkl"))
            out["costs"]["mapping"]["received_mb"] = kept / 1e6
        peaks = [main_peak_mb()] + (list(cluster.client.run(main_peak_mb).values()) if cluster else [])
    out["peak_mb"] = max(peaks)
    models = sparse_models(ws / "sparse") if (ws / "sparse").is_dir() else []
    out["registered"] = max((m.num_reg_images() for m in models), default=0)
    out["models"] = len(models)
    gt_dir = images.parent / "gt" / "sparse"
    acc = accuracy_summary([poses(m) for m in models], load_ground_truth(gt_dir)) if gt_dir.is_dir() else {}
    out["auc@1"], out["auc@5"] = acc.get("auc@1"), acc.get("auc@5")
    print(json.dumps(out))


def code_env() -> dict:
    return {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def front_end_times(images: Path, ws: Path, address: str | None) -> dict:
    """Seconds of the features and matching stages in a fresh workspace `ws`, run as `reconstruct` runs them
    (one process, one cluster for both when `address` is given), without the mapping: per stage (the cluster's
    start counted in the features stage) and the whole process (`total`, Python's start-up included)."""
    shutil.rmtree(ws, ignore_errors=True)
    start = time.perf_counter()
    out = subprocess.run([sys.executable, __file__, "--front-end", str(images), "--work", str(ws),
                          *(["--cluster", address] if address else [])],
                         check=True, env=code_env(), stdout=subprocess.PIPE, text=True).stdout
    total = time.perf_counter() - start
    return {**json.loads(out.strip().splitlines()[-1]), "total": total}


def run_front_end(images: Path, ws: Path, address: str | None) -> None:
    """The subprocess of `front_end_times`: prints {"features": s, "matching": s} as its last line, and with a
    cluster its start (s), its worker threads and per stage the costs of `stage_costs`."""
    config, out = FrontendConfig(), {"cpu": {}}
    start, cpu = time.perf_counter(), all_cpu_seconds(None)
    ws = Workspace(ws).create()
    with ws.lock(), open_cluster(ClusterSpec(address)) if address else contextlib.nullcontext() as cluster:
        if cluster is not None:
            out["started"], out["workers"], out["costs"] = time.perf_counter() - start, cluster.workers, {}
        for stage in ("features", "matching"):
            with stage_costs(cluster, stage, images, out) if cluster else contextlib.nullcontext():
                if stage == "features":
                    extract_features(config, images, ws, cluster=cluster)
                else:
                    match(config, ws, cluster=cluster)
            out[stage] = time.perf_counter() - start
            out["cpu"][stage] = all_cpu_seconds(cluster) - cpu
            start, cpu = time.perf_counter(), all_cpu_seconds(cluster)
    print(json.dumps(out))


def all_cpu_seconds(cluster) -> float:
    """CPU seconds so far of this process and of the workers: the process pool's (executor.cpu_seconds), or the
    cluster's worker processes (on a LocalCluster the scheduler and nannies run in this process). On a shared
    machine each process gets its share of the cores, so the stages' CPU is what their wall time follows."""
    if cluster is None:
        return pool_cpu_seconds()
    return cpu_seconds() + sum(cluster.client.run(cpu_seconds).values()) + forkserver_cpu_seconds()


def forkserver_cpu_seconds() -> float:
    """CPU seconds of the forkserver the workers of a `local:N` cluster are forked from (it imports Dask once for
    them; it is not this process's child that RUSAGE_CHILDREN would count), 0 without one."""
    pid = getattr(forkserver._forkserver, "_forkserver_pid", None)
    return process_cpu_seconds(pid) if pid else 0.0


def overhead(images: Path, work: Path, address: str, repeats: int) -> dict:
    """{"pool": [runs], "cluster": [runs]} of `front_end_times`, alternated (the pool first in odd rounds). Each
    run is saved in WORK/runs.json as it ends; the rounds found there (of the same images and cluster) are kept,
    so an interrupted benchmark goes on where it stopped."""
    saved = work / "runs.json"
    key = {"images": str(images.resolve()), "cluster": address}
    old = json.loads(saved.read_text()) if saved.is_file() else {}
    runs = old["runs"] if old.get("key") == key else {"pool": [], "cluster": []}
    for k in range(repeats):
        order = ["pool", "cluster"] if k % 2 == 0 else ["cluster", "pool"]
        for kind in order:
            if len(runs[kind]) > k:
                continue
            runs[kind].append(front_end_times(images, work / f"ws-{kind}", address if kind == "cluster" else None))
            saved.write_text(json.dumps({"key": key, "runs": runs}))
            print(f"round {k + 1} {kind}: " + ", ".join(f"{s} {runs[kind][-1][s]:.1f} s"
                                                        for s in ("features", "matching", "total")), flush=True)
    return runs


def stage_of(key) -> str | None:
    """The stage a task of the task stream belongs to, by its key's prefix."""
    return next((s for prefix, s in STAGE_OF_TASK.items() if str(key).startswith(prefix)), None)


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


@contextlib.contextmanager
def stage_costs(cluster, stage: str, images: Path, out: dict):
    """The costs of the stage run in the block, into out["costs"][stage]: its tasks, their compute and transfer
    seconds on the workers (Dask's task stream), the longest task's compute, the seconds from the first task's
    start to the last one's end, this process's CPU seconds (the client, and a LocalCluster's scheduler), the MB
    the client sent and received, the MB the workers sent one another, the images' MB."""
    sent, received, peer = cluster.sent_bytes, cluster.received_bytes, cluster.peer_bytes()
    cpu = cpu_seconds()
    with get_task_stream(cluster.client) as stream:
        yield
    cpu = cpu_seconds() - cpu
    tasks, compute, transfer, longest, first, last = 0, 0.0, 0.0, 0.0, float("inf"), 0.0
    for record in stream.data:
        if stage_of(record["key"]) != stage:
            continue
        tasks += 1
        for step in record["startstops"]:
            if step["action"] == "compute":
                compute += step["stop"] - step["start"]
                longest = max(longest, step["stop"] - step["start"])
                first, last = min(first, step["start"]), max(last, step["stop"])
            elif step["action"] == "transfer":
                transfer += step["stop"] - step["start"]
    image_bytes = sum(p.stat().st_size for p in images.rglob("*") if p.is_file()) if stage == "features" else 0
    received = cluster.received_bytes - received
    peer = cluster.peer_bytes() - peer - received  # what workers sent, less the results fetched from them
    out["costs"][stage] = {"tasks": tasks, "compute_s": compute, "transfer_s": transfer, "client_cpu_s": cpu,
                           "longest_task_s": longest, "tasks_span_s": max(0.0, last - first),
                           "sent_mb": (cluster.sent_bytes - sent) / 1e6, "received_mb": received / 1e6,
                           "peer_mb": max(0, peer) / 1e6, "image_mb": image_bytes / 1e6}


def predict(stage: dict, machines: int, cores: int, bandwidth_mbs: float) -> tuple[float, str]:
    """(predicted wall s, the term that bounds it) of a stage on `machines` machines of `cores` cores."""
    terms = {"compute": stage["compute_s"] / (machines * cores), "client CPU": stage["client_cpu_s"],
             "client link": (stage["sent_mb"] + stage["received_mb"]) / bandwidth_mbs,
             "image reads": stage["image_mb"] / bandwidth_mbs}
    bound = max(terms, key=terms.get)
    return terms[bound], bound


def report(images: Path, runs: dict, model: dict, started: float, workers: int, mapping: dict, args) -> str:
    """The markdown section: the overhead, the measured costs, the mapping runs (`mapping`: "whole" and "parts",
    run_mapping's figures, when measured) and the prediction for N machines."""
    lines = []
    n_images = sum(1 for p in images.rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    lines.append(f"Scene: `{images}` ({n_images} images); cluster `{args.cluster}` ({workers} worker threads); "
                 f"{args.repeats} alternated rounds; medians.\n")
    lines.append("| stage | local pool (s) | cluster (s) | cluster / pool |")
    lines.append("|---|---|---|---|")
    for stage in ("features", "matching", "total"):  # total: the whole process, Python's start-up included
        pool = statistics.median(r[stage] for r in runs["pool"][:args.repeats])
        clus = statistics.median(r[stage] for r in runs["cluster"][:args.repeats])
        lines.append(f"| {stage} | {pool:.1f} | {clus:.1f} | {clus / pool:.2f} |")
    lines.append("\nCPU seconds of the stage (this process and its workers; a LocalCluster's scheduler and nannies run "
                 "in this process):\n")
    lines.append("| stage | local pool (CPU s) | cluster (CPU s) | cluster / pool |")
    lines.append("|---|---|---|---|")
    for stage in ("features", "matching"):
        pool = statistics.median(r["cpu"][stage] for r in runs["pool"][:args.repeats])
        clus = statistics.median(r["cpu"][stage] for r in runs["cluster"][:args.repeats])
        lines.append(f"| {stage} | {pool:.1f} | {clus:.1f} | {clus / pool:.2f} |")
    total_ratio = statistics.median(r["total"] for r in runs["cluster"][:args.repeats]) / \
        statistics.median(r["total"] for r in runs["pool"][:args.repeats])
    lines.append(f"\nOverhead target (cluster within 1.2x of the pool's wall time): "
                 f"{'met' if total_ratio <= 1.2 else 'NOT met'} ({total_ratio:.2f}x). The cluster's features time "
                 f"includes starting it ({started:.1f} s in the last run).\n")
    lines.append("Measured costs (the last cluster run):\n")
    lines.append("| stage | tasks | compute / task (s) | client CPU / task (ms) | client sent (MB) | "
                 "client received (MB) | worker to worker (MB) | images read by workers (MB) |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for stage in ("features", "matching"):
        s = model[stage]
        n = max(1, s["tasks"])
        lines.append(f"| {stage} | {s['tasks']} | {s['compute_s'] / n:.3f} | {1000 * s['client_cpu_s'] / n:.1f} | "
                     f"{s['sent_mb']:.1f} | {s['received_mb']:.1f} | {s['peer_mb']:.1f} | {s['image_mb']:.1f} |")
    whole, parts = mapping.get("whole"), mapping.get("parts")
    if whole is not None:
        lines.append(mapping_table(whole, parts, args))
    lines.append(f"\nPredicted wall time on N machines of {args.cores} cores (bandwidth {args.bandwidth:g} MB/s "
                 "into the client and the file server; the bounding term in brackets):\n")
    head = "| N | features (s) | matching (s) |"
    if whole is not None:
        head += " mapping on the client (s) |"
    if parts is not None:
        head += " mapping in parts (s) |"
    if whole is not None:
        head += " whole run (s) |"
    lines.append(head)
    lines.append("|" + "---|" * (head.count("|") - 1))
    first = {}
    for machines in (1, 4, 16, 64):
        cells, total = [], started
        for stage in ("features", "matching"):
            t, bound = predict(model[stage], machines, args.cores, args.bandwidth)
            if bound != "compute":
                first.setdefault(stage, machines)
            cells.append(f"{t:.1f} ({bound})")
            total += t
        mapped = None if whole is None else whole["mapping"]
        if whole is not None:
            cells.append(f"{whole['mapping']:.0f}")
        if parts is not None:
            t, bound = predict_parts(parts, machines, args.cores)
            if bound != "parts":
                first.setdefault("mapping in parts", machines)
            cells.append(f"{t:.0f} ({bound})")
            mapped = min(mapped, t)
        if mapped is not None:
            cells.append(f"{total + mapped:.0f}")
        lines.append(f"| {machines} | " + " | ".join(cells) + " |")
    stops = sorted(first.items(), key=lambda kv: kv[1])
    if stops:
        lines.append("\nStops scaling first: " + "; ".join(f"{s} at N = {n} machines" for s, n in stops) + ".")
    else:
        lines.append("\nNo stage stops scaling up to 64 machines in this model.")
    if whole is not None:
        lines.append(f"Mapped whole, the mapping runs on the client ({whole['mapping']:.0f} s) whatever N"
                     + (": the whole run takes the faster of the two mappings." if parts is not None else "."))
    lines.append(f"\nCommand: `python tools/bench_distributed.py {images} --repeats {args.repeats}"
                 + (" --map" if args.map and not args.partition_size else "")
                 + (f" --partition-size {args.partition_size}" if args.partition_size else "")
                 + (f" --cluster {args.cluster}" if args.cluster != "local:2" else "") + "`")
    return "\n".join(lines) + "\n"


def mapping_table(whole: dict, parts: dict | None, args) -> str:
    """The mapping runs' table and, for the parts, where their time went."""
    def fmt(x):
        return "-" if x is None else f"{x:.3f}"

    lines = ["\nMapping, once each, default settings (the matching's database; the model scored against the scene's "
             "ground truth):\n",
             "| mapping | wall s | CPU s | peak MB (one process) | registered | models | AUC@1 | AUC@5 |",
             "|---|---|---|---|---|---|---|---|"]
    rows = [("whole, on the client", whole)]
    if parts is not None:
        c = parts["costs"]["mapping"]
        rows.append((f"in parts of at most {args.partition_size} ({c['tasks']} parts) on `{args.cluster}`", parts))
    for label, r in rows:
        lines.append(f"| {label} | {r['mapping']:.0f} | {r['cpu']:.0f} | {r['peak_mb']:.0f} | {r['registered']} | "
                     f"{r['models']} | {fmt(r['auc@1'])} | {fmt(r['auc@5'])} |")
    if parts is not None:
        c = parts["costs"]["mapping"]
        serial = parts["mapping"] - c["tasks_span_s"]
        lines.append(f"\nIn parts: {serial:.0f} s on the client (reading the database, splitting the view graph, "
                     f"merging the parts, the final bundle adjustment) and {c['tasks_span_s']:.0f} s from the first "
                     f"part's start to the last one's end; the parts' compute {c['compute_s']:.0f} s in all, the "
                     f"longest {c['longest_task_s']:.0f} s; the client sent {c['sent_mb']:.1f} MB and received "
                     f"{c['received_mb']:.1f} MB (the parts' models).")
    return "\n".join(lines)


def predict_parts(run: dict, machines: int, cores: int) -> tuple[float, str]:
    """(predicted wall s, bounding term) of mapping in parts on `machines` machines of `cores` cores: the client's
    share as measured, plus the parts' compute spread over the worker threads but never below the longest part."""
    c = run["costs"]["mapping"]
    serial = run["mapping"] - c["tasks_span_s"]
    spread, longest = c["compute_s"] / (machines * cores), c["longest_task_s"]
    return serial + max(spread, longest), "parts" if spread >= longest else "longest part"


def write_section(path: Path, text: str) -> None:
    """Replace the measured section of `path` (between MARK and END), or append one."""
    page = path.read_text() if path.is_file() else ""
    block = f"{MARK}\n{text}{END}"
    if MARK in page and END in page:
        page = page[:page.index(MARK)] + block + page[page.index(END) + len(END):]
    else:
        page = page.rstrip("\n") + "\n\n" + block + "\n"
    path.write_text(page)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("images", type=Path, help="a scene's images folder")
    parser.add_argument("--cluster", default=None, help="the cluster measured (default local:2)")
    parser.add_argument("--repeats", type=int, default=3, help="alternated rounds of pool and cluster (3)")
    parser.add_argument("--cores", type=int, default=2, help="cores per machine in the prediction (2)")
    parser.add_argument("--bandwidth", type=float, default=110.0, help="MB/s of the client's link (110)")
    parser.add_argument("--map", action="store_true", help="time the mapping stage once, as a serial term")
    parser.add_argument("--partition-size", type=int, default=0,
                        help="also map in parts of at most P images on the cluster (implies --map)")
    parser.add_argument("--mapping", action="store_true", help=argparse.SUPPRESS)  # mapping_times's run
    parser.add_argument("--work", type=Path, default=Path("out/bench_distributed"), help="scratch folder")
    parser.add_argument("--out", type=Path, default=None, help="markdown page to write the section into")
    parser.add_argument("--front-end", action="store_true", help=argparse.SUPPRESS)  # front_end_times's run
    args = parser.parse_args(argv)
    if args.front_end:
        run_front_end(args.images, args.work, args.cluster)
        return 0
    if args.mapping:
        run_mapping(args.images, args.work, args.cluster, args.partition_size)
        return 0
    args.cluster = args.cluster or "local:2"
    args.work.mkdir(parents=True, exist_ok=True)
    runs = overhead(args.images, args.work, args.cluster, args.repeats)
    last = runs["cluster"][args.repeats - 1]  # the costs of the last cluster run
    model, started, workers = last["costs"], last["started"], last["workers"]
    mapping = {}
    if args.map or args.partition_size:
        source = args.work / "ws-pool"
        mapping["whole"] = mapping_times(args.images, source, args.work / "ws-map-whole", None, 0)
        print(f"mapping on the client: {mapping['whole']['mapping']:.1f} s", flush=True)
    if args.partition_size:
        mapping["parts"] = mapping_times(args.images, source, args.work / "ws-map-parts", args.cluster,
                                         args.partition_size)
        print(f"mapping in parts on {args.cluster}: {mapping['parts']['mapping']:.1f} s", flush=True)
    (args.work / "figures.json").write_text(json.dumps({"runs": runs, "model": model, "cluster_start_s": started,
                                                        "mapping": mapping}, indent=1))
    text = report(args.images, runs, model, started, workers, mapping, args)
    print(text)
    if args.out is not None:
        write_section(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
