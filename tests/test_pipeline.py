"""The plan (what runs, what is skipped and why) and the stages end to end with stand-in
networks whose outputs are known, so results can be checked analytically."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from relightcli.batch import ItemReport
from relightcli.nets.delight import DelightResult
from relightcli.errors import RelightError
from relightcli.nets.blaze import Detection
from relightcli.nets.geometry import GeometryMaps
from relightcli.nets.pose import Pose
from relightcli.pipeline import RelightOptions, plan_stages, run_stages
from relightcli.stages.compose import layer_image
from relightcli.stages.frame import Models


def plan(outputs, method="raytrace", has_alpha=True, albedo="ratio"):
    return plan_stages(RelightOptions(outputs=tuple(outputs), method=method, albedo=albedo), has_alpha=has_alpha)


def test_mask_only_runs_no_network_when_alpha_given():
    p = plan(["mask"], has_alpha=True)
    assert p.run == ["mask"]
    assert "people" in p.skipped and "geometry" in p.skipped


def test_people_are_found_without_alpha():
    p = plan(["mask"], has_alpha=False)
    assert p.run == ["people", "mask"] and "people" not in p.skipped


def test_full_paper_method_runs_every_stage_but_sh(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: model == "face_refine")
    p = plan(["relit"])
    assert p.run == ["people", "mask", "crop", "body", "body_maps", "geometry", "ao", "reconstruct", "delight", "face",
                     "raytrace", "refine", "face_refine", "compose"]
    assert plan(["relit"], albedo="solve").run == p.run  # the same stages: the solve needs none more
    assert "sh_shading" in p.skipped


def test_the_face_plans_the_people_although_the_input_brings_a_mask(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: model == "face_refine")
    assert "people" in plan(["relit"], has_alpha=True).run
    monkeypatch.setattr(pipeline, "_ships", lambda model: False)
    p = plan(["relit"], method="sh9", has_alpha=True)
    assert "people" not in p.run and "face" in p.skipped["people"]


@pytest.mark.parametrize("method", ["raytrace", "raytrace-norefine"])
def test_ray_tracing_plans_the_body_fit_and_its_people_although_the_input_brings_a_mask(method):
    p = plan(["relit"], method=method, has_alpha=True)
    assert p.run.index("people") < p.run.index("body") < p.run.index("raytrace")


def test_no_face_refinement_model_plans_no_face_fit(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: False)
    p = plan(["relit"])
    assert "face" not in p.run and "face_refine" not in p.run and "refine" in p.run
    assert "face_refine" in p.skipped["face"] and "face_refine" in p.skipped["face_refine"]


@pytest.mark.parametrize("method", ["sh9", "sh25"])
def test_sh_methods_skip_ray_tracing_and_refinement(method):
    p = plan(["relit"], method=method)
    assert "raytrace" not in p.run and "reconstruct" not in p.run and "refine" not in p.run
    assert "spherical harmonics" in p.skipped["raytrace"]


def test_norefine_skips_refinement_and_face(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: model == "face_refine")
    p = plan(["relit"], method="raytrace-norefine")
    assert "refine" not in p.run and "face" not in p.run and "ao" not in p.run
    assert p.skipped["refine"] == "--method raytrace-norefine"


def test_normals_alone_need_only_the_geometry_net(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: False)
    assert plan(["normal"]).run == ["mask", "crop", "geometry"]


def test_the_prior_net_plans_the_body_fit_before_the_geometry(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: model == "geometry_prior")
    p = plan(["normal"], has_alpha=True)
    assert p.run == ["people", "mask", "crop", "body", "body_maps", "geometry"]
    p = plan(["relit"], method="sh9")
    assert p.run.index("body_maps") < p.run.index("geometry") < p.run.index("delight")


def test_the_light_solve_plans_the_mesh_and_the_bodies_before_the_delighting():
    p = plan(["albedo"], method="sh9", has_alpha=True, albedo="solve")
    assert p.run.index("reconstruct") < p.run.index("delight") and p.run.index("body") < p.run.index("delight")
    assert "reconstruct" not in plan(["albedo"]).run  # the default, ratio, needs no mesh
    assert "raytrace" not in p.run  # the target's shading is not needed for the albedo


def test_mesh_needs_reconstruction_but_no_lighting():
    p = plan(["mesh"])
    assert "reconstruct" in p.run and "raytrace" not in p.run and "delight" not in p.run


class StandInModels(Models):
    """Networks with known outputs: normals facing the camera, a disc mask, constant AO and
    albedo. Records which families were asked for; the environment cache is the real one."""

    def __init__(self, albedo=0.5, input_light=0.0):
        super().__init__(threads=1)
        self.albedo, self.input_light, self.used = albedo, input_light, []

    def get(self, family):
        self.used.append(family)
        return self

    people_disc = None  # (cx, cy, radius) in photo pixels of the stand-in person, or None

    def detect(self, image, rect=None):  # the person detector, and the face detector (rect)
        if self.people_disc is None:
            return []
        cx, cy, radius = self.people_disc
        return [Detection(np.array([cx - 5, cy - radius, cx + 5, cy - radius + 10]),
                          np.array([[cx, cy], [cx, cy - radius]], np.float64), 0.9)]

    def landmarks(self, image, rect):
        """A person whose segmentation is the disc, blurred as an enlarged net map is; no
        person (presence 0) without a disc."""
        if self.people_disc is None:
            return Pose(rect, 0.0, np.zeros((33, 5)), np.zeros((33, 3)), np.zeros(image.shape[:2], np.float32), rect)
        cx, cy, radius = self.people_disc
        y, x = np.mgrid[:image.shape[0], :image.shape[1]] + 0.5
        mask = cv2.GaussianBlur(((x - cx) ** 2 + (y - cy) ** 2 < radius ** 2).astype(np.float32), (0, 0), 2.0)
        return Pose(rect, 1.0, np.zeros((33, 5)), np.zeros((33, 3)), mask, rect)

    def mirrored_segmentation(self, image, rect):
        """The net's segmentation of the crop's mirror image: the same disc."""
        return StandInModels.landmarks(self, image, rect).mask

    def predict(self, image, normal=None):
        size = image.shape[0]
        if normal is not None:  # delight
            return DelightResult(np.full(image.shape, self.albedo, np.float32),
                                 np.full((16, 32, 3), self.input_light, np.float32))
        y, x = np.mgrid[:size, :size]
        disc = (((x - size / 2) ** 2 + (y - size / 2) ** 2) < (0.3 * size) ** 2).astype(np.float32)
        normals = np.zeros(image.shape, np.float32)
        normals[..., 2] = 1.0
        depth = np.zeros(image.shape[:2], np.float32)
        return GeometryMaps(normals, -normals, depth, depth - 0.1, disc)


def photo_with_person(height=90, width=70):
    image = np.full((height, width, 3), 0.3, np.float32)
    mask = np.zeros((height, width), np.float32)
    mask[20:80, 25:50] = 1.0
    return image, mask


@pytest.mark.parametrize("method", ["sh9", "sh25"])
def test_sh_relit_under_constant_light_is_albedo_times_light(method):
    # White furnace through the whole pipeline: crop, SH shading at +Z normals, compose, paste.
    image, mask = photo_with_person()
    env = np.full((16, 32, 3), [2.0, 1.0, 0.5], np.float32)
    # (the SH-9 ratio albedo is exact here; the solve's traced input shading has Monte Carlo noise)
    options = RelightOptions(outputs=("relit",), method=method, resolution=32, albedo="ratio")
    models = StandInModels(albedo=0.5)
    frame, _ = run_stages(image, mask, env, options, ItemReport("x"), models)
    inside = mask > 0.5
    inner = np.zeros_like(inside)
    inner[24:76, 29:46] = True  # away from the crop-resampling edge of the mask
    np.testing.assert_allclose(frame.relit[inner], np.broadcast_to([1.0, 0.5, 0.25], (inner.sum(), 3)), rtol=2e-3)
    assert frame.relit[~inside].max() <= 1.0 and np.isfinite(frame.relit).all()
    assert models.used.count("geometry") == 1 and "ao" not in models.used  # no AO net for SH


def test_a_soft_mask_is_applied_once_and_does_not_darken_the_layers():
    # A mask of 0.8 over the person (a segmentation that is unsure) relights the person as a
    # mask of 1 does: the layers are straight, the relit composite takes 0.8 of it once
    image, mask = photo_with_person()
    env = np.full((16, 32, 3), [2.0, 1.0, 0.5], np.float32)
    options = RelightOptions(outputs=("relit", "albedo"), method="sh9", resolution=32, albedo="ratio")
    hard, _ = run_stages(image, mask, env, options, ItemReport("x"), StandInModels(albedo=0.5))
    soft, _ = run_stages(image, 0.8 * mask, env, options, ItemReport("x"), StandInModels(albedo=0.5))
    inner = np.zeros(mask.shape, bool)
    inner[24:76, 29:46] = True
    np.testing.assert_allclose(soft.relit[inner], hard.relit[inner], rtol=1e-4)
    np.testing.assert_allclose(soft.relit[inner], np.broadcast_to([1.0, 0.5, 0.25], (inner.sum(), 3)), rtol=2e-3)
    rgb, _ = layer_image("relit", soft, RelightOptions(outputs=("relit",), background="#000000"), hdr=True)[:2]
    np.testing.assert_allclose(rgb[inner], 0.8 * soft.relit[inner], rtol=1e-4)
    albedo = layer_image("albedo", soft, options)[0]
    np.testing.assert_allclose(albedo[inner], 0.8 * 0.5, rtol=2e-3)  # over black, as the file


@pytest.mark.parametrize("source", ["solve", "ratio", "net"])
def test_albedo_is_the_photo_over_the_estimated_shading_or_the_nets(source, stand_in_normals):
    # Under the stand-in's constant input light 0.6 every normal's SH-9 irradiance is 0.6: the
    # photo's two halves (0.3 and 0.15) divide into 0.5 and 0.25, which the ratio albedo keeps
    # as detail (2:1) at the net's level (a flat 0.25 lies between them); the light solved on
    # the stand-in's flat mesh lights both halves alike, so the solve keeps the same 2:1;
    # --albedo net keeps the net's flat 0.25.
    image, mask = photo_with_person()
    image[:, 38:] = 0.15
    # (the solve's input shading is ray-traced: enough samples that its noise stays below 1%)
    options = RelightOptions(outputs=("albedo",), method="sh9", resolution=32, albedo=source, spp=1024)
    frame, _ = run_stages(image, mask, np.ones((8, 16, 3), np.float32), options, ItemReport("x"),
                          StandInModels(albedo=0.25, input_light=0.6))
    # inside, 2 px from the outline (the solve's traced shading bends at the stand-in slab's rim)
    inside = cv2.erode((frame.crop_mask > 0.999).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    values = frame.albedo[inside].mean(axis=-1)
    if source == "net":
        np.testing.assert_allclose(values, 0.25, rtol=2e-3)
        return
    if source == "solve":
        assert frame.notes["delight"]["light"] == "inverse rendering" and frame.notes["delight"]["pixels"] > 0
        assert np.isfinite(frame.light).all() and frame.light.min() >= 0 and frame.light.max() > 0
    # the two halves' levels: the medians above and below the median
    middle = np.median(values)
    bright, dark = np.median(values[values > middle]), np.median(values[values <= middle])
    np.testing.assert_allclose(bright / dark, 2.0, rtol=1e-2)
    assert dark < 0.25 < bright


def test_the_input_lights_shading_is_traced_on_a_coarser_grid_unless_every_pixel_is_asked_for():
    # The solved input light is a 16x32 map: soft shadows, so `--shadows half` traces its
    # shading (which the albedo divides by) on a grid of ~128 pixels across the crop (every
    # fourth pixel at 512, every second at 256, as the target's); `full` every pixel
    image, mask = photo_with_person()
    runs = {}
    for resolution, shadows in ((512, "half"), (512, "full"), (256, "half")):
        options = RelightOptions(outputs=("albedo",), method="sh9", resolution=resolution, spp=4, shadows=shadows)
        frame, _ = run_stages(image, mask, np.ones((8, 16, 3), np.float32), options, ItemReport("x"),
                              StandInModels(albedo=0.25, input_light=0.6))
        runs[resolution, shadows] = frame.notes["delight"]["input_shading"]
        assert np.isfinite(frame.albedo).all()
    assert [run["shadow_step"] for run in runs.values()] == [4, 1, 2]
    assert 0 < runs[512, "half"]["rays"] < 0.15 * runs[512, "full"]["rays"]


def test_people_and_mask_stages_run_only_without_alpha(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: False)  # no prior net: no body fit
    image, mask = photo_with_person()
    env = np.ones((8, 16, 3), np.float32)
    options = RelightOptions(outputs=("normal",), method="sh9", resolution=32)
    with_alpha = StandInModels()
    run_stages(image, mask, env, options, ItemReport("x"), with_alpha)
    without_alpha = StandInModels()
    without_alpha.people_disc = (35.0, 50.0, 20.0)
    frame, _ = run_stages(image, None, env, options, ItemReport("x"), without_alpha)
    assert with_alpha.used == ["geometry"]
    assert without_alpha.used == ["person_detector", "pose_landmarks", "geometry"]
    assert frame.notes["mask"]["source"] == "pose segmentation of 1 person"
    assert len(frame.notes["people"]["found"]) == 1 and frame.notes["people"]["turned_down"] == []
    assert frame.mask.shape == image.shape[:2] and 0 < frame.mask.mean() < 1


def test_over_an_image_the_relit_output_sharpens_a_predicted_mask_and_keeps_an_input_mask(monkeypatch):
    # The predicted mask is a segmentation probability: over the kept photo or the environment
    # view the relit person is composited with it stretched from PREDICTED_MATTE to 0..1; over a
    # colour (the paper's protocol scores the relit person over black) and as the transparent
    # output's alpha it stays the mask, as does a mask the user gives, and the layer files
    from relightcli import pipeline
    from relightcli.compose import PREDICTED_MATTE, paste_back, sharpened
    from relightcli.stages.compose import background_view

    monkeypatch.setattr(pipeline, "_ships", lambda model: False)
    image, mask = photo_with_person()
    env = np.ones((8, 16, 3), np.float32)
    options = RelightOptions(outputs=("relit", "albedo"), method="sh9", resolution=32, albedo="ratio")
    models = StandInModels()
    models.people_disc = (35.0, 50.0, 20.0)
    predicted, _ = run_stages(image, None, env, options, ItemReport("x"), models)
    given, _ = run_stages(image, predicted.mask.copy(), env, options, ItemReport("x"), StandInModels())
    assert predicted.mask_predicted and not given.mask_predicted
    soft = (predicted.mask > 0.05) & (predicted.mask < 0.95)
    assert soft.sum() > 20  # the stand-in's segmentation is blurred: a soft edge to sharpen
    grey = np.float32(0.21586)  # #808080, linear
    for frame in (predicted, given):
        alpha = (sharpened(frame.mask, PREDICTED_MATTE) if frame.mask_predicted else frame.mask)[..., None]
        keep = layer_image("relit", frame, RelightOptions(background="keep"), hdr=True)[0]
        np.testing.assert_allclose(keep, alpha * frame.relit + (1.0 - alpha) * image, rtol=1e-5, atol=1e-6)
        assert ("matte" in frame.notes["relit"]) == frame.mask_predicted  # the report says so
        view = background_view(frame, RelightOptions(background="env"))
        over_env = layer_image("relit", frame, RelightOptions(background="env"), hdr=True)[0]
        np.testing.assert_allclose(over_env, alpha * frame.relit + (1.0 - alpha) * view, rtol=1e-5, atol=1e-6)
        plain = frame.mask[..., None]
        over_grey = layer_image("relit", frame, RelightOptions(background="#808080"), hdr=True)[0]
        np.testing.assert_allclose(over_grey, plain * frame.relit + (1.0 - plain) * grey, rtol=1e-4, atol=1e-5)
        transparent = layer_image("relit", frame, RelightOptions(background="transparent"), hdr=True)[1]
        np.testing.assert_allclose(transparent, frame.mask, atol=1e-6)
        albedo = layer_image("albedo", frame, options)[0]  # the layer file: the mask as alpha
        np.testing.assert_allclose(albedo, plain * paste_back(frame.albedo, frame.box, *image.shape[:2]),
                                   rtol=1e-5, atol=1e-6)


class Undetected(StandInModels):
    """A person the detector misses, whom the landmark net sees (at `presence`) in any crop;
    `rects` records the crops it was shown."""

    people_disc = (37.0, 50.0, 20.0)

    def __init__(self, presence=1.0):
        super().__init__()
        self.presence, self.rects = presence, []

    def detect(self, image, rect=None):
        return []

    def landmarks(self, image, rect):
        self.rects.append(rect)
        return replace(super().landmarks(image, rect), presence=self.presence)


@pytest.mark.parametrize("presence", [1.0, 0.7])
def test_the_mask_places_the_landmarks_when_the_detector_finds_nobody(presence):
    """The input's mask says a person is there: MediaPipe's presence 0.5 will do (its stand-in
    detection scores 0, which from the detector would need nets.pose.WEAK_DETECTION_PRESENCE)."""
    from relightcli.stages.frame import Frame
    from relightcli.stages.people import stage_people

    models = Undetected(presence)
    rects = models.rects
    image, mask = photo_with_person()  # the mask's box: columns [25, 50), rows [20, 80)
    frame = Frame(image=image, mask=mask, env=None)
    stage_people(frame, None, models)
    assert len(frame.people) == 1 and "from_mask" in frame.notes["people"]
    assert frame.notes["people"]["found"][0]["detection_score"] == 0.0
    # the landmark crop is centred on the box, upright, its side 1.25 x the box's larger extent
    first = rects[0]
    assert first.centre == pytest.approx((37.5, 50.0)) and first.rotation == pytest.approx(0.0, abs=1e-9)
    assert first.width == pytest.approx(75.0) and first.height == pytest.approx(75.0)


@pytest.mark.parametrize("presence, found", [(0.999, True), (0.99, False)])
def test_without_a_mask_the_landmarks_look_at_the_whole_photo_when_the_detector_finds_nobody(presence, found):
    from relightcli.nets.pose import WHOLE_PHOTO_PRESENCE
    from relightcli.stages.frame import Frame
    from relightcli.stages.people import stage_people

    models = Undetected(presence)
    rects = models.rects
    image, _ = photo_with_person()  # 90 rows, 70 columns
    frame = Frame(image=image, mask=None, env=None)
    stage_people(frame, None, models)
    # the first landmark crop is the whole photo: centred, upright, 1.25 x its larger side
    assert rects[0].centre == pytest.approx((35.0, 45.0)) and rects[0].width == pytest.approx(112.5)
    assert (presence >= WHOLE_PHOTO_PRESENCE) == found
    if found:
        assert len(frame.people) == 1 and frame.notes["people"]["whole_photo"].startswith("no person detected:")
    else:  # the net is not sure enough, and the portrait fallback finds no face either: nobody
        assert frame.people == [] and "0.990" in frame.notes["people"]["whole_photo"]
        assert "no body and no face" in frame.notes["people"]["portrait"]


def test_the_peoples_mask_is_snapped_to_the_photos_edges():
    # A red person on a green background; the stand-in segmentation is the disc blurred and
    # 2 px too small: the guided filter pulls its edge to the photo's
    height, width = 180, 140
    y, x = np.mgrid[:height, :width] + 0.5
    person = (x - 70) ** 2 + (y - 90) ** 2 < 56**2
    image = np.where(person[..., None], [0.6, 0.05, 0.05], [0.05, 0.4, 0.1]).astype(np.float32)
    models = StandInModels()
    models.people_disc = (70.0, 90.0, 54.0)
    options = RelightOptions(outputs=("mask",), method="sh9", resolution=512)
    frame, _ = run_stages(image, None, np.ones((8, 16, 3), np.float32), options, ItemReport("x"), models)
    assert frame.notes["mask"]["edges"] == "guided filter"
    raw = models.landmarks(image, None).mask
    error = lambda a: np.abs(a - person)[np.abs(cv2.Laplacian(person.astype(np.float32), cv2.CV_32F)) > 0].mean()  # noqa: E731
    assert error(frame.mask) < error(raw)


def test_a_photo_without_a_person_fails_saying_how_to_fix_it():
    image = np.full((60, 50, 3), 0.3, np.float32)
    options = RelightOptions(outputs=("relit",), method="sh9", resolution=32)
    with pytest.raises(RelightError, match="no person found.*--mask"):
        run_stages(image, None, np.ones((8, 16, 3), np.float32), options, ItemReport("x"), StandInModels())


class SphereModels(StandInModels):
    """Stand-in geometry of a ball filling the crop: exact front/back depth and normals."""

    def predict(self, image, normal=None):
        if normal is not None:
            return super().predict(image, normal)
        size = image.shape[0]
        centres = -1.0 + (np.arange(size) + 0.5) * 2.0 / size
        x, y = np.meshgrid(centres, -centres)
        r2 = x**2 + y**2
        inside = r2 < 0.6**2
        z = np.sqrt(np.clip(0.6**2 - r2, 0, None)).astype(np.float32)
        normals = np.stack([x, y, z], axis=-1) / 0.6 * inside[..., None]
        return GeometryMaps(normals.astype(np.float32), normals * [1, 1, -1], z * inside, -z * inside, inside.astype(np.float32))


def test_raytraced_ball_under_constant_light_is_white_furnace(stand_in_normals):
    # Reconstruct the stand-in ball, smooth it, ray-trace it under a constant environment:
    # an unoccluded convex surface has shading == L exactly (MIS is exact for a constant map).
    image = np.full((64, 64, 3), 0.3, np.float32)
    mask = np.zeros((64, 64), np.float32)
    mask[8:56, 8:56] = 1.0
    env = np.full((8, 16, 3), 1.5, np.float32)
    options = RelightOptions(outputs=("shading", "mesh"), method="raytrace-norefine", resolution=48, spp=8)
    frame, plan = run_stages(image, mask, env, options, ItemReport("x"), SphereModels())
    assert plan.run == ["people", "mask", "crop", "body", "body_maps", "geometry", "reconstruct", "raytrace"]
    assert frame.bodies == [] and "no converged body fit" in frame.notes["raytrace"]["body"]
    assert frame.mesh.to_trimesh().is_watertight
    # The square mask makes a slab around the ball: the ball's top cap sees the whole
    # hemisphere (shading == L exactly), its rim is shadowed by the slab (below L, never above).
    centres = -1.0 + (np.arange(48) + 0.5) * 2.0 / 48
    x, y = np.meshgrid(centres, -centres)
    cap = x**2 + y**2 < 0.15**2  # tilt < 15 deg: the hemisphere meets z = 0 beyond the slab
    np.testing.assert_allclose(frame.coarse_shading[cap], 1.5, rtol=1e-4)
    inside = frame.crop_mask > 0.5
    assert np.isfinite(frame.coarse_shading).all()
    assert frame.coarse_shading[inside].max() <= 1.5 * (1 + 1e-4)
    assert frame.coarse_shading[inside].min() > 0.0
    assert frame.notes["raytrace"]["rays"] > 0
    # The cosine term uses the normal net's normals (the ball's), the mesh only for visibility
    length = np.linalg.norm(frame.geometry.front_normal, axis=-1, keepdims=True)
    net = frame.geometry.front_normal / np.maximum(length, 1e-6)
    used = frame.hits.mask & inside & (np.sum(net * frame.hits.geometric_normal, axis=-1) > 0)
    ball = inside & (length[..., 0] > 0)
    assert used[ball].mean() > 0.9
    np.testing.assert_allclose(frame.hits.normal[used], net[used], atol=1e-5)


class PlateBodyModels(SphereModels):
    """The ball, and as the "body model" a flat plate facing the camera in front of it."""

    def body_model(self):
        from types import SimpleNamespace

        return SimpleNamespace(triangles=PLATE_FACES)


# A 4x4-vertex plate over [-3, 3]^2 at z = 2 (all vertex normals +Z): in front of the ball
_GRID = np.linspace(-3.0, 3.0, 4)
PLATE_VERTICES = np.array([(x, y, 2.0) for y in _GRID for x in _GRID])
PLATE_FACES = np.array([[r * 4 + c, r * 4 + c + 1, (r + 1) * 4 + c + 1] for r in range(3) for c in range(3)]
                       + [[r * 4 + c, (r + 1) * 4 + c + 1, (r + 1) * 4 + c] for r in range(3) for c in range(3)],
                       np.int32)


def _ball_frame(models, resolution=48, shadows="half"):
    """The stand-in ball reconstructed and ray-traced under a constant environment 1.5."""
    image = np.full((64, 64, 3), 0.3, np.float32)
    mask = np.zeros((64, 64), np.float32)
    mask[8:56, 8:56] = 1.0
    options = RelightOptions(outputs=("shading",), method="raytrace-norefine", resolution=resolution, spp=8,
                             shadows=shadows)
    frame, _ = run_stages(image, mask, np.full((8, 16, 3), 1.5, np.float32), options, ItemReport("x"), models)
    return frame, options


def test_shadows_are_traced_on_every_second_pixel_unless_asked_for_every_pixel(stand_in_normals):
    half, _ = _ball_frame(SphereModels(), resolution=64)
    full, _ = _ball_frame(SphereModels(), resolution=64, shadows="full")
    assert (half.notes["raytrace"]["shadow_step"], full.notes["raytrace"]["shadow_step"]) == (2, 1)
    assert half.notes["raytrace"]["rays"] < 0.35 * full.notes["raytrace"]["rays"]
    inside = half.crop_mask > 0.5
    assert np.isfinite(half.coarse_shading).all()
    # The ball's top sees the whole sky either way (exact), the rim is shadowed by the slab:
    # 8 samples per pixel, so the two agree on average, not pixel by pixel
    assert half.coarse_shading[inside].max() <= 1.5 * (1 + 1e-4)
    assert half.coarse_shading[inside].mean() == pytest.approx(full.coarse_shading[inside].mean(), rel=0.02)
    centres = -1.0 + (np.arange(64) + 0.5) * 2.0 / 64
    x, y = np.meshgrid(centres, -centres)
    rim = inside & (np.hypot(x, y) > 0.45) & (np.hypot(x, y) < 0.58)
    assert half.coarse_shading[rim].mean() == pytest.approx(full.coarse_shading[rim].mean(), rel=0.03)
    assert full.coarse_shading[rim].mean() < 1.45


def test_a_converged_body_fit_is_ray_traced_and_averaged_with_the_reconstruction():
    from types import SimpleNamespace

    from relightcli.stages.body import stage_body_maps
    from relightcli.stages.shading import BODY_SHADING_WEIGHT, stage_raytrace

    models = PlateBodyModels()
    frame, options = _ball_frame(models)
    reconstruction = frame.coarse_shading.copy()
    # The plate sees the whole hemisphere: its shading is the environment's 1.5 at every pixel
    frame.bodies = [SimpleNamespace(vertices=PLATE_VERTICES, converged=True)]
    frame.scene = None  # closed by run_stages: ray-trace anew, now with the body
    try:
        stage_body_maps(frame, options, models)
        stage_raytrace(frame, options, models)
    finally:
        frame.scene.close(), frame.body_scene.close()
    inside = frame.crop_mask > 0.5
    expected = (1.0 - BODY_SHADING_WEIGHT) * reconstruction + BODY_SHADING_WEIGHT * 1.5
    np.testing.assert_allclose(frame.coarse_shading[inside], expected[inside], rtol=1e-4)
    assert frame.notes["raytrace"]["body"]["weight"] == BODY_SHADING_WEIGHT
    assert frame.notes["raytrace"]["body"]["rays"] > 0


def test_the_ao_layer_blends_in_the_fitted_bodies_traced_ao_and_the_refinement_keeps_the_nets():
    from types import SimpleNamespace

    from relightcli.stages.body import stage_body_maps
    from relightcli.stages.geometry import BODY_AO_WEIGHT, stage_ao

    models = PlateBodyModels()
    frame, options = _ball_frame(models)
    frame.bodies = [SimpleNamespace(vertices=PLATE_VERTICES, converged=True)]
    ao_net = SimpleNamespace(predict=lambda image: np.full(image.shape[:2], 0.6, np.float32))
    models.get = lambda family: ao_net if family == "ao" else PlateBodyModels.get(models, family)
    models.has = lambda name: name != "ao_prior"  # no AO prior net: the blend
    try:
        stage_body_maps(frame, options, models)
        options.outputs = ("shading",)  # the refinement's input only: nothing traced
        stage_ao(frame, options, models)
        net = frame.ao_net.copy()
        assert frame.ao is frame.ao_net and "ao" not in frame.notes
        options.outputs = ("ao",)
        stage_ao(frame, options, models)
    finally:
        frame.body_scene.close()
    # the plate alone in its scene sees the whole hemisphere: its AO is 1 wherever it covers
    np.testing.assert_array_equal(frame.ao_net, net)
    np.testing.assert_allclose(frame.ao, (1.0 - BODY_AO_WEIGHT) * net + BODY_AO_WEIGHT * 1.0, atol=1e-6)
    assert frame.notes["ao"]["body_weight"] == BODY_AO_WEIGHT


def test_the_ao_prior_net_reads_the_fitted_bodies_maps_and_traced_ao():
    from types import SimpleNamespace

    from relightcli.stages.body import stage_body_maps
    from relightcli.stages.geometry import stage_ao

    models = PlateBodyModels()
    frame, options = _ball_frame(models)
    frame.bodies = [SimpleNamespace(vertices=PLATE_VERTICES, converged=True)]
    seen = {}

    def prior_net(image, prior):  # stands in for the AO prior net: what it gets, as its map
        seen["image"], seen["prior"] = image, prior
        return prior[..., 9].copy()

    nets = {"ao": SimpleNamespace(predict=lambda image: np.full(image.shape[:2], 0.6, np.float32)),
            "ao_prior": SimpleNamespace(predict=prior_net, trained_resolution=24)}
    models.get = lambda family: nets.get(family) or PlateBodyModels.get(models, family)
    models.has = lambda name: True
    options.outputs = ("ao",)
    try:
        stage_body_maps(frame, options, models)
        stage_ao(frame, options, models)
    finally:
        frame.body_scene.close()
    # at the net's side, ten channels: the body maps' nine and the bodies' AO, 1 on the lone plate
    assert seen["image"].shape == (24, 24, 3) and seen["prior"].shape == (24, 24, 10)
    np.testing.assert_allclose(seen["prior"][..., 9], 1.0, atol=1e-6)
    import cv2

    coverage = cv2.resize(frame.body_maps.mask.astype(np.float32), (24, 24), interpolation=cv2.INTER_AREA)
    assert coverage.max() == 1.0
    np.testing.assert_allclose(seen["prior"][..., 8], coverage, atol=1e-6)  # the plate where the person is
    # the layer is the prior net's map at the working resolution; the refinement keeps the net's
    assert frame.ao.shape == (48, 48)
    np.testing.assert_allclose(frame.ao, 1.0, atol=1e-6)
    np.testing.assert_array_equal(frame.ao_net, np.float32(0.6))
    assert frame.notes["ao"] == {"net": "ao_prior"}


def test_the_ao_layer_plans_the_body_fit(monkeypatch):
    from relightcli import pipeline

    monkeypatch.setattr(pipeline, "_ships", lambda model: False)
    assert plan(["ao"], has_alpha=True).run == ["people", "mask", "crop", "body", "body_maps", "ao"]


def test_the_blend_of_two_renders_reaches_the_target_with_samples_in_proportion_to_weight():
    from relightcli.stages.shading import blend_targets

    for weight in (0.1, 0.3, 0.5, 0.9):
        own, body = blend_targets(0.04, weight, everywhere=True)
        # independent renders: the blend's variance is the weighted sum of theirs
        assert np.hypot((1 - weight) * own, weight * body) == pytest.approx(0.04)
        # the cheapest split: samples (1 / error^2) in proportion to the weights
        assert (1 / own ** 2) / (1 / body ** 2) == pytest.approx((1 - weight) / weight)
    # a person shaded by the reconstruction alone keeps the whole target there
    assert blend_targets(0.04, 0.3, everywhere=False)[0] == 0.04
    assert blend_targets(0.04, 0.0, everywhere=True) == (0.04, 0.04)


def test_the_blended_shading_reports_its_own_error():
    from types import SimpleNamespace

    from relightcli.stages.body import stage_body_maps
    from relightcli.stages.shading import stage_raytrace

    models = PlateBodyModels()
    frame, options = _ball_frame(models)
    options.spp, options.target_error = None, 0.05
    frame.bodies = [SimpleNamespace(vertices=PLATE_VERTICES, converged=True)]
    frame.scene = None
    try:
        stage_body_maps(frame, options, models)
        stage_raytrace(frame, options, models)
    finally:
        frame.scene.close(), frame.body_scene.close()
    note = frame.notes["raytrace"]
    # the plate sees the whole (constant) sky: exact; at every pixel the blend's relative
    # error is the ball's times (1 - w) m / ((1 - w) m + w 1.5) < 1, and so is the median's
    assert note["body"]["rel_error"] == 0.0
    assert note["rel_error"] <= note["reconstruction_rel_error"] <= 0.05


def test_a_person_whose_fit_did_not_converge_keeps_the_reconstruction_shading():
    from types import SimpleNamespace

    from relightcli import compose
    from relightcli.stages.body import body_shading_pixels
    from relightcli.stages.frame import Frame, PerceptionView

    frame = Frame(image=np.zeros((20, 20, 3), np.float32), mask=None, env=None,
                  crop_mask=np.ones((10, 10), np.float32), box=compose.CropBox(0, 0, 20, 10))
    frame.view = PerceptionView(np.zeros((10, 10, 3), np.float32), (0.5, 0.5))  # the photo at half size
    left, right = np.zeros((10, 10), np.float32), np.zeros((10, 10), np.float32)
    left[:, :5], right[:, 5:] = 1.0, 1.0
    frame.people = [SimpleNamespace(pose=SimpleNamespace(mask=left)), SimpleNamespace(pose=SimpleNamespace(mask=right))]
    frame.bodies = [SimpleNamespace(converged=False), SimpleNamespace(converged=True)]
    usable = body_shading_pixels(frame)
    assert not usable[:, :4].any() and usable[:, 6:].all()


def test_uncovered_mask_pixels_take_the_nearest_shading():
    from relightcli.compose import fill_uncovered

    shading = np.zeros((1, 5, 3), np.float32)
    shading[0, 0] = 1.0
    shading[0, 4] = 3.0
    covered = np.array([[True, False, False, False, True]])
    wanted = np.array([[True, True, False, True, True]])
    filled = fill_uncovered(shading, covered, wanted)
    np.testing.assert_array_equal(filled[0, :, 0], [1.0, 1.0, 0.0, 3.0, 3.0])


def test_the_soft_edge_of_the_person_is_shaded_too():
    """Pixels the soft crop mask keeps at 0.5 or less (its anti-aliased edge) are multiplied
    by the mask, not dropped: those the mesh misses take the nearest covered pixel's shading."""
    frame, _ = _ball_frame(SphereModels())
    soft = (frame.crop_mask > 0) & (frame.crop_mask <= 0.5)
    assert (soft & ~frame.hits.mask).any()
    assert (frame.coarse_shading[soft] > 0).all()
    assert (frame.shading[soft] > 0).all()


