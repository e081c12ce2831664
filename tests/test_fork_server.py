"""The pool's fork server started as a fork of the console script (executors.fork_the_fork_server):
workers fork from it and run the same code, it ends with its parent, and a process with other
threads gets the usual new-interpreter server instead."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

pytestmark = pytest.mark.skipif(
    not (sys.platform.startswith("linux") and (3, 11) <= sys.version_info[:2] <= (3, 13)),
    reason="the fork is taken on Linux with CPython 3.11–3.13 only",
)

_SERVER = """
import gc, os, sys, threading, time
if sys.argv[1] == "thread":  # another thread: the fork is not safe, the usual server starts
    threading.Thread(target=time.sleep, args=(30,), daemon=True).start()
from concurrent.futures import ProcessPoolExecutor
import multiprocessing as mp
from multiprocessing import forkserver
from labelaudit import executors as E
assert E.start_fork_server(("labelaudit.constants",), fork=True)
from multiprocessing import resource_tracker
server, tracker = forkserver._forkserver._forkserver_pid, resource_tracker._resource_tracker._pid
me = open("/proc/self/cmdline", "rb").read()
forked = [open(f"/proc/{p}/cmdline", "rb").read() == me for p in (server, tracker)]
with ProcessPoolExecutor(2, mp_context=mp.get_context("forkserver")) as pool:  # semaphores: the tracker's
    parents = {pool.submit(os.getppid).result() for _ in range(4)}
    got = pool.submit(pow, 3, 4).result()
    collects = pool.submit(gc.isenabled).result()  # a worker inherits the server's collector
    frozen = pool.submit(gc.get_freeze_count).result() > 0
for _ in range(100):  # a forked one names itself once it runs
    names = [open(f"/proc/{p}/comm").read().strip() for p in (server, tracker)]
    named = names == [E.FORKED_SERVER_NAME, E.FORKED_TRACKER_NAME]
    if named or not forked[0]:
        break
    time.sleep(0.05)
print(server, tracker, forked[0] == forked[1] == named, forked[0], parents == {server}, got, collects, frozen)
"""


def _gone(pid: int, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":  # a zombie waiting for its reaper: ended
                    return True
        except OSError:
            return True
        time.sleep(0.05)
    return False


@pytest.mark.parametrize("case, forked", [("alone", True), ("thread", False)])
def test_the_fork_server_is_a_fork_only_of_a_single_threaded_process_and_ends_with_it(case, forked):
    done = subprocess.run([sys.executable, "-c", _SERVER, case], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    server, tracker, alike, was_forked, from_server, got, collects, frozen = done.stdout.split()
    assert alike == "True" and was_forked == str(forked) and from_server == "True" and got == "81"
    # the forked server imports its preload with the collector off, then freezes what it holds and
    # collects again: its workers collect, without walking the server's objects
    assert collects == "True" and frozen == str(forked)
    assert _gone(int(server)) and _gone(int(tracker))  # their parent exited: so did they
    assert done.stderr == ""  # no leaked semaphore, no traceback


def test_infer_through_the_console_script_writes_the_same_rows_with_two_workers_as_with_one(tmp_path):
    from labelaudit.sim.dataset import simulate_dataset

    data = tmp_path / "kitti"
    simulate_dataset(data, frames=4, seed=3, progress=False)
    tables = {}
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}"
        done = subprocess.run(
            [sys.executable, "-m", "labelaudit", "infer", data, "-o", out, "--workers", workers, "-q"],
            capture_output=True,
            text=True,
            timeout=600,
            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        )
        assert done.returncode == 0, done.stderr
        tables[workers] = {
            p.relative_to(out): p.read_bytes() for d in ("objects", "missing") for p in (out / d).glob("*")
        }
    assert pq.read_table(tmp_path / "w1" / "objects").num_rows > 0
    assert tables["1"] == tables["2"]  # the shards, byte for byte
