"""The cores and the memory this process may use, as a container engine or a service manager
set them: the CPU affinity (`docker run --cpuset-cpus`, taskset), the cgroup's CPU quota
(`--cpus`) and the cgroup's memory limit (`--memory`), cgroup v2 or v1.

Reads /proc and /sys only; the CLI turns the result into the default --threads and --workers.
`cgroup_root` and `self_cgroup` are arguments so tests can lay out fake cgroup files.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

CGROUP_ROOT = Path("/sys/fs/cgroup")
SELF_CGROUP = Path("/proc/self/cgroup")

# cgroup v1 writes "no memory limit" as 2**63 - 1 rounded down to a page; anything this large
# is no limit.
NO_MEMORY_LIMIT = 1 << 60


@dataclass(frozen=True)
class Limits:
    """affinity_cores: CPUs the scheduler may run this process on. quota_cores: CPU time the
    cgroup allows per second of wall time, in cores (1.5 = --cpus=1.5); None without a quota.
    memory_bytes: the cgroup's memory limit, None without one. physical_bytes: the machine's
    RAM, None where unknown. cgroup: "v2", "v1" or None (no cgroup filesystem found)."""

    affinity_cores: int
    quota_cores: float | None = None
    memory_bytes: int | None = None
    physical_bytes: int | None = None
    cgroup: str | None = None

    @property
    def cores(self) -> int:
        """Cores to plan threads for: the affinity, lowered to the quota rounded up (a quota
        of 1.5 cores gets 2 threads, which together may run 1.5 cores' worth)."""
        if self.quota_cores is None:
            return max(1, self.affinity_cores)
        return max(1, min(self.affinity_cores, math.ceil(self.quota_cores)))

    @property
    def usable_memory(self) -> int | None:
        """Bytes this process tree may use: the cgroup limit or the RAM, whichever is lower."""
        known = [b for b in (self.memory_bytes, self.physical_bytes) if b is not None]
        return min(known) if known else None


def read_limits(cgroup_root: Path = CGROUP_ROOT, self_cgroup: Path = SELF_CGROUP,
                affinity: int | None = None) -> Limits:
    """The limits of the calling process. `affinity`: the CPU count to use instead of asking
    the scheduler (tests)."""
    cgroup_root = Path(cgroup_root)
    membership = _read_text(Path(self_cgroup)) or ""
    if (cgroup_root / "cgroup.controllers").is_file():
        version, quota, memory = "v2", _quota_v2(cgroup_root, membership), _memory_v2(cgroup_root, membership)
    elif cgroup_root.is_dir() and any(cgroup_root.iterdir()):
        version, quota, memory = "v1", _quota_v1(cgroup_root, membership), _memory_v1(cgroup_root, membership)
    else:
        version, quota, memory = None, None, None
    return Limits(affinity_cores=_affinity_cores() if affinity is None else affinity,
                  quota_cores=quota, memory_bytes=memory, physical_bytes=_physical_memory(),
                  cgroup=version)


def _affinity_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):  # not POSIX, or the name is unknown here
        return None


# --- where the files are -------------------------------------------------------------------

def _own_path(membership: str, controller: str | None) -> str | None:
    """This process's cgroup path from /proc/self/cgroup: the v2 line `0::/path` when
    `controller` is None, else the v1 line naming `controller` (`4:cpu,cpuacct:/docker/ab12`)."""
    for line in membership.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controller is None and parts[0] == "0" and controllers == "":
            return path
        if controller is not None and controller in controllers.split(","):
            return path
    return None


def _levels(mount: Path, own: str | None) -> list[Path]:
    """The cgroup directories whose limits apply, innermost first: this process's own cgroup
    and each parent up to the mount. A container sees only its own cgroup, mounted at the root,
    while /proc/self/cgroup may still name the host's path (cgroup v1): then the mount alone."""
    if own is not None:
        inner = mount / own.strip("/")
        if inner.is_dir():
            return [inner, *[p for p in inner.parents if p == mount or mount in p.parents]]
    return [mount]


def _v1_mount(root: Path, controller: str) -> Path | None:
    for name in (controller, f"{controller},cpuacct", f"cpuacct,{controller}"):
        if (root / name).is_dir():
            return root / name
    return None


# --- what they say -------------------------------------------------------------------------

def _quota_v2(root: Path, membership: str) -> float | None:
    """cpu.max: "QUOTA PERIOD" in microseconds, or "max PERIOD" for none; the tightest level wins."""
    quotas = []
    for level in _levels(root, _own_path(membership, None)):
        fields = (_read_text(level / "cpu.max") or "").split()
        if len(fields) == 2 and fields[0] != "max":
            quotas.append(_ratio(fields[0], fields[1]))
    return _tightest(quotas)


def _memory_v2(root: Path, membership: str) -> int | None:
    """memory.max: bytes, or "max" for none."""
    limits = [_bytes(_read_text(level / "memory.max")) for level in _levels(root, _own_path(membership, None))]
    return _tightest(limits)


def _quota_v1(root: Path, membership: str) -> float | None:
    """cpu.cfs_quota_us / cpu.cfs_period_us; a quota of -1 is none."""
    mount = _v1_mount(root, "cpu")
    if mount is None:
        return None
    quotas = []
    for level in _levels(mount, _own_path(membership, "cpu")):
        quota, period = _read_text(level / "cpu.cfs_quota_us"), _read_text(level / "cpu.cfs_period_us")
        if quota is not None and period is not None and quota.strip() != "-1":
            quotas.append(_ratio(quota, period))
    return _tightest(quotas)


def _memory_v1(root: Path, membership: str) -> int | None:
    """memory.limit_in_bytes; a huge value (about 2**63) is none."""
    mount = _v1_mount(root, "memory")
    if mount is None:
        return None
    return _tightest([_bytes(_read_text(level / "memory.limit_in_bytes"))
                      for level in _levels(mount, _own_path(membership, "memory"))])


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:  # absent at this level, or not readable: no limit known here
        return None


def _ratio(quota: str, period: str) -> float | None:
    try:
        quota_us, period_us = int(quota), int(period)
    except ValueError:
        return None
    return quota_us / period_us if quota_us > 0 and period_us > 0 else None


def _bytes(text: str | None) -> int | None:
    if text is None or text.strip() == "max":
        return None
    try:
        value = int(text)
    except ValueError:
        return None
    return value if 0 < value < NO_MEMORY_LIMIT else None


def _tightest(values):
    known = [v for v in values if v is not None]
    return min(known) if known else None