def test_turntable_builds_the_scene_once_and_relights_each_frame():
    from relightcli.io.envmap import rotate_envmap

    image = np.full((64, 64, 3), 0.3, np.float32)
    mask = np.zeros((64, 64), np.float32)
    mask[8:56, 8:56] = 1.0
    env = np.full((8, 16, 3), 0.2, np.float32)
    env[2, 4] = 500.0  # a sun: each turn lights the ball from another side
    lightings = [rotate_envmap(env, 90.0 * k) for k in range(4)]
    options = RelightOptions(outputs=("shading",), method="raytrace-norefine", resolution=32, spp=4)
    shadings = []
    frame, _ = run_stages(image, mask, env, options, ItemReport("x"), SphereModels(), lightings=lightings,
                          on_lighting=lambda k, f: shadings.append(f.shading.copy()))
    assert frame.notes["scene_builds"] == 1
    assert len(shadings) == 4
    assert not np.allclose(shadings[0], shadings[1])  # the light moved
    assert frame.scene is not None  # closed by run_stages, kept for inspection


def test_face_stage_is_planned_and_runs_once_a_face_refinement_ships(monkeypatch):
    from pathlib import Path

    from relightcli import pipeline
    from relightcli.io.envmap import load_envmap
    from relightcli.io.images import read_image

    monkeypatch.setattr(pipeline, "_ships", lambda model: model == "face_refine")
    assert "face" in plan(["relit"]).run
    examples = Path(__file__).resolve().parents[1] / "examples"
    image = read_image(examples / "skier.jpg").rgb
    mask = read_image(examples / "skier_mask.png", srgb=False).rgb[..., 0]
    options = RelightOptions(outputs=("relit",), resolution=128, threads=1)
    monkeypatch.setattr(pipeline, "output_needs", lambda output, method: ("face",))
    frame, _ = run_stages(image, mask, load_envmap(examples / "noon_grass.hdr"), options,
                          ItemReport("skier"), Models(1))
    info = frame.notes["face"]
    assert ("skipped" in info) != bool(frame.faces)  # a fit, or a reason


