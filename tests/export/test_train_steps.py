"""The trainer on a tiny fake dataset: a few steps lower the loss of every net family,
resuming from a checkpoint is bit-exact, and validation metrics are relightcli.metrics'."""

import json

import numpy as np
import pytest
import torch
from torch import nn

from export.train.config import ConfigError, TrainConfig
from export.train.data import sample_rng
from export.train.fake_data import FakeDataset
from export.train.tasks import hwc, make_task, protocol_encode
from export.train.trainer import Trainer, TrainingError
from relightcli import metrics

torch.set_num_threads(1)
OVERRIDES = {"batch_size": 2, "threads": 1, "face_crop_size": 32, "val_max_samples": 2, "lr": 1e-3,
             "lr_disc": 1e-4, "log_every": 1}


@pytest.fixture(scope="module")
def dataset():
    return FakeDataset({"train": 4, "val": 2, "test": 1}, size=32, seed=0)


def small_config(net, **extra):
    return TrainConfig(net=net, size="small", seed=0, steps=4, **{**OVERRIDES, **extra})


@pytest.mark.parametrize("net", ["geometry", "geometry_prior", "ao", "ao_prior", "delight", "body_refine",
                                 "face_refine"])
def test_a_few_steps_lower_the_loss(net, dataset, tmp_path):
    trainer = Trainer(small_config(net), dataset, tmp_path)
    batch = trainer.next_batch()
    first = trainer.train_step(batch)["reconstruction"]
    for _ in range(6):
        last = trainer.train_step(batch)["reconstruction"]
    assert last < 0.9 * first


@pytest.mark.parametrize("net", ["geometry", "geometry_prior", "ao", "ao_prior", "delight"])
def test_the_arrays_a_task_loads_are_all_its_examples_read(net, dataset):
    # the trainer loads only task.sample_keys(): the examples must be those of whole samples
    task = make_task(small_config(net))
    for sample_id in dataset.ids("train"):
        whole = task.example(dataset.load("train", sample_id), np.random.default_rng(1))
        some = task.example(dataset.load("train", sample_id, task.sample_keys()), np.random.default_rng(1))
        assert whole.keys() == some.keys()
        for key in whole:
            assert np.array_equal(whole[key], some[key]), key


@pytest.mark.parametrize("net", ["body_refine", "geometry_prior", "ao_prior"])
def test_resume_continues_bit_exactly(net, dataset, tmp_path):
    # body_refine: net + discriminator + two optimisers + the stand-in noise;
    # geometry_prior, ao_prior: two inputs, the prior maps flipped with the image
    straight = Trainer(small_config(net), dataset, tmp_path / "a")
    straight.run(steps=4, validate=False)
    Trainer(small_config(net), dataset, tmp_path / "b").run(steps=2, validate=False)
    resumed = Trainer(small_config(net), dataset, tmp_path / "b")
    assert resumed.step == 2
    resumed.run(steps=4, validate=False)
    for module in ("net", "disc") if net == "body_refine" else ("net",):
        a, b = getattr(straight, module).state_dict(), getattr(resumed, module).state_dict()
        for key in a:
            assert torch.equal(a[key], b[key]), f"{module}.{key}"


def test_resume_takes_the_learning_rate_of_the_new_config(dataset, tmp_path):
    Trainer(small_config("ao"), dataset, tmp_path).run(steps=1, validate=False)
    resumed = Trainer(small_config("ao", lr=5e-5), dataset, tmp_path)
    assert resumed.step == 1 and resumed.opt.param_groups[0]["lr"] == 5e-5


def test_resume_refuses_a_checkpoint_of_another_net(dataset, tmp_path):
    Trainer(small_config("ao"), dataset, tmp_path).run(steps=1, validate=False)
    with pytest.raises(TrainingError, match="ao/small"):
        Trainer(small_config("geometry"), dataset, tmp_path)


