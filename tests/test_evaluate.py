"""The Table 1 protocol: sRGB-encoded, clipped, masked metrics; shading normalised per scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from relightcli import metrics
from relightcli.evaluate import (
    PSNR_CAP,
    evaluate,
    find_scenes,
    format_table,
    layer_metrics,
    load_scene,
    scene_metrics,
    shading_normaliser,
)
from relightcli.io.images import linear_to_srgb, write_image

from exr_testing import write_float_exr


def make_scene(folder: Path, seed: int = 0, shading_level: float = 5.0) -> Path:
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    h, w = 48, 40
    mask = np.zeros((h, w), np.float32)
    mask[8:44, 10:30] = 1.0
    albedo = rng.uniform(0.1, 0.9, (h, w, 3)).astype(np.float32)
    shading = (shading_level * rng.uniform(0.5, 1.5, (h, w, 3))).astype(np.float32)
    write_image(folder / "input.png", np.clip(albedo * 0.6, 0, 1))
    write_image(folder / "target.hdr", np.ones((8, 16, 3), np.float32))
    write_image(folder / "gt_mask.png", mask, bits=8, srgb=False)
    write_image(folder / "gt_albedo.exr", albedo, half=False)
    write_image(folder / "gt_shading.exr", shading, half=False)
    write_image(folder / "gt_relit.exr", albedo * shading, half=False)
    return folder


def oracle(scene):
    return {"relit": scene.relit, "albedo": scene.albedo, "shading": scene.shading}


def test_perfect_prediction_scores_perfectly(tmp_path):
    scene = load_scene(make_scene(tmp_path / "s0"))
    result = scene_metrics(scene, oracle(scene))
    for layer in ("relit", "albedo", "shading"):
        assert result[layer]["mse"] == 0.0
        assert result[layer]["ssim"] == pytest.approx(1.0)
        assert result[layer]["psnr"] == PSNR_CAP


def test_mask_round_trips_exactly(tmp_path):
    scene = load_scene(make_scene(tmp_path / "s0"))
    assert set(np.unique(scene.mask)) == {0.0, 1.0}


def test_shading_normaliser_maps_p95_to_0_8():
    shading = np.linspace(0, 10, 3000, dtype=np.float32).reshape(1000, 1, 3)
    mask = np.ones((1000, 1), np.float32)
    scale = shading_normaliser(shading, mask)
    assert np.percentile(shading / scale, 95) == pytest.approx(0.8, rel=1e-5)


def test_bright_shading_error_is_not_hidden_by_the_clip(tmp_path):
    # Ground truth shading around 5: without normalisation both sides would clip to 1 and a
    # prediction twice too bright would look perfect.
    scene = load_scene(make_scene(tmp_path / "s0", shading_level=5.0))
    pred = oracle(scene) | {"shading": 2.0 * scene.shading}
    assert scene_metrics(scene, pred)["shading"]["psnr"] < 15.0
    assert layer_metrics(2.0 * scene.shading, scene.shading, scene.mask)["psnr"] == PSNR_CAP


def test_layer_metrics_use_srgb_encoded_clipped_values():
    rng = np.random.default_rng(3)
    gt = rng.uniform(0, 1.5, (30, 30, 3)).astype(np.float32)
    pred = gt * 0.9
    mask = np.ones((30, 30), np.float32)
    a, b = linear_to_srgb(np.clip(pred, 0, 1)), linear_to_srgb(np.clip(gt, 0, 1))
    out = layer_metrics(pred, gt, mask)
    assert out["mse"] == pytest.approx(metrics.mse(a, b) * 1e3)
    assert out["psnr"] == pytest.approx(metrics.psnr(a, b))


def test_failed_scene_is_reported_and_others_still_count(tmp_path):
    make_scene(tmp_path / "a", seed=1)
    broken = make_scene(tmp_path / "b", seed=2)
    (broken / "gt_relit.exr").unlink()
    result = evaluate(find_scenes(tmp_path), oracle, "oracle")
    assert result["scenes"] == 1 and result["failed"] == 1
    errors = [e["error"] for e in result["per_scene"] if e["error"]]
    assert len(errors) == 1 and "gt_relit.exr" in errors[0]
    assert result["albedo"]["mse"] == 0.0


def test_metrics_average_over_scenes(tmp_path):
    for seed in (1, 2):
        make_scene(tmp_path / f"s{seed}", seed=seed)
    noisy = lambda scene: oracle(scene) | {"albedo": scene.albedo * 0.8}
    result = evaluate(find_scenes(tmp_path), noisy, "noisy")
    per = [e["albedo"]["psnr"] for e in result["per_scene"]]
    assert result["albedo"]["psnr"] == pytest.approx(np.mean(per))
    assert "paper" in format_table(result) and "ours: noisy" in format_table(result)


def test_eval_cli_reports_every_scene(tmp_path, capsys):
    import json

    from relightcli.cli import main

    make_scene(tmp_path / "a", seed=1)
    make_scene(tmp_path / "b", seed=2)
    code = main(["eval", str(tmp_path), "--method", "sh9", "--use-gt-mask", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert code == 0, result["per_scene"]
    assert result["method"] == "sh9" and result["scenes"] == 2 and result["failed"] == 0
    assert [e["scene"] for e in result["per_scene"]] == ["a", "b"]
    for layer in ("relit", "albedo", "shading"):
        assert 0 < result[layer]["psnr"] < 100 and 0 <= result[layer]["mse"]


def test_eval_cli_without_models_fails_every_scene_with_exit_3(tmp_path, capsys, monkeypatch):
    import json

    from relightcli.cli import main

    empty = tmp_path / "no_models"
    empty.mkdir()
    (empty / "manifest.json").write_text('{"version": 1, "models": {}}')
    monkeypatch.setenv("RELIGHT_MODELS_DIR", str(empty))
    make_scene(tmp_path / "data" / "a", seed=1)
    code = main(["eval", str(tmp_path / "data"), "--method", "sh9", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert code == 3 and result["failed"] == 1 and "manifest" in result["per_scene"][0]["error"]


def test_eval_cli_on_a_folder_without_scenes_is_usage_error(tmp_path):
    from relightcli.cli import main

    (tmp_path / "empty").mkdir()
    assert main(["eval", str(tmp_path / "empty")]) == 2


def test_normal_error_is_the_mean_angle_over_the_mask_where_both_give_a_normal():
    from relightcli.evaluate import normal_metrics

    truth = np.zeros((4, 4, 3), np.float32)
    truth[..., 2] = 1.0
    mask = np.ones((4, 4), np.float32)
    pred = truth.copy()
    pred[0, :] = (1.0, 0.0, 1.0)  # 45 degrees off, not unit: renormalised
    pred[3, :] = 0.0  # no prediction there: left out, and said so
    found = normal_metrics(pred, truth, mask)
    assert found["covered"] == 0.75
    assert abs(found["deg"] - 45.0 / 3) < 1e-4
    assert normal_metrics(np.zeros_like(pred), truth, mask) == {"deg": None, "covered": 0.0}


def test_eval_scores_the_layers_the_product_writes(tmp_path, capsys):
    # The relit person over black and the albedo and shading files of `relight` with the same
    # mask are exactly what the eval scores: straight layers times the mask, once
    import json

    from relightcli.cli import main
    from relightcli.io.images import read_image
    from relightcli.pipeline import RelightOptions, predict_scene

    folder = make_scene(tmp_path / "a", seed=3)
    out = tmp_path / "out" / "a.exr"
    code = main([str(folder / "input.png"), "--hdr", str(folder / "target.hdr"), "--mask", str(folder / "gt_mask.png"),
                 "--method", "sh9", "--background", "#000000", "--outputs", "relit,albedo,shading",
                 "-o", str(out), "--json"])
    report = json.loads(capsys.readouterr().out)["items"][0]
    assert code == 0, report["error"]
    predicted = predict_scene(load_scene(folder), RelightOptions(method="sh9"), use_gt_mask=True)
    for layer in ("relit", "albedo", "shading"):
        written = read_image(report["outputs"][layer]).rgb
        np.testing.assert_allclose(predicted[layer], written, rtol=2e-3, atol=1e-6, err_msg=layer)
        assert written[load_scene(folder).mask == 0].max() == 0  # black off the person


def test_a_malformed_scene_is_skipped_with_its_reason_and_the_json_stays_json(tmp_path, capsys):
    """A true normal map of the wrong size, NaN in a truth file, an input of another size than
    its truth: each scene fails with the file named, the good one is scored, and --json prints
    strict JSON (no NaN), the means over the good scene alone."""
    import json

    from relightcli.cli import main

    make_scene(tmp_path / "a_good", seed=1)
    normal = make_scene(tmp_path / "b_normal", seed=2)
    write_image(normal / "gt_normal.exr", np.zeros((10, 10, 3), np.float32), half=False)
    nan = make_scene(tmp_path / "c_nan", seed=3)
    albedo = np.full((48, 40, 3), 0.5, np.float32)
    albedo[20, 20] = np.nan
    write_float_exr(nan / "gt_albedo.exr", albedo)  # write_image would write the NaN as 0
    size = make_scene(tmp_path / "d_size", seed=4)
    write_image(size / "input.png", np.full((36, 36, 3), 0.3, np.float32))
    code = main(["eval", str(tmp_path), "--method", "sh9", "--use-gt-mask", "--json"])
    text = capsys.readouterr().out
    result = json.loads(text, parse_constant=lambda name: pytest.fail(f"{name} in the JSON"))
    assert code == 1 and result["scenes"] == 1 and result["failed"] == 3
    errors = {e["scene"]: e["error"] for e in result["per_scene"]}
    assert errors["a_good"] is None
    assert "gt_normal.exr is not the size of gt_mask.png" in errors["b_normal"]
    assert "gt_albedo.exr holds NaN or Inf values" in errors["c_nan"]
    assert "input.png" in errors["d_size"] and "36x36" in errors["d_size"] and "40x48" in errors["d_size"]
    good = next(e for e in result["per_scene"] if e["scene"] == "a_good")
    assert result["relit"]["psnr"] == pytest.approx(good["relit"]["psnr"])


def test_finite_json_makes_every_nan_and_infinity_null():
    from relightcli.evaluate import finite_json

    value = {"a": float("nan"), "b": [1.0, float("inf"), {"c": -float("inf")}], "d": "x", "e": None, "f": 2}
    assert finite_json(value) == {"a": None, "b": [1.0, None, {"c": None}], "d": "x", "e": None, "f": 2}