class LowResolutionModels(StandInModels):
    """Stand-in nets trained on 16-pixel crops; records the sides the nets were run at."""

    trained_resolution = 16

    def __init__(self):
        super().__init__(albedo=0.25, input_light=0.6)
        self.sides = []

    def predict(self, image, *more):
        self.sides.append(image.shape[0])
        if not more and image.ndim == 3 and self.used[-1] == "ao":
            return np.full(image.shape[:2], 0.8, np.float32)
        return super().predict(image, *more)


def test_nets_run_at_their_training_resolution_and_come_back_at_the_working_one():
    from relightcli.stages.crop import stage_crop
    from relightcli.stages.delight import stage_delight
    from relightcli.stages.frame import Frame
    from relightcli.stages.geometry import stage_ao, stage_geometry

    image, mask = photo_with_person()
    models = LowResolutionModels()
    frame = Frame(image=image, mask=mask, env=np.ones((8, 16, 3), np.float32))
    options = RelightOptions(resolution=32, albedo="ratio")
    for stage in (stage_crop, stage_geometry, stage_ao, stage_delight):
        stage(frame, options, models)
    assert models.sides == [16] * 5  # geometry and de-lighting twice (the crop and its mirror), ao once
    assert frame.geometry.front_normal.shape == (32, 32, 3) and frame.ao.shape == (32, 32)
    np.testing.assert_allclose(np.linalg.norm(frame.geometry.front_normal, axis=-1), 1.0, rtol=1e-5)
    assert frame.albedo.shape == (32, 32, 3)


