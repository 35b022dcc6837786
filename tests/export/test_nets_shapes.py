"""Torch-side properties of the net definitions: output shapes, ranges, the residual structure,
the delight ablation configs, the discriminators."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from export.nets import build_net  # noqa: E402
from export.nets.body_refine import N_SCALES  # noqa: E402
from export.nets.delight import DELIGHT_CONFIGS, DelightNet  # noqa: E402
from export.nets.discriminators import (  # noqa: E402
    LSGAN_CONFIGS, PATCHGAN_CONFIGS, LSGANDiscriminator, MultiscalePatchGAN,
)
from export.onnx_export import person_like_inputs  # noqa: E402

torch.set_num_threads(1)


def run(net, h, w, seed=0):
    feeds = person_like_inputs(net.io_contract(), h, w, seed=seed)
    with torch.no_grad():
        return net.eval()(*(torch.from_numpy(feeds[t.name]) for t in net.io_contract().inputs)), feeds


def test_geometry_outputs_are_unit_normals_ordered_depths_and_a_mask():
    torch.manual_seed(0)
    (front_n, back_n, front_d, back_d, mask), _ = run(build_net("geometry", "small"), 32, 48)
    assert front_n.shape == (1, 3, 32, 48) and mask.shape == (1, 1, 32, 48)
    torch.testing.assert_close(front_n.norm(dim=1), torch.ones(1, 32, 48), atol=1e-5, rtol=0)
    torch.testing.assert_close(back_n.norm(dim=1), torch.ones(1, 32, 48), atol=1e-5, rtol=0)
    assert (back_d <= front_d).all()
    assert ((mask >= 0) & (mask <= 1)).all()


def test_the_prior_net_starts_from_the_fitted_body_and_keeps_depths_ordered():
    torch.manual_seed(0)
    net = build_net("geometry_prior", "small")
    (front_n, back_n, front_d, back_d, mask), feeds = run(net, 32, 48)
    prior = torch.from_numpy(feeds["prior"])
    covered = prior[:, 8] > 0.5
    assert front_n.shape == (1, 3, 32, 48) and mask.shape == (1, 1, 32, 48)
    # unit where the prior covers (off it the untrained head's tiny vectors meet the epsilon)
    torch.testing.assert_close(front_n.norm(dim=1)[covered], torch.ones(int(covered.sum())), atol=1e-5, rtol=0)
    assert (back_d <= front_d).all()
    # untrained, the corrections are small: the output is near the prior where the body covers
    cosine = (front_n * prior[:, 0:3]).sum(dim=1)[covered]
    assert cosine.mean() > 0.95
    assert (front_d[:, 0] - prior[:, 6]).abs()[covered].mean() < 0.2
    # the prior matters: without it the same net gives other normals
    with torch.no_grad():
        bare = net(torch.from_numpy(feeds["image"]), torch.zeros_like(prior))[0]
    assert (bare - front_n).abs().max() > 0.1


def test_ao_is_in_unit_range():
    ao, _ = run(build_net("ao", "small"), 32, 32)
    assert ao.shape == (1, 1, 32, 32) and ((ao >= 0) & (ao <= 1)).all()


def test_the_ao_prior_net_starts_from_the_bodies_ao():
    torch.manual_seed(0)
    net = build_net("ao_prior", "small")
    ao, feeds = run(net, 32, 48)
    prior = torch.from_numpy(feeds["prior"])
    covered = prior[:, 8] > 0.99
    assert ao.shape == (1, 1, 32, 48) and ((ao >= 0) & (ao <= 1)).all()
    # untrained, the correction is small where the body covers: near the body's own AO
    body = prior[:, 9].clamp(0.02, 0.98)
    assert (ao[:, 0] - body).abs()[covered].mean() < 0.05
    # and the body's AO matters: a darker one gives a darker map
    darker = prior.clone()
    darker[:, 9] *= 0.5
    with torch.no_grad():
        dimmed = net(torch.from_numpy(feeds["image"]), darker)
    assert (dimmed - ao)[:, 0][covered].mean() < -0.1


@pytest.mark.parametrize("size", ["small", "vanilla", "five_stage", "unet"])
def test_delight_configs_give_albedo_and_16x32_light(size):
    torch.manual_seed(0)
    net = DelightNet(DELIGHT_CONFIGS[size])
    (albedo, light), _ = run(net, 64, 32)
    assert albedo.shape == (1, 3, 64, 32) and light.shape == (1, 3, 16, 32)
    assert ((albedo >= 0) & (albedo <= 1)).all() and (light >= 0).all()


def test_paper_delight_is_the_supplement_hrnet():
    cfg = DELIGHT_CONFIGS["paper"]
    assert (cfg.stem_stride, cfg.first_stage_residual, len(cfg.widths), cfg.modules, cfg.blocks) == (
        1, False, 6, (1, 2, 2, 2, 2), 2)
    assert cfg.multiple == 32


def test_body_refine_gives_five_non_negative_scales():
    (outputs), _ = run(build_net("body_refine", "small"), 64, 32)
    assert len(outputs) == N_SCALES
    for k, out in enumerate(outputs):
        assert out.shape == (1, 3, 64 >> k, 32 >> k) and (out >= 0).all()


def test_body_refine_with_zero_residual_returns_the_coarse_shading():
    net = build_net("body_refine", "small")
    for conv in net.outputs:
        torch.nn.init.zeros_(conv.weight)
        torch.nn.init.zeros_(conv.bias)
    outputs, feeds = run(net, 32, 32)
    torch.testing.assert_close(outputs[0], torch.from_numpy(feeds["coarse_shading"]), atol=1e-5, rtol=1e-5)


def test_face_refine_with_zero_residual_returns_the_body_crop():
    net = build_net("face_refine", "small")
    torch.nn.init.zeros_(net.out.weight)
    torch.nn.init.zeros_(net.out.bias)
    out, feeds = run(net, 32, 32)
    torch.testing.assert_close(out, torch.from_numpy(feeds["body_shading"]), atol=1e-5, rtol=1e-5)


def test_face_refine_paper_widths_follow_the_supplement():
    cfg = build_net("face_refine", "paper").cfg
    assert (cfg.encoder, cfg.decoder, cfg.n_bottleneck) == ((64, 128, 256, 512), (256, 128, 64, 64), 3)


def test_multiscale_patchgan_gives_one_map_per_scale():
    d = MultiscalePatchGAN(7, PATCHGAN_CONFIGS["small"])
    maps = d(torch.rand(2, 7, 64, 64))
    assert len(maps) == 3
    assert maps[0].shape[:2] == (2, 1) and maps[1].shape[-1] < maps[0].shape[-1]


def test_lsgan_discriminator_scores_each_face():
    d = LSGANDiscriminator(6, LSGAN_CONFIGS["small"])
    assert d(torch.rand(2, 6, 128, 128)).shape == (2, 1)


def test_lsgan_discriminator_rejects_other_sizes():
    with pytest.raises(ValueError, match="128x128"):
        LSGANDiscriminator(6, LSGAN_CONFIGS["small"])(torch.rand(1, 6, 64, 64))


@pytest.mark.parametrize("family", ["nope"])
def test_unknown_family_is_rejected(family):
    with pytest.raises(ValueError, match="unknown net family"):
        build_net(family)
