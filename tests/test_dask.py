"""``infer --scheduler``: the Dask executor on a real ``distributed.LocalCluster`` (processes, 2 workers).

Rows must equal the process pool's bit for bit; a worker killed mid-run must change nothing; a
killed client must leave a folder the next run resumes; a scheduler that cannot be reached or
runs another labelaudit must be exit 2 naming the address / both versions (docs/scale.md).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from labelaudit import results as R
from labelaudit.errors import ClusterError, UsageError
from labelaudit.executors import DaskExecutor, PoolExecutor, make_executor, parse_scheduler
from labelaudit.infer.run import InferRequest, resolve_config, run_infer

distributed = pytest.importorskip("distributed")
import cloudpickle  # noqa: E402

cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test module

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- no cluster needed


def test_parse_scheduler_addresses_and_worker_counts():
    assert parse_scheduler("tcp://10.0.0.5:8786") == ("tcp://10.0.0.5:8786", None)
    assert parse_scheduler("sched.example:8786") == ("tcp://sched.example:8786", None)
    assert parse_scheduler("local:3") == (None, 3)
    assert parse_scheduler("local", workers=2) == (None, 2)
    assert parse_scheduler("local")[1] == (os.cpu_count() or 1)
    for bad in ("nonsense", "tcp://host", "local:0", "local:x", "http://h:80/path"):
        with pytest.raises(UsageError, match="--scheduler"):
            parse_scheduler(bad)
    with pytest.raises(UsageError, match="disagree"):
        parse_scheduler("local:2", workers=3)
    with pytest.raises(UsageError, match="drop --workers"):
        parse_scheduler("tcp://h:8786", workers=2)
    assert isinstance(make_executor(None, scheduler="local:2"), DaskExecutor) and isinstance(
        make_executor(2, scheduler="local"), DaskExecutor
    )


def test_run_module_keeps_the_core_out_of_the_main_process():
    """The process that plans and writes never imports Open3D, numba or Dask (start-up cost)."""
    code = (
        "import sys, labelaudit.cli.infer, labelaudit.infer.run, labelaudit.executors, labelaudit.config as c; c.constants_digest();"
        "bad = [m for m in ('open3d', 'numba', 'distributed', 'dask', 'scipy.stats', 'labelaudit.core.posterior') if m in sys.modules];"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_unreachable_scheduler_is_exit_2_naming_the_address(tmp_path):
    from labelaudit.sim.dataset import simulate_dataset

    data = tmp_path / "sim"
    simulate_dataset(data, frames=1, seed=1, progress=False)
    address = f"tcp://127.0.0.1:{_free_port()}"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    t = time.perf_counter()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "labelaudit.cli",
            "infer",
            str(data),
            "-o",
            str(tmp_path / "res"),
            "--scheduler",
            address,
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    elapsed = time.perf_counter() - t
    assert done.returncode == 2, done.stderr
    assert address in done.stderr and "Traceback" not in done.stderr
    assert elapsed < 30.0
    assert not (tmp_path / "res" / R.OBJECTS_DIR).exists()  # failed before the folder was touched


# --------------------------------------------------------------------------- a real LocalCluster


@pytest.fixture(scope="module")
def cluster():
    from labelaudit import constants as C

    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0", preload=list(C.WORKER_PRELOAD)
        ) as cl,
        distributed.Client(cl, set_as_default=False) as client,
    ):
        client.wait_for_workers(2, timeout=120)
        yield cl, client


@pytest.fixture(scope="module")
def sim_data(tmp_path_factory) -> Path:
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.noise import NoiseSpec

    root = tmp_path_factory.mktemp("dask") / "sim"
    simulate_dataset(root, frames=10, seed=5, noise=NoiseSpec(fraction=0.3, gross_fraction=0.1), progress=False)
    return root


@pytest.fixture(scope="module")
def pool_rows(sim_data, tmp_path_factory) -> list[dict]:
    out = tmp_path_factory.mktemp("pool") / "res"
    run_infer(
        InferRequest(sim_data, out, chunk_units=1), resolve_config(None, "kitti", ["all"]), executor=PoolExecutor(2)
    )
    return _rows(out)


def _rows(out: Path) -> list[dict]:
    return sorted(R.open_results(out).read().to_pylist(), key=lambda r: (r["frame_id"], r["object_index"]))


@pytest.mark.slow
def test_dask_rows_equal_the_pool_rows(cluster, sim_data, pool_rows, tmp_path):
    cl, _ = cluster
    cfg = resolve_config(None, "kitti", ["all"])
    summary = run_infer(
        InferRequest(sim_data, tmp_path / "res", chunk_units=1), cfg, executor=DaskExecutor(cl.scheduler_address)
    )
    assert summary.chunks == 10 and summary.frames == 10 and summary.failed_frames == 0
    assert _rows(tmp_path / "res") == pool_rows and len(pool_rows) > 50
    assert len(list((tmp_path / "res" / R.OBJECTS_DIR).glob("*.parquet"))) == 10


@pytest.mark.slow
def test_dask_rows_equal_the_pool_rows_on_argoverse2_logs(cluster, tmp_path):
    """A log is one unit: its frames travel to a worker by path and come back as the pool's rows."""
    from labelaudit.sim.av2_writer import simulate_av2_log, write_av2_log
    from labelaudit.sim.noise import NoiseSpec

    for seed in (0, 1):
        write_av2_log(
            simulate_av2_log(seed=seed, frames=2, label_noise=NoiseSpec(fraction=0.3, gross_fraction=0.1)),
            tmp_path / "av2" / "val",
        )
    cl, _ = cluster
    cfg = resolve_config(None, "av2")
    run_infer(InferRequest(tmp_path / "av2", tmp_path / "pool"), cfg, executor=PoolExecutor(2))
    summary = run_infer(
        InferRequest(tmp_path / "av2", tmp_path / "dask"), cfg, executor=DaskExecutor(cl.scheduler_address)
    )
    assert summary.chunks == 2 and summary.frames == 4 and summary.failed_frames == 0
    rows = _rows(tmp_path / "dask")
    assert rows == _rows(tmp_path / "pool") and len(rows) > 10 and {r["dataset"] for r in rows} == {"av2"}


