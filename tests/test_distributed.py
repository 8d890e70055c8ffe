"""Scale-out on Ray (drcpo.distributed): a local 2-worker cluster gives the same bytes as one
process for ``drcpo augment`` (also after a stop or a kill, resumed on either engine),
``drcpo build-db`` and ``drcpo index``. Skipped when Ray is not installed; CI's ray step sets
DRCPO_REQUIRE_RAY=1, which turns the skip into a failure."""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from export_support import random_transform, small_kitti, tree_bytes

from drcpo.datasets.export import augment_kitti
from drcpo.errors import ConfigError, DataError
from drcpo.staging import staging_path

REQUIRED = os.environ.get("DRCPO_REQUIRE_RAY") == "1"
RAY_HINT = 'the distributed tests need Ray: pip install -e ".[test,ray]"'


def ray_or_skip() -> None:
    if importlib.util.find_spec("ray") is None:
        if REQUIRED:
            pytest.fail(f"DRCPO_REQUIRE_RAY=1 but Ray is not installed; {RAY_HINT}", pytrace=False)
        pytest.skip(f"Ray is not installed; {RAY_HINT}")


@pytest.fixture(scope="module")
def cluster():
    """One local cluster of 2 workers for the module (starting one takes seconds)."""
    ray_or_skip()
    from drcpo.distributed import connect

    connection = connect("local", workers=2)
    yield connection
    connection.close()


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    return small_kitti(tmp_path_factory.mktemp("kitti") / "root", frames=8)


@pytest.fixture(scope="module")
def database(kitti, tmp_path_factory):
    """A database of the small root's cars, with its index (what DR.CPO needs)."""
    from drcpo.database.build import build_database
    from drcpo.index_build import build_index

    path = tmp_path_factory.mktemp("db") / "db"
    db = build_database(kitti, "train", path, ["Car"])
    build_index(db).save(path)
    return path


def drcpo_pipeline(database):
    from drcpo.database import GroundTruthDatabase
    from drcpo.pipeline import build_pipeline

    return build_pipeline("default", GroundTruthDatabase.open(database))


@pytest.fixture(scope="module")
def reference(kitti, database, tmp_path_factory):
    """One-process outputs: the global augmentation and the default DR.CPO pipeline."""
    base = tmp_path_factory.mktemp("reference")
    augment_kitti(kitti, "train", random_transform(), base / "global", seed=9)
    augment_kitti(kitti, "train", drcpo_pipeline(database), base / "drcpo", seed=9)
    return base


def stop_after(k: int):
    def progress(done: int, total: int) -> None:
        if done >= k:
            raise KeyboardInterrupt

    return progress


