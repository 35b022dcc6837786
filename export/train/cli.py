"""Command line of the trainer (see export/train/README.md):

    python -m export.train NET --config export/train/configs/NET_small.json --data DIR --out RUN
    python -m export.train all --size small --data DIR --out RUNS [--export-to models/]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from export.train.config import (ALL_NETS, EXTRA_NETS, ConfigError, default_config_path, load_config,
                                 merge_overrides)
from export.train.trainer import Trainer, TrainingError
from relightcli.errors import RelightError


def open_dataset(root):
    """The relighting dataset at `root` (export.factory.dataset); imported late so `--help`
    works without it."""
    try:
        from export.factory.dataset import open_dataset as factory_open
    except ImportError as exc:
        raise TrainingError(f"cannot import export.factory ({exc}); the data factory is needed "
                            "to read --data") from exc
    return factory_open(root)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m export.train", description=__doc__.splitlines()[0])
    parser.add_argument("net", choices=list(ALL_NETS + EXTRA_NETS) + ["all"], help="the net to train, or all of them in turn")
    parser.add_argument("--config", help="JSON config (one net only; default configs/NET_SIZE.json)")
    parser.add_argument("--size", default="small", help="config size for the default configs: small or paper")
    parser.add_argument("--data", required=True, help="dataset root (export.factory output)")
    parser.add_argument("--out", required=True, help="run directory (for all: one subdirectory per net)")
    parser.add_argument("--steps", type=int, help="override the config's total steps")
    parser.add_argument("--max-minutes", type=float, help="stop each net after this many minutes of this call")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                        help="override a config key, e.g. --set lr=1e-4 --set loss.l1=2 (repeatable)")
    parser.add_argument("--threads", type=int, help="torch intra-op threads")
    parser.add_argument("--no-resume", action="store_true", help="start over even if the run has a checkpoint")
    parser.add_argument("--export-to", help="after training, export ONNX + manifest entries into this models dir")
    return parser


def train_one(net: str, config_path: Path, args, dataset, out: Path) -> dict:
    """Train (or resume) one net; export it when asked. Returns Trainer.run's summary."""
    overrides = merge_overrides(args.set)
    for key, value in (("steps", args.steps), ("max_minutes", args.max_minutes), ("threads", args.threads)):
        if value is not None:
            overrides[key] = value
    config = load_config(config_path, overrides)
    if config.net != net:
        raise ConfigError(f"{config_path} configures {config.net!r}, not {net!r}")
    trainer = Trainer(config, dataset, out, resume=not args.no_resume)
    run = trainer.run()
    if args.export_to:
        from export.train.export_models import export_trained

        export_trained(trainer, args.export_to, dataset.card, run)
    return run


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        dataset = open_dataset(args.data)
        if args.net == "all":
            if args.config:
                raise ConfigError("--config is for one net; `all` reads configs/NET_SIZE.json (use --size)")
            for net in ALL_NETS:
                run = train_one(net, default_config_path(net, args.size), args, dataset, Path(args.out) / net)
                print(f"{net}: step {run['step']} ({run['stopped_by']}), val {run['metrics']}")
        else:
            path = Path(args.config) if args.config else default_config_path(args.net, args.size)
            run = train_one(args.net, path, args, dataset, Path(args.out))
            print(f"{args.net}: step {run['step']} ({run['stopped_by']}), val {run['metrics']}")
    except (ConfigError, TrainingError, RelightError, FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0
