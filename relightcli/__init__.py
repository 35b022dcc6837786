"""relightcli: single-image full-body human relighting (ECCV 2022, Ji et al.) on CPU."""

import os

# numpy's and scipy's BLAS (OpenBLAS) run on one thread: the parallel work is the ray tracer's
# own workers and ONNX Runtime's threads, and OpenBLAS's spinning threads beside them slowed the
# whole 512 pipeline (docs/RESULTS.md, Speed and memory). Set before numpy loads its BLAS; a caller's setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"


def __getattr__(name):
    """relightcli.relight, relightcli.Relighter and relightcli.Result (relightcli.api), imported
    on first use: `relight --help` and the workers' start stay light."""
    if name in ("relight", "Relighter", "Result"):
        from relightcli import api

        return getattr(api, name)
    raise AttributeError(f"module 'relightcli' has no attribute {name!r}")


__all__ = ["relight", "Relighter", "Result", "__version__"]
