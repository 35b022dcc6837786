"""relightcli: single-image full-body human relighting (ECCV 2022, Ji et al.) on CPU."""

import os

# numpy's and scipy's BLAS (OpenBLAS) run on one thread: the parallel work is the ray tracer's
# own workers and ONNX Runtime's threads, and OpenBLAS's spinning threads beside them slowed the
# whole 512 pipeline (README, Speed). Set before numpy loads its BLAS; a caller's setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