def test_run_logs_every_step_and_writes_metrics(dataset, tmp_path):
    Trainer(small_config("ao"), dataset, tmp_path).run(steps=3)
    lines = (tmp_path / "log.jsonl").read_text().splitlines()
    assert [json.loads(line)["step"] for line in lines] == [1, 2, 3]
    assert json.loads((tmp_path / "metrics.json").read_text())["metrics"]["count"] == 2


def test_time_budget_stops_the_run(dataset, tmp_path):
    run = Trainer(small_config("ao"), dataset, tmp_path).run(steps=10_000, max_minutes=0.01, validate=False)
    assert run["stopped_by"] == "time" and 0 < run["step"] < 10_000


class AlbedoIsThePhoto(nn.Module):
    """Stub de-lighting net: albedo = the clipped photo, a constant light."""

    output_names = ("albedo", "light")

    def forward(self, image, normal):
        return image.clamp(0, 1), torch.ones(image.shape[0], 3, 16, 32)


class RefinedIsCoarse(nn.Module):
    """Stub body-refinement net: returns its coarse input at every scale."""

    output_names = ("shading",) + tuple(f"shading_s{k}" for k in range(1, 5))

    def forward(self, coarse, ao):
        return tuple(torch.nn.functional.avg_pool2d(coarse, 2**k) if k else coarse for k in range(5))


def test_albedo_metrics_agree_with_relightcli_metrics(dataset, tmp_path):
    trainer = Trainer(small_config("delight"), dataset, tmp_path)
    trainer.net = AlbedoIsThePhoto()
    got = trainer.validate("val")
    expected = {"albedo_mse": [], "albedo_psnr": [], "albedo_ssim": []}
    for sample_id in dataset.ids("val"):
        s = dataset.load("val", sample_id)
        pred, true = protocol_encode(np.clip(s["input"], 0, 1)), protocol_encode(s["albedo"])
        expected["albedo_mse"].append(metrics.mse(pred, true, s["mask"]))
        expected["albedo_psnr"].append(metrics.psnr(pred, true, s["mask"]))
        expected["albedo_ssim"].append(metrics.ssim(pred, true, s["mask"]))
    for key, values in expected.items():
        assert got[key] == pytest.approx(np.mean(values), rel=1e-5), key


def test_refinement_that_returns_the_coarse_shading_gains_nothing(dataset, tmp_path):
    trainer = Trainer(small_config("body_refine"), dataset, tmp_path)
    trainer.net = RefinedIsCoarse()
    got = trainer.validate("val")
    assert got["shading_psnr_gain"] == pytest.approx(0.0, abs=1e-9)
    # and the coarse PSNR is the protocol's PSNR of the stand-in against the truth
    values = []
    for sample_id in dataset.ids("val"):
        example = trainer.task.example(dataset.load("val", sample_id), sample_rng(0, "val", sample_id))
        true, coarse, mask = hwc(example["shading"]), hwc(example["coarse_shading"]), example["mask"][0]
        scale = np.percentile(true[mask > 0.5], 95) / 0.8
        values.append(metrics.psnr(protocol_encode(coarse, scale), protocol_encode(true, scale), mask))
    assert got["shading_psnr_coarse"] == pytest.approx(np.mean(values), rel=1e-6)


def test_normal_angle_metric_of_the_truth_is_zero(dataset, tmp_path):
    trainer = Trainer(small_config("geometry"), dataset, tmp_path)
    example = trainer.task.example(dataset.load("val", "val_0000"), np.random.default_rng(0))
    out = {k: example[k] for k in ("front_normal", "back_normal", "front_depth", "back_depth", "mask")}
    got = trainer.task.metrics(out, example)
    assert got["normal_angle_deg"] == pytest.approx(0.0, abs=0.05)
    assert got["front_depth_mae"] == 0.0


class RenderedDataset(FakeDataset):
    """The fake samples plus what export.factory.coarse and face_closeups add: a coarse body
    shading, a predicted AO and, the samples being 32 px like the face crop, close-up arrays."""

    def load(self, split, sample_id, names=None):
        sample = super().load(split, sample_id)
        sample["coarse_shading_b"] = 0.7 * sample["shading_b"]
        sample["ao_pred"] = np.full_like(sample["ao"], 0.5)
        sample["coarse_face_b"] = 1.3 * sample["shading_b"]
        sample["body_shading_b"] = 0.9 * sample["shading_b"]
        sample["face_pixels"] = sample["mask"]
        return sample


