"""bench/net_curves.py's bookkeeping: the pipeline's version, paired differences."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import net_curves  # noqa: E402


def test_paired_difference_compares_the_scenes_both_scored():
    run = {"per_scene": {"a": {"relit": 17.0}, "b": {"relit": 18.0}, "c": {"relit": 16.0}, "d": {"relit": 9.0}}}
    shipped = {"per_scene": {"a": {"relit": 16.5}, "b": {"relit": 18.2}, "c": {"relit": 15.0}}}
    # d is left out (the shipped net has no score there): +0.5, -0.2, +1.0
    assert net_curves.paired_difference(run, shipped, "relit") == "+0.433 (se 0.348 over 3 people, better in 2 of 3)"
    assert net_curves.paired_difference({}, shipped, "relit") == "-"  # a score from before per-scene ones
    # a and b are one person: the standard error is over the people's means (+0.15 and +1.0)
    for scene in "ab":
        run["per_scene"][scene]["person"] = 7
    assert net_curves.paired_difference(run, shipped, "relit") == "+0.433 (se 0.425 over 2 people, better in 2 of 3)"
    assert net_curves.paired_difference(run, shipped, "shading") == "-"


def test_the_pipeline_version_is_a_short_stable_digest():
    version = net_curves.pipeline_version()
    assert version == net_curves.pipeline_version() and len(version) == 12


def test_runs_of_another_length_or_crop_are_named_for_it():
    from pathlib import Path

    runs = Path("runs")
    assert net_curves.run_dir(runs, "delight", "small", 2400, 1500, 128).name == "small_2400"
    assert net_curves.run_dir(runs, "delight", "small", 2400, 3000, 128).name == "small_2400_steps3000"
    assert net_curves.run_dir(runs, "delight", "small", 2400, 3000, None).name == "small_2400_steps3000_whole"
    assert net_curves.run_dir(runs, "geometry_prior", "small", 1200, 3000, None).name == "small_1200"
    assert net_curves.run_dir(runs, "ao", "small_half", 1200, 3000, 64).name == "small_half_1200_crop64"
    assert net_curves.run_dir(runs, "delight", "small", 2400, 1000, None, "models/delight.onnx").name == \
        "small_2400_steps1000_whole_from_delight"
    command = net_curves.train_command("delight", "DATA", runs / "r", "small", 2400, 1000, None, "models/delight.onnx")
    assert command[-2:] == ["--set", 'init="models/delight.onnx"']
    # another learning rate: its own run, and the trainer told it
    assert net_curves.run_dir(runs, "delight", "small", 2400, 1000, None, "models/delight.onnx", 5e-5).name == \
        "small_2400_steps1000_whole_from_delight_lr5e-05"
    command = net_curves.train_command("delight", "DATA", runs / "r", "small", 2400, 1000, None, "models/delight.onnx", 5e-5)
    assert command[-2:] == ["--set", "lr=5e-05"]
    from export.train.config import merge_overrides

    assert merge_overrides([command[-1]]) == {"lr": 5e-05}
    # any other setting: its own run too
    settings = ("loss.level=100",)
    assert net_curves.run_dir(runs, "delight", "small", 1900, 1000, None, "models/delight.onnx", None, settings).name \
        == "small_1900_steps1000_whole_from_delight_loss.level100"
    command = net_curves.train_command("delight", "DATA", runs / "r", "small", 1900, 1000, None, None, None, settings)
    assert command[-2:] == ["--set", "loss.level=100"] and merge_overrides([command[-1]]) == {"loss": {"level": 100}}
    # a long value (a list of lights held out) is named by a digest
    assert net_curves.setting_name('exclude_lights=["a_1k.hdr", "b_1k.hdr"]') == "exclude_lights" + \
        hashlib.sha256(b'["a_1k.hdr", "b_1k.hdr"]').hexdigest()[:6]


def test_a_run_is_exported_for_scoring_with_its_own_config(tmp_path, monkeypatch):
    """Scoring resumes the run at its last step to export it: with the run's own config.json
    (a command rebuilt from the family's config rewrote the run's learning rate and loss)."""
    import json
    import subprocess

    run = tmp_path / "small_1900_steps1000_whole_from_delight_lr2e-05"
    run.mkdir()
    (run / "log.jsonl").write_text(json.dumps({"step": 1000}) + "\n")
    commands = []
    monkeypatch.setattr(subprocess, "run", lambda command, **kwargs: commands.append(command))
    monkeypatch.setattr(net_curves, "net_seconds", lambda path: 0.1)
    monkeypatch.setattr(net_curves, "eval_scores", lambda models, scenes: {"relit": 17.0})
    scores = net_curves.pipeline_scores(run, "delight", "DATA", ["SCENES"], {"size": "small", "lr": 2e-05})
    assert scores == {"seconds": 0.1, "SCENES": {"relit": 17.0}}
    [command] = commands
    assert command[command.index("--config") + 1] == str(run / "config.json")
    assert command[command.index("--steps") + 1] == "1000" and "--set" not in command


def test_ship_records_the_runs_scores_in_its_manifest_entry(tmp_path, monkeypatch):
    import json
    import subprocess
    from argparse import Namespace

    import pytest

    (tmp_path / "models").mkdir()
    entry = {"sha256": "x", "metrics": {"split": "val", "count": 0}, "training": {"run_dir": "elsewhere"}}
    (tmp_path / "models" / "manifest.json").write_text(json.dumps({"version": 1, "models": {"delight": entry}}))
    monkeypatch.setattr(net_curves, "ROOT", tmp_path)
    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "log.jsonl").write_text(json.dumps({"step": 1000}) + "\n")
    args = Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r", calibrate_to=None)
    commands = []
    monkeypatch.setattr(subprocess, "run", lambda command, **kwargs: commands.append(command))
    with pytest.raises(SystemExit, match="score --eval"):  # not scored yet
        net_curves.ship(args)
    version = net_curves.pipeline_version()
    (run / "pipeline.json").write_text(json.dumps({
        "1000 seconds": 0.03, f"1000 {version} SETS": {"relit": 17.8, "per_scene": {"a": {"relit": 17.8}}},
        f"900 {version} SETS": {"relit": 1.0}, "1000 oldversion SETS": {"relit": 2.0}}))
    net_curves.ship(args)
    [command] = commands
    assert command[command.index("--export-to") + 1] == str(tmp_path / "models")
    shipped = json.loads((tmp_path / "models" / "manifest.json").read_text())["models"]["delight"]
    assert shipped["metrics"] == {"split": "val", "count": 0, "pipeline": {"SETS": {"relit": 17.8}}}
    assert shipped["training"]["run_dir"] == "runs/r"


def test_with_people_marks_each_scene_with_its_person(tmp_path):
    for scene, seed in (("val_000000", 11), ("val_000001", 11), ("val_000002", 12)):
        (tmp_path / scene).mkdir()
        (tmp_path / scene / "scene.json").write_text(json.dumps({"spec": {"person_seed": seed}}))
    scores = {"per_scene": {name: {"relit": 17.0} for name in ("val_000000", "val_000001", "val_000002", "gone")}}
    marked = net_curves.with_people(scores, str(tmp_path))["per_scene"]
    assert [marked[name].get("person") for name in sorted(marked)] == [None, 11, 11, 12]


def test_export_makes_a_models_folder_with_the_runs_net(tmp_path, monkeypatch):
    """`export` copies the shipped models and exports the run at its last step into the copy;
    it refuses a folder that exists (nothing overwritten)."""
    import subprocess
    from argparse import Namespace

    import pytest

    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "manifest.json").write_text("{}")
    monkeypatch.setattr(net_curves, "ROOT", tmp_path)
    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "log.jsonl").write_text(json.dumps({"step": 700}) + "\n")
    commands = []
    monkeypatch.setattr(subprocess, "run", lambda command, **kwargs: commands.append(command))
    to = tmp_path / "out" / "models_r"
    net_curves.export(Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r", to=str(to),
                                     calibrate_to=None))
    assert (to / "manifest.json").read_text() == "{}"
    [command] = commands
    assert command[command.index("--export-to") + 1] == str(to)
    assert command[command.index("--steps") + 1] == "700"
    with pytest.raises(SystemExit, match="exists"):
        net_curves.export(Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r", to=str(to),
                                     calibrate_to=None))


def test_a_calibrated_ship_brings_the_new_nets_level_to_the_shipped_nets(tmp_path, monkeypatch):
    """--calibrate-to measures the reference net before the export replaces it, then the new net
    on the same samples, and writes the gain that moves the new net's median level onto the
    reference's into the manifest entry (a level > 0: the net's albedo darker than the truth)."""
    import subprocess
    from argparse import Namespace

    import delight_level

    (tmp_path / "models").mkdir()
    entry = {"sha256": "x", "metrics": {}, "training": {}}
    (tmp_path / "models" / "manifest.json").write_text(json.dumps({"version": 1, "models": {"delight": entry}}))
    monkeypatch.setattr(net_curves, "ROOT", tmp_path)
    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "log.jsonl").write_text(json.dumps({"step": 1000}) + "\n")
    version = net_curves.pipeline_version()
    # the net as it is was scored, not calibrated: ship --calibrate-to wants the calibrated net's scores
    (run / "pipeline.json").write_text(json.dumps({f"1000 {version} SETS": {"relit": 17.8}}))
    with pytest.raises(SystemExit, match="calibrated to models"):
        net_curves.ship(Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r",
                                  calibrate_to="models"))
    (run / "pipeline.json").write_text(json.dumps({f"1000 {version}+calibrated-to:models SETS": {"relit": 17.9}}))
    events = []
    monkeypatch.setattr(subprocess, "run", lambda command, **kwargs: events.append("export"))

    class Data:
        def ids(self, split):
            return [f"{split}_{i:06d}" for i in range(400)]

    monkeypatch.setattr(delight_level.dataset, "open_dataset", lambda path: Data())

    def measure(models, data, split, ids):
        events.append(("measure", len(ids), ids[0]))
        level = 0.2 if "export" not in events else -0.05  # the reference, then the new net
        return {"samples": len(ids), "level_median": level, "rows": []}

    monkeypatch.setattr(delight_level, "measure", measure)
    args = Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r", calibrate_to="models")
    net_curves.ship(args)
    assert events == [("measure", 200, "val_000100"), "export", ("measure", 200, "val_000100")]
    calibration = json.loads((tmp_path / "models" / "manifest.json").read_text())["models"]["delight"]["calibration"]
    assert calibration["albedo_gain"] == round(2.0 ** -0.25, 4)  # 0.25 stops darker: the reference's level
    assert calibration["measured"]["samples"] == 200 and calibration["reference"] == "models"
    shipped = json.loads((tmp_path / "models" / "manifest.json").read_text())["models"]["delight"]
    assert shipped["metrics"]["pipeline"] == {"SETS": {"relit": 17.9}}  # the calibrated net's scores
    with pytest.raises(SystemExit, match="de-lighting"):
        net_curves.level_reference(Namespace(family="ao", data="DATA", calibrate_to="models"))


def test_a_calibrated_nets_scores_are_kept_apart_from_the_net_as_it_is(tmp_path):
    run = tmp_path / "small_double_2400"
    run.mkdir()
    (run / "log.jsonl").write_text(json.dumps({"step": 1800}) + "\n")
    version = net_curves.pipeline_version()
    calibrated = type("Args", (), {"calibrate_to": "models"})()
    tag = net_curves.calibration_tag(calibrated)
    assert tag == "+calibrated-to:models" and " " not in tag
    assert net_curves.calibration_tag(type("Args", (), {"calibrate_to": None})()) == ""
    kept = {"1800 seconds": 0.09, f"1800 {version} S": {"relit": 17.0}, f"1800 {version}{tag} S": {"relit": 17.5}}
    (run / "pipeline.json").write_text(json.dumps(kept))
    # both found in the cache: nothing is exported or run
    assert net_curves.pipeline_scores(run, "delight", "DATA", ["S"])["S"] == {"relit": 17.0}
    assert net_curves.pipeline_scores(run, "delight", "DATA", ["S"], calibrated, {"level_median": 0.2})["S"] == \
        {"relit": 17.5}


def test_a_candidate_ships_into_its_own_folder_and_adopt_ships_it_as_it_is(tmp_path, monkeypatch):
    import subprocess
    from argparse import Namespace

    from export.manifest import update_manifest
    from relightcli.nets.manifest import sha256_file

    models = tmp_path / "models"
    models.mkdir()
    (models / "delight.onnx").write_bytes(b"the shipped net")
    update_manifest(models, "delight", {"file": "delight.onnx", "sha256": sha256_file(models / "delight.onnx"),
                                        "metrics": {}, "training": {}})
    monkeypatch.setattr(net_curves, "ROOT", tmp_path)
    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "log.jsonl").write_text(json.dumps({"step": 1800}) + "\n")
    (run / "pipeline.json").write_text(json.dumps({f"1800 {net_curves.pipeline_version()} SETS": {"relit": 18.1}}))

    def exporter(command, **kwargs):  # what export.train --export-to does: the net's file and its entry
        into = Path(command[command.index("--export-to") + 1])
        (into / "delight.onnx").write_bytes(b"the new net")
        update_manifest(into, "delight", {"file": "delight.onnx", "sha256": sha256_file(into / "delight.onnx"),
                                          "metrics": {}, "training": {}})

    monkeypatch.setattr(subprocess, "run", exporter)
    candidate = tmp_path / "candidate"
    net_curves.ship(Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r",
                              calibrate_to=None, to=str(candidate)))
    assert (models / "delight.onnx").read_bytes() == b"the shipped net"  # models/ untouched
    assert sorted(p.name for p in candidate.iterdir()) == ["delight.onnx", "manifest.json"]
    entry = json.loads((candidate / "manifest.json").read_text())["models"]["delight"]
    assert entry["metrics"]["pipeline"] == {"SETS": {"relit": 18.1}} and entry["training"]["run_dir"] == "runs/r"
    with pytest.raises(SystemExit, match="exists"):
        net_curves.ship(Namespace(family="delight", data="DATA", runs=str(tmp_path / "runs"), run="r",
                                  calibrate_to=None, to=str(candidate)))
    copy = tmp_path / "models_copy"
    shutil.copytree(models, copy)
    net_curves.adopt(Namespace(family="delight", candidate=str(candidate), into=str(copy)))
    assert (copy / "delight.onnx").read_bytes() == b"the new net"
    assert (models / "delight.onnx").read_bytes() == b"the shipped net"
    net_curves.adopt(Namespace(family="delight", candidate=str(candidate), into=None))
    assert (models / "delight.onnx").read_bytes() == b"the new net"
    assert json.loads((models / "manifest.json").read_text())["models"]["delight"] == entry
    (candidate / "delight.onnx").write_bytes(b"another net")
    with pytest.raises(SystemExit, match="sha256"):
        net_curves.adopt(Namespace(family="delight", candidate=str(candidate), into=None))
