"""Writing `models/manifest.json` from the export side (the runtime reads it through
relightcli.nets.manifest; torch-free, so every export command can use it)."""

from __future__ import annotations

import json
from pathlib import Path

from relightcli.nets.manifest import MANIFEST_NAME, MANIFEST_VERSION


def update_manifest(models_dir: str | Path, name: str, entry: dict) -> Path:
    """Insert or replace model `name` in `<models_dir>/manifest.json` (created when absent)."""
    path = Path(models_dir) / MANIFEST_NAME
    manifest = json.loads(path.read_text()) if path.is_file() else {"version": MANIFEST_VERSION, "models": {}}
    manifest["models"][name] = entry
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)
    return path