def test_the_light_layer_takes_the_prior_where_no_pixel_sees_the_light(monkeypatch):
    from types import SimpleNamespace

    from relightcli.stages import delight
    from relightcli.stages.delight import LAYER_SEEN_SHARE, light_layer

    blur = delight.LAYER_BLUR_DEG
    monkeypatch.setattr(delight, "LAYER_BLUR_DEG", 0.0)  # the blend alone first

    rng = np.random.default_rng(3)
    solved = rng.uniform(0.5, 2.0, (16, 32, 3)).astype(np.float32)
    prior = np.full((16, 32, 3), 0.1, np.float32)
    seen = np.zeros(16 * 32, np.float32)
    seen[:256] = 1.0  # the upper half seen fully
    seen[256:264] = 0.5 * LAYER_SEEN_SHARE  # half-way to seen
    matrix = np.tile(seen / 3, (3, 1))  # three pixels share the transport (a negative entry: occlusion)
    matrix[0, 300] = -0.5
    got = light_layer(solved, prior, SimpleNamespace(matrix=matrix))
    np.testing.assert_array_equal(got[:8], solved[:8])
    # the prior at the solved light's level where seen (weighted as seen)
    level = (solved[:8].sum() + 0.5 * solved[8, :8].sum()) / (prior[:8].sum() + 0.5 * prior[8, :8].sum())
    np.testing.assert_allclose(got[9:], prior[9:] * level, rtol=1e-5)
    np.testing.assert_allclose(got[8, :8], 0.5 * solved[8, :8] + 0.5 * prior[8, :8] * level, rtol=1e-5)
    # Nothing seen (no pixel): the solved light as it is
    np.testing.assert_array_equal(light_layer(solved, prior, SimpleNamespace(matrix=np.zeros_like(matrix))), solved)
    # and the layer as shipped is that blend blurred on the sphere
    monkeypatch.setattr(delight, "LAYER_BLUR_DEG", blur)
    assert blur > 0
    np.testing.assert_allclose(light_layer(solved, prior, SimpleNamespace(matrix=matrix)),
                               delight.sphere_blur(got, blur), rtol=1e-6)


