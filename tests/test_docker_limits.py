"""Cores and memory from a container's limits (issue 51): cgroup v2 and v1 files faked under a
temporary root, and what the CLI's default --threads, --workers and `relight info` make of them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from relightcli import cli
from relightcli.cli.limits import Limits, read_limits

GIB = 2**30
V1_NO_LIMIT = "9223372036854771712\n"  # what cgroup v1 reports without --memory


def lay_out(root: Path, files: dict[str, str], membership: str) -> tuple[Path, Path]:
    """Write `files` (path under the cgroup root -> content) and a /proc/self/cgroup."""
    cgroup_root = root / "sys_fs_cgroup"
    cgroup_root.mkdir()
    for name, text in files.items():
        path = cgroup_root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    self_cgroup = root / "self_cgroup"
    self_cgroup.write_text(membership)
    return cgroup_root, self_cgroup


def v2(tmp_path, files, membership="0::/\n", affinity=8) -> Limits:
    """A cgroup v2 container: its own cgroup mounted at the root (cgroup namespace)."""
    cgroup_root, self_cgroup = lay_out(tmp_path, {"cgroup.controllers": "cpu memory\n", **files}, membership)
    return read_limits(cgroup_root, self_cgroup, affinity=affinity)


def v1(tmp_path, files, affinity=8) -> Limits:
    """A cgroup v1 container: each controller's mount shows the container's own cgroup, while
    /proc/self/cgroup still names the host's path, which does not exist inside."""
    membership = "12:memory:/docker/4f1e\n5:cpu,cpuacct:/docker/4f1e\n1:name=systemd:/docker/4f1e\n"
    cgroup_root, self_cgroup = lay_out(tmp_path, files, membership)
    return read_limits(cgroup_root, self_cgroup, affinity=affinity)


# --- cgroup v2 -----------------------------------------------------------------------------

def test_v2_cpus_1_gives_one_core(tmp_path):
    limits = v2(tmp_path, {"cpu.max": "100000 100000\n", "memory.max": "max\n"})
    assert (limits.cgroup, limits.quota_cores, limits.cores, limits.memory_bytes) == ("v2", 1.0, 1, None)


def test_v2_fractional_quota_rounds_up(tmp_path):
    limits = v2(tmp_path, {"cpu.max": "150000 100000\n"})
    assert limits.quota_cores == 1.5 and limits.cores == 2


def test_v2_without_quota_keeps_the_affinity(tmp_path):
    limits = v2(tmp_path, {"cpu.max": "max 100000\n"}, affinity=6)
    assert limits.quota_cores is None and limits.cores == 6


def test_v2_quota_above_the_affinity_keeps_the_affinity(tmp_path):
    """--cpus=4 --cpuset-cpus=0,1: two cores."""
    assert v2(tmp_path, {"cpu.max": "400000 100000\n"}, affinity=2).cores == 2


def test_v2_memory_limit(tmp_path):
    assert v2(tmp_path, {"memory.max": f"{GIB}\n"}).memory_bytes == GIB


def test_v2_the_tightest_level_of_a_nested_cgroup_wins(tmp_path):
    """Without a cgroup namespace the process sits deeper; a parent's limit applies too."""
    limits = v2(tmp_path, {"machine.slice/cpu.max": "200000 100000\n",
                           "machine.slice/job/cpu.max": "max 100000\n",
                           "machine.slice/memory.max": f"{4 * GIB}\n",
                           "machine.slice/job/memory.max": f"{GIB}\n"},
                membership="0::/machine.slice/job\n")
    assert limits.quota_cores == 2.0 and limits.memory_bytes == GIB


# --- cgroup v1 -----------------------------------------------------------------------------

def test_v1_cpus_1_and_memory_1g(tmp_path):
    limits = v1(tmp_path, {"cpu,cpuacct/cpu.cfs_quota_us": "100000\n",
                           "cpu,cpuacct/cpu.cfs_period_us": "100000\n",
                           "memory/memory.limit_in_bytes": f"{GIB}\n"})
    assert (limits.cgroup, limits.quota_cores, limits.cores, limits.memory_bytes) == ("v1", 1.0, 1, GIB)


def test_v1_no_quota_and_no_memory_limit(tmp_path):
    limits = v1(tmp_path, {"cpu/cpu.cfs_quota_us": "-1\n", "cpu/cpu.cfs_period_us": "100000\n",
                           "memory/memory.limit_in_bytes": V1_NO_LIMIT}, affinity=3)
    assert limits.quota_cores is None and limits.memory_bytes is None and limits.cores == 3


