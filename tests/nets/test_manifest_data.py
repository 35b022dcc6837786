"""Data entries of the manifest (files the runtime reads that are not networks)."""

from __future__ import annotations

import hashlib
import json

import pytest

from relightcli.errors import MissingDependencyError
from relightcli.nets.manifest import load_manifest, verified_file


def write_manifest(directory, payload: bytes, sha=None):
    (directory / "thing.npz").write_bytes(payload)
    entry = {"kind": "data", "file": "thing.npz", "sha256": sha or hashlib.sha256(payload).hexdigest(),
             "description": "test data", "license": "CC0"}
    (directory / "manifest.json").write_text(json.dumps({"version": 1, "models": {"thing": entry}}))


def test_data_entry_needs_no_io_contract(tmp_path):
    write_manifest(tmp_path, b"abc")
    entry = load_manifest(tmp_path)["thing"]
    assert entry.kind == "data" and entry.inputs == () and entry.description == "test data"


def test_verified_file_checks_sha256(tmp_path):
    write_manifest(tmp_path, b"abc")
    assert verified_file("thing", tmp_path) == tmp_path / "thing.npz"
    (tmp_path / "thing.npz").write_bytes(b"abd")
    with pytest.raises(MissingDependencyError, match="thing.npz.*sha256"):
        verified_file("thing", tmp_path)


def test_verified_file_missing(tmp_path):
    write_manifest(tmp_path, b"abc")
    (tmp_path / "thing.npz").unlink()
    with pytest.raises(MissingDependencyError, match="not found"):
        verified_file("thing", tmp_path)


def test_unknown_kind_is_refused(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"version": 1, "models": {"x": {"kind": "weird", "file": "x", "sha256": "0"}}}))
    with pytest.raises(MissingDependencyError, match="unknown kind"):
        load_manifest(tmp_path)


def test_shipped_face_model_matches_manifest():
    assert verified_file("face_model").name == "face_model.npz"