def _exit_soon() -> None:
    """Run on a worker: die (no cleanup, like a crash) just after answering."""
    import threading

    threading.Timer(0.05, os._exit, args=(1,)).start()


class _KillOneWorker:
    """Progress sink that, at the first finished chunk, kills a worker that is computing a task."""

    def __init__(self, client):
        self.client = client
        self.killed: str | None = None
        self.before: set[str] = set()
        self.results = 0

    def start(self, total_units, done_units):
        pass

    def advance(self, result):
        self.results += 1
        if self.killed is None:
            busy = [w for w, keys in self.client.processing().items() if keys]
            assert busy, "no worker had a task in flight"
            self.before = set(self.client.scheduler_info()["workers"])
            self.killed = busy[0]
            self.client.run(_exit_soon, workers=[self.killed])

    def stop(self):
        pass


@pytest.mark.slow
def test_a_worker_killed_mid_run_changes_no_row(cluster, sim_data, pool_rows, tmp_path):
    cl, client = cluster
    killer = _KillOneWorker(client)
    cfg = resolve_config(None, "kitti", ["all"])
    summary = run_infer(
        InferRequest(sim_data, tmp_path / "res", chunk_units=1),
        cfg,
        killer,
        executor=DaskExecutor(cl.scheduler_address),
    )
    assert killer.killed is not None and killer.results == 10  # every chunk came back once
    assert summary.chunks == 10 and summary.frames == 10
    assert _rows(tmp_path / "res") == pool_rows
    # the worker really died (its nanny starts a new one under another address)
    client.wait_for_workers(2, timeout=120)
    assert killer.killed not in set(client.scheduler_info()["workers"])


