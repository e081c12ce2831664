"""The CLI through Typer's test runner: help texts, exit codes 0/1/2, stdout vs stderr, end to end."""

from __future__ import annotations

import csv
import io
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from labelaudit import __version__
from labelaudit import results as R
from labelaudit.cli import app
from results_factory import make_results, make_row

runner = CliRunner()
COMMANDS = ["infer", "rank", "check", "simulate", "demo", "export", "eval"]


def invoke(*args: str):
    return runner.invoke(app, [str(a) for a in args])


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help_with_an_example(command):
    result = invoke(command, "--help")
    assert result.exit_code == 0
    assert "Examples" in result.stdout
    assert f"labelaudit {command}" in result.stdout


def test_top_level_help_and_version():
    result = invoke("--help")
    assert result.exit_code == 0 and all(c in result.stdout for c in COMMANDS)
    result = invoke("--version")
    assert result.exit_code == 0 and result.stdout.strip() == f"labelaudit {__version__}"


# --------------------------------------------------------------------------- check


@pytest.fixture()
def good(tmp_path) -> Path:
    return make_results(tmp_path / "good", [[make_row("000001", i, jiou_gt=0.85) for i in range(20)]])


@pytest.fixture()
def bad(tmp_path) -> Path:
    return make_results(tmp_path / "bad", [[make_row("000001", i, jiou_gt=0.2) for i in range(20)]])


def test_check_pass_exit_0_table_on_stdout(good):
    result = invoke("check", good)
    assert result.exit_code == 0, result.output
    assert "min_median_jiou_gt" in result.stdout and "PASS" in result.stdout


def test_check_fail_exit_1_with_json_and_junit(bad, tmp_path):
    junit = tmp_path / "reports" / "gate.xml"
    result = invoke("check", bad, "--json", "--junit", junit)
    assert result.exit_code == 1
    data = json.loads(result.stdout)  # stdout is pure JSON
    assert data["verdict"] == "FAIL"
    failed = {r["rule"] for r in data["rules"] if r["status"] == "fail"}
    assert {"min_median_jiou_gt", "max_fraction_jiou_gt_below"} <= failed
    suite = ET.parse(junit).getroot().find("testsuite")
    assert int(suite.get("failures")) == len([r for r in data["rules"] if r["status"] == "fail"])


def test_check_exit_2_cases(tmp_path, good):
    empty = make_results(tmp_path / "empty", [[]])
    r = invoke("check", empty)
    assert r.exit_code == 2 and "no objects" in r.stderr
    r = invoke("check", tmp_path / "does-not-exist")
    assert r.exit_code == 2 and "does-not-exist" in r.stderr and "labelaudit infer" in r.stderr
    gate = tmp_path / "gate.toml"
    gate.write_text("[default]\nmin_median_jiou = 0.5\n")
    r = invoke("check", good, "--config", gate)
    assert r.exit_code == 2 and "gate.toml" in r.stderr and "min_median_jiou" in r.stderr
    assert "Traceback" not in r.output
    skipped = make_results(tmp_path / "skipped", [[make_row("000001", 0, status="skipped", message="too long")]])
    r = invoke("check", skipped)
    assert r.exit_code == 2  # nothing evaluable: never 0
    incomplete = make_results(tmp_path / "incomplete", [[make_row("000001", 0)]], complete=False)
    r = invoke("check", incomplete)
    assert r.exit_code == 2 and "did not finish" in r.stderr


def test_check_uses_a_custom_gate(bad, tmp_path):
    lenient = tmp_path / "lenient.toml"
    lenient.write_text("[default]\nmin_median_jiou_gt = 0.1\n")
    assert invoke("check", bad, "--config", lenient).exit_code == 0


# --------------------------------------------------------------------------- rank


@pytest.fixture()
def mixed(tmp_path) -> Path:
    rows = [
        make_row("000001", i, jiou_gt=j, label_error=e) for i, (j, e) in enumerate([(0.9, 0.1), (0.3, 0.8), (0.6, 0.4)])
    ]
    rows.append(make_row("000002", 0, "Pedestrian", jiou_gt=0.1, label_error=0.2))
    return make_results(tmp_path / "mixed", [rows])


def test_rank_json_default_is_lowest_jiou_first(mixed):
    r = invoke("rank", mixed, "--format", "json", "--top", "3")
    assert r.exit_code == 0, r.output
    records = json.loads(r.stdout)
    assert [x["jiou_gt"] for x in records] == [0.1, 0.3, 0.6]
    assert set(R.COLUMN_NAMES) <= set(records[0])


