"""Torch definitions of the relighting nets, one module per family, each with a "paper" and a
"small" config. `build_net(family, size)` is the single factory the exporter and trainers use."""

from __future__ import annotations

from torch import nn

from .body_refine import BODY_REFINE_CONFIGS, BodyRefineNet
from .delight import DELIGHT_CONFIGS, DelightNet
from .face_refine import FACE_REFINE_CONFIGS, FaceRefineNet
from .geometry import AO_CONFIGS, GEOMETRY_CONFIGS, AONet, AOPriorNet, GeometryNet, GeometryPriorNet

FAMILIES = {
    "geometry": (GeometryNet, GEOMETRY_CONFIGS),
    "geometry_prior": (GeometryPriorNet, GEOMETRY_CONFIGS),
    "ao": (AONet, AO_CONFIGS),
    "ao_prior": (AOPriorNet, AO_CONFIGS),
    "delight": (DelightNet, DELIGHT_CONFIGS),
    "body_refine": (BodyRefineNet, BODY_REFINE_CONFIGS),
    "face_refine": (FaceRefineNet, FACE_REFINE_CONFIGS),
}


def build_net(family: str, size: str = "paper") -> nn.Module:
    """A freshly initialised net of `family` ("geometry", "ao", "delight", "body_refine",
    "face_refine") at config `size` ("paper", "small", or an ablation name: "vanilla", ... for
    "delight")."""
    if family not in FAMILIES:
        raise ValueError(f"unknown net family {family!r}; known: {sorted(FAMILIES)}")
    cls, configs = FAMILIES[family]
    if size not in configs:
        raise ValueError(f"unknown size {size!r} for {family}; known: {sorted(configs)}")
    return cls(configs[size])
