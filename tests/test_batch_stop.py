"""Stopping and resuming a batch (issue 22): SIGINT / SIGTERM stop it within seconds, leave
every item's outputs whole (all of this run's, or none), no process behind, and a summary;
--skip-existing completes an item that has only some of its layers."""

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
from relightcli.io.images import read_image, write_image

REPO = Path(__file__).resolve().parents[1]
# Three layers, each needing the de-lighting net at a tiny working resolution: about 0.1 s an
# item, so a batch of 80 runs for several seconds and every item writes several files.
LAYERS = ("mask", "albedo", "light")
FAST = ["--outputs", ",".join(LAYERS), "--albedo", "net", "--resolution", "64"]
PLACEHOLDER = 0.25  # the value of every pixel of an output "from an earlier run"


def make_photos(root: Path, count: int) -> Path:
    """Tiny RGBA photos (the alpha channel is the mask, so no mask net) and a constant sky."""
    folder = root / "in"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for index in range(count):
        rgb = rng.uniform(0.0, 1.0, (40, 36, 3)).astype(np.float32)
        alpha = np.clip(rng.normal(0.6, 0.4, (40, 36)), 0, 1).astype(np.float32)
        write_image(folder / f"p{index:03d}.png", rgb, alpha, bits=16)
    write_image(root / "env.hdr", np.ones((4, 8, 3), np.float32))
    return folder


def layer_paths(out: Path, stem: str) -> dict[str, Path]:
    return {"mask": out / f"{stem}_mask.png", "albedo": out / f"{stem}_albedo.png",
            "light": out / f"{stem}_light.hdr"}


def write_placeholders(out: Path, stems) -> None:
    """Complete outputs of an earlier run: every layer of every item, constant images."""
    out.mkdir()
    for stem in stems:
        for path in layer_paths(out, stem).values():
            write_image(path, np.full((4, 4, 3), PLACEHOLDER, np.float32), srgb=False)


def is_placeholder(path: Path) -> bool:
    pixels = read_image(path).rgb  # raises on a half-written file
    return bool(np.allclose(pixels, pixels.flat[0])) and pixels.shape[:2] == (4, 4)


