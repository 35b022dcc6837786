"""export.int8_eval: quantise an exported net and compare it with fp32 on validation samples."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from export.int8_eval import evaluate  # noqa: E402
from export.onnx_export import main as export_main  # noqa: E402
from export.train.fake_data import FakeDataset  # noqa: E402


def test_int8_evaluation_reports_quality_time_and_a_decision(tmp_path):
    import torch

    torch.manual_seed(0)
    export_main(["--families", "ao", "--out", str(tmp_path)])
    dataset = FakeDataset({"train": 3, "val": 3, "test": 1}, size=32)
    result = evaluate("ao", tmp_path, dataset, calibration=3, count=3, workdir=tmp_path)
    assert result["samples"] == 3
    for name in ("fp32", "int8"):
        assert np.isfinite(result[name]["quality_psnr_db"]) and result[name]["median_ms"] > 0
        assert "ao_mae" in result[name]["metrics"]
    assert result["drop_db"] == pytest.approx(
        result["fp32"]["quality_psnr_db"] - result["int8"]["quality_psnr_db"], abs=2e-3)
    assert result["ship_int8"] == (result["drop_db"] < 0.3 and
                                   result["int8"]["median_ms"] < result["fp32"]["median_ms"])
    assert (tmp_path / "ao.int8.onnx").is_file()