# Without Ray ----------------------------------------------------------------------------------
def test_without_ray_the_error_names_the_install(monkeypatch, kitti, tmp_path):
    from drcpo.distributed import augment_kitti_cluster, connect

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    with pytest.raises(ConfigError, match=r"pip install drcpo\[ray\]"):
        connect("local")
    with pytest.raises(ConfigError, match=r"pip install drcpo\[ray\]"):
        augment_kitti_cluster(kitti, "train", random_transform(), tmp_path / "out")
    assert list(tmp_path.iterdir()) == []
    from typer.testing import CliRunner

    from drcpo.cli import app

    args = ["build-db", "--kitti", str(kitti), "--out", str(tmp_path / "db"), "--cluster", "local"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 1 and "pip install drcpo[ray]" in result.output
    assert "Traceback" not in result.output and list(tmp_path.iterdir()) == []


# The work queue -------------------------------------------------------------------------------
def test_work_comes_back_in_item_order_and_a_lost_worker_is_named(cluster):
    import random

    import ray

    from drcpo.distributed.cluster import WorkerLost, in_order, kill_actors, run_on_actors
    from drcpo.distributed.index import BlockRanker

    def slow_square(item):  # pickled by value: the workers need no test module
        time.sleep(random.uniform(0, 0.05))
        return os.getpid(), item * item

    actors = [ray.remote(BlockRanker).remote() for _ in range(2)]
    try:
        ray.get([a.load.remote(slow_square) for a in actors])
        pairs = list(run_on_actors(actors, lambda a, i: a.rank.remote(i), range(20)))
        assert sorted(p for p, _ in pairs) == list(range(20))
        assert len({pid for _, (pid, _) in pairs}) == 2  # both workers took items
        results = in_order(run_on_actors(actors, lambda a, i: a.rank.remote(i), range(20)))
        assert [r for _, r in results] == [i * i for i in range(20)]

        def dies_at_5(item):
            if item == 5:
                os._exit(1)
            return item

        ray.get([a.load.remote(dies_at_5) for a in actors])
        with pytest.raises(WorkerLost, match="rerun the same command"):
            list(run_on_actors(actors, lambda a, i: a.rank.remote(i), range(10)))
    finally:
        kill_actors(actors)


def test_stopping_the_work_finishes_what_workers_started_and_drops_the_rest(cluster, tmp_path):
    """A consumer that stops early (Ctrl-C, an error) returns only when no worker is still in
    the middle of an item (a frame half-written after the call would race the rerun's), and no
    item beyond those already handed out starts."""
    from contextlib import closing

    import ray

    from drcpo.distributed.cluster import kill_actors, run_on_actors
    from drcpo.distributed.index import BlockRanker

    def logged(item):  # a start and an end mark around half a second of work
        (tmp_path / f"start-{item}").touch()
        time.sleep(0.5 if item else 0.05)
        (tmp_path / f"end-{item}").touch()
        return item

    actor_class = ray.remote(num_cpus=1)(BlockRanker)
    actors = [actor_class.remote() for _ in range(2)]
    try:
        ray.get([a.load.remote(logged) for a in actors])
        with closing(run_on_actors(actors, lambda a, i: a.rank.remote(i), range(20))) as work:
            assert next(work)[1] == 0  # item 1 starts after it; item 2 is half done
    finally:
        kill_actors(actors)

    def marks(kind: str) -> set[str]:
        return {p.name.split("-")[1] for p in tmp_path.glob(f"{kind}-*")}

    started = marks("start")
    assert "1" in started and marks("end") == started
    assert started <= {str(i) for i in range(5)}  # 2 handed to each worker, 1 more after item 0
    time.sleep(1.0)
    assert marks("start") == started


# augment --------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["global", "drcpo"])
def test_cluster_augment_equals_one_process(cluster, kitti, database, reference, tmp_path, kind):
    from drcpo.distributed import augment_kitti_cluster

    transform = random_transform() if kind == "global" else drcpo_pipeline(database)
    out = tmp_path / "out"
    summary = augment_kitti_cluster(
        kitti, "train", transform, out, seed=9, cluster=cluster, workers=2
    )
    assert tree_bytes(out) == tree_bytes(reference / kind)
    workers = summary["cluster"]["workers"]
    assert len({w["pid"] for w in workers}) == 2 and os.getpid() not in {w["pid"] for w in workers}
    assert all(w["peak_rss_mb"] > 0 and w["warmup_s"] > 0 for w in workers)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_stopped_cluster_run_resumes_on_either_engine(cluster, kitti, reference, tmp_path):
    from drcpo.distributed import augment_kitti_cluster

    for name, resume in (("cluster", augment_kitti_cluster), ("one", augment_kitti)):
        out = tmp_path / name
        with pytest.raises(KeyboardInterrupt):
            augment_kitti_cluster(
                kitti, "train", random_transform(), out, seed=9, progress=stop_after(3)
            )
        done = len(list((staging_path(out) / "frames").iterdir()))
        assert 3 <= done < 8 and not out.exists()
        extra = {"cluster": cluster} if resume is augment_kitti_cluster else {}
        summary = resume(kitti, "train", random_transform(), out, seed=9, **extra)
        assert summary["resumed"] >= 3
        assert tree_bytes(out) == tree_bytes(reference / "global")
        time.sleep(0.5)  # a worker of the stopped run still writing would show by now
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_bad_frame_on_a_worker_raises_its_own_error(cluster, kitti, tmp_path):
    from drcpo.distributed import augment_kitti_cluster

    root = tmp_path / "kitti"
    shutil.copytree(kitti, root)
    (root / "training" / "velodyne" / "000005.bin").write_bytes(b"12345")  # not N x 4 float32
    with pytest.raises(DataError, match="000005.bin"):
        augment_kitti_cluster(root, "train", random_transform(), tmp_path / "out", cluster=cluster)
    assert (staging_path(tmp_path / "out") / "frames").is_dir()
    assert not (tmp_path / "out").exists()


def test_cli_augment_on_the_cluster(cluster, kitti, database, reference, tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    out = tmp_path / "out"
    args = ["augment", "--kitti", str(kitti), "--db", str(database), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--seed", "9", "--cluster", "local", "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert tree_bytes(out) == tree_bytes(reference / "drcpo")


def test_a_killed_cluster_run_resumes(kitti, database, reference, tmp_path):
    """The driver of a local cluster killed with SIGKILL after some frames; the same command
    again finishes the others and the output equals the one-process run."""
    ray_or_skip()
    out = tmp_path / "out"
    command = [sys.executable, "-m", "drcpo.cli", "augment", "--kitti", str(kitti)]
    command += ["--db", str(database), "--out", str(out), "--seed", "9"]
    command += ["--cluster", "local", "--workers", "2"]
    records = staging_path(out) / "frames"
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    process = subprocess.Popen(command, env=env, start_new_session=True, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and process.poll() is None:
            if records.is_dir() and len(list(records.iterdir())) >= 2:
                break
            time.sleep(0.02)
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # the driver and the cluster it started
        process.wait()
    assert process.returncode == -signal.SIGKILL, process.stderr.read().decode()[-2000:]
    assert not out.exists()
    done = len(list(records.iterdir()))
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert tree_bytes(out) == tree_bytes(reference / "drcpo")
    assert done >= 2


# build-db and index ---------------------------------------------------------------------------
def test_cluster_build_db_equals_one_process(cluster, kitti, database, tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app
    from drcpo.database import GroundTruthDatabase
    from drcpo.distributed import build_database_cluster

    seen = []
    db = build_database_cluster(
        kitti,
        "train",
        tmp_path / "db",
        ["Car"],
        progress=lambda d, t: seen.append(d),
        cluster=cluster,
    )
    assert seen == list(range(1, 9))
    assert db.checksum == GroundTruthDatabase.open(database).checksum
    one = {k: v for k, v in tree_bytes(database).items() if not k.startswith("index/")}
    assert tree_bytes(tmp_path / "db") == one
    args = ["build-db", "--kitti", str(kitti), "--out", str(tmp_path / "cli"), "--classes", "Car"]
    result = CliRunner().invoke(app, [*args, "--cluster", "local", "--workers", "2"])
    assert result.exit_code == 0, result.output
    assert tree_bytes(tmp_path / "cli") == one


def test_cluster_build_db_of_a_nuscenes_style_data_set_equals_one_process(cluster, tmp_path):
    """Any data set of frames (here nuScenes-style, 5-feature multi-sweep points, velocities)
    goes to the actors whole and gives the one-process database."""
    from typer.testing import CliRunner

    from drcpo.cli import app
    from drcpo.database.build import build_database_from
    from drcpo.datasets.nuscenes import NuScenesDataset
    from drcpo.distributed import build_dataset_cluster
    from drcpo.synth.nuscenes import NuScenesSynthConfig, write_synthetic_nuscenes

    root = tmp_path / "nuscenes"
    config = NuScenesSynthConfig(samples=3, sweeps_before=2)
    write_synthetic_nuscenes(root, 2, seed=5, config=config, version="v1.0-mini")
    dataset = NuScenesDataset(root, "v1.0-mini", sweeps=2)
    one = build_database_from(dataset, tmp_path / "one", ["car", "pedestrian", "bicycle"])
    spread = build_dataset_cluster(
        dataset, tmp_path / "spread", ["car", "pedestrian", "bicycle"], cluster=cluster
    )
    assert one.velocity is not None and one.point_features == ("intensity", "time_lag")
    assert tree_bytes(tmp_path / "spread") == tree_bytes(tmp_path / "one")
    assert spread.checksum == one.checksum
    args = ["build-db", "--nuscenes", str(root), "--version", "v1.0-mini", "--sweeps", "2"]
    args += ["--out", str(tmp_path / "cli"), "--classes", "car,pedestrian,bicycle"]
    result = CliRunner().invoke(app, [*args, "--cluster", "local", "--workers", "2"])
    assert result.exit_code == 0, result.output
    cli_db = tree_bytes(tmp_path / "cli")
    assert {k: v for k, v in cli_db.items() if k != "manifest.json"} == {
        k: v for k, v in tree_bytes(tmp_path / "one").items() if k != "manifest.json"
    }


def many_objects(seed: int = 3):
    """A database of 300 cars and 120 pedestrians of random sizes and points (many blocks)."""
    import numpy as np

    from drcpo.database import GroundTruthDatabase, ObjectRecord

    rng = np.random.default_rng(seed)
    records = []
    for name, count, size in (("Car", 300, (4.0, 1.7, 1.5)), ("Pedestrian", 120, (0.8, 0.6, 1.7))):
        for _ in range(count):
            dims = np.asarray(size) * rng.uniform(0.8, 1.2, 3)
            points = (rng.uniform(-0.5, 0.5, (int(rng.integers(6, 80)), 3)) * dims).astype(
                np.float32
            )
            points = np.column_stack([points, rng.uniform(0, 1, len(points))]).astype(np.float32)
            records.append(ObjectRecord(points, name, np.r_[0.0, 0.0, 0.0, dims, 0.0]))
    return GroundTruthDatabase.from_records(records)


@pytest.mark.parametrize("approximate_above", [None, 100])
def test_cluster_index_equals_one_process(cluster, tmp_path, approximate_above):
    import numpy as np

    from drcpo.database import GroundTruthDatabase
    from drcpo.distributed import build_index_cluster
    from drcpo.index import IndexConfig
    from drcpo.index_build import build_index

    many_objects().save(tmp_path / "db")
    database = GroundTruthDatabase.open(tmp_path / "db")
    config = IndexConfig(k=20, block_size=16, approximate_above=approximate_above)
    one = build_index(database, config)
    seen: dict[str, list[int]] = {}
    spread = build_index_cluster(
        database, config, lambda name, d, t: seen.setdefault(name, []).append(d), cluster=cluster
    )
    assert seen["Car"][-1] == 300 and len(seen["Car"]) == 300 // 16 + 1
    assert np.array_equal(one.candidates, spread.candidates)
    assert np.array_equal(one.densities, spread.densities)
    assert (one.candidates[:, 0] >= 0).all()  # every object got candidates
    assert one.classes == spread.classes
    one.save(tmp_path / "one")
    spread.save(tmp_path / "spread")
    assert tree_bytes(tmp_path / "one") == tree_bytes(tmp_path / "spread")


def test_cli_index_on_the_cluster(cluster, database, tmp_path):
    from typer.testing import CliRunner

    from drcpo.cli import app

    db = tmp_path / "db"
    shutil.copytree(database, db)
    result = CliRunner().invoke(
        app, ["index", str(db), "--overwrite", "--cluster", "local", "--workers", "2"]
    )
    assert result.exit_code == 0, result.output
    assert tree_bytes(db / "index") == tree_bytes(database / "index")
