"""Batches: process pool and Ray Data give the same bytes as a sequential run; failures are
recorded per item; reports come back in input order."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from relightcli.cli import main
from relightcli.io.images import write_image

REPO = Path(__file__).resolve().parents[1]


def make_folder(root: Path, count: int, bad: int = 1) -> Path:
    folder = root / "in"
    folder.mkdir()
    rng = np.random.default_rng(7)
    for index in range(count):
        rgb = rng.uniform(0.0, 1.0, (40, 36, 3)).astype(np.float32)
        alpha = np.clip(rng.normal(0.6, 0.4, (40, 36)), 0, 1).astype(np.float32)
        write_image(folder / f"p{index:02d}.png", rgb, alpha, bits=16)
    for index in range(bad):
        (folder / f"z_bad{index}.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    env = np.ones((4, 8, 3), np.float32)
    write_image(root / "env.hdr", env)
    return folder


def run(capsys, folder: Path, out: Path, *extra: str):
    code = main([str(folder), "--hdr", str(folder.parent / "env.hdr"), "-o", str(out), "--outputs", "mask", "--json", *extra])
    return code, json.loads(capsys.readouterr().out)


def output_bytes(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())}


def test_pool_matches_sequential_byte_for_byte(tmp_path, capsys):
    folder = make_folder(tmp_path, 5)
    code1, report1 = run(capsys, folder, tmp_path / "seq", "--workers", "1")
    code2, report2 = run(capsys, folder, tmp_path / "pool", "--workers", "2")
    assert code1 == code2 == 1
    assert output_bytes(tmp_path / "seq") == output_bytes(tmp_path / "pool")
    assert [i["input"] for i in report1["items"]] == [i["input"] for i in report2["items"]]
    assert [bool(i["error"]) for i in report2["items"]] == [False] * 5 + [True]


def test_interrupted_batch_resumes_with_skip_existing(tmp_path, capsys):
    folder = make_folder(tmp_path, 3, bad=0)
    out = tmp_path / "out"
    assert run(capsys, folder, out)[0] == 0
    (out / "p01_mask.png").unlink()  # as if the batch had stopped before this item
    code, report = run(capsys, folder, out, "--skip-existing")
    assert code == 0
    skipped = [Path(i["input"]).name for i in report["items"] if i.get("skipped")]
    assert skipped == ["p00.png", "p02.png"]
    assert (out / "p01_mask.png").is_file()


def test_ray_engine_without_ray_fails_clearly(tmp_path, capsys, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    folder = make_folder(tmp_path, 1, bad=0)
    code = main([str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / "o"), "--outputs", "mask", "--engine", "ray"])
    assert code == 3
    assert "relightcli[ray]" in capsys.readouterr().err


def run_ray_cli(tmp_path, *options: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """The CLI in a process of its own (a connection attempt left running stays there)."""
    folder = make_folder(tmp_path, 2, bad=0)
    env = {key: value for key, value in os.environ.items() if key != "RAY_ADDRESS"}
    return subprocess.run([sys.executable, "-m", "relightcli", str(folder), "--hdr", str(tmp_path / "env.hdr"),
                           "-o", str(tmp_path / "out"), "--outputs", "mask", "--engine", "ray", *options],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


def test_an_unreachable_ray_cluster_fails_clearly_within_the_timeout(tmp_path):
    """ray.init retried an address where nothing answers for minutes, silently."""
    pytest.importorskip("ray.data")
    done = run_ray_cli(tmp_path, "--address", "127.0.0.1:1", "--ray-timeout", "2")
    assert done.returncode == 2, done.stderr
    assert "no Ray cluster answered at 127.0.0.1:1 within 2 s" in done.stderr
    assert "--ray-timeout" in done.stderr and "Traceback" not in done.stderr


def test_ray_address_auto_without_a_cluster_fails_clearly(tmp_path):
    pytest.importorskip("ray.data")
    done = run_ray_cli(tmp_path, "--address", "auto")
    assert done.returncode == 2, done.stderr
    assert "cannot connect to a Ray cluster at auto (" in done.stderr and "Traceback" not in done.stderr
    assert "SIGTERM handler" not in done.stderr  # Ray's notice: the connection runs in a thread


def test_a_ray_client_address_without_ray_client_is_a_missing_dependency(tmp_path, capsys, monkeypatch):
    pytest.importorskip("ray.data")
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *args: None if name == "grpc" else find_spec(name, *args))
    folder = make_folder(tmp_path, 1, bad=0)
    code = main([str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / "o"), "--outputs", "mask",
                 "--engine", "ray", "--address", "ray://127.0.0.1:10001"])
    err = capsys.readouterr().err
    assert code == 3
    assert "ray://127.0.0.1:10001" in err and "pip install 'ray[client]'" in err and "Traceback" not in err


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux /proc")
def test_sigterm_stops_a_ray_batch_with_a_summary(tmp_path):
    """Ray's own SIGTERM handler used to end the batch by sys.exit: exit 2, no summary."""
    pytest.importorskip("ray.data")
    from tests.test_batch_stop import make_photos, processes_with, wait_for_new_output

    folder = make_photos(tmp_path, 6)
    out = tmp_path / "out"
    marker = uuid.uuid4().hex
    since_ns = time.time_ns()
    proc = subprocess.Popen(
        [sys.executable, "-m", "relightcli", str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(out),
         "--outputs", "mask,albedo", "--albedo", "net", "--resolution", "64", "--engine", "ray",
         "--workers", "2", "--threads", "2", "--json"],
        cwd=REPO, env=dict(os.environ, RELIGHT_RAY_STOP_TEST=marker), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        wait_for_new_output(out, since_ns, proc, timeout=300)
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
        print(f"stopped in {time.monotonic() - sent:.2f} s")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, stderr
    report = json.loads(stdout)
    assert report["failed"] == 0 and report["ok"] + report["stopped"] == 6 and report["stopped"] > 0
    ok = {Path(item["input"]).stem for item in report["items"] if not item["error"]}
    written = {f"{stem}{layer}.png" for stem in ok for layer in ("_mask", "_albedo")}
    assert {p.name for p in out.iterdir()} == written  # the report matches the disk, no staging left
    deadline = time.monotonic() + 60
    while processes_with(marker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert processes_with(marker) == []


def test_more_workers_than_cores_are_warned_about(tmp_path, capsys, monkeypatch):
    import relightcli.cli

    monkeypatch.setattr(relightcli.cli, "default_threads", lambda: 2)
    folder = make_folder(tmp_path, 1, bad=0)
    for workers, warned in (("2", False), ("3", True)):
        code = main([str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / f"o{workers}"),
                     "--outputs", "mask", "--workers", workers])
        err = capsys.readouterr().err
        assert code == 0
        assert ("--workers 3 is more than the 2 core(s) available" in err) == warned, err
        assert ("up to ~750 MB" in err) == warned


def test_address_without_ray_engine_is_usage_error(tmp_path):
    folder = make_folder(tmp_path, 1, bad=0)
    assert main([str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / "o"), "--address", "auto"]) == 2


