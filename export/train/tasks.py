"""One `Task` per net family: the data adapter (dataset sample -> the net's inputs and
targets), the paper's loss for that net, its discriminator (if any) and its validation metrics.

An *example* is a dict of float32 CHW numpy arrays for one training pair; a *batch* is the
same keys stacked into NCHW torch tensors. `Task.example` returns None for a sample that
cannot make one (the face net on a sample without a visible face).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from export.nets import build_net
from export.nets.blocks import encode_log_shading
from export.nets.discriminators import (LSGAN_CONFIGS, PATCHGAN_CONFIGS, LSGANConfig, LSGANDiscriminator,
                                        MultiscalePatchGAN)
from export.train import data
from export.train.config import ConfigError, TrainConfig
from export.train.losses import (angular_loss, fft_l1, gradient_l1, light_loss, masked_l1, perceptual,
                                 pyramid)
from relightcli import metrics
from relightcli.compose import RATIO_DARK, anchor_albedo, ratio_albedo
from relightcli.io.images import linear_to_srgb
from relightcli.nets.geometry import ao_prior_channels, prior_channels
from relightcli.nets.refine import shading_scale
from relightcli.render.sh import irradiance_basis, project_sh, sh_irradiance_shading


def chw(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, C) -> (C, H, W) float32."""
    image = np.asarray(image, dtype=np.float32)
    return np.ascontiguousarray(image[None] if image.ndim == 2 else image.transpose(2, 0, 1))


def hwc(image: np.ndarray) -> np.ndarray:
    """(C, H, W) -> (H, W, C); a single channel comes back as (H, W)."""
    return image[0] if image.shape[0] == 1 else image.transpose(1, 2, 0)


def collate(examples: list[dict]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.stack([e[k] for e in examples])) for k in examples[0]}


