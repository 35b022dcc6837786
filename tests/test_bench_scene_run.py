"""bench/scene_run.py: a replaced function or stage is put back, whatever happens inside the block."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from scene_run import replaced, replaced_stage  # noqa: E402


def test_replaced_puts_the_function_back_after_an_error():
    owner = types.SimpleNamespace(solve=lambda: "product")
    original = owner.solve
    with replaced(owner, "solve", lambda: "variant"):
        assert owner.solve() == "variant"
    assert owner.solve is original
    with pytest.raises(RuntimeError), replaced(owner, "solve", lambda: "variant"):
        raise RuntimeError("a scene failed")
    assert owner.solve is original


def test_replaced_stage_wraps_the_stage_and_puts_it_back_after_an_error():
    from relightcli.stages import STAGES

    original = STAGES["body"]
    with replaced_stage("body", lambda stage: ("wrapped", stage)):
        assert STAGES["body"] == ("wrapped", original)
    assert STAGES["body"] is original
    with pytest.raises(RuntimeError), replaced_stage("body"):
        assert STAGES["body"] is original
        raise RuntimeError("a scene failed")
    assert STAGES["body"] is original
