"""Pretrained perception (person and face detection, pose landmarks, face mesh, selfie
segmentation) from the MediaPipe package, converted from TFLite to ONNX: `python -m export.perception`."""
