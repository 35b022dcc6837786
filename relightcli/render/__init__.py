"""Ray-traced environment lighting: sampling trios, the Embree scene, the orthographic camera
and the Monte Carlo integrator (see DESIGN.md for the conventions they share).

The names below are re-exported lazily, so importing one submodule (e.g. render.camera) does
not import the integrator with it.
"""

_EXPORTS = {
    "EnvironmentLight": "relightcli.render.environment",
    "Hits": "relightcli.render.scene",
    "LightingPlan": "relightcli.render.integrator",
    "PixelGeometry": "relightcli.render.camera",
    "Scene": "relightcli.render.scene",
    "ShadingResult": "relightcli.render.integrator",
    "ambient_occlusion": "relightcli.render.integrator",
    "default_rect": "relightcli.render.camera",
    "pixel_centres": "relightcli.render.camera",
    "plan_lighting": "relightcli.render.integrator",
    "render_pixel_geometry": "relightcli.render.camera",
    "shade_environment": "relightcli.render.integrator",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'relightcli.render' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(_EXPORTS[name]), name)
