"""Crash safety of ``deliffas convert``: SIGKILL at seeded random points, then ``--resume``.

Each kill chain is one output folder: a real ``python -m deliffas convert`` is killed with SIGKILL
at a seeded random point, then ``--resume`` runs and may itself be killed, and a last ``--resume``
completes. Kill points: during set-up (imports, planning, ``meta.h5``), or a random delay after the
manifest lists k of the 7 shards (so kills land inside shard writing, between the rename of a
shard and the manifest update, or while the manifest is rewritten). Chain 1 kills five times with
``--jobs 1``; chain 2 kills a ``--jobs 2`` conversion (whose spawned workers must die with it).
While any of these processes runs, a watcher thread polls the output folder and checks:

- every ``*.h5`` under its final name is byte-identical to the uninterrupted reference (so it is
  complete: no partial shard is ever visible under its final name) and passes ``ShardFile.check``;
- ``manifest.json`` always parses, and every shard it lists exists and equals the reference.

After each kill the spawned workers (``--jobs 2``) must be gone; after the resume: exit 0,
``verify`` passes, the manifest and every shard equal the reference byte for byte, no temporary
file is left. Across all runs the source folder (every path, size, mtime and sha256) is unchanged.
"""

from __future__ import annotations

import hashlib
import random
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from reliability_support import CONVERT_ARGS, COUNTS, KILL_ROUNDS, tree_state

from deliffas.data.shards import ShardFile, read_manifest, verify_shards

pytestmark = pytest.mark.timeout(600 * KILL_ROUNDS)

SEED = 20231210
KILL_TIMEOUT_S = 120.0


@dataclass
class KillPlan:
    """Where to kill one ``convert`` process."""

    jobs: int
    phase: str  # "setup": delay_s after the start; "shards": delay_s after the manifest lists `after_shards`
    after_shards: int = 0
    delay_s: float = 0.0


@dataclass
class Watch:
    """What the watcher saw."""

    polls: int = 0
    files_checked: int = 0
    manifests_read: int = 0
    problems: list[str] = field(default_factory=list)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Watcher(threading.Thread):
    """Polls ``out`` until stopped: final-name files must equal the reference, the manifest must parse."""

    def __init__(self, out: Path, reference: dict[str, str], watch: Watch):
        super().__init__(daemon=True)
        self.out, self.reference, self.watch = out, reference, watch
        self.stop = threading.Event()
        self.seen: set[tuple] = set()
        self.manifest_key = None

    def check_file(self, p: Path) -> None:
        name = str(p.relative_to(self.out))
        try:
            st = p.stat()
        except FileNotFoundError:
            return
        key = (name, st.st_ino, st.st_mtime_ns, st.st_size)
        if key in self.seen:
            return
        try:
            sha = _sha(p)
        except FileNotFoundError:  # replaced by an identical file between listing and reading
            return
        if sha != self.reference.get(name):
            self.watch.problems.append(f"{name}: visible under its final name but differs from the reference")
            return
        if name.startswith("shards/"):
            reader = ShardFile(p)
            try:
                reader.check()
            except Exception as err:  # noqa: BLE001 - any failure is a finding
                self.watch.problems.append(f"{name}: fails ShardFile.check ({err})")
            finally:
                reader.close()
        self.seen.add(key)
        self.watch.files_checked += 1

    def poll(self) -> None:
        self.watch.polls += 1
        for p in sorted(self.out.glob("shards/*.h5")) + [self.out / "meta.h5"]:
            if not p.name.startswith(".") and p.exists():
                self.check_file(p)
        mp = self.out / "manifest.json"
        try:
            st = mp.stat()
        except FileNotFoundError:
            return
        if (st.st_ino, st.st_mtime_ns, st.st_size) != self.manifest_key:
            self.manifest_key = (st.st_ino, st.st_mtime_ns, st.st_size)
            try:
                m = read_manifest(self.out)
            except FileNotFoundError:
                return
            except ValueError as err:
                self.watch.problems.append(f"manifest.json: unreadable while converting ({err})")
                return
            self.watch.manifests_read += 1
            for entry in m["shards"]:
                if entry["sha256"] != self.reference.get(entry["name"]):
                    self.watch.problems.append(f"manifest lists {entry['name']} with a checksum not of the reference")
                if not (self.out / entry["name"]).exists():
                    self.watch.problems.append(f"manifest lists {entry['name']}, which does not exist")

    def run(self) -> None:
        while not self.stop.is_set():
            self.poll()
            time.sleep(0.005)
        self.poll()