def test_rank_label_error_descending_and_asc_override(mixed):
    r = invoke("rank", mixed, "--by", "label_error", "--format", "json")
    assert [x["label_error"] for x in json.loads(r.stdout)] == [0.8, 0.4, 0.2, 0.1]
    r = invoke("rank", mixed, "--by", "label_error", "--asc", "--format", "json", "--top", "1")
    assert [x["label_error"] for x in json.loads(r.stdout)] == [0.1]


def test_rank_csv_and_class_filter(mixed):
    r = invoke("rank", mixed, "--format", "csv", "--class", "Car")
    rows = list(csv.DictReader(io.StringIO(r.stdout)))
    assert [row["class_name"] for row in rows] == ["Car"] * 3
    assert [float(row["jiou_gt"]) for row in rows] == [0.3, 0.6, 0.9]


def test_rank_table_and_usage_errors(mixed, tmp_path):
    r = invoke("rank", mixed, "--top", "2")
    assert r.exit_code == 0 and "000002" in r.stdout and "jiou_gt" in r.stdout
    r = invoke("rank", mixed, "--by", "class_name")
    assert r.exit_code == 2 and "not a numeric column" in r.stderr
    r = invoke("rank", mixed, "--status", "fine")
    assert r.exit_code == 2
    r = invoke("rank", tmp_path / "nothing-here")
    assert r.exit_code == 2 and "nothing-here" in r.stderr


# --------------------------------------------------------------------------- infer / simulate / demo


def test_infer_bad_inputs_exit_2_with_one_line(tmp_path):
    r = invoke("infer", tmp_path / "no-such-dataset", "-o", tmp_path / "out")
    assert r.exit_code == 2
    assert r.stderr.strip().count("\n") == 0 and "no-such-dataset" in r.stderr and "Traceback" not in r.output
    r = invoke("infer", tmp_path, "--workers", "0")
    assert r.exit_code == 2


def test_infer_unknown_config_key_exit_2(tmp_path):
    from labelaudit.sim.dataset import simulate_dataset

    data = tmp_path / "data"
    simulate_dataset(data, frames=1, seed=0, progress=False)
    cfg = tmp_path / "model.toml"
    cfg.write_text("[model]\nsigmaa = 0.2\n")
    r = invoke("infer", data, "-o", tmp_path / "out", "--config", cfg)
    assert r.exit_code == 2 and "model.toml" in r.stderr and "sigmaa" in r.stderr


def test_simulate_writes_a_kitti_dataset(tmp_path):
    out = tmp_path / "sim"
    r = invoke("simulate", out, "--frames", "2", "--seed", "4", "--noise-fraction", "0.5", "-q")
    assert r.exit_code == 0, r.output
    assert len(list((out / "training" / "velodyne").glob("*.bin"))) == 2 and (out / "manifest.parquet").is_file()
    assert invoke("simulate", out, "--frames", "2", "-q").exit_code == 2  # exists, no --overwrite
    assert invoke("simulate", out, "--frames", "0").exit_code == 2


def test_simulate_see_through_vehicles(tmp_path):
    out = tmp_path / "sim"
    r = invoke("simulate", out, "--frames", "2", "--see-through", "0.5", "--under-chassis", "1", "-q")
    assert r.exit_code == 0, r.output
    table = pq.read_table(out / "manifest.parquet")
    assert sum(table.column("glass_rays").to_pylist()) > 0 and sum(table.column("under_rays").to_pylist()) > 0
    r = invoke("simulate", tmp_path / "bad", "--see-through", "1.5")
    assert r.exit_code == 2 and "--see-through" in r.stderr and "1.5" in r.stderr
    r = invoke("simulate", tmp_path / "seq", "--dataset-format", "av2", "--under-chassis", "0.5")
    assert r.exit_code == 2 and "KITTI only" in r.stderr


@pytest.mark.slow
def test_infer_rank_check_end_to_end_and_resume(tmp_path):
    r = invoke("simulate", tmp_path / "data", "--frames", "4", "--seed", "2", "--gross-fraction", "0.2", "-q")
    assert r.exit_code == 0, r.output
    out = tmp_path / "res"
    r = invoke("infer", tmp_path / "data", "-o", out, "--workers", "1")
    assert r.exit_code == 0, r.output
    assert r.stdout == ""  # progress and summary go to stderr
    assert "median JIoU-GT" in r.stderr
    manifest = R.read_manifest(out)
    assert manifest["complete"] and manifest["format"] == "kitti"
    r = invoke("rank", out, "--format", "json", "--top", "5")
    values = [x["jiou_gt"] for x in json.loads(r.stdout)]
    assert values == sorted(values) and len(values) == 5
    assert invoke("check", out, "--json").exit_code in (0, 1)
    # same options: resumes (nothing to do); other parameters: refused unless --overwrite
    r = invoke("infer", tmp_path / "data", "-o", out, "--workers", "1", "-q")
    assert r.exit_code == 0
    r = invoke("infer", tmp_path / "data", "-o", out, "--classes", "all", "-q")
    assert r.exit_code == 2 and "--overwrite" in r.stderr
    r = invoke("infer", tmp_path / "data", "-o", out, "--classes", "all", "--overwrite", "-q", "--workers", "1")
    assert r.exit_code == 0, r.output


