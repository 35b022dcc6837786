"""The README figure, made by the tool itself from the shipped example: input, albedo, and the
shading and relit image under the two example environments.

    python examples/make_figure.py            # -> docs/figure.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from relightcli import compose  # noqa: E402
from relightcli.batch import ItemReport  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.io.images import read_image, write_image  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

EXAMPLES = REPO / "examples"
ENVIRONMENTS = ("noon_grass.hdr", "kloofendal_overcast.hdr")


def main() -> None:
    image = read_image(EXAMPLES / "skier.jpg").rgb
    options = RelightOptions(outputs=("relit",), threads=2)
    models = Models(options.threads)
    tiles = []
    for name in ENVIRONMENTS:
        env = load_envmap(EXAMPLES / name)
        frame, _ = run_stages(image, None, env, options, ItemReport(name), models)  # the mask it finds
        if not tiles:
            tiles += [("input", compose.to_display(frame.crop)), ("albedo", compose.to_display(frame.albedo))]
        crop_relit = compose.crop_square(frame.relit, frame.box)
        shading_scale = compose.display_exposure(frame.shading, frame.crop_mask, 0.8)
        relit_scale = compose.display_exposure(crop_relit, frame.crop_mask, 0.8)
        env_scale = 0.8 / max(float(np.percentile(env @ compose.LUMINANCE, 99.0)), 1e-12)
        short = name.split("_")[0]
        tiles += [(f"shading: {short}", compose.to_display(frame.shading, shading_scale)),
                  (f"relit: {short}", compose.to_display(crop_relit, relit_scale)),
                  (short, compose.to_display(env, env_scale))]
    out = REPO / "docs" / "figure.png"
    out.parent.mkdir(exist_ok=True)
    write_image(out, compose.preview_sheet(tiles, height=256), srgb=False)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