@pytest.mark.slow
def test_resume_after_a_killed_client(cluster, sim_data, pool_rows, tmp_path):
    cl, _ = cluster
    out = tmp_path / "res"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [
        sys.executable,
        "-m",
        "labelaudit.cli",
        "infer",
        str(sim_data),
        "-o",
        str(out),
        "--classes",
        "all",
        "--scheduler",
        cl.scheduler_address,
        "-q",
    ]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    shards = out / R.OBJECTS_DIR
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline and proc.poll() is None and not list(shards.glob("*.parquet")):
        time.sleep(0.02)
    assert proc.poll() is None, "the client finished before it could be killed: " + proc.stderr.read().decode()
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    kept = {p.name: p.stat().st_mtime_ns for p in shards.glob("*.parquet")}
    assert 0 < len(kept) < 10
    done = subprocess.run(cmd[:-1], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert {p.name: p.stat().st_mtime_ns for p in shards.glob("*.parquet") if p.name in kept} == kept  # not recomputed
    assert f"({len(kept)} of 10 shards already done)" in done.stderr
    assert _rows(out) == pool_rows


def _set_worker_version(version: str | None) -> str:
    import labelaudit
    from labelaudit import executors

    old = getattr(labelaudit, "_true_version", labelaudit.__version__)
    labelaudit._true_version = old  # type: ignore[attr-defined]
    labelaudit.__version__ = version or old
    executors.code_fingerprint.cache_clear()
    return old


@pytest.mark.slow
def test_workers_of_another_labelaudit_are_refused_naming_both_versions(cluster, sim_data, tmp_path):
    cl, client = cluster
    import labelaudit

    client.run(_set_worker_version, "9.9.9")
    try:
        ex = DaskExecutor(cl.scheduler_address)
        with pytest.raises(
            ClusterError,
            match=r"labelaudit 9\.9\.9.*this client labelaudit " + labelaudit.__version__.replace(".", r"\."),
        ):
            ex.start()
        ex.close()
        # a worker that changes after the connect-time check is caught by the task itself
        ex = DaskExecutor(cl.scheduler_address)
        client.run(_set_worker_version, None)
        ex.start()
        client.run(_set_worker_version, "9.9.9")
        cfg = resolve_config(None, "kitti", ["all"])
        with pytest.raises(ClusterError, match=r"9\.9\.9"):
            run_infer(InferRequest(sim_data, tmp_path / "res", chunk_units=5), cfg, executor=ex)
    finally:
        client.run(_set_worker_version, None)


@pytest.mark.slow
def test_local_cluster_of_the_executor_gives_the_pool_rows(sim_data, pool_rows, tmp_path):
    """``--scheduler local:2``: the executor starts (and stops) its own LocalCluster, preloaded."""
    cfg = resolve_config(None, "kitti", ["all"])
    ex = DaskExecutor(None, 2)
    run_infer(InferRequest(sim_data, tmp_path / "res", chunk_units=3), cfg, executor=ex)
    assert ex._client is None and ex._cluster is None  # closed after the run
    assert _rows(tmp_path / "res") == pool_rows


class _Threads:
    """Chunks on several threads of this process, as a Dask worker started with ``--nthreads 4`` runs them."""

    def start(self) -> None:
        pass

    def run(self, units, fn):
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(4) as pool:
            yield from pool.map(fn, units)

    def close(self) -> None:
        pass


def test_chunks_on_several_threads_of_one_worker_give_the_pool_rows(sim_data, pool_rows, tmp_path):
    cfg = resolve_config(None, "kitti", ["all"])
    run_infer(InferRequest(sim_data, tmp_path / "res", chunk_units=1), cfg, executor=_Threads())
    assert _rows(tmp_path / "res") == pool_rows


def test_local_cluster_workers_fork_from_the_preloaded_fork_server():
    """``local:N`` workers are children of the fork server, not fresh interpreters started by the
    nanny (which runs in this process): they start with the core already imported."""
    ex = DaskExecutor(None, 2)
    ex.start()
    try:
        parents = ex._client.run(os.getppid)
        loaded = ex._client.run(
            lambda: "labelaudit.core.posterior" in sys.modules and "multiprocessing.forkserver" in sys.modules
        )
        profiling = ex._client.run(lambda: __import__("dask").config.get("distributed.worker.profile.enabled"))
    finally:
        ex.close()
    assert len(parents) == 2 and os.getpid() not in parents.values()
    assert all(loaded.values())
    assert set(profiling.values()) == {False}  # constants.DASK_LOCAL_CONFIG reached the workers


def test_open3d_loads_on_first_use_without_its_plotting_chain_and_still_plots():
    code = (
        "import sys, labelaudit.infer.crop as c;"
        "assert 'open3d' not in sys.modules, 'Open3D loaded by the import';"
        "o3d = c.open3d();"
        "assert not {'dash', 'plotly'} & set(sys.modules), 'plotting chain loaded';"
        "import numpy as np;"
        "pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.rand(5, 3)));"
        "fig = o3d.visualization.get_plotly_fig([pc]);"
        "assert type(fig).__name__ == 'Figure' and 'plotly' in sys.modules"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr


def test_fork_server_marker_skips_the_teardown_only_in_the_marked_server():
    """With the marker of its parent and the fork server module loaded, exit skips the teardown
    (here visible as exit code 0 instead of 3); without the marker nothing changes."""
    from labelaudit.executors import FORK_SERVER_ENV

    code = "import sys, multiprocessing.forkserver, labelaudit.infer.warmup; sys.exit(3)"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    marked = subprocess.run(
        [sys.executable, "-c", code], env={**env, FORK_SERVER_ENV: str(os.getpid())}, capture_output=True
    )
    other = subprocess.run([sys.executable, "-c", code], env={**env, FORK_SERVER_ENV: "1"}, capture_output=True)
    plain = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True)
    assert (marked.returncode, other.returncode, plain.returncode) == (0, 3, 3)


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_allocator_tuning_takes_on_glibc():
    """Workers keep freed blocks for the next box (constants.MALLOC_*): glibc accepts both settings."""
    from labelaudit.executors import tune_allocator

    tune_allocator.cache_clear()
    assert tune_allocator() is True
