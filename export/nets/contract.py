"""The I/O contract each exportable net declares: tensor names, shapes (with symbolic N, H, W),
dtype, the multiple H and W must be divisible by, colour space and normalisation.

The exporter stores it in the ONNX metadata and in `models/manifest.json`; the runtime
(`relightcli.nets.session`) checks the loaded graph against it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output: `shape` uses "N" for batch, "H"/"W" for dynamic spatial dims."""

    name: str
    shape: tuple
    dtype: str = "float32"
    description: str = ""


@dataclass(frozen=True)
class IOContract:
    family: str
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    multiple: int
    colour_space: str
    normalisation: str
    config: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        for key in ("inputs", "outputs"):
            d[key] = [{**t, "shape": list(t["shape"])} for t in d[key]]
        return d


def image_spec(name: str, channels: int, description: str = "", h="H", w="W") -> TensorSpec:
    """An NCHW float32 image tensor."""
    return TensorSpec(name, ("N", channels, h, w), "float32", description)