def test_body_refinement_trains_on_the_rendered_coarse_shading_and_predicted_ao(tmp_path):
    data = RenderedDataset({"train": 4, "val": 2, "test": 1}, size=32, seed=0)
    trainer = Trainer(small_config("body_refine", coarse_shading="coarse_shading_b", ao_key="ao_pred"), data, tmp_path)
    sample = data.load("val", "val_0000")
    example = trainer.task.example(sample, np.random.default_rng(0))
    inside = example["mask"][0] > 0.5
    ratio = example["coarse_shading"][:, inside] / np.maximum(example["shading"][:, inside], 1e-12)
    assert np.allclose(ratio[example["shading"][:, inside] > 1e-3], 0.7, rtol=1e-4)
    assert np.all(example["ao"] == 0.5)
    batch = trainer.next_batch()
    first = trainer.train_step(batch)["reconstruction"]
    for _ in range(6):
        last = trainer.train_step(batch)["reconstruction"]
    assert last < 0.9 * first


def test_face_refinement_on_closeups_reports_the_gain_over_the_body_shading(tmp_path):
    data = RenderedDataset({"train": 4, "val": 2, "test": 1}, size=32, seed=0)
    trainer = Trainer(small_config("face_refine", coarse_shading="coarse_face_b"), data, tmp_path)
    trainer.net = RefinedIsBody()
    got = trainer.validate("val")
    assert got["face_psnr_gain_over_body"] == pytest.approx(0.0, abs=1e-9)
    assert got["face_psnr_body"] > got["face_psnr_coarse"]  # 0.9 x the truth vs 1.3 x


def test_face_closeups_are_normalised_by_the_body_shading_as_at_run_time(tmp_path):
    """stages.face.stage_face_refine divides by the scale of the body shading it has, not the truth's."""
    from relightcli.nets.refine import shading_scale

    data = RenderedDataset({"train": 4, "val": 2, "test": 1}, size=32, seed=0)
    trainer = Trainer(small_config("face_refine", coarse_shading="coarse_face_b"), data, tmp_path)
    sample = data.load("val", "val_0000")
    example = trainer.task.example(sample, np.random.default_rng(0))
    body = np.moveaxis(example["body_shading"], 0, -1)
    assert shading_scale(body, sample["mask"]) == pytest.approx(1.0, rel=1e-5)
    truth = np.moveaxis(example["shading"], 0, -1)
    assert shading_scale(truth, sample["mask"]) == pytest.approx(1 / 0.9, rel=1e-4)


class RefinedIsBody(nn.Module):
    """Stub face-refinement net: returns its body shading input."""

    output_names = ("shading",)

    def forward(self, body_shading, face_shading):
        return (body_shading,)


def test_delight_irradiance_loss_is_the_runtime_sh9_shading_of_the_predicted_light(tmp_path, dataset):
    from relightcli.render.sh import project_sh, sh_irradiance_shading

    config = small_config("delight", loss={"l1": 500.0, "perceptual": 100.0, "light": 0.025, "irradiance": 10.0})
    trainer = Trainer(config, dataset, tmp_path)
    sample = dataset.load("val", "val_0000")
    example = trainer.task.example(sample, np.random.default_rng(0))
    light = np.random.default_rng(1).uniform(0.0, 2.0, (16, 32, 3)).astype(np.float32)
    got = trainer.task.irradiance(torch.from_numpy(light.transpose(2, 0, 1)[None]),
                                  torch.from_numpy(example["irradiance_basis"][None]))[0].numpy()
    bright = example["bright"][0] > 0.5
    want = sh_irradiance_shading(project_sh(light, 2), sample["normal"])
    assert bright.any()
    np.testing.assert_allclose(np.moveaxis(got, 0, -1)[bright], want[bright], rtol=1e-4, atol=1e-5)
    terms = trainer.train_step(trainer.next_batch())
    assert np.isfinite(terms["irradiance"]) and terms["irradiance"] > 0
    assert "ratio_albedo_psnr" in trainer.validate("val")


