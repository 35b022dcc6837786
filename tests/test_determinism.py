"""An item's outputs are a function of (input, environment, options, seed) only: the same bytes
alone, second in a batch, with one or two workers, one or two threads, on the local pool or Ray.

Runs the shipped models on the example photo without its mask, so the people's detection and
segmentation run too; every layer is compared byte for byte."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from relightcli.cli import main

REPO = Path(__file__).resolve().parents[1]
LAYERS = "relit,albedo,normal,ao,shading,mask,mesh,light,preview"
OPTIONS = ["--outputs", LAYERS, "--resolution", "256", "--seed", "7", "--json"]


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """A folder whose second photo is the example: the first is the example mirrored, a
    different photo that leaves its state (random generators, sessions) to the second; the
    third holds two people (the example beside its mirror image), two faces."""
    folder = tmp_path_factory.mktemp("determinism") / "in"
    folder.mkdir()
    skier = cv2.imread(str(REPO / "examples" / "skier.jpg"))
    cv2.imwrite(str(folder / "a_mirrored.png"), skier[:, ::-1])
    (folder / "b_skier.jpg").write_bytes((REPO / "examples" / "skier.jpg").read_bytes())
    cv2.imwrite(str(folder / "c_pair.png"), np.concatenate([skier, skier[:, ::-1]], axis=1))
    return folder


def relight(capsys, inputs: Path, out: Path, *extra: str, item: str = "b_skier") -> dict[str, bytes]:
    """The outputs (name -> bytes) of one run of the CLI for one item (by default the example)."""
    code = main([str(inputs), "--hdr", str(REPO / "examples" / "noon_grass.hdr"), "-o", str(out), *OPTIONS, *extra])
    report = json.loads(capsys.readouterr().out)
    assert code == 0, report
    folder = out if out.is_dir() else out.parent
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.name.startswith(item)}


def test_an_item_gives_the_same_bytes_alone_and_anywhere_in_a_batch(batch, tmp_path, capsys):
    alone = relight(capsys, batch / "b_skier.jpg", tmp_path / "alone" / "b_skier.png", "--threads", "2")
    assert len(alone) == len(LAYERS.split(","))
    assert relight(capsys, batch, tmp_path / "w1", "--workers", "1", "--threads", "2") == alone
    assert relight(capsys, batch, tmp_path / "w2", "--workers", "2", "--threads", "2") == alone


def test_two_faces_give_the_same_bytes_alone_and_in_a_batch(batch, tmp_path, capsys):
    """Two people: two body fits and two faces. Alone the item runs in this process, which
    loaded numpy before relightcli (OpenBLAS kept its default threads: the pipeline must hold
    BLAS to one thread itself), in the batch in a worker."""
    alone = relight(capsys, batch / "c_pair.png", tmp_path / "alone" / "c_pair.png", "--threads", "2", item="c_pair")
    assert len(alone) == len(LAYERS.split(","))
    assert relight(capsys, batch, tmp_path / "w2", "--workers", "2", "--threads", "2", item="c_pair") == alone


def test_an_item_gives_the_same_bytes_on_one_thread_and_two(batch, tmp_path, capsys):
    two = relight(capsys, batch / "b_skier.jpg", tmp_path / "t2" / "b_skier.png", "--threads", "2")
    assert relight(capsys, batch / "b_skier.jpg", tmp_path / "t1" / "b_skier.png", "--threads", "1") == two


def test_the_ratio_albedo_gives_the_same_bytes_on_one_thread_and_two(batch, tmp_path, capsys):
    # the default (--albedo solve) is the test above
    two = relight(capsys, batch / "b_skier.jpg", tmp_path / "t2" / "b_skier.png", "--threads", "2", "--albedo", "ratio")
    assert relight(capsys, batch / "b_skier.jpg", tmp_path / "t1" / "b_skier.png", "--threads", "1",
                   "--albedo", "ratio") == two
    assert two != relight(capsys, batch / "b_skier.jpg", tmp_path / "solve" / "b_skier.png", "--threads", "1")


def test_an_item_gives_the_same_bytes_on_ray_as_alone(batch, tmp_path, capsys):
    pytest.importorskip("ray.data")
    alone = relight(capsys, batch / "b_skier.jpg", tmp_path / "alone" / "b_skier.png", "--threads", "1")
    assert relight(capsys, batch, tmp_path / "ray", "--engine", "ray", "--workers", "2", "--threads", "2") == alone


def test_an_item_gives_the_same_bytes_in_separate_processes(tmp_path):
    # Per-process state (Intel IPP in OpenCV's distance transform, inside the body fit) once
    # gave two or three outcomes in six runs on the same input: six fresh processes must agree
    import subprocess
    import sys

    outputs = []
    for k in range(6):
        out = tmp_path / f"p{k}" / "s.png"
        subprocess.run([sys.executable, "-m", "relightcli", str(REPO / "examples" / "skier.jpg"), "--hdr",
                        str(REPO / "examples" / "noon_grass.hdr"), "-o", str(out), "--outputs", "shading",
                        "--method", "raytrace-norefine", "--threads", "1"], check=True, capture_output=True)
        outputs.append((out.parent / "s_shading.exr").read_bytes())
    assert all(o == outputs[0] for o in outputs)