def test_v1_host_process_reads_its_own_cgroup(tmp_path):
    """Outside a container the path in /proc/self/cgroup exists under the mount."""
    cgroup_root, self_cgroup = lay_out(tmp_path, {
        "cpu/cpu.cfs_quota_us": "-1\n", "cpu/cpu.cfs_period_us": "100000\n",
        "cpu/batch.slice/cpu.cfs_quota_us": "50000\n", "cpu/batch.slice/cpu.cfs_period_us": "100000\n",
        "memory/memory.limit_in_bytes": V1_NO_LIMIT}, "4:cpu:/batch.slice\n3:memory:/\n")
    limits = read_limits(cgroup_root, self_cgroup, affinity=4)
    assert limits.quota_cores == 0.5 and limits.cores == 1


# --- nothing to read -----------------------------------------------------------------------

def test_no_cgroup_filesystem(tmp_path):
    limits = read_limits(tmp_path / "absent", tmp_path / "absent_self", affinity=5)
    assert (limits.cgroup, limits.quota_cores, limits.memory_bytes, limits.cores) == (None, None, None, 5)


def test_malformed_files_are_no_limit(tmp_path):
    limits = v2(tmp_path, {"cpu.max": "lots\n", "memory.max": "a gigabyte\n"})
    assert limits.quota_cores is None and limits.memory_bytes is None


def test_usable_memory_is_the_lower_of_limit_and_ram():
    assert Limits(2, memory_bytes=GIB, physical_bytes=8 * GIB).usable_memory == GIB
    assert Limits(2, memory_bytes=None, physical_bytes=8 * GIB).usable_memory == 8 * GIB
    assert Limits(2).usable_memory is None


# --- the CLI's defaults --------------------------------------------------------------------

@pytest.mark.parametrize("threads, memory, workers", [
    (8, GIB, 1),            # --memory=1g: one worker, whatever the cores
    (8, 4 * GIB, 6),        # 4096 MiB / 600 MiB
    (2, 64 * GIB, 2),       # plenty of memory: one per core
    (4, 100 * 2**20, 1),    # less than one worker's worth: still one
    (3, None, 3),           # memory unknown: one per core
])
def test_default_workers_fit_cores_and_memory(threads, memory, workers):
    assert cli.default_workers(threads, memory) == workers


@pytest.fixture
def one_core_one_gib(monkeypatch):
    """A container run with --cpus=1 --memory=1g on an 8-core, 64 GB host."""
    limits = Limits(affinity_cores=8, quota_cores=1.0, memory_bytes=GIB, physical_bytes=64 * GIB, cgroup="v2")
    monkeypatch.setattr("relightcli.cli.limits.read_limits", lambda *args, **kwargs: limits)
    return limits


def test_default_threads_follow_the_quota(one_core_one_gib):
    assert cli.default_threads() == 1


def test_relight_info_shows_what_it_sees(one_core_one_gib, capsys):
    assert cli.main(["info", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["cores"] == {"affinity": 8, "quota": 1.0, "cgroup": "v2"}
    assert report["memory_mib"] == {"limit": 1024, "ram": 65536}
    assert report["threads"] == 1 and report["workers"] == 1


def test_a_batch_runs_as_many_workers_as_the_memory_holds(monkeypatch, tmp_path):
    """4 cores but 1 GB: the batch gets one worker with the four threads."""
    from relightcli import batch
    from relightcli.io.images import write_image

    import numpy as np

    limits = Limits(affinity_cores=4, memory_bytes=GIB, physical_bytes=64 * GIB, cgroup="v2")
    monkeypatch.setattr("relightcli.cli.limits.read_limits", lambda *args, **kwargs: limits)
    seen = {}

    def run_items(items, worker, *, workers, **kwargs):
        seen.update(workers=workers, threads=worker.options.threads)
        return [batch.ItemReport(str(item.input)) for item in items]

    monkeypatch.setattr(batch, "run_items", run_items)
    for name in ("a", "b", "c"):
        write_image(tmp_path / f"{name}.png", np.full((8, 8, 3), 0.5, np.float32))
    write_image(tmp_path / "env.hdr", np.ones((4, 8, 3), np.float32))
    code = cli.main([str(tmp_path / n) for n in ("a.png", "b.png", "c.png")]
                    + ["--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / "out")])
    assert code == 0 and seen == {"workers": 1, "threads": 4}
