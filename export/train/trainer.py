"""The training loop: Adam on the task's loss (plus the discriminator's, for the refinement
nets), JSONL loss logs, validation on the val split, resumable checkpoints.

Run directory layout (`out`):
    config.json        the resolved config of the run
    checkpoint.pt      model + discriminator + optimisers + step + RNG states (resume point)
    log.jsonl          one line per `log_every` steps: step, seconds, every loss term
    val.jsonl          one line per validation: step, split, mean metrics
    metrics.json       the last validation (what the export puts in the manifest)

Resuming (`resume=True` with a checkpoint present) continues bit-exactly: the data order,
augmentations and stand-in noise all come from one numpy Generator whose state is saved.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from export.train.config import TrainConfig
from export.train.data import augment, sample_rng
from export.train.losses import lsgan_loss
from export.train.tasks import collate, make_task

CHECKPOINT_NAME = "checkpoint.pt"
MAX_DRAWS_PER_EXAMPLE = 50  # a batch gives up when this many samples in a row have no example


class TrainingError(RuntimeError):
    """The run cannot go on (no data, a checkpoint of another net, non-finite loss...)."""


def _atomic_torch_save(obj, path: Path) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(obj, tmp)
    tmp.replace(path)


def input_light(dataset, sample_id: str) -> str | None:
    """The name of a training sample's input light (its spec's lighting_a), None if unrecorded."""
    return dataset.meta("train", sample_id).get("spec", {}).get("lighting_a", {}).get("name")


class Trainer:
    """Trains `config.net` on `dataset` (the export.factory.dataset interface), writing to `out`."""

    def __init__(self, config: TrainConfig, dataset, out: str | Path, resume: bool = True):
        self.config = config
        self.dataset = dataset
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        if config.threads:
            torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        self.task = make_task(config)
        self.net = self.task.build_net()
        if config.init:
            self._start_from(Path(config.init))
        self.disc = self.task.build_discriminator()
        self.opt = torch.optim.Adam(self.net.parameters(), lr=config.lr, betas=config.betas)
        self.opt_disc = (torch.optim.Adam(self.disc.parameters(), lr=config.lr_disc, betas=config.betas)
                         if self.disc is not None else None)
        self.step = 0
        self.elapsed_s = 0.0
        ids = list(dataset.ids("train"))
        if config.exclude_lights:
            ids = [i for i in ids if input_light(dataset, i) not in config.exclude_lights]
        self.train_ids = ids[:config.train_samples]
        if not self.train_ids:
            raise TrainingError("the dataset has no training samples; generate data first (export.factory)")
        checkpoint = self.out / CHECKPOINT_NAME
        if resume and checkpoint.is_file():
            self.load_checkpoint(checkpoint)
        (self.out / "config.json").write_text(json.dumps(config.to_dict(), indent=2, sort_keys=True) + "\n")

    # --- data --------------------------------------------------------------------------------

    def next_batch(self) -> dict[str, torch.Tensor]:
        """`batch_size` augmented training examples drawn at random (with replacement)."""
        examples, misses = [], 0
        while len(examples) < self.config.batch_size:
            sample_id = self.train_ids[int(self.rng.integers(len(self.train_ids)))]
            loaded = self.dataset.load("train", sample_id, self.task.sample_keys())
            sample = augment(loaded, self.rng, self.config.flip,
                             None if self.task.family == "face_refine" else self.config.crop)
            example = self.task.example(sample, self.rng)
            if example is None:
                misses += 1
                if misses >= MAX_DRAWS_PER_EXAMPLE:
                    raise TrainingError(f"{misses} training samples in a row gave no {self.task.family} example "
                                        "(no visible face?); check the dataset's face boxes")
                continue
            misses = 0
            examples.append(example)
        return collate(examples)

    # --- one step ----------------------------------------------------------------------------

    def _start_from(self, path: Path) -> None:
        """The net's weights read from a shipped ONNX file of it (export.reexport.net_from_onnx;
        a resumed run's checkpoint then replaces them)."""
        from export.reexport import net_from_onnx

        shipped = net_from_onnx(path).state_dict()
        own = self.net.state_dict()
        if set(shipped) != set(own) or any(shipped[k].shape != own[k].shape for k in own):
            raise TrainingError(f"{path} is not a {self.config.net}/{self.config.size} net: its weights do not fit")
        self.net.load_state_dict(shipped, strict=True)

    def train_mode(self) -> None:
        """The net in training mode; a net started from an ONNX file (`init`) keeps its
        BatchNorms in eval mode: the file folded their statistics away (their scale and shift
        still learn)."""
        self.net.train()
        if self.config.init:
            for module in self.net.modules():
                if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                    module.eval()

    def train_step(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One Adam step of the net (and of the discriminator); returns every loss term."""
        self.train_mode()
        out = self.task.forward(self.net, batch)
        terms = self.task.losses(out, batch)
        reconstruction = sum(terms.values())
        total = reconstruction
        if self.disc is not None:
            self.disc.train()
            real, fake = self.task.discriminator_pair(out, batch)
            self.disc.requires_grad_(False)
            terms["adversarial"] = self.config.loss["adversarial"] * lsgan_loss(self.disc(fake), real=True)
            self.disc.requires_grad_(True)
            total = reconstruction + terms["adversarial"]
        if not torch.isfinite(total):
            raise TrainingError(f"non-finite loss at step {self.step}: {({k: float(v) for k, v in terms.items()})}; "
                                "lower the learning rate")
        self.opt.zero_grad(set_to_none=True)
        total.backward()
        if self.config.lr_schedule == "cosine":
            progress = min(self.step / max(self.config.steps, 1), 1.0)
            for group in self.opt.param_groups:
                group["lr"] = self.config.lr * 0.5 * (1.0 + math.cos(math.pi * progress))
        self.opt.step()
        log = {k: float(v.detach()) for k, v in terms.items()}
        log.update(loss=float(total.detach()), reconstruction=float(reconstruction.detach()))
        if self.disc is not None:
            # LSGAN discriminator: real -> 1, fake -> 0 (the fake detached from the generator)
            d_loss = 0.5 * (lsgan_loss(self.disc(real), real=True) + lsgan_loss(self.disc(fake.detach()), real=False))
            self.opt_disc.zero_grad(set_to_none=True)
            d_loss.backward()
            self.opt_disc.step()
            log["discriminator"] = float(d_loss.detach())
        return log

    # --- the loop ----------------------------------------------------------------------------

    def run(self, steps: int | None = None, max_minutes: float | None = None, validate: bool = True) -> dict:
        """Train until `steps` (total, counting resumed ones) or `max_minutes` of this call;
        then checkpoint and validate. Returns {"step", "elapsed_s", "stopped_by", "metrics"}."""
        steps = self.config.steps if steps is None else steps
        max_minutes = self.config.max_minutes if max_minutes is None else max_minutes
        deadline = math.inf if max_minutes is None else time.monotonic() + 60.0 * max_minutes
        stopped_by = "steps"
        while self.step < steps:
            if time.monotonic() >= deadline:
                stopped_by = "time"
                break
            start = time.monotonic()
            log = self.train_step(self.next_batch())
            self.step += 1
            self.elapsed_s += time.monotonic() - start
            if self.step % self.config.log_every == 0 or self.step == steps:
                self._append("log.jsonl", {"step": self.step, "elapsed_s": round(self.elapsed_s, 3), **log})
            if self.step % self.config.checkpoint_every == 0:
                self.save_checkpoint()
            if validate and self.step % self.config.val_every == 0 and self.step < steps:
                self.validate_and_log()
        self.save_checkpoint()
        metrics = self.validate_and_log() if validate else {}
        return {"step": self.step, "elapsed_s": self.elapsed_s, "stopped_by": stopped_by, "metrics": metrics}

    def _append(self, name: str, record: dict) -> None:
        with open(self.out / name, "a") as f:
            f.write(json.dumps(record, sort_keys=True) + "\n")

    # --- validation --------------------------------------------------------------------------

    def predict(self, example: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The net (eval mode) on one example: output name -> (C, H, W) float32."""
        self.net.eval()
        with torch.no_grad():
            out = self.task.forward(self.net, collate([example]))
        return {k: v[0].numpy() for k, v in out.items()}

    def validate(self, split: str = "val", max_samples: int | None = None) -> dict[str, float]:
        """Mean metrics over the first `max_samples` samples of `split` (no augmentation; the
        stand-in noise fixed per sample), plus "count"."""
        limit = self.config.val_max_samples if max_samples is None else max_samples
        totals: dict[str, list[float]] = {}
        for sample_id in list(self.dataset.ids(split))[:limit]:
            sample = self.dataset.load(split, sample_id, self.task.sample_keys())
            example = self.task.example(sample, sample_rng(self.config.seed, split, sample_id))
            if example is None:
                continue
            for key, value in self.task.metrics(self.predict(example), example).items():
                totals.setdefault(key, []).append(value)
        self.train_mode()
        if not totals:
            return {"count": 0}
        return {"count": len(next(iter(totals.values()))), **{k: float(np.mean(v)) for k, v in totals.items()}}

    def validate_and_log(self, split: str = "val") -> dict[str, float]:
        metrics = self.validate(split)
        self._append("val.jsonl", {"step": self.step, "split": split, **metrics})
        record = {"step": self.step, "split": split, "metrics": metrics}
        (self.out / "metrics.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
        return metrics

    # --- checkpoints -------------------------------------------------------------------------

    def state(self) -> dict:
        return {
            "config": self.config.to_dict(),
            "step": self.step,
            "elapsed_s": self.elapsed_s,
            "net": self.net.state_dict(),
            "opt": self.opt.state_dict(),
            "disc": self.disc.state_dict() if self.disc is not None else None,
            "opt_disc": self.opt_disc.state_dict() if self.opt_disc is not None else None,
            "numpy_rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
        }

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        path = Path(path) if path is not None else self.out / CHECKPOINT_NAME
        _atomic_torch_save(self.state(), path)
        return path

    def load_checkpoint(self, path: str | Path) -> None:
        state = torch.load(path, map_location="cpu", weights_only=False)
        saved = state["config"]
        if (saved["net"], saved["size"]) != (self.config.net, self.config.size):
            raise TrainingError(f"checkpoint {path} is for {saved['net']}/{saved['size']}, not "
                                f"{self.config.net}/{self.config.size}; use another --out or delete it")
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])
        if self.disc is not None:
            self.disc.load_state_dict(state["disc"])
            self.opt_disc.load_state_dict(state["opt_disc"])
        # The config's learning rates win over the saved ones, so a resumed run can change them.
        for opt, lr in ((self.opt, self.config.lr), (self.opt_disc, self.config.lr_disc)):
            for group in (opt.param_groups if opt is not None else []):
                group["lr"] = lr
        self.rng.bit_generator.state = state["numpy_rng"]
        torch.set_rng_state(state["torch_rng"])
        self.step = int(state["step"])
        self.elapsed_s = float(state["elapsed_s"])
