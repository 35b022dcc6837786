"""Benchmark of the face stage: landmark fit (target <= 200 ms on 2 cores) and the face chain.

Usage: python bench/bench_face.py [--repeats N] [--threads T]
Prints one JSON line: median / p90 wall milliseconds (and median process CPU ms, which a
busy machine does not inflate) of fit_face on synthetic 68-landmark inputs
(1 px noise, random identity, pose within +-30 degrees) and of find_face (face detector +
face mesh, relightcli.nets.face_mesh) on the whole of a sample photo.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _limit_threads(threads: int) -> None:
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(threads)


def bench_fit(model, repeats: int):
    import numpy as np

    from relightcli.geometry.face_fit import fit_face
    from relightcli.geometry.face_model import rotation_matrix, transform, world_to_pixel

    rect, resolution = (-0.5, 0.5, 1.2, 2.2), (128, 128)
    rng = np.random.default_rng(0)
    times, cpu, iterations = [], [], []
    for _ in range(repeats):
        identity = rng.normal(size=model.n_identity)
        expression = np.zeros(model.n_expression)
        expression[rng.integers(model.n_expression, size=3)] = rng.uniform(0.2, 0.8, 3)
        rotation = rotation_matrix(*rng.uniform(-30, 30, 3))
        points = transform(model.landmarks(identity, expression), 0.05, rotation,
                           [0.0, 1.7, 0.0])
        pixels = world_to_pixel(points, rect, resolution) + rng.normal(0, 1.0, (68, 2))
        start, start_cpu = time.perf_counter(), time.process_time()
        fit = fit_face(pixels, model, rect, resolution)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        iterations.append(fit.iterations)
    return times, cpu, iterations


def bench_detect(repeats: int):
    import numpy as np

    from relightcli.io.images import linear_to_srgb, read_image
    from relightcli.nets.face_mesh import FaceDetector, FaceMesh, find_face

    photo = REPO / ".." / "shared" / "data" / "photos" / "pexels_woman_with_dog.jpg"
    if not photo.is_file():
        return None, None
    image = np.clip(linear_to_srgb(read_image(photo).rgb), 0.0, 1.0).astype(np.float32)
    detector, mesh = FaceDetector(threads=1), FaceMesh(threads=1)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        find_face(image, None, detector, mesh)
        times.append(time.perf_counter() - start)
    return times, image.shape[:2]


def _summary(times):
    import numpy as np

    ms = 1e3 * np.asarray(times)
    return {"median_ms": round(float(np.median(ms)), 1),
            "p90_ms": round(float(np.percentile(ms, 90)), 1),
            "max_ms": round(float(ms.max()), 1)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description="face stage benchmark")
    parser.add_argument("--repeats", type=int, default=50)
    # BLAS threads: the fit works on ~100x100 matrices, where extra threads only add
    # synchronisation (measured: 1 thread 19 ms, 2 threads 197 ms on a busy 2-core machine)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    _limit_threads(args.threads)
    sys.path.insert(0, str(REPO))
    from relightcli.geometry.face_model import FaceModel

    start = time.perf_counter()
    model = FaceModel.load()
    load_ms = 1e3 * (time.perf_counter() - start)
    bench_fit(model, 3)  # warm-up
    fit_times, fit_cpu, iterations = bench_fit(model, args.repeats)
    detect_times, shape = bench_detect(max(3, args.repeats // 10))
    report = {"threads": args.threads, "model_load_ms": round(load_ms, 1),
              "fit": {**_summary(fit_times), "cpu_median_ms": _summary(fit_cpu)["median_ms"],
                      "repeats": args.repeats,
                      "mean_iterations": round(sum(iterations) / len(iterations), 1)}}
    if detect_times:
        report["detect"] = {**_summary(detect_times), "image_hw": list(shape)}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
