"""The bench scripts' common harness: the product's pipeline on one eval scene folder, with one
of its functions replaced while it runs (to keep what that function sees, or to try a variant).

    with replaced(delight, "solve_input_light", keeping):
        frame = run_scene(folder, options, models)
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from relightcli.batch import ItemReport  # noqa: E402
from relightcli.evaluate import load_scene  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.io.images import read_image  # noqa: E402
from relightcli.pipeline import run_stages  # noqa: E402
from relightcli.stages import STAGES  # noqa: E402


@contextmanager
def replaced(owner, name: str, replacement):
    """`owner.name` is `replacement` inside the block, and what it was after it, whatever happens."""
    original = getattr(owner, name)
    setattr(owner, name, replacement)
    try:
        yield
    finally:
        setattr(owner, name, original)


@contextmanager
def replaced_stage(name: str, wrap=None):
    """The pipeline's stage `name` is `wrap(stage)` inside the block (itself where `wrap` is None),
    and the stage it was after it, whatever happens."""
    original = STAGES[name]
    STAGES[name] = original if wrap is None else wrap(original)
    try:
        yield
    finally:
        STAGES[name] = original


def run_scene(folder: Path, options, models, use_gt_mask: bool = True, scene=None):
    """The frame the pipeline leaves for a scene folder: its photo, its true mask (or the
    product's own where use_gt_mask is false), its target light. `scene`: the folder's
    `load_scene`, when the caller has it already (for its truth)."""
    scene = load_scene(folder) if scene is None else scene
    frame, _ = run_stages(read_image(scene.input_path).rgb, scene.mask if use_gt_mask else None,
                          load_envmap(scene.target_path), options, ItemReport(str(folder)), models)
    return frame