@pytest.mark.slow
def test_demo_runs_the_whole_loop(tmp_path):
    r = invoke("demo", tmp_path / "demo", "--frames", "4", "--workers", "1")
    assert r.exit_code == 0, r.output
    assert "worst" in r.stdout and "labelaudit check" in r.stdout
    assert (tmp_path / "demo" / "results" / "manifest.json").is_file()
    # it ends with a short eval of a synthetic detector, included in the report
    assert "5/6 eval" in r.stderr and "JIoU-ratio" in r.stdout
    assert (tmp_path / "demo" / "eval" / "summary.json").is_file()
    assert "JIoU" in (tmp_path / "demo" / "report.html").read_text()


def test_rank_where_option(mixed):
    r = invoke("rank", mixed, "--where", "label_error>=0.4", "--format", "json")
    assert r.exit_code == 0, r.output
    assert sorted(x["label_error"] for x in json.loads(r.stdout)) == [0.4, 0.8]
    r = invoke("rank", mixed, "--where", "oops")
    assert r.exit_code == 2 and "COLUMN OP VALUE" in r.stderr


def test_internal_errors_exit_3_with_one_line_and_debug_shows_the_traceback(mixed, monkeypatch):
    import labelaudit.rank

    def boom(*a, **k):
        raise RuntimeError("a bug")

    monkeypatch.setattr(labelaudit.rank, "rank_results", boom)
    r = invoke("rank", mixed)
    assert r.exit_code == 3 and "a bug" in r.stderr and "--debug" in r.stderr and "Traceback" not in r.output
    r = invoke("rank", mixed, "--debug")
    assert r.exit_code != 0 and isinstance(r.exception, RuntimeError)


def test_rank_notes_incomplete_results(tmp_path):
    partial = make_results(tmp_path / "partial", [[make_row("000001", 0)]], complete=False)
    r = invoke("rank", partial, "--format", "json")
    assert r.exit_code == 0 and len(json.loads(r.stdout)) == 1 and "incomplete" in r.stderr


def test_the_console_script_starts_infers_fork_server_only_when_a_pool_will_run():
    import os
    import subprocess
    import sys

    from labelaudit import __main__ as launch
    from labelaudit import constants as C
    from labelaudit.executors import fork_server_preload, local_cluster_preload

    assert fork_server_preload(2) == tuple(C.WORKER_PRELOAD)
    assert fork_server_preload(None) == (tuple(C.WORKER_PRELOAD) if (os.cpu_count() or 1) > 1 else None)
    assert (
        fork_server_preload(1) is None and fork_server_preload(0) is None
    )  # serial; a bad count is the command's to report
    assert fork_server_preload(None, "local:2") == local_cluster_preload()
    assert (
        fork_server_preload(None, "tcp://h:8786") is None and fork_server_preload(3, "tcp://h:8786") is None
    )  # a usage error, reported later
    for argv in (
        ["labelaudit", "rank", "r/"],
        ["labelaudit", "infer", "d", "--workers", "1"],
        ["labelaudit", "infer", "d", "--workers=x"],
        ["labelaudit", "infer", "d", "--workers", "2", "--help"],
        ["labelaudit", "infer", "d", "--scheduler", "tcp://h:1"],
        ["labelaudit"],
    ):
        assert launch.start_infer_fork_server(argv) is False, argv
    assert (
        launch.start_infer_fork_server(["labelaudit", "infer", "d", "--workers=2", "-o", "out"]) is True
    )  # the pool's own preload
    done = subprocess.run([sys.executable, "-m", "labelaudit", "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "infer" in done.stdout
    from importlib.metadata import entry_points

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "labelaudit"]
    assert script.value == "labelaudit.__main__:main"


def test_the_console_script_runs_infers_main_process_with_one_blas_thread_unless_told():
    """``labelaudit infer``'s main process only plans and writes: it sets one BLAS thread before NumPy
    loads (OpenBLAS's idle threads spin through the imports), keeps a number the caller set, and
    leaves other commands alone."""
    import os
    import subprocess
    import sys

    probe = (
        "import os, sys; sys.argv = {argv!r}; import labelaudit.cli as c; "
        "c.main = lambda: print(os.environ.get('OPENBLAS_NUM_THREADS'), 'numpy' in sys.modules); "
        "import labelaudit.__main__ as m; m.main()"
    )
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
    }

    def run(argv, **extra):
        code = probe.format(argv=argv)
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env={**env, **extra}
        )
        assert done.returncode == 0, done.stderr
        return done.stdout.split()

    # set before NumPy was imported (the CLI's own modules do not load it), so OpenBLAS reads it
    assert run(["labelaudit", "infer", "d", "--workers", "1"]) == ["1", "False"]
    assert run(["labelaudit", "infer", "d", "--workers", "1"], OPENBLAS_NUM_THREADS="3")[0] == "3"
    assert run(["labelaudit", "rank", "r/"])[0] == "None"