def test_delight_level_loss_is_the_log_ratio_of_the_albedo_means_over_the_person(tmp_path, dataset):
    config = small_config("delight", loss={"l1": 500.0, "perceptual": 100.0, "light": 0.025, "level": 10.0})
    trainer = Trainer(config, dataset, tmp_path)
    batch = trainer.next_batch()
    mask = batch["mask"]
    assert mask.sum() > 0
    out = {"albedo": batch["albedo"] * 2.0, "light": batch["light"]}  # twice the truth: one stop off
    terms = trainer.task.losses(out, batch)
    assert abs(float(terms["level"]) - 10.0 * np.log(2.0)) < 1e-4
    # the level alone: the same mean over the person, other pixels elsewhere, costs nothing
    person = (mask > 0.5).expand_as(batch["albedo"])
    shuffled = batch["albedo"].clone()
    shuffled[~person] = 0.9
    terms = trainer.task.losses({"albedo": shuffled, "light": batch["light"]}, batch)
    assert float(terms["level"]) < 1e-5
    assert np.isfinite(trainer.train_step(batch)["level"])


class WithPredictedNormals:
    """A dataset whose samples also hold "normal_pred": the true normals, mirrored in x."""

    def __init__(self, data):
        self.data, self.card, self.split_names = data, data.card, data.split_names

    def ids(self, split):
        return self.data.ids(split)

    def load(self, split, sample_id, names=None):
        sample = self.data.load(split, sample_id, names)
        sample["normal_pred"] = sample["normal"] * np.array([-1, 1, 1], np.float32)
        return sample


def test_delight_can_be_fed_the_predicted_normals_and_keeps_the_true_ones_for_its_irradiance(tmp_path, dataset):
    loss = {"l1": 500.0, "perceptual": 100.0, "light": 0.025, "irradiance": 10.0}
    config = small_config("delight", loss=loss, normal_key="normal_pred")
    with pytest.raises(ConfigError, match="normal_pred"):
        Trainer(config, dataset, tmp_path / "missing").task.example(dataset.load("val", "val_0000"), np.random.default_rng(0))
    data = WithPredictedNormals(dataset)
    trainer = Trainer(config, data, tmp_path / "pred")
    sample = data.load("val", "val_0000")
    example = trainer.task.example(sample, np.random.default_rng(0))
    np.testing.assert_array_equal(hwc(example["normal"]), sample["normal_pred"])
    truth = Trainer(small_config("delight", loss=loss), dataset, tmp_path / "true").task.example(
        dataset.load("val", "val_0000"), np.random.default_rng(0))
    np.testing.assert_array_equal(example["irradiance_basis"], truth["irradiance_basis"])
    assert np.isfinite(trainer.train_step(trainer.next_batch())["loss"])


def test_train_samples_limits_training_to_the_first_samples(dataset, tmp_path):
    # the learning curves over data size train on the first N training samples only
    trainer = Trainer(small_config("ao", train_samples=2), dataset, tmp_path)
    assert trainer.train_ids == list(dataset.ids("train"))[:2]
    with pytest.raises(ConfigError, match="train_samples"):
        small_config("ao", train_samples=0)


@pytest.mark.parametrize("net", ["delight", "geometry"])
@pytest.mark.parametrize("size", ["small_half", "small_double"])
def test_the_learning_curve_widths_train(net, size, dataset, tmp_path):
    trainer = Trainer(TrainConfig(net=net, size=size, seed=0, steps=2, **OVERRIDES), dataset, tmp_path)
    trainer.run(steps=2, validate=False)
    assert trainer.step == 2