def _children(pid: int) -> list[int]:
    """Direct children of a live process (Linux /proc)."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def _convert_cmd(subject: Path, out: Path, jobs: int, resume: bool = False) -> list[str]:
    cmd = [sys.executable, "-m", "deliffas", "convert", str(subject), str(out), *CONVERT_ARGS, "--no-progress",
           "--jobs", str(jobs)]
    return cmd + (["--resume"] if resume else [])


def _manifest_key(out: Path):
    try:
        st = (out / "manifest.json").stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def _listed(out: Path) -> int:
    try:
        return len(read_manifest(out)["shards"])
    except (FileNotFoundError, ValueError, KeyError):
        return -1


def _run_and_kill(cmd: list[str], out: Path, plan: KillPlan) -> dict:
    """Start ``cmd``, kill it with SIGKILL at ``plan``; returns what happened.

    ``setup``: ``delay_s`` after the start (imports, planning, meta.h5); ``shards``: ``delay_s``
    after this process's manifest lists at least ``after_shards`` shards.
    """
    launch_key = _manifest_key(out)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    started = time.monotonic()
    deadline = started + KILL_TIMEOUT_S
    armed_at = started if plan.phase == "setup" else None
    children: set[int] = set()
    seen_key = launch_key
    while proc.poll() is None and time.monotonic() < deadline:
        if plan.jobs > 1:
            children.update(_children(proc.pid))
        if armed_at is None:
            key = _manifest_key(out)
            if key is not None and key != seen_key:  # this process rewrote the manifest
                seen_key = key
                if _listed(out) >= plan.after_shards:
                    armed_at = time.monotonic()
        if armed_at is not None and time.monotonic() - armed_at >= plan.delay_s:
            if plan.jobs > 1:
                children.update(_children(proc.pid))
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.002)
    stderr = proc.communicate(timeout=60)[1].decode(errors="replace")
    # Workers of a killed parent must die with it (PR_SET_PDEATHSIG): no orphan keeps writing.
    t0 = time.monotonic()
    while any(_alive(c) for c in children) and time.monotonic() - t0 < 30:
        time.sleep(0.05)
    orphans = [c for c in children if _alive(c)]
    return {"rc": proc.returncode, "killed": proc.returncode == -signal.SIGKILL, "stderr": stderr[-2000:],
            "children": len(children), "orphans": orphans, "listed_at_kill": _listed(out),
            "temp_files": len(list(out.glob("shards/.*.tmp-*")) + list(out.glob(".*.tmp-*"))) if out.exists() else 0}


def _chains(num_shards: int, rounds: int = 1) -> list[list[KillPlan]]:
    """Seeded kill points. Each chain is one output folder: its first process converts, every later
    one is a ``--resume`` of the killed one, and after the last kill a clean ``--resume`` completes.
    ``rounds`` > 1 (the soak) repeats both chains with further seeds."""
    if rounds > 1:
        return [c for r in range(rounds) for c in _chains_round(num_shards, random.Random(SEED + r))]
    return _chains_round(num_shards, random.Random(SEED))


def _chains_round(num_shards: int, rng: random.Random) -> list[list[KillPlan]]:
    a, b, c = sorted(rng.sample(range(0, num_shards - 2), 3))
    delay = lambda: rng.uniform(0.0, 0.04)  # noqa: E731 - within the next shard or two
    setup = lambda: rng.uniform(0.3, 1.2)  # noqa: E731 - imports (torch alone takes longer), planning
    chain_jobs1 = [
        KillPlan(1, "setup", 0, setup()),
        KillPlan(1, "shards", a, delay()),
        KillPlan(1, "setup", 0, setup()),  # a resume killed before it converts anything
        KillPlan(1, "shards", b, delay()),
        KillPlan(1, "shards", c, delay()),
    ]
    chain_jobs2 = [KillPlan(2, "shards", rng.randrange(0, num_shards - 3), delay())]
    return [chain_jobs1, chain_jobs2]


@pytest.mark.slow
def test_sigkill_then_resume_equals_uninterrupted(rel_subject, rel_reference, tmp_path):
    ref_manifest = (rel_reference / "manifest.json").read_bytes()
    m = read_manifest(rel_reference)
    reference = {e["name"]: e["sha256"] for e in m["shards"]}
    reference["meta.h5"] = m["meta"]["sha256"]
    num_shards = len(m["planned"])
    assert num_shards == 7
    source_before = tree_state(rel_subject)

    kills = chains = missed = 0
    watch = Watch()
    log = []
    for r, kill_plans in enumerate(_chains(num_shards, KILL_ROUNDS)):
        out = tmp_path / f"chain{r}"
        watcher = Watcher(out, reference, watch)
        watcher.start()
        try:
            for k, plan in enumerate(kill_plans):
                res = _run_and_kill(_convert_cmd(rel_subject, out, plan.jobs, resume=k > 0), out, plan)
                log.append((r, plan, {key: v for key, v in res.items() if key != "stderr"}))
                if not res["killed"]:  # a fast machine finished before the kill point: fine, but count it
                    assert res["rc"] == 0, f"chain {r} run {k} failed (rc {res['rc']}): {res['stderr']}"
                    missed += 1
                    continue
                assert not res["orphans"], f"chain {r}: worker processes {res['orphans']} outlived the killed convert"
                if plan.jobs > 1:
                    assert res["children"] >= 2, "the --jobs 2 run was killed before it started its workers"
                kills += 1
            resumed = subprocess.run(_convert_cmd(rel_subject, out, 1, resume=True), capture_output=True, text=True,
                                     timeout=KILL_TIMEOUT_S)
            assert resumed.returncode == 0, resumed.stderr[-3000:]
        finally:
            watcher.stop.set()
            watcher.join(timeout=30)
        chains += 1
        assert watch.problems == [], watch.problems[:5]
        assert (out / "manifest.json").read_bytes() == ref_manifest, f"chain {r}: manifest differs from the reference"
        for name, sha in reference.items():
            assert _sha(out / name) == sha, f"chain {r}: {name} differs from the reference"
        assert not list(out.glob("shards/.*")) and not list(out.glob(".*.tmp-*")), "temporary files left"
        assert verify_shards(out).problems == ()
    from deliffas.cli import main as cli_main

    assert cli_main(["verify", str(out)]) == 0
    assert tree_state(rel_subject) == source_before, "the source folder changed"
    assert watch.files_checked > 0 and watch.manifests_read > 0
    assert kills >= 4 * KILL_ROUNDS, f"only {kills} of {kills + missed} kills landed before the conversion finished"

    listed = [x[2]["listed_at_kill"] for x in log]
    COUNTS["convert: SIGKILLs survived"] += kills
    COUNTS["convert: kill chains resumed to the reference"] += chains
    COUNTS["convert: runs that finished before their kill point"] += missed
    COUNTS["convert: kills with a temporary file left behind"] += sum(x[2]["temp_files"] > 0 for x in log)
    COUNTS["convert: final-name files checked while converting"] += watch.files_checked
    COUNTS["convert: manifest versions checked while converting"] += watch.manifests_read
    print(f"\n[convert-crash] {kills} SIGKILLs in {chains} chains survived ({missed} runs finished before their "
          f"kill point); shards listed at each kill: {listed}; "
          f"{watch.files_checked} final-name files and {watch.manifests_read} manifests checked in {watch.polls} polls")