def processes_with(marker: str) -> list[str]:
    """Every live process whose environment holds `marker` (the CLI's children inherit it)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            environ = (entry / "environ").read_bytes()
            if marker.encode() in environ:
                stat = (entry / "stat").read_text()
                if stat.rsplit(")", 1)[1].split()[0] != "Z":
                    found.append(f"{entry.name} {(entry / 'cmdline').read_bytes()[:80]!r}")
        except OSError:
            continue
    return found


def wait_for_new_output(out: Path, since_ns: int, proc, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"the batch ended (exit {proc.returncode}) before any output appeared")
        if any(p.stat().st_mtime_ns > since_ns for p in out.glob("p*")):
            return
        time.sleep(0.02)
    pytest.fail("no output appeared")


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux /proc")
@pytest.mark.parametrize("how, workers, expected", [
    ("SIGINT", 1, 130),
    ("SIGTERM", 1, 143),
    ("SIGINT", 2, 130),
    ("SIGTERM", 2, 143),
    ("Ctrl-C", 2, 130),  # SIGINT to the whole process group, as a terminal sends it
])
def test_signal_stops_the_batch_cleanly(tmp_path, how, workers, expected):
    count = 80
    folder = make_photos(tmp_path, count)
    out = tmp_path / "out"
    stems = [f"p{index:03d}" for index in range(count)]
    write_placeholders(out, stems)
    marker = f"RELIGHT_STOP_TEST={uuid.uuid4().hex}"
    env = dict(os.environ, RELIGHT_STOP_TEST=marker.split("=")[1])
    since_ns = time.time_ns()
    proc = subprocess.Popen(
        [sys.executable, "-m", "relightcli", str(folder), "--hdr", str(tmp_path / "env.hdr"),
         "-o", str(out), *FAST, "--overwrite", "--workers", str(workers), "--threads", "2", "--json"],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True)
    try:
        wait_for_new_output(out, since_ns, proc)
        sent = time.monotonic()
        if how == "Ctrl-C":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(getattr(signal, how))
        stdout, stderr = proc.communicate(timeout=30)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()

    assert proc.returncode == expected, stderr
    print(f"{how} workers={workers}: stopped in {took:.2f} s")
    assert took < 5.0, f"took {took:.1f} s to stop"
    deadline = time.monotonic() + 5.0  # the resource tracker sees its pipe close, then exits
    while processes_with(marker) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert processes_with(marker) == []

    report = json.loads(stdout)
    stopped = [Path(i["input"]).stem for i in report["items"] if i.get("stopped")]
    finished = [Path(i["input"]).stem for i in report["items"] if not i["error"]]
    assert report["stopped"] == len(stopped) > 0 and report["failed"] == 0
    assert report["ok"] == len(finished) > 0 and len(finished) + len(stopped) == count
    for stem in stems:
        # All of an item's layers are this run's or none are; every file decodes.
        old = {name: is_placeholder(path) for name, path in layer_paths(out, stem).items()}
        assert len(set(old.values())) == 1, (stem, old)
        assert all(old.values()) == (stem in stopped), stem
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no staging files


def test_sigint_in_process_reports_the_stopped_items(tmp_path, capsys, monkeypatch):
    """The human summary names finished and stopped items (Ctrl-C after the second item)."""
    from relightcli import batch

    folder = make_photos(tmp_path, 4)
    done = []

    def interrupt_after_two(report):
        done.append(report)
        if len(done) == 2:
            raise KeyboardInterrupt

    real_run_items = batch.run_items
    monkeypatch.setattr(batch, "run_items",
                        lambda *a, **k: real_run_items(*a, **{**k, "on_done": interrupt_after_two}))
    code = main([str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / "out"),
                 "--outputs", "mask", "--workers", "1"])
    captured = capsys.readouterr()
    assert code == 130
    assert captured.out.count("ok ") == 2
    assert [line.split()[0] for line in captured.err.splitlines()] == ["stopped", "stopped", "2"]
    assert "2 ok, 0 failed, 2 stopped" in captured.err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["p000_mask.png", "p001_mask.png"]


def run_relight(tmp_path, capsys, layers, workers, *extra):
    code = main([str(tmp_path / "in"), "--hdr", str(tmp_path / "env.hdr"), "-o", str(tmp_path / "out"),
                 "--outputs", ",".join(layers), "--albedo", "net", "--resolution", "64",
                 "--workers", str(workers), "--json", *extra])
    return code, json.loads(capsys.readouterr().out)


def snapshot(paths) -> dict[Path, tuple[int, bytes]]:
    return {path: (path.stat().st_mtime_ns, path.read_bytes()) for path in paths}


@pytest.mark.parametrize("workers", [1, 2])
def test_skip_existing_adds_a_layer_added_on_a_rerun(tmp_path, capsys, workers):
    make_photos(tmp_path, 2)
    out = tmp_path / "out"
    assert run_relight(tmp_path, capsys, ["mask"], workers)[0] == 0
    masks = snapshot(sorted(out.glob("*_mask.png")))
    code, report = run_relight(tmp_path, capsys, ["mask", "light"], workers, "--skip-existing")
    assert code == 0
    assert snapshot(masks) == masks  # the existing layer is left alone
    assert all(read_image(layer_paths(out, stem)["light"]) is not None for stem in ("p000", "p001"))
    assert [item["kept"] for item in report["items"]] == [["mask"], ["mask"]]


@pytest.mark.parametrize("workers", [1, 2])
def test_skip_existing_completes_an_item_missing_some_layers(tmp_path, capsys, workers):
    make_photos(tmp_path, 3)
    out = tmp_path / "out"
    assert run_relight(tmp_path, capsys, LAYERS, workers)[0] == 0
    light = out / "p001_light.hdr"
    expected_light = light.read_bytes()
    light.unlink()
    (out / "p002_albedo.png").unlink()
    before = snapshot(p for p in out.iterdir())
    code, report = run_relight(tmp_path, capsys, LAYERS, workers, "--skip-existing")
    assert code == 0
    assert snapshot(before) == before
    assert light.read_bytes() == expected_light  # the same bytes as the first run
    assert (out / "p002_albedo.png").is_file()
    items = {Path(item["input"]).stem: item for item in report["items"]}
    assert items["p000"]["skipped"]
    assert items["p001"]["kept"] == ["mask", "albedo"]
    assert items["p002"]["kept"] == ["mask", "light"]
