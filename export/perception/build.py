"""Build the pretrained perception models: fetch the registry package that ships them, convert
each TFLite model to ONNX, check ONNX Runtime against the TFLite interpreter on real photos,
and write `models/<name>.onnx`, their manifest entries, the license and the NOTICE.

    python -m export.perception --out models

The archive is pinned by version, file name and sha256, and downloaded with `pip download`
(the package is never installed); conversion is deterministic, so the same archive gives the
same ONNX bytes. The parity check needs the TFLite interpreter (`ai-edge-litert`, in the
`export` extra); `--no-parity` skips it where that is not installed.
"""

from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from export.manifest import update_manifest
from export.perception.tflite_onnx import convert_tflite
from relightcli.nets.manifest import sha256_file

REPO = Path(__file__).resolve().parents[2]
CACHE = REPO / "export" / ".cache" / "perception"
LICENSE_FILE = "LICENSE.mediapipe"
NOTICE_FILE = "NOTICE"


@dataclass(frozen=True)
class Archive:
    """A registry package file that carries models, pinned by name and sha256."""

    requirement: str
    file: str
    sha256: str
    pip_options: tuple[str, ...]
    license_member: str
    license: str


MEDIAPIPE = Archive(
    requirement="mediapipe==0.10.14",
    file="mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
    sha256="a807328339e7356fda0bb14df12fedbf1d33bdf81649c5f8666b0026b1cc30b4",
    pip_options=("--only-binary=:all:", "--platform", "manylinux2014_x86_64", "--python-version", "3.11",
                 "--implementation", "cp", "--abi", "cp311"),
    license_member="mediapipe-0.10.14.dist-info/LICENSE",
    license="Apache-2.0",
)


@dataclass(frozen=True)
class PerceptionModel:
    """One model to convert: where it lies in the archive, its I/O names, its input."""

    name: str
    member: str
    rename: dict[str, str]
    description: str
    value_range: tuple[float, float]  # what RGB in [0, 1] is mapped to at the input
    thresholds: dict[str, float] = field(default_factory=dict)  # map outputs: the decision level
    archive: Archive = MEDIAPIPE
    metrics: dict = field(default_factory=dict)

    @property
    def file(self) -> str:
        return f"{self.name}.onnx"


MODELS = (
    PerceptionModel(
        "person_detector", "mediapipe/modules/pose_detection/pose_detection.tflite",
        {"input_1": "image", "Identity": "boxes", "Identity_1": "scores"},
        "BlazePose person detector: 2254 anchors, each a face box + 4 keypoints (hip centre, "
        "body size, face centre, head size) in 224 px units and a score logit", (-1.0, 1.0)),
    PerceptionModel(
        "pose_landmarks", "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
        {"input_1": "image", "Identity": "landmarks", "Identity_1": "presence", "Identity_2": "segmentation",
         "Identity_3": "heatmap", "Identity_4": "world_landmarks"},
        "BlazePose GHUM 3D (full): 39 landmarks (x, y, z, visibility, presence logits) in 256 px "
        "crop units, person presence logit, 256x256 segmentation logits, 39 metric 3D world "
        "landmarks (hip-centred, metres)", (0.0, 1.0), {"segmentation": 0.0}),
    PerceptionModel(
        "face_detector", "mediapipe/modules/face_detection/face_detection_short_range.tflite",
        {"input": "image", "regressors": "boxes", "classificators": "scores"},
        "BlazeFace short range (faces within ~2 m): 896 anchors, each a box + 6 keypoints in "
        "128 px units and a score logit", (-1.0, 1.0)),
    PerceptionModel(
        "face_mesh", "mediapipe/modules/face_landmark/face_landmark.tflite",
        {"input_1": "image", "conv2d_21": "landmarks", "conv2d_31": "face_flag"},
        "MediaPipe face mesh: 468 3D face landmarks (x, y in 192 px crop units, z relative) "
        "and a face-presence logit", (0.0, 1.0)),
    PerceptionModel(
        "selfie_segmentation", "mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite",
        {"input_1": "image", "activation_10": "mask"},
        "MediaPipe selfie segmentation (general, 256x256): person probability for head-and-"
        "shoulders shots", (0.0, 1.0), {"mask": 0.5}),
)


# ----------------------------------------------------------------------------- fetch
def fetch(archive: Archive, cache: Path = CACHE) -> Path:
    """The archive's path in `cache`, downloaded with pip when absent; checked by sha256."""
    path = cache / archive.file
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "--disable-pip-version-check",
                        *archive.pip_options, "-d", str(cache), archive.requirement], check=True)
    digest = sha256_file(path)
    if digest != archive.sha256:
        raise RuntimeError(f"{path}: sha256 {digest} is not the pinned {archive.sha256}; delete it and fetch again")
    return path


def read_member(archive_path: Path, member: str) -> bytes:
    with zipfile.ZipFile(archive_path) as zf:
        return zf.read(member)


