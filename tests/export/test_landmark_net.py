"""The landmark net's soft-argmax and in-graph normalisation (analytic checks)."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from export.nets import build_net  # noqa: E402
from export.nets.landmarks import CROP, soft_argmax, standardise  # noqa: E402


def test_a_sharp_peak_gives_the_centre_of_its_cell():
    logits = torch.full((1, 2, 32, 32), -1e4)
    logits[0, 0, 5, 9] = 0.0     # row 5, column 9
    logits[0, 1, 31, 0] = 0.0
    points = soft_argmax(logits, stride=4)
    # cell (a, b) covers pixels [4b, 4b + 4): centre at 4b + 1.5 (pixel centres at j)
    torch.testing.assert_close(points[0], torch.tensor([[37.5, 21.5], [1.5, 125.5]]))


def test_flat_logits_give_the_crop_centre():
    points = soft_argmax(torch.zeros(1, 68, 32, 32), stride=4)
    torch.testing.assert_close(points, torch.full((1, 68, 2), (CROP - 1) / 2.0))


def test_standardisation_removes_exposure():
    image = torch.rand(1, 3, 16, 16) * 0.5
    brighter = image * 1.8  # an exposure change, still below clipping
    a, b = standardise(image), standardise(brighter)
    # gamma makes an exposure a gain in the encoded values up to the offset, which the
    # per-image mean and deviation remove
    assert torch.allclose(a.mean(), torch.tensor(0.0), atol=1e-5)
    assert (a - b).abs().max() < 0.05


@pytest.mark.parametrize("size", ["small", "regression_small"])
def test_both_heads_give_68_points_in_pixels(size):
    torch.manual_seed(0)
    out = build_net("landmarks", size).eval()(torch.rand(2, 3, CROP, CROP))
    assert out.shape == (2, 68, 2) and torch.isfinite(out).all()