def test_the_console_script_collects_no_garbage_during_start_up_and_every_command_runs_with_the_collector_on():
    """The console script turns the garbage collector off while it imports and builds the command
    group; the group's callback freezes what the start-up made and turns it back on, so a command
    (here a probe registered on the app) runs with it on. Outside the console script (Typer's test
    runner) nothing is frozen."""
    import subprocess
    import sys

    probe = (
        "import gc, sys; from labelaudit.cli import app; "
        "app.command('probe')(lambda: print(gc.isenabled(), gc.get_freeze_count() > 0)); "
        "sys.argv = ['labelaudit', 'probe']; import labelaudit.__main__ as m; m.main()"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "True"]
    import gc

    before = gc.get_freeze_count()
    r = invoke("rank", "--help")
    assert r.exit_code == 0 and gc.isenabled() and gc.get_freeze_count() == before


def test_infer_ends_without_the_interpreters_teardown_and_loses_nothing():
    """``labelaudit infer`` exits without tearing down its modules (an object held by a module is never
    finalised), after the exit handlers ran and buffered output was flushed, with the command's exit
    code; another command, a text exit code, a non-daemon thread or a child process still running take
    the usual exit."""
    import subprocess
    import sys

    probe = (
        "import atexit, sys, threading, time\n"
        "class Held:\n"
        "    def __del__(self):\n"
        "        print('torn down', flush=True)\n"
        "held = Held()\n"
        "sys.argv = {argv!r}\n"
        "import labelaudit.cli as c\n"
        "def command():\n"
        "    atexit.register(print, 'exit handler')\n"
        "    print('written')\n"
        "    {extra}\n"
        "    raise SystemExit({code!r})\n"
        "c.main = command\n"
        "import labelaudit.__main__ as m; m.main()\n"
    )

    def run(argv, code, extra="pass"):
        done = subprocess.run(
            [sys.executable, "-c", probe.format(argv=argv, code=code, extra=extra)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        return done.returncode, done.stdout.split("\n")[:-1], done.stderr

    infer = ["labelaudit", "infer", "d", "--workers", "1"]
    assert run(infer, 3)[:2] == (3, ["written", "exit handler"])
    assert run(infer, None)[:2] == (0, ["written", "exit handler"])
    assert run(["labelaudit", "rank", "r/"], 3)[:2] == (3, ["written", "exit handler", "torn down"])
    late = "threading.Thread(target=time.sleep, args=(0.2,)).start()"
    assert run(infer, 3, late)[:2] == (3, ["written", "exit handler", "torn down"])
    child = "__import__('multiprocessing').get_context('fork').Process(target=time.sleep, args=(0.3,)).start()"
    assert run(infer, 3, child)[:2] == (3, ["written", "exit handler", "torn down"])
    code, out, err = run(infer, "a message")
    assert (code, out) == (1, ["written", "exit handler", "torn down"]) and "a message" in err


def test_dataset_format_choices_are_the_readers():
    """``--dataset-format`` (one enum for infer and eval) offers exactly auto and the readers' formats."""
    from labelaudit.cli.app import DatasetFormat
    from labelaudit.datasets import FORMATS

    assert [f.value for f in DatasetFormat] == ["auto", *FORMATS]


def test_rank_by_label_error_notes_classes_without_a_score(tmp_path):
    """label_error is null for classes it is not validated for: sorting by it says so (stderr) and
    ranks the others; sorting by another column says nothing."""
    rows = [
        make_row("000001", 0, label_error=0.7),
        make_row("000001", 1, "Pedestrian", label_error=None),
        make_row("000001", 2, "Cyclist", label_error=None),
        make_row("000001", 3, "Pedestrian", label_error=None),
    ]
    res = make_results(tmp_path / "classes", [rows])
    r = invoke("rank", res, "--by", "label_error", "--format", "json")
    assert r.exit_code == 0, r.output
    assert [x["class_name"] for x in json.loads(r.stdout)] == ["Car"]
    assert "label_error is null for Cyclist: 1, Pedestrian: 2" in r.stderr and "not validated" in r.stderr
    assert "null" not in invoke("rank", res, "--format", "json").stderr
    assert "Pedestrian" not in invoke("rank", res, "--by", "label_error", "--class", "Car").stderr