def test_the_sphere_blur_keeps_a_sky_and_spreads_a_sun_around_its_own_texel():
    from relightcli.io.envmap import texel_solid_angles
    from relightcli.stages.delight import sphere_blur

    sky = np.full((16, 32, 3), 0.7, np.float32)
    np.testing.assert_allclose(sphere_blur(sky, 8.0), sky, rtol=1e-6)  # a constant stays put
    sun = np.full((16, 32, 3), 1.0, np.float32)
    sun[4, 20] = 1e6  # a sun a million times the sky
    blurred = sphere_blur(sun, 8.0)
    assert np.isfinite(blurred).all() and blurred.min() > 0
    luminance = blurred[..., 1]
    assert np.unravel_index(np.argmax(luminance), luminance.shape) == (4, 20)
    assert luminance[4, 20] < 0.9e6 and luminance[4, 21] > 1e3  # spread to its neighbours
    omega = texel_solid_angles(16, 32)[..., None]
    energy = lambda light: float((light * omega).sum())  # noqa: E731
    assert abs(energy(blurred) / energy(sun) - 1.0) < 1e-3
    np.testing.assert_array_equal(sphere_blur(sun, 0.0), sun)  # 0: the light as it is
    huge = np.full((16, 32, 3), 1e38, np.float32)
    assert np.isfinite(sphere_blur(huge, 8.0)).all()


