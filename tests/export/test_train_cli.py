"""`python -m export.train` in-process: one net, all nets end to end with the ONNX export into a
models dir whose manifest the runtime sessions load, and the exit code of user mistakes."""

import json

import numpy as np
import pytest
import torch

from export.train.cli import main
from export.train.fake_data import write_fake_dataset

torch.set_num_threads(1)
TINY = ["--steps", "2", "--threads", "1", "--set", "batch_size=2", "--set", "face_crop_size=32",
        "--set", "export_size=32", "--set", "val_max_samples=1"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return write_fake_dataset(tmp_path_factory.mktemp("data"), {"train": 3, "val": 1, "test": 1}, size=32)


@pytest.fixture(scope="module")
def all_nets(data_dir, tmp_path_factory):
    """Train every net 2 steps and export them all (the slowest part of this file, ~15 s)."""
    runs, models = tmp_path_factory.mktemp("runs"), tmp_path_factory.mktemp("models")
    code = main(["all", "--size", "small", "--data", str(data_dir), "--out", str(runs),
                 "--export-to", str(models), *TINY])
    return code, runs, models


def test_one_net_trains_with_its_config_file(data_dir, tmp_path):
    code = main(["ao", "--config", "export/train/configs/ao_small.json", "--data", str(data_dir),
                 "--out", str(tmp_path), *TINY])
    assert code == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["step"] == 2
    assert (tmp_path / "checkpoint.pt").is_file()


def test_all_nets_exit_zero(all_nets):
    assert all_nets[0] == 0


def test_all_nets_write_one_run_each(all_nets):
    _, runs, _ = all_nets
    for net in ("geometry", "ao", "delight", "body_refine", "face_refine"):
        assert (runs / net / "checkpoint.pt").is_file(), net
        assert (runs / net / "log.jsonl").is_file(), net


def test_manifest_entries_carry_config_data_card_and_metrics(all_nets):
    _, _, models = all_nets
    entries = json.loads((models / "manifest.json").read_text())["models"]
    assert sorted(entries) == ["ao", "body_refine", "delight", "face_refine", "geometry"]
    delight = entries["delight"]
    assert delight["training"]["config"]["net"] == "delight"
    assert delight["training_data"]["counts"] == {"train": 3, "val": 1, "test": 1}
    assert "albedo_psnr" in delight["metrics"] and delight["metrics"]["split"] == "val"
    assert "shading_psnr_gain" in entries["body_refine"]["metrics"]


def test_exported_models_load_in_the_runtime_sessions(all_nets):
    from relightcli.nets.delight import DelightNet
    from relightcli.nets.geometry import AONet, GeometryNet
    from relightcli.nets.refine import BodyRefineNet, FaceRefineNet

    _, _, models = all_nets
    image = np.full((32, 32, 3), 0.5, dtype=np.float32)
    assert AONet(models_dir=models, threads=1).predict(image).shape == (32, 32)
    assert GeometryNet(models_dir=models, threads=1).predict(image).mask.shape == (32, 32)
    for session in (DelightNet, BodyRefineNet, FaceRefineNet):
        assert session(models_dir=models, threads=1).entry.sha256


def test_missing_dataset_exits_2(tmp_path, capsys):
    assert main(["ao", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "run")]) == 2
    assert "dataset" in capsys.readouterr().err


def test_config_of_another_net_exits_2(data_dir, tmp_path, capsys):
    code = main(["geometry", "--config", "export/train/configs/ao_small.json", "--data", str(data_dir),
                 "--out", str(tmp_path), *TINY])
    assert code == 2
    assert "configures 'ao'" in capsys.readouterr().err


def test_typo_in_an_override_exits_2(data_dir, tmp_path, capsys):
    code = main(["ao", "--data", str(data_dir), "--out", str(tmp_path), "--set", "bach_size=2"])
    assert code == 2
    assert "bach_size" in capsys.readouterr().err


def test_a_net_fine_tuned_from_a_shipped_file_keeps_its_record(all_nets, data_dir, tmp_path):
    """`init` = a models folder's file: the export into that folder records what it replaced."""
    import shutil

    _, _, models = all_nets
    folder = tmp_path / "models"
    shutil.copytree(models, folder)
    before = json.loads((folder / "manifest.json").read_text())["models"]["ao"]
    code = main(["ao", "--data", str(data_dir), "--out", str(tmp_path / "run"), "--export-to", str(folder),
                 *TINY, "--set", f'init="{folder / "ao.onnx"}"', "--set", "train_samples=2"])
    assert code == 0
    after = json.loads((folder / "manifest.json").read_text())["models"]["ao"]
    assert after["sha256"] != before["sha256"]
    assert after["fine_tuned_from"] == {key: before[key] for key in ("sha256", "training", "training_data", "metrics")}
    assert after["training"]["config"]["init"] == str(folder / "ao.onnx")
    # the training samples it saw: 2 of the 3 (train_samples)
    assert after["training_data"]["samples_used"] == {"train": 2, "val": 1, "test": 1}
    # exported again from the same run: the file it replaced is its own export, the origin stands
    assert main(["ao", "--data", str(data_dir), "--out", str(tmp_path / "run"), "--export-to", str(folder),
                 *TINY, "--set", f'init="{folder / "ao.onnx"}"', "--set", "train_samples=2"]) == 0
    again = json.loads((folder / "manifest.json").read_text())["models"]["ao"]
    assert again["fine_tuned_from"] == after["fine_tuned_from"]
