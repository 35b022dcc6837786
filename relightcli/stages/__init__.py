"""The stages of one relighting run, in the paper's order, each a function of (frame, options,
models) in a module named after it; relightcli.pipeline plans which of them a run needs.

    people, mask   everyone in the photo and the person mask       (stages.people)
    crop           the square working crop around the person       (stages.crop)
    body           a MakeHuman body fitted under each person        (stages.body)
    geometry       normals and depth, AO, the reconstructed mesh    (stages.geometry)
    delight        the input light and the albedo                   (stages.delight)
    face           the face found and the ICT model fitted to it    (stages.face)
    raytrace       shading under the target environment             (stages.shading)
    refine         the body and face refinement nets                (stages.refine, stages.face)
    compose        relit = albedo x shading, and the output layers  (stages.compose)

`Frame` (stages.frame) carries what earlier stages produced. Networks see the crop as the photo
shows it (background included, as in training); their outputs are masked afterwards.
"""

from __future__ import annotations

from relightcli.stages.body import stage_body, stage_body_maps
from relightcli.stages.compose import stage_compose
from relightcli.stages.crop import stage_crop
from relightcli.stages.delight import stage_delight
from relightcli.stages.face import stage_face, stage_face_refine
from relightcli.stages.frame import Frame, Models
from relightcli.stages.geometry import stage_ao, stage_geometry, stage_reconstruct
from relightcli.stages.people import stage_mask, stage_people
from relightcli.stages.refine import stage_refine
from relightcli.stages.shading import stage_raytrace, stage_sh_shading

STAGES = {
    "people": stage_people,
    "mask": stage_mask,
    "crop": stage_crop,
    "geometry": stage_geometry,
    "ao": stage_ao,
    "delight": stage_delight,
    "reconstruct": stage_reconstruct,
    "body": stage_body,
    "body_maps": stage_body_maps,
    "face": stage_face,
    "raytrace": stage_raytrace,
    "sh_shading": stage_sh_shading,
    "refine": stage_refine,
    "face_refine": stage_face_refine,
    "compose": stage_compose,
}

# Stages whose result depends on the lighting: a turntable runs only these once per frame.
LIGHTING_STAGES = ("raytrace", "sh_shading", "refine", "face_refine", "compose")

__all__ = ["STAGES", "LIGHTING_STAGES", "Frame", "Models"]
