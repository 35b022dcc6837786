"""bench/scene_run.py: a replaced function is put back, whatever happens inside the block."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from scene_run import replaced  # noqa: E402


def test_replaced_puts_the_function_back_after_an_error():
    owner = types.SimpleNamespace(solve=lambda: "product")
    original = owner.solve
    with replaced(owner, "solve", lambda: "variant"):
        assert owner.solve() == "variant"
    assert owner.solve is original
    with pytest.raises(RuntimeError), replaced(owner, "solve", lambda: "variant"):
        raise RuntimeError("a scene failed")
    assert owner.solve is original
