"""Display exposure follows the scene, not the result (issue 22, item 5): --exposure changes the
LDR relit by its factor, a black map gives a black person and a warning, and a 1e30 texel stays
finite in the shading EXR."""

from __future__ import annotations

import numpy as np
import pytest

from relightcli import compose
from relightcli.errors import RelightWarning
from relightcli.io.envmap import expose
from relightcli.io.images import read_image
from relightcli.pipeline import RelightOptions, write_layer
from relightcli.stages.compose import relit_image, scene_exposure, stage_compose
from relightcli.stages.frame import Frame

SIDE = 32


def sky(height=16):
    """(H, 2H, 3) sky brighter above, with a bright texel."""
    env = np.full((height, 2 * height, 3), 0.3, np.float32)
    env[: height // 2] = 1.0
    env[3, height] = 50.0
    return env


def lit_frame(env, ev=0.0):
    """A square person whose relit crop scales with the map's radiance, as shading does."""
    env = expose(env, ev) if ev else env
    mask = np.zeros((SIDE, SIDE), np.float32)
    mask[8:24, 8:24] = 1.0
    frame = Frame(image=np.full((SIDE, SIDE, 3), 0.2, np.float32), mask=mask, env=env,
                  box=compose.CropBox(0, 0, SIDE, SIDE))
    frame.crop_mask = mask
    frame.albedo = np.full((SIDE, SIDE, 3), 0.4, np.float32) * mask[..., None]
    frame.shading = np.full((SIDE, SIDE, 3), 0.01, np.float32) * np.float32(2.0 ** ev) * mask[..., None]
    return frame


def test_scene_exposure_reads_the_map_before_exposure():
    env = sky()
    assert scene_exposure(expose(env, 3.0), 3.0) == pytest.approx(scene_exposure(env), rel=1e-6)
    assert scene_exposure(np.zeros((4, 8, 3), np.float32)) == 1.0


@pytest.mark.parametrize("ev", [3.0, -3.0])
@pytest.mark.parametrize("background", ["keep", "#808080"])
def test_exposure_changes_the_ldr_relit_by_its_factor(ev, background):
    options = RelightOptions(background=background)
    frame = lit_frame(sky())
    stage_compose(frame, options, None)
    plain, _, _ = relit_image(frame, options, hdr=False)
    exposed_options = RelightOptions(background=background, exposure_ev=ev)
    exposed_frame = lit_frame(sky(), ev)
    stage_compose(exposed_frame, exposed_options, None)
    exposed, _, _ = relit_image(exposed_frame, exposed_options, hdr=False)
    person = frame.mask == 1.0
    np.testing.assert_allclose(exposed[person], plain[person] * 2.0 ** ev, rtol=1e-5)
    np.testing.assert_array_equal(exposed[~person], plain[~person])  # the background stays


def test_black_map_gives_a_black_person_and_a_warning():
    frame = lit_frame(np.zeros((16, 32, 3), np.float32))  # shading as a refinement residual
    with pytest.warns(RelightWarning, match="all black"):
        stage_compose(frame, RelightOptions(), None)
    rgb, _, _ = relit_image(frame, RelightOptions(background="#808080"), hdr=False)
    assert not rgb[frame.mask == 1.0].any()


def test_huge_texel_stays_finite_in_the_shading_exr(tmp_path):
    frame = lit_frame(sky())
    frame.shading = frame.shading * np.float32(1e30)
    path = tmp_path / "shading.exr"
    write_layer("shading", path, frame, RelightOptions())
    written = read_image(path).rgb
    assert np.isfinite(written).all()
    assert written.max() == pytest.approx(1e28, rel=1e-3)
