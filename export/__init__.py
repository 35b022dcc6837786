"""Torch side of relightcli: synthetic data factory, networks, training and ONNX export.

`export` may import `relightcli`; `relightcli` never imports `export`.
"""
