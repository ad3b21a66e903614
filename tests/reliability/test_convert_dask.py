"""``deliffas convert --dask``: equal to ``--jobs 1`` byte for byte, through worker and client kills.

A LocalCluster of 2 worker processes (127.0.0.1, one thread each) converts the reliability
suite's capture (4 cameras at 48 x 48, 7 shards). Checked against the in-process reference:

- the Dask conversion's manifest and every shard are byte-identical, and the workers import this
  checkout's deliffas;
- a worker SIGKILLed while it writes a shard (its ``.<name>.tmp-<pid>`` file open) is restarted by
  its nanny, the shard runs again, the result is identical and no temporary file is left;
- ``convert --dask local:2`` killed with SIGKILL (its worker processes die with it), then
  ``--resume`` on Dask or with ``--jobs 1``, yields the reference (a watcher checks every
  final-name file and manifest while the processes run);
- an unreachable scheduler is one error line within seconds and nothing is written; a bad
  ``--dask`` value is refused at parse time.

Every cluster is closed even when a test fails; each test has a timeout.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from reliability_support import CONVERT_ARGS, CONVERT_KW, COUNTS
from test_convert_crash import KILL_TIMEOUT_S, KillPlan, Watch, Watcher, _run_and_kill, _sha

from deliffas.data.convert import ConvertConfig, convert
from deliffas.data.shards import read_manifest, verify_shards

distributed = pytest.importorskip("distributed")

pytestmark = pytest.mark.timeout(300)

SLOW_PUT_S = 0.15
"""Added to every image written while the slow-writer plugin is on (a kill then lands inside a shard)."""


class SlowWriter(distributed.WorkerPlugin):
    """Test-only worker plugin: ``ShardWriter.put`` sleeps first, so a shard takes about a second to write.

    Registered on the scheduler, it is applied to workers the nanny restarts too; teardown restores ``put``.
    """

    def setup(self, worker) -> None:
        from deliffas.data.shards import ShardWriter

        original = ShardWriter.put
        self.original = original

        def put(self_, *args, **kwargs):
            time.sleep(SLOW_PUT_S)
            return original(self_, *args, **kwargs)

        ShardWriter.put = put

    def teardown(self, worker) -> None:
        from deliffas.data.shards import ShardWriter

        ShardWriter.put = self.original


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of 2 worker processes and a client of it (closed even when a test fails)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as lc, distributed.Client(lc, set_as_default=False) as client:
        yield lc, client


def _assert_equals_reference(out: Path, reference: Path) -> None:
    assert (out / "manifest.json").read_bytes() == (reference / "manifest.json").read_bytes()
    m = read_manifest(reference)
    for name in [e["name"] for e in m["shards"]] + ["meta.h5"]:
        assert _sha(out / name) == _sha(reference / name), f"{name} differs from the --jobs 1 reference"
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == sorted(
        p.relative_to(reference) for p in reference.rglob("*")), "OUT holds other files than --jobs 1 writes"
    assert verify_shards(out).problems == ()


def test_dask_conversion_equals_jobs_1(cluster, rel_subject, rel_reference, tmp_path):
    lc, client = cluster
    here = str(Path(__file__).resolve().parents[2] / "deliffas")
    files = client.run(lambda: __import__("deliffas").__file__)
    assert len(files) == 2 and all(f.startswith(here) for f in files.values()), files
    out = tmp_path / "out"
    res = convert(rel_subject, out, ConvertConfig(**CONVERT_KW, dask=lc.scheduler_address, progress=False))
    assert res.shards_converted == res.shards_total == 7
    _assert_equals_reference(out, rel_reference)


def test_worker_sigkilled_mid_shard_yields_the_reference(cluster, rel_subject, rel_reference, tmp_path):
    lc, client = cluster
    out = tmp_path / "out"
    client.register_plugin(SlowWriter(), name="slow-writer")
    errors: list[BaseException] = []

    def run() -> None:
        try:
            convert(rel_subject, out, ConvertConfig(**CONVERT_KW, dask=lc.scheduler_address, progress=False))
        except BaseException as err:  # noqa: BLE001 - reported by the test thread
            errors.append(err)

    thread = threading.Thread(target=run, daemon=True)
    killed_mid_shard = 0
    try:
        thread.start()
        deadline = time.monotonic() + 120
        while thread.is_alive() and not killed_mid_shard and time.monotonic() < deadline:
            workers = set(client.run(os.getpid, on_error="ignore").values())  # a restarting worker is skipped
            temps = [p for p in out.glob("shards/.*.tmp-*") if int(p.name.rsplit("-", 1)[1]) in workers]
            if temps:
                os.kill(int(temps[0].name.rsplit("-", 1)[1]), signal.SIGKILL)
                time.sleep(0.5)
                killed_mid_shard += temps[0].exists()  # the killed writer's temporary file is left behind
            time.sleep(0.01)
        thread.join(timeout=180)
    finally:
        client.unregister_worker_plugin("slow-writer")
    assert not thread.is_alive(), "the Dask conversion did not finish after a worker was killed"
    assert errors == [], errors
    assert killed_mid_shard == 1, "no worker was killed while writing a shard"
    _assert_equals_reference(out, rel_reference)  # incl. no temporary file of the killed attempt
    COUNTS["convert --dask: workers SIGKILLed mid-shard"] += killed_mid_shard


def _dask_cmd(subject: Path, out: Path, resume: bool, dask: str | None = "local:2") -> list[str]:
    cmd = [sys.executable, "-m", "deliffas", "convert", str(subject), str(out), *CONVERT_ARGS, "--no-progress"]
    cmd += ["--dask", dask] if dask else ["--jobs", "1"]
    return cmd + (["--resume"] if resume else [])


@pytest.mark.slow
@pytest.mark.parametrize("resume_on", ["dask", "jobs1"])
def test_client_sigkilled_then_resume_equals_reference(resume_on, rel_subject, rel_reference, tmp_path):
    m = read_manifest(rel_reference)
    reference = {e["name"]: e["sha256"] for e in m["shards"]}
    reference["meta.h5"] = m["meta"]["sha256"]
    out = tmp_path / "out"
    watch = Watch()
    watcher = Watcher(out, reference, watch)
    watcher.start()
    try:
        # jobs=2 makes _run_and_kill collect the client's child processes (the LocalCluster's workers)
        res = _run_and_kill(_dask_cmd(rel_subject, out, resume=False), out, KillPlan(2, "shards", 2, 0.02))
        assert res["killed"], f"the Dask conversion finished before its kill point (rc {res['rc']}): {res['stderr']}"
        assert res["children"] >= 2 and not res["orphans"], res
        assert 2 <= res["listed_at_kill"] < 7, res
        resumed = subprocess.run(_dask_cmd(rel_subject, out, resume=True, dask="local:2" if resume_on == "dask" else None),
                                 capture_output=True, text=True, timeout=KILL_TIMEOUT_S)
        assert resumed.returncode == 0, resumed.stderr[-3000:]
    finally:
        watcher.stop.set()
        watcher.join(timeout=30)
    assert watch.problems == [], watch.problems[:5]
    _assert_equals_reference(out, rel_reference)
    COUNTS["convert --dask: client SIGKILLs resumed to the reference"] += 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_a_quick_error_and_writes_nothing(rel_subject, tmp_path, capsys):
    from deliffas.cli import main as cli_main

    out = tmp_path / "out"
    t0 = time.monotonic()
    rc = cli_main(["convert", str(rel_subject), str(out), *CONVERT_ARGS, "--no-progress", "--dask",
                   f"127.0.0.1:{_free_port()}"])
    elapsed = time.monotonic() - t0
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "no Dask scheduler answered" in err[0], err
    assert elapsed < 10, f"took {elapsed:.1f} s"
    assert not out.exists()


@pytest.mark.parametrize("value", ["local:0", "local:x", "no address", "tcp://host"])
def test_bad_dask_value_is_refused_at_parse_time(value, rel_subject, tmp_path, capsys):
    from deliffas.cli import main as cli_main

    with pytest.raises(SystemExit) as exc:
        cli_main(["convert", str(rel_subject), str(tmp_path / "out"), "--dask", value])
    assert exc.value.code == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1 and "--dask" in errors[0], errors
    assert not (tmp_path / "out").exists()


def test_missing_dask_names_the_package(monkeypatch):
    from deliffas.parallel import open_executor

    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask[distributed] were not installed
    with pytest.raises(ImportError, match=r'pip install "dask\[distributed\]"'):
        open_executor(dask="local:1")
