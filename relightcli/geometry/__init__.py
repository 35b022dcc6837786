"""Geometry: maps from the geometry net -> a watertight body mesh; smoothing; the face model.

Body (see each module's docstring):
- normal_integration.integrate_normals / double_sided_depth: normal maps -> depth maps
  (bilateral normal integration; a depth prior sets offsets and jumps).
- mesh.reconstruct_mesh: mask + front/back depth + crop rectangle -> closed trimesh in the
  crop's camera frame, pixel-aligned (DESIGN.md camera); mesh.save_mesh writes .ply/.glb/.obj
  atomically.
- smoothing.smooth_mesh: cotangent-weighted Laplacian smoothing, 10 steps by default (the
  paper's; the pipeline's reconstruction takes 20 on its grid of every second pixel).

Submodules are imported where used, so importing the face model does not pull in trimesh.
"""