# ----------------------------------------------------------------------------- parity
def sample_inputs(shape: tuple[int, ...], value_range: tuple[float, float]) -> list[np.ndarray]:
    """Real photos (the shipped example and ../shared/data/photos) resized to the model's
    (1, H, W, 3) input, in its value range."""
    import cv2

    photos = [REPO / "examples" / "skier.jpg", *sorted((REPO.parent / "shared" / "data" / "photos").glob("*.[jp][pn]g"))]
    low, high = value_range
    inputs = []
    for photo in photos:
        bgr = cv2.imread(str(photo), cv2.IMREAD_COLOR)
        if bgr is None:
            continue
        rgb = cv2.resize(bgr[..., ::-1], (shape[2], shape[1]), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        inputs.append((low + (high - low) * rgb)[None])
    return inputs


def parity(tflite_bytes: bytes, onnx_bytes: bytes, inputs: list[np.ndarray],
           thresholds: dict[str, float]) -> dict[str, float]:
    """Per output, the largest |ONNX Runtime - TFLite| over `inputs`, relative to the largest
    |TFLite| value (both on the same input); for the outputs in `thresholds` also the share of
    pixels that land on the other side of the threshold ("<name>_side_changes")."""
    import onnxruntime
    from ai_edge_litert.interpreter import Interpreter

    interpreter = Interpreter(model_content=tflite_bytes)
    interpreter.allocate_tensors()
    session = onnxruntime.InferenceSession(onnx_bytes, providers=["CPUExecutionProvider"])
    details = interpreter.get_output_details()
    names = [o.name for o in session.get_outputs()]  # the same order as the TFLite outputs
    worst = {name: 0.0 for name in names} | {f"{name}_side_changes": 0.0 for name in thresholds}
    for x in inputs:
        interpreter.set_tensor(interpreter.get_input_details()[0]["index"], x)
        interpreter.invoke()
        got = session.run(None, {session.get_inputs()[0].name: x})
        for name, detail, value in zip(names, details, got):
            reference = interpreter.get_tensor(detail["index"])
            scale = max(float(np.abs(reference).max()), 1e-6)
            worst[name] = max(worst[name], float(np.abs(value - reference).max()) / scale)
            if name in thresholds:
                changed = float(np.mean((value > thresholds[name]) != (reference > thresholds[name])))
                worst[f"{name}_side_changes"] = max(worst[f"{name}_side_changes"], changed)
    return worst


# ----------------------------------------------------------------------------- build
def build_model(spec: PerceptionModel, archive_path: Path, out: Path, check: bool) -> dict:
    """Convert one model into `out`; returns its manifest entry."""
    tflite_bytes = read_member(archive_path, spec.member)
    model = convert_tflite(tflite_bytes, spec.rename)
    onnx_bytes = model.SerializeToString()
    target = out / spec.file
    tmp = target.with_suffix(".onnx.tmp")
    tmp.write_bytes(onnx_bytes)
    tmp.replace(target)

    def contract(values):
        return [{"name": v.name, "shape": [d.dim_value for d in v.type.tensor_type.shape.dim], "dtype": "float32"}
                for v in values]

    entry = {
        "file": spec.file,
        "sha256": sha256_file(target),
        "inputs": contract(model.graph.input),
        "outputs": contract(model.graph.output),
        "multiple": 1,
        "colour_space": "sRGB-encoded RGB, NHWC",
        "normalisation": f"RGB in [0, 1] mapped linearly to [{spec.value_range[0]:g}, {spec.value_range[1]:g}]",
        "description": spec.description,
        "license": f"{spec.archive.license} (models/{LICENSE_FILE}); converted from TFLite, see models/{NOTICE_FILE}",
        "source": {"package": spec.archive.requirement, "archive": spec.archive.file,
                   "archive_sha256": spec.archive.sha256, "member": spec.member,
                   "member_sha256": hashlib.sha256(tflite_bytes).hexdigest(),
                   "converter": "python -m export.perception (export/perception/tflite_onnx.py)"},
        "config": {"value_range": list(spec.value_range)},
    }
    if check:
        shape = tuple(entry["inputs"][0]["shape"])
        entry["metrics"] = {"parity_max_relative_error": parity(tflite_bytes, onnx_bytes,
                                                                sample_inputs(shape, spec.value_range),
                                                                spec.thresholds)}
    return entry


def write_notice(out: Path, archive_path: Path, archive: Archive) -> None:
    (out / LICENSE_FILE).write_bytes(read_member(archive_path, archive.license_member))
    names = "\n".join(f"  {m.file:<26} <- {m.member}" for m in MODELS if m.archive == archive)
    (out / NOTICE_FILE).write_text(
        "relightcli models\n\n"
        f"The following models are converted from TFLite to ONNX by `python -m export.perception`\n"
        f"from the {archive.requirement} package (PyPI file {archive.file},\n"
        f"sha256 {archive.sha256}), Copyright The MediaPipe Authors, licensed under the\n"
        f"Apache License 2.0 ({LICENSE_FILE}). The conversion changes the file format and the\n"
        f"weights' storage (sparse weights decoded to dense; float16 weights kept as float16, cast\n"
        f"to float32 in the graph), not the networks.\n\n"
        f"{names}\n\n"
        "The other models in this folder are relightcli's own (see MODEL_CARD.md and manifest.json).\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m export.perception", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(REPO / "models"), help="models folder to write (default: models/)")
    parser.add_argument("--cache", default=str(CACHE), help="where the downloaded archive is kept")
    parser.add_argument("--no-parity", action="store_true", help="skip the TFLite interpreter check")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    archive_path = fetch(MEDIAPIPE, Path(args.cache))
    for spec in MODELS:
        entry = build_model(spec, archive_path, out, check=not args.no_parity)
        update_manifest(out, spec.name, entry)
        print(f"{spec.file}: {(out / spec.file).stat().st_size / 1e6:.1f} MB, "
              f"parity {entry.get('metrics', {}).get('parity_max_relative_error', 'not checked')}")
    write_notice(out, archive_path, MEDIAPIPE)