def test_ray_engine_matches_local(tmp_path, capsys):
    pytest.importorskip("ray.data")
    folder = make_folder(tmp_path, 4)
    own_mask = np.zeros((40, 36), np.float32)
    own_mask[5:30, 8:20] = 1.0
    write_image(folder / "p01_mask.png", own_mask, bits=8, srgb=False)  # p01's own mask
    code_local, report_local = run(capsys, folder, tmp_path / "local", "--workers", "1")
    code_ray, report_ray = run(capsys, folder, tmp_path / "ray", "--engine", "ray", "--workers", "2", "--threads", "2")
    assert code_local == code_ray == 1
    assert output_bytes(tmp_path / "local") == output_bytes(tmp_path / "ray")
    assert [i["input"] for i in report_ray["items"]] == [i["input"] for i in report_local["items"]]
    assert "p01_mask.png" in report_ray["items"][1]["stages"]["mask"]["source"]
    bad = [i for i in report_ray["items"] if i["error"]]
    assert len(bad) == 1 and "z_bad0.png" in bad[0]["error"]


def test_reports_carry_worker_memory(tmp_path, capsys):
    folder = make_folder(tmp_path, 2, bad=0)
    code, report = run(capsys, folder, tmp_path / "out", "--workers", "1")
    assert code == 0
    assert all(item["worker_rss_mb"] > 10 for item in report["items"])


FRAGMENTED_HEAP = """
import numpy as np
from relightcli.batch import release_free_memory, resident_memory_mb
big = np.ones(4_000_000); del big          # glibc raises its mmap threshold past 32 MB
held = [np.ones(60_000) for _ in range(100)]  # 100 x 480 kB, now from the heap
pinned = np.ones(60_000)                  # above them: the heap top cannot shrink
del held
before = resident_memory_mb()
trimmed = release_free_memory()
print(trimmed, before, resident_memory_mb())
"""


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs Linux /proc")
def test_free_heap_is_handed_back_after_an_item():
    """The batch trims the heap after every item (issue 8: no RSS growth over a long batch):
    48 MB of freed arrays trapped below a live one are returned to the OS."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", FRAGMENTED_HEAP], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[1]).stdout.split()
    trimmed, before, after = out[0] == "True", float(out[1]), float(out[2])
    if not trimmed:
        pytest.skip("this libc has no malloc_trim")
    assert before - after > 30.0, (before, after)