def test_the_solved_light_is_made_grey_and_keeps_its_own_shape_and_luminance():
    from relightcli.compose import LUMINANCE
    from relightcli.stages.delight import grey_light

    rng = np.random.default_rng(0)
    shape = rng.uniform(0.1, 2.0, (16, 32, 1)).astype(np.float32)
    solved = shape * np.array([0.4, 1.0, 0.3], np.float32)  # a green cast from a green outfit
    got = grey_light(solved)
    colour = got.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(colour, colour[1], rtol=1e-5)
    np.testing.assert_allclose(got[..., 0] / shape[..., 0], colour[0] / shape.mean(), rtol=1e-4)  # the solve's shape
    np.testing.assert_allclose(colour @ LUMINANCE, solved.reshape(-1, 3).mean(axis=0) @ LUMINANCE, rtol=1e-5)
    black = np.zeros_like(solved)
    np.testing.assert_array_equal(grey_light(black), black)
    no_blue = solved * np.array([1.0, 1.0, 0.0], np.float32)
    np.testing.assert_array_equal(grey_light(no_blue), no_blue)


def _relit_by_two_lines(monkeypatch, raising: str | None = None):
    """run_stages on two threads (the default method: the de-lighting beside the ray tracing),
    recording each stage's thread; `raising` names a stage that raises."""
    import threading

    from relightcli import stages

    seen = {}
    for name, function in list(stages.STAGES.items()):
        def recorded(frame, options, models, name=name, function=function):
            seen[name] = threading.current_thread().name
            if name == raising:
                raise RelightError(f"{name} failed")
            function(frame, options, models)
        monkeypatch.setitem(stages.STAGES, name, recorded)
    image, mask = photo_with_person()
    options = RelightOptions(outputs=("relit",), method="raytrace-norefine", resolution=32, spp=4, threads=2)
    frame, _ = run_stages(image, mask, np.ones((8, 16, 3), np.float32), options, ItemReport("x"),
                          StandInModels(albedo=0.25, input_light=0.6))
    return frame, seen


def test_on_two_threads_the_delighting_runs_beside_the_ray_tracing_with_the_same_result(monkeypatch, stand_in_normals):
    frame, seen = _relit_by_two_lines(monkeypatch)
    assert seen["delight"].startswith("relight-side") and seen["raytrace"] == seen["compose"] == "MainThread"
    image, mask = photo_with_person()
    options = RelightOptions(outputs=("relit",), method="raytrace-norefine", resolution=32, spp=4, threads=1)
    alone, _ = run_stages(image, mask, np.ones((8, 16, 3), np.float32), options, ItemReport("x"),
                          StandInModels(albedo=0.25, input_light=0.6))
    for layer in ("albedo", "shading", "relit"):
        np.testing.assert_array_equal(getattr(frame, layer), getattr(alone, layer))


@pytest.mark.parametrize("raising", ["delight", "raytrace"])
def test_an_error_on_either_line_fails_the_item_after_the_other_line_stopped(monkeypatch, stand_in_normals, raising):
    import threading

    with pytest.raises(RelightError, match=f"{raising} failed"):
        _relit_by_two_lines(monkeypatch, raising)
    assert not [t for t in threading.enumerate() if t.name.startswith("relight-side")]
