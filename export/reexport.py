"""Export a shipped net again from its own ONNX file: the weights read from the graph's
initializers into today's torch module (the family and config from the contract stored in the
file), exported with today's code, and checked against the file it replaces. For a change to a
module's forward that computes the same function faster (issue 50: body_refine's AFF without its
120-channel concat), without the training checkpoint.

    python -m export.reexport models/body_refine.onnx [--side 512] [--tolerance 1e-5]

The new graph's outputs must match the old one's within `tolerance` x the output's largest
magnitude on person-like inputs at `side` (ONNX Runtime, both files); then the file is replaced
and its `models/manifest.json` entry gets the new sha256 and a `reexported` record (the old
sha256, the largest difference, both run times), its training record and metrics kept. The
weights are read by name where the initializers carry the parameters' names; where the exporter
folded each BatchNorm into the convolution before it (unnamed initializers, as in the shipped
de-lighting net), by the order the forward runs its convolutions (`load_folded`). A graph whose
convolutions do not line up with the module's is refused (the fused AFF's split: a re-exported
body refinement is exported next from its checkpoint).
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
    for name in net.state_dict():  # a BatchNorm's step count is not part of its function
        if name.endswith(".num_batches_tracked") and name not in state:
            state[name] = torch.tensor(0)
    missing = [name for name in net.state_dict() if name not in state]
    if missing:  # folded into unnamed constants: matched by the convolutions' order
        state = load_folded(net, model, state, path)
    net.load_state_dict({name: state[name] for name in net.state_dict()}, strict=True)
    return net.eval()


def load_folded(net: torch.nn.Module, model, state: dict, path: Path) -> dict:
    """`state` completed for a graph whose exporter folded each BatchNorm into the convolution
    before it: the graph's Conv nodes, in order, are the module's Conv2d layers in the order its
    forward runs them, less those whose results reach no output (the exporter drops them: the
    last HRNet module's fusions into branches no head reads), each weight's shape checked; a
    folded convolution's BatchNorm becomes an affine layer that is the identity plus the folded
    bias (running mean 0, variance 1 - eps, weight 1), the same function in eval mode.
    Fine-tuning such a net keeps its BatchNorms in eval mode (their statistics are gone)."""
    modules = dict(net.named_modules())
    convs = {name: m for name, m in modules.items() if isinstance(m, torch.nn.Conv2d)}
    order: list[str] = []
    hooks = [m.register_forward_hook(lambda *_, name=name: order.append(name)) for name, m in convs.items()]
    feeds = person_like_inputs(net.io_contract(), 64, 64)
    outputs = net.eval()(*(torch.from_numpy(feeds[spec.name]) for spec in net.io_contract().inputs))
    for hook in hooks:
        hook.remove()
    weights = [convs[name].weight for name in convs]
    grads = torch.autograd.grad(sum(out.sum() for out in outputs), weights, allow_unused=True)
    live = {name for name, grad in zip(convs, grads) if grad is not None}
    order = [name for name in order if name in live]
    nodes = [node for node in model.graph.node if node.op_type == "Conv"]
    if len(order) != len(nodes):
        raise SystemExit(f"{path}: {len(nodes)} convolutions in the graph, {len(order)} in the module's forward: "
                         "its weights cannot be read back; export it from its checkpoint")
    norm_after = {}  # conv name -> the BatchNorm2d right after it in the same Sequential
    for name, module in modules.items():
        if isinstance(module, torch.nn.Sequential):
            children = list(module.named_children())
            for (a, first), (b, second) in zip(children, children[1:]):
                if isinstance(first, torch.nn.Conv2d) and isinstance(second, torch.nn.BatchNorm2d):
                    norm_after[f"{name}.{a}" if name else a] = f"{name}.{b}" if name else b
    state = dict(state)
    for name, node in zip(order, nodes):
        weight = state[node.input[1]]
        bias = state[node.input[2]] if len(node.input) > 2 and node.input[2] else torch.zeros(weight.shape[0])
        if tuple(weight.shape) != tuple(convs[name].weight.shape):
            raise SystemExit(f"{path}: the graph's convolution {node.name} {tuple(weight.shape)} does not line up "
                             f"with {name} {tuple(convs[name].weight.shape)}; export it from its checkpoint")
        state[f"{name}.weight"] = weight
        norm = norm_after.get(name)
        if norm is None:
            if convs[name].bias is not None:
                state[f"{name}.bias"] = bias
            continue
        eps = modules[norm].eps
        state.update({f"{norm}.weight": torch.ones_like(bias), f"{norm}.bias": bias,
                      f"{norm}.running_mean": torch.zeros_like(bias),
                      f"{norm}.running_var": torch.full_like(bias, 1.0 - eps),
                      f"{norm}.num_batches_tracked": torch.tensor(0)})
    # The dropped convolutions (and their BatchNorms) keep the module's own values: no output
    # depends on them
    dead = {name for name in convs if name not in live}
    dead |= {norm_after[name] for name in dead if name in norm_after}
    own = net.state_dict()
    for name in own:
        if name not in state and name.rsplit(".", 1)[0] in dead:
            state[name] = own[name]
    missing = [name for name in own if name not in state]
    if missing:
        raise SystemExit(f"{path}: no initializer for {missing[0]!r} (and {len(missing) - 1} more); "
                         "export it from its checkpoint")
    return state


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
