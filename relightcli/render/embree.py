"""Embree scenes that compiled kernels trace from any thread: the library embreex ships, called
through ctypes.

embreex holds the GIL while it traces (two threads run no faster than one), and its scene
handle is not reachable from Python, so a compiled kernel cannot call Embree on it. The same
libembree4 that the embreex wheel carries is loaded here: scenes are built with its C API,
and kernels (relightcli.render.kernels) call `rtcOccluded1` on the scene handle in a loop,
without the GIL. Measured on the 107k-triangle body, 2M occlusion rays from the visible
surface: embreex 5.4-5.9 Mrays/s, the kernel's loop 6.7-7.1 Mrays/s on one thread and 2.0x
that on two (identical answers).
"""

from __future__ import annotations

import ctypes
import glob
import os
import weakref

import numpy as np

# Embree 4 enums (rtcore_geometry.h, rtcore_common.h)
_GEOMETRY_TYPE_TRIANGLE = 0
_BUFFER_TYPE_INDEX, _BUFFER_TYPE_VERTEX = 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003

_LIBRARY = None
_DEVICES = {}  # one device per process: a forked child makes its own


def library_path() -> str | None:
    """The libembree4 shared library inside the installed embreex wheel, or None."""
    try:
        import embreex
    except ImportError:
        return None
    site = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    found = sorted(glob.glob(os.path.join(site, "embreex.libs", "libembree4*.so*")))
    return found[0] if found else None


def library() -> ctypes.CDLL:
    """The loaded library with the signatures this module uses (RuntimeError if none)."""
    global _LIBRARY
    if _LIBRARY is None:
        path = library_path()
        if path is None:
            raise RuntimeError("libembree4 not found next to the embreex package")
        lib = ctypes.CDLL(path)
        handle, size, uint = ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint
        signatures = {
            "rtcNewDevice": (handle, [ctypes.c_char_p]),
            "rtcGetDeviceError": (ctypes.c_int, [handle]),
            "rtcNewScene": (handle, [handle]),
            "rtcNewGeometry": (handle, [handle, ctypes.c_int]),
            "rtcSetNewGeometryBuffer": (handle, [handle, ctypes.c_int, uint, ctypes.c_int, size, size]),
            "rtcCommitGeometry": (None, [handle]),
            "rtcAttachGeometry": (uint, [handle, handle]),
            "rtcReleaseGeometry": (None, [handle]),
            "rtcCommitScene": (None, [handle]),
            "rtcReleaseScene": (None, [handle]),
        }
        for name, (restype, argtypes) in signatures.items():
            function = getattr(lib, name)
            function.restype, function.argtypes = restype, argtypes
        _LIBRARY = lib
    return _LIBRARY


def _device():
    pid = os.getpid()
    if pid not in _DEVICES:
        _DEVICES[pid] = library().rtcNewDevice(None)
    return _DEVICES[pid]


class NativeScene:
    """One committed Embree scene of a triangle mesh: `handle` (int) is the RTCScene that
    kernels trace. vertices (V, 3) float32 and faces (F, 3) int in the caller's frame
    (the Scene's local frame); both are copied into Embree's own buffers."""

    def __init__(self, vertices, faces):
        lib, device = library(), _device()
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces = np.ascontiguousarray(faces, dtype=np.uint32)
        scene = lib.rtcNewScene(device)
        geometry = lib.rtcNewGeometry(device, _GEOMETRY_TYPE_TRIANGLE)
        for kind, fmt, array in ((_BUFFER_TYPE_VERTEX, _FORMAT_FLOAT3, vertices),
                                 (_BUFFER_TYPE_INDEX, _FORMAT_UINT3, faces)):
            # Embree allocates (and pads for its vector loads); the mesh is copied in
            target = lib.rtcSetNewGeometryBuffer(geometry, kind, 0, fmt, 12, array.shape[0])
            if not target:
                raise RuntimeError(f"Embree could not allocate a buffer (error {lib.rtcGetDeviceError(device)})")
            ctypes.memmove(target, array.ctypes.data, array.nbytes)
        lib.rtcCommitGeometry(geometry)
        lib.rtcAttachGeometry(scene, geometry)
        lib.rtcReleaseGeometry(geometry)
        lib.rtcCommitScene(scene)
        error = lib.rtcGetDeviceError(device)
        if error:
            lib.rtcReleaseScene(scene)
            raise RuntimeError(f"Embree scene build failed (error {error})")
        self.handle = int(scene)
        self._finalizer = weakref.finalize(self, lib.rtcReleaseScene, ctypes.c_void_p(scene))
