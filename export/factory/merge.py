"""One dataset made of several: the union of their samples, linked, not copied.

    python -m export.factory.merge OUT SOURCE [SOURCE ...]

Each source's sample `<split>/<id>.npz` appears in OUT as `<split>/<k>_<id>.npz`, a relative
symbolic link (k: the source's position on the command line), so two sources may use the same
ids. The card is the first source's, with the counts on disk summed, and a `merged` entry that
lists every source's card (its command, seed, counts and what was added to it). The sources
must have the same resolution and format; a source added later to OUT is linked on a new run
(existing links are kept, so a merge is resumable and can grow).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from relightcli.errors import UsageError

from . import dataset


def merge(out, sources) -> dict:
    """Link every sample of `sources` (dataset roots) into `out`; returns the written card."""
    out = Path(out)
    opened = [dataset.open_dataset(s) for s in sources]
    if not opened:
        raise UsageError("nothing to merge", fix="name at least one source dataset")
    resolutions = {d.card.get("resolution") for d in opened}
    if len(resolutions) != 1:
        raise UsageError(f"sources of different resolutions {sorted(map(str, resolutions))}",
                         fix="merge datasets rendered at one resolution")
    counts = dict.fromkeys(dataset.SPLITS, 0)
    for k, data in enumerate(opened):
        for split in dataset.SPLITS:
            ids = data.ids(split)
            counts[split] += len(ids)
            if not ids:
                continue
            folder = out / split
            folder.mkdir(parents=True, exist_ok=True)
            for sample_id in ids:
                link = folder / f"{k}_{sample_id}.npz"
                if not link.is_symlink():
                    target = dataset.sample_path(data.root, split, sample_id).resolve()
                    os.symlink(os.path.relpath(target, folder.resolve()), link)
    card = {key: value for key, value in opened[0].card.items() if key != "format_version"}
    card["counts_on_disk"] = counts
    card["merged"] = [{"source": str(Path(s)), "prefix": f"{k}_", **_card_digest(d.card)}
                      for k, (s, d) in enumerate(zip(sources, opened))]
    dataset.write_card(out, card)
    return card


def _card_digest(card: dict) -> dict:
    keys = ("command", "seed", "counts_on_disk", "added")
    return {key: card[key] for key in keys if key in card}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.factory.merge", description=__doc__.splitlines()[0])
    parser.add_argument("out", help="the merged dataset's root (created)")
    parser.add_argument("sources", nargs="+", help="dataset roots (export.factory.generate output)")
    args = parser.parse_args(argv)
    card = merge(args.out, args.sources)
    print(f"{args.out}: {card['counts_on_disk']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
