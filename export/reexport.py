"""Export a shipped net again from its own ONNX file: the weights read from the graph's
initializers into today's torch module (the family and config from the contract stored in the
file), exported with today's code, and checked against the file it replaces. For a change to a
module's forward that computes the same function faster (issue 50: body_refine's AFF without its
120-channel concat), without the training checkpoint.

    python -m export.reexport models/body_refine.onnx [--side 512] [--tolerance 1e-5]

The new graph's outputs must match the old one's within `tolerance` x the output's largest
magnitude on person-like inputs at `side` (ONNX Runtime, both files); then the file is replaced
and its `models/manifest.json` entry gets the new sha256 and a `reexported` record (the old
sha256, the largest difference, both run times), its training record and metrics kept. Only
a file whose initializers carry the parameters' names can be read back (the legacy exporter
keeps them unless it folds the weights into new constants, as the fused AFF's split does: a
re-exported body refinement is exported next from its checkpoint).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from export.manifest import update_manifest
from export.nets import FAMILIES
from export.onnx_export import METADATA_KEY, export_onnx, person_like_inputs
from relightcli.nets.manifest import MANIFEST_NAME, sha256_file


def net_from_onnx(path: Path) -> torch.nn.Module:
    """The torch module of the file's family and config, with the file's weights: every
    parameter and buffer of the module read from the initializer of its name."""
    model = onnx.load(path)
    contract = json.loads({p.key: p.value for p in model.metadata_props}[METADATA_KEY])
    cls, configs = FAMILIES[contract["family"]]
    config_type = type(next(iter(configs.values())))
    net = cls(config_type(**contract["config"]))
    state = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in model.graph.initializer}
    missing = [name for name in net.state_dict() if name not in state]
    if missing:  # folded into unnamed constants: a graph exported from an already fused forward
        raise SystemExit(f"{path}: no initializer named {missing[0]!r} (and {len(missing) - 1} more): "
                         "this file's weights cannot be read back by name; export it from its checkpoint")
    net.load_state_dict({name: state[name] for name in net.state_dict()}, strict=True)
    return net.eval()


def run_seconds(path: Path, feeds: dict, runs: int = 3, threads: int = 1, warm_up: bool = False) -> tuple[list, float]:
    """(outputs, the median seconds of `runs` runs on `threads` threads, after one untimed run
    if `warm_up`)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    if warm_up:
        session.run(None, feeds)
    seconds = []
    for _ in range(runs):
        start = time.perf_counter()
        outputs = session.run(None, feeds)
        seconds.append(time.perf_counter() - start)
    return outputs, float(np.median(seconds))


def reexport(path: Path, side: int, tolerance: float) -> dict:
    net = net_from_onnx(path)
    new = path.with_suffix(".new.onnx")
    entry = export_onnx(net, new)
    feeds = person_like_inputs(net.io_contract(), side, side)
    (old_out, old_s), (new_out, new_s) = run_seconds(path, feeds), run_seconds(new, feeds)
    worst = max(float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-12)) for a, b in zip(old_out, new_out))
    if worst > tolerance:
        new.unlink()
        raise SystemExit(f"{path}: the new graph differs by {worst:.2e} of the output's scale "
                         f"(tolerance {tolerance:.0e}); nothing replaced")
    manifest = json.loads((path.parent / MANIFEST_NAME).read_text())["models"]
    name = next(n for n, e in manifest.items() if e["file"] == path.name)
    record = {"from_sha256": manifest[name]["sha256"], "max_relative_difference": worst, "side": side,
              "seconds_one_thread": {"before": round(old_s, 4), "after": round(new_s, 4)},
              "command": f"python -m export.reexport {path.parent.name}/{path.name} --side {side}"}
    new.replace(path)
    update_manifest(path.parent, name, {**manifest[name], "sha256": sha256_file(path),
                                        "inputs": entry["inputs"], "outputs": entry["outputs"],
                                        "reexported": record})
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--side", type=int, default=512)
    parser.add_argument("--tolerance", type=float, default=1e-5)
    args = parser.parse_args()
    print(json.dumps(reexport(args.model, args.side, args.tolerance), indent=2))


if __name__ == "__main__":
    main()