def test_a_run_started_from_an_onnx_file_starts_at_its_function_and_keeps_its_batchnorms(dataset, tmp_path):
    """`init`: fine-tuning a shipped net whose exporter folded its BatchNorms (no checkpoint):
    the run starts at the file's function, and its BatchNorms stay in eval mode while it trains
    (their scale and shift learn, their statistics stay)."""
    from export.onnx_export import export_onnx

    first = Trainer(small_config("delight"), dataset, tmp_path / "first")
    for _ in range(3):
        first.train_step(first.next_batch())
    export_onnx(first.net.eval(), tmp_path / "delight.onnx")
    tuned = Trainer(small_config("delight", init=str(tmp_path / "delight.onnx")), dataset, tmp_path / "tuned")
    example = tuned.task.example(dataset.load("val", dataset.ids("val")[0], tuned.task.sample_keys()),
                                 sample_rng(0, "val", dataset.ids("val")[0]))
    for key, value in first.predict(example).items():
        np.testing.assert_allclose(tuned.predict(example)[key], value, rtol=1e-4, atol=1e-5)
    norms = [m for m in tuned.net.modules() if isinstance(m, nn.BatchNorm2d)]
    before = [m.running_var.clone() for m in norms]
    shift = [m.bias.detach().clone() for m in norms]
    tuned.train_step(tuned.next_batch())
    assert all(torch.equal(m.running_var, b) for m, b in zip(norms, before))
    assert any(not torch.equal(m.bias, b) for m, b in zip(norms, shift))
    with pytest.raises(TrainingError, match="do not fit"):
        Trainer(small_config("ao", init=str(tmp_path / "delight.onnx")), dataset, tmp_path / "other")


class WithInputLights:
    """A dataset whose training samples record an input light: "a.hdr" for every other one."""

    def __init__(self, data):
        self.data, self.card, self.split_names = data, data.card, data.split_names
        self.load = data.load

    def ids(self, split):
        return self.data.ids(split)

    def meta(self, split, sample_id):
        name = "a.hdr" if self.data.ids(split).index(sample_id) % 2 == 0 else "sky"
        return {"spec": {"lighting_a": {"name": name}}}


def test_samples_lit_by_excluded_lights_are_left_out_of_training(tmp_path, dataset):
    lit = WithInputLights(dataset)
    ids = lit.ids("train")
    trainer = Trainer(small_config("ao", exclude_lights=["a.hdr"]), lit, tmp_path / "a")
    assert trainer.train_ids == ids[1::2] and trainer.config.to_dict()["exclude_lights"] == ["a.hdr"]
    # train_samples counts what is left
    trainer = Trainer(small_config("ao", exclude_lights=["a.hdr"], train_samples=1), lit, tmp_path / "b")
    assert trainer.train_ids == ids[1:2]
    assert Trainer(small_config("ao"), lit, tmp_path / "c").train_ids == ids
    with pytest.raises(ConfigError, match="exclude_lights"):
        small_config("ao", exclude_lights="a.hdr")


def test_delight_shape_loss_leaves_out_the_level_and_gives_it_no_gradient(tmp_path, dataset):
    config = small_config("delight", loss={"l1": 500.0, "perceptual": 100.0, "light": 0.025, "shape": 10.0})
    trainer = Trainer(config, dataset, tmp_path)
    batch = trainer.next_batch()
    mask = batch["mask"]
    # twice the truth: one stop off and the right shape, no cost
    terms = trainer.task.losses({"albedo": batch["albedo"] * 2.0, "light": batch["light"]}, batch)
    assert float(terms["shape"]) < 1e-5
    # a wrong shape at the right level costs its L1 at that level
    noisy = batch["albedo"] * (1.0 + 0.2 * torch.sign(torch.randn_like(batch["albedo"])))
    noisy.requires_grad_(True)
    terms = trainer.task.losses({"albedo": noisy, "light": batch["light"]}, batch)
    assert float(terms["shape"]) > 0.01
    # its gradient does not move the level: summed over the person it is nearly nil
    terms["shape"].backward()
    person = (mask > 0.5).expand_as(noisy)
    along_level = float((noisy.grad * noisy.detach())[person].sum())
    assert abs(along_level) < 1e-4 * float((noisy.grad.abs() * noisy.detach().abs())[person].sum())
    assert np.isfinite(trainer.train_step(batch)["shape"])