def protocol_encode(x: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """The evaluation protocol's encoding (DESIGN.md): divide by `scale`, clip to [0, 1], sRGB."""
    return linear_to_srgb(np.clip(x / np.float32(scale), 0.0, 1.0))


def mean_angle_deg(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    """Mean angle in degrees between (H, W, 3) normal maps over mask > 0.5 (pred renormalised)."""
    inside = mask > 0.5
    p = pred[inside] / np.maximum(np.linalg.norm(pred[inside], axis=-1, keepdims=True), 1e-8)
    t = target[inside] / np.maximum(np.linalg.norm(target[inside], axis=-1, keepdims=True), 1e-8)
    cos = np.clip(np.sum(p * t, axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def masked_mae(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    return float(np.abs(pred - target)[mask > 0.5].mean())


class Task:
    """Base: subclasses set `family`, `input_keys` and implement example / losses / metrics."""

    family = ""
    input_keys: tuple[str, ...] = ()

    def __init__(self, config: TrainConfig):
        self.config = config
        self.w = config.loss

    def build_net(self) -> nn.Module:
        return build_net(self.family, self.config.size)

    def build_discriminator(self) -> nn.Module | None:
        return None

    def sample_keys(self) -> tuple[str, ...] | None:
        """The dataset arrays `example` reads (the trainer loads only those), None: all."""
        return None

    def example(self, sample: dict, rng: np.random.Generator) -> dict | None:
        raise NotImplementedError

    def forward(self, net: nn.Module, batch: dict) -> dict[str, torch.Tensor]:
        out = net(*(batch[k] for k in self.input_keys))
        out = (out,) if isinstance(out, torch.Tensor) else out
        return dict(zip(net.output_names, out))

    def losses(self, out: dict, batch: dict) -> dict[str, torch.Tensor]:
        """Weighted reconstruction terms (their sum is the loss without the adversarial term)."""
        raise NotImplementedError

    def discriminator_pair(self, out: dict, batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """(real, fake) discriminator inputs; only for the adversarial tasks."""
        raise NotImplementedError

    def metrics(self, out: dict[str, np.ndarray], example: dict[str, np.ndarray]) -> dict[str, float]:
        """Validation metrics of one example: `out` maps output names to (C, H, W) arrays."""
        raise NotImplementedError


class GeometryTask(Task):
    """image -> front/back normals, front/back depth (translation-invariant), mask.
    Loss (paper: 5 L1 + perceptual) on each map, plus an angular term on the normals."""

    family = "geometry"
    input_keys = ("image",)

    def sample_keys(self):
        return ("input", "normal", "back_normal", "front_depth", "back_depth", "mask", "rect")

    def example(self, sample, rng):
        front, back = data.relative_depths(sample)
        return {"image": chw(sample["input"]), "front_normal": chw(sample["normal"]),
                "back_normal": chw(sample["back_normal"]), "front_depth": chw(front),
                "back_depth": chw(back), "mask": chw(sample["mask"])}

    def losses(self, out, batch):
        m = batch["mask"]
        terms = {}
        for key in ("front_normal", "back_normal"):
            terms[f"{key}_l1"] = self.w["l1"] * masked_l1(out[key], batch[key], m)
            terms[f"{key}_angular"] = self.w["angular"] * angular_loss(out[key], batch[key], m)
            terms[f"{key}_perceptual"] = self.w["perceptual"] * perceptual(
                (out[key] + 1) / 2 * m, (batch[key] + 1) / 2 * m, m)
        for key in ("front_depth", "back_depth"):
            terms[f"{key}_l1"] = self.w["l1"] * masked_l1(out[key], batch[key], m)
            terms[f"{key}_gradient"] = self.w["perceptual"] * gradient_l1(out[key], batch[key], m)
        terms["mask_l1"] = self.w["l1"] * masked_l1(out["mask"], m)
        terms["mask_perceptual"] = self.w["perceptual"] * perceptual(out["mask"], m)
        return terms

    def metrics(self, out, example):
        mask = example["mask"][0]
        return {
            "normal_angle_deg": mean_angle_deg(hwc(out["front_normal"]), hwc(example["front_normal"]), mask),
            "back_normal_angle_deg": mean_angle_deg(hwc(out["back_normal"]), hwc(example["back_normal"]), mask),
            "front_depth_mae": masked_mae(out["front_depth"][0], example["front_depth"][0], mask),
            "back_depth_mae": masked_mae(out["back_depth"][0], example["back_depth"][0], mask),
            "mask_mae": float(np.abs(out["mask"][0] - mask).mean()),
        }


PRIOR_KEYS = ("prior_mask", "prior_normal", "prior_back_normal", "prior_front_depth", "prior_back_depth")


def sample_prior(sample: dict) -> np.ndarray:
    """relightcli.nets.geometry.prior_channels of a sample's "prior_*" maps, at its side."""
    return prior_channels(sample["prior_mask"], sample["prior_normal"], sample["prior_back_normal"],
                          sample["prior_front_depth"], sample["prior_back_depth"], sample["mask"].shape[0])


class GeometryPriorTask(GeometryTask):
    """(image, fitted body's prior maps) -> the geometry maps, with the GeometryTask's loss.
    The prior is relightcli.nets.geometry.prior_channels of the sample's "prior_*" arrays (the
    runtime's own fit, export.factory.coarse --priors): what the runtime feeds the net.
    Metrics add the errors on the pixels the body covers, of the net and of the prior alone."""

    family = "geometry_prior"
    input_keys = ("image", "prior")

    def sample_keys(self):
        return super().sample_keys() + PRIOR_KEYS

    def example(self, sample, rng):
        if "prior_mask" not in sample:
            raise ConfigError("the dataset has no prior maps: add them with "
                              "`python -m export.factory.coarse DATA --priors`")
        return dict(super().example(sample, rng), prior=chw(sample_prior(sample)))

    def metrics(self, out, example):
        found = super().metrics(out, example)
        covered = example["mask"][0] * (example["prior"][8] > 0.5)
        if covered.sum() > 0:
            truth = hwc(example["front_normal"])
            found["covered_share"] = float(covered.sum() / max(float((example["mask"][0] > 0.5).sum()), 1.0))
            found["normal_angle_deg_covered"] = mean_angle_deg(hwc(out["front_normal"]), truth, covered)
            found["prior_normal_angle_deg_covered"] = mean_angle_deg(hwc(example["prior"][0:3]), truth, covered)
        return found


class AOTask(Task):
    """image -> AO. Loss (paper: 5 L1 + perceptual) over the person."""

    family = "ao"
    input_keys = ("image",)

    def sample_keys(self):
        return ("input", "ao", "mask")

    def example(self, sample, rng):
        return {"image": chw(sample["input"]), "ao": chw(sample["ao"]), "mask": chw(sample["mask"])}

    def losses(self, out, batch):
        m = batch["mask"]
        return {"ao_l1": self.w["l1"] * masked_l1(out["ao"], batch["ao"], m),
                "ao_perceptual": self.w["perceptual"] * perceptual(out["ao"] * m, batch["ao"] * m, m)}

    def metrics(self, out, example):
        return {"ao_mae": masked_mae(out["ao"][0], example["ao"][0], example["mask"][0])}


class AOPriorTask(AOTask):
    """(image, fitted bodies' prior maps and ray-traced AO) -> AO, with the AOTask's loss. The
    prior is relightcli.nets.geometry.ao_prior_channels of the sample's "prior_*" arrays (the
    runtime's own fit and AO, export.factory.coarse --prior-ao). Metrics add the MAE of the net
    and of the bodies' AO alone on the pixels the bodies cover."""

    family = "ao_prior"
    input_keys = ("image", "prior")

    def sample_keys(self):
        return super().sample_keys() + PRIOR_KEYS + ("prior_ao",)

    def example(self, sample, rng):
        if "prior_ao" not in sample:
            raise ConfigError("the dataset has no prior AO: add it with "
                              "`python -m export.factory.coarse DATA --prior-ao`")
        prior = ao_prior_channels(sample_prior(sample), sample["prior_ao"])
        return dict(super().example(sample, rng), prior=chw(prior))

    def metrics(self, out, example):
        found = super().metrics(out, example)
        body = example["prior"][9]
        covered = example["mask"][0] * (example["prior"][8] > 0.5)
        if covered.sum() > 0:
            found["ao_mae_covered"] = masked_mae(out["ao"][0], example["ao"][0], covered)
            found["body_ao_mae_covered"] = masked_mae(body, example["ao"][0], covered)
        return found


class DelightTask(Task):
    """[image, normal] -> albedo, light. Loss (paper): 500 L1 + 100 perceptual on the albedo
    over the person, 0.025 solid-angle-weighted log-L2 on the 16x32 light. The normal input
    is config `normal_key`: the ground truth (the paper), or "normal_pred", the geometry net's
    normals as the runtime feeds them (export.factory.coarse --normals-only).

    Ours, optional (loss weight "irradiance"): log-L1 between the SH-9 irradiance of the
    predicted light at the true normals and the true input shading, where that shading is not
    dark: what the runtime's ratio albedo (relightcli.compose.ratio_albedo) divides by. And
    ("level") the log-L1 between the albedo's mean over the person (channels and pixels) and the
    truth's: the level the runtime gives its albedo (relightcli.compose.albedo_gain). And
    ("shape") the L1 of the albedo brought to the truth's mean over the person by one gain per
    sample: it does not change when the albedo's level does (a level the photo cannot tell)."""

    family = "delight"
    input_keys = ("image", "normal")

    def __init__(self, config: TrainConfig):
        super().__init__(config)
        self._projection = None

    def sample_keys(self):
        return ("input", "normal", self.config.normal_key, "albedo", "light_a", "mask", "shading_a")

    def example(self, sample, rng):
        if self.config.normal_key not in sample:
            raise ConfigError(f"config normal_key={self.config.normal_key!r} but the dataset samples have no such "
                              "array; use \"normal\" or add it with python -m export.factory.coarse --normals-only")
        example = {"image": chw(sample["input"]), "normal": chw(sample[self.config.normal_key]),
                   "albedo": chw(sample["albedo"]), "light": chw(sample["light_a"]), "mask": chw(sample["mask"])}
        if self.w.get("irradiance"):
            shading, mask = sample["shading_a"], sample["mask"] > 0.5
            level = shading.mean(axis=-1)
            median = float(np.median(level[mask])) if mask.any() else 0.0
            bright = mask & (level > RATIO_DARK * median)
            # at the true normals: the true shading is theirs, whatever the net is fed
            example.update(irradiance_basis=chw(irradiance_basis(sample["normal"], 2) * bright[..., None]),
                           shading_a=chw(shading), bright=chw(bright.astype(np.float32)),
                           shading_floor=np.full((1, 1, 1), 0.01 * max(median, 1e-6), np.float32))
        return example

    def losses(self, out, batch):
        m = batch["mask"]
        terms = {"albedo_l1": self.w["l1"] * masked_l1(out["albedo"], batch["albedo"], m),
                 "albedo_perceptual": self.w["perceptual"] * perceptual(out["albedo"] * m, batch["albedo"] * m, m),
                 "light": self.w["light"] * light_loss(out["light"], batch["light"])}
        if self.w.get("irradiance"):
            irradiance = self.irradiance(out["light"], batch["irradiance_basis"])
            floor, bright = batch["shading_floor"], batch["bright"]
            d = (torch.log(irradiance.clamp_min(0) + floor) - torch.log(batch["shading_a"] + floor)).abs()
            terms["irradiance"] = self.w["irradiance"] * (d * bright).sum() / (3 * bright.sum()).clamp_min(1)
        if self.w.get("level") or self.w.get("shape"):
            area = 3 * m.sum(dim=(1, 2, 3)).clamp_min(1)
            ours, true = ((a * m).sum(dim=(1, 2, 3)) / area for a in (out["albedo"], batch["albedo"]))
        if self.w.get("level"):
            terms["level"] = self.w["level"] * (torch.log(ours.clamp_min(1e-3)) - torch.log(true.clamp_min(1e-3))).abs().mean()
        if self.w.get("shape"):
            gain = (true / ours.clamp_min(1e-3)).view(-1, 1, 1, 1)
            terms["shape"] = self.w["shape"] * masked_l1(out["albedo"] * gain, batch["albedo"], m)
        return terms

    def irradiance(self, light: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) SH-9 irradiance / pi of (N, 3, h, w) light maps at the normals whose
        (N, 9, H, W) `irradiance_basis` is given (linear in the light: one matrix)."""
        if self._projection is None or self._projection.shape[1] != light.shape[-2] * light.shape[-1]:
            self._projection = torch.from_numpy(sh_projection_matrix(*light.shape[-2:])).to(light.dtype)
        coefficients = torch.einsum("kt,nct->nkc", self._projection, light.flatten(2))
        return torch.einsum("nkhw,nkc->nchw", basis, coefficients)

    def metrics(self, out, example):
        mask = example["mask"][0]
        pred = protocol_encode(hwc(out["albedo"]))
        true = protocol_encode(hwc(example["albedo"]))
        with torch.no_grad():
            light = float(light_loss(torch.from_numpy(out["light"][None]), torch.from_numpy(example["light"][None])))
        # The runtime's default albedo: the photo over the SH-9 shading of the predicted light,
        # anchored to the net's albedo level and outline
        normal = hwc(example["normal"])
        shading = sh_irradiance_shading(project_sh(hwc(out["light"]), 2), normal)
        ratio = anchor_albedo(ratio_albedo(hwc(example["image"]), shading, hwc(out["albedo"]), mask),
                              hwc(out["albedo"]), mask)
        return {"albedo_mse": metrics.mse(pred, true, mask), "albedo_psnr": metrics.psnr(pred, true, mask),
                "albedo_ssim": metrics.ssim(pred, true, mask), "light_log_l2": light,
                "ratio_albedo_psnr": metrics.psnr(protocol_encode(ratio), true, mask)}


def sh_projection_matrix(height: int, width: int) -> np.ndarray:
    """(9, height * width) float32: project_sh(light, 2) = matrix @ light texels (row-major)."""
    texels = height * width
    one_hot = np.eye(texels, dtype=np.float64).reshape(height, width, texels)
    return project_sh(one_hot, 2).astype(np.float32)


def coarse_body_shading(config: TrainConfig, sample: dict, rng: np.random.Generator) -> np.ndarray:
    """The coarse shading the body net refines: the stand-in, or a dataset key once the
    pipeline renders the reconstructed mesh (config `coarse_shading`)."""
    if config.coarse_shading == "standin":
        return data.standin_coarse_shading(sample[config.shading_key], sample["ao"], sample["mask"],
                                           rng, config.standin)
    if config.coarse_shading not in sample:
        raise ConfigError(f"config coarse_shading={config.coarse_shading!r} but the dataset samples have no "
                          "such array; use \"standin\" or add it with python -m export.factory.coarse")
    return sample[config.coarse_shading]


class GANTask(Task):
    """Shared by the refinement nets: the discriminator sees [condition, log(1 + shading)]."""

    def discriminator_pair(self, out, batch):
        condition = self.condition(batch)
        real = torch.cat([condition, encode_log_shading(batch["shading"])], dim=1)
        fake = torch.cat([condition, encode_log_shading(out["shading"])], dim=1)
        return real, fake

    def condition(self, batch: dict) -> torch.Tensor:
        raise NotImplementedError


class BodyRefineTask(GANTask):
    """[coarse shading, AO] -> shading, all shadings divided by the coarse shading's
    `shading_scale` as at run time. Loss (paper): 10 sum_k L1 over the 5 output scales +
    PatchGAN adversarial + 0.001 sum_k L1 of the FFTs."""

    family = "body_refine"
    input_keys = ("coarse_shading", "ao")

    def build_discriminator(self):
        return MultiscalePatchGAN(3 + 1 + 3, PATCHGAN_CONFIGS[self.config.size])

    def example(self, sample, rng):
        coarse = coarse_body_shading(self.config, sample, rng)
        scale = np.float32(shading_scale(coarse, sample["mask"]))
        if self.config.ao_key not in sample:
            raise ConfigError(f"config ao_key={self.config.ao_key!r} but the dataset samples have no such "
                              "array; use \"ao\" or add it with python -m export.factory.coarse")
        return {"coarse_shading": chw(coarse / scale), "ao": chw(sample[self.config.ao_key]),
                "shading": chw(sample[self.config.shading_key] / scale), "mask": chw(sample["mask"])}

    def losses(self, out, batch):
        names = ["shading"] + [f"shading_s{k}" for k in range(1, 5)]
        targets, masks = pyramid(batch["shading"], 5), pyramid(batch["mask"], 5)
        l1 = sum(masked_l1(out[n], t, m) for n, t, m in zip(names, targets, masks))
        fft = sum(fft_l1(out[n] * m, t * m) for n, t, m in zip(names, targets, masks))
        return {"shading_l1": self.w["l1"] * l1, "shading_fft": self.w["fft"] * fft}

    def condition(self, batch):
        return torch.cat([encode_log_shading(batch["coarse_shading"]), batch["ao"]], dim=1)

    def metrics(self, out, example):
        mask = example["mask"][0]
        true = hwc(example["shading"])
        scale = shading_scale(true, mask)  # the evaluation protocol's per-scene constant
        refined, coarse = hwc(out["shading"]), hwc(example["coarse_shading"])
        t = protocol_encode(true, scale)
        r, c = protocol_encode(refined, scale), protocol_encode(coarse, scale)
        psnr_r, psnr_c = metrics.psnr(r, t, mask), metrics.psnr(c, t, mask)
        return {"shading_psnr_refined": psnr_r, "shading_psnr_coarse": psnr_c,
                "shading_psnr_gain": psnr_r - psnr_c, "shading_mse_refined": metrics.mse(r, t, mask),
                "shading_ssim_refined": metrics.ssim(r, t, mask)}


class FaceRefineTask(GANTask):
    """[face crop of the refined body shading, coarse face shading] -> face shading crop,
    crops resampled to `face_crop_size`, shadings divided by the body's scale. Loss (paper):
    5 L1 over the person + LSGAN adversarial."""

    family = "face_refine"
    input_keys = ("body_shading", "face_shading")

    def build_discriminator(self):
        widths = LSGAN_CONFIGS[self.config.size].widths
        size = self.config.face_crop_size
        if size % 2 ** len(widths):
            raise ValueError(f"face_crop_size {size} must be a multiple of {2 ** len(widths)}")
        return LSGANDiscriminator(3 + 3, LSGANConfig(widths=widths, input_size=size))

    def example(self, sample, rng):
        if self.config.coarse_shading != "standin":
            return self._closeup_example(sample)
        if not data.has_face(sample):
            return None
        shading = sample[self.config.shading_key]
        body, face = data.standin_face_shadings(shading, sample["mask"], rng, self.config.standin)
        cx, cy, side = data.face_square(sample["face_box"], self.config.face_margin)
        size = self.config.face_crop_size

        def crop(image):
            return chw(data.crop_resample(image, cx, cy, side, size))

        # The run time divides by the face crop's own scale (of the body shading, close to the truth)
        scale = np.float32(shading_scale(data.crop_resample(shading, cx, cy, side, size),
                                         data.crop_resample(sample["mask"], cx, cy, side, size)))

        return {"body_shading": crop(body / scale), "face_shading": crop(face / scale),
                "shading": crop(shading / scale), "mask": crop(sample["mask"])}

    def _closeup_example(self, sample):
        """A close-up of export/factory/face_closeups.py: already the 128 face crop, with the
        runtime's coarse face shading (config `coarse_shading`, e.g. "coarse_face_b") and the
        body shading at the person crop's resolution. The loss and metrics cover the fitted
        face's pixels, where the runtime blends the net's answer in."""
        key = self.config.coarse_shading
        if key not in sample or "body_shading_b" not in sample:
            raise ConfigError(f"config coarse_shading={key!r} needs face close-ups with {key!r} and "
                              "'body_shading_b': python -m export.factory.face_closeups")
        shading, mask = sample[self.config.shading_key], sample["mask"] * sample["face_pixels"]
        if shading.shape[0] != self.config.face_crop_size or not mask.any():
            return None
        # The runtime's normaliser: the scale of the body shading it gets (stages.face.stage_face_refine)
        scale = np.float32(shading_scale(sample["body_shading_b"], sample["mask"]))
        return {"body_shading": chw(sample["body_shading_b"] / scale), "face_shading": chw(sample[key] / scale),
                "shading": chw(shading / scale), "mask": chw(mask)}

    def losses(self, out, batch):
        return {"shading_l1": self.w["l1"] * masked_l1(out["shading"], batch["shading"], batch["mask"])}

    def condition(self, batch):
        return encode_log_shading(batch["face_shading"])

    def metrics(self, out, example):
        mask = example["mask"][0]
        true = hwc(example["shading"])
        scale = shading_scale(true, mask)
        t = protocol_encode(true, scale)
        r = protocol_encode(hwc(out["shading"]), scale)
        c = protocol_encode(hwc(example["face_shading"]), scale)
        b = protocol_encode(hwc(example["body_shading"]), scale)
        psnr_r, psnr_c, psnr_b = (metrics.psnr(x, t, mask) for x in (r, c, b))
        # the gain that matters at run time is over the body shading the face would keep
        return {"face_psnr_refined": psnr_r, "face_psnr_coarse": psnr_c, "face_psnr_gain": psnr_r - psnr_c,
                "face_psnr_body": psnr_b, "face_psnr_gain_over_body": psnr_r - psnr_b}


TASKS = {t.family: t for t in (GeometryTask, GeometryPriorTask, AOTask, AOPriorTask, DelightTask,
                                BodyRefineTask, FaceRefineTask)}


def make_task(config: TrainConfig) -> Task:
    return TASKS[config.net](config)
