"""Shared fixtures for the data-factory tests: skip cleanly without the MakeHuman data."""

from pathlib import Path

import pytest

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "makehuman"


@pytest.fixture(scope="session")
def makehuman_data():
    if not (DATA / "base.obj").is_file() or not (DATA / "makehuman_core_data.tar.xz").is_file():
        pytest.skip(f"MakeHuman data not found in {DATA}")
    return DATA


@pytest.fixture(scope="session")
def base(makehuman_data):
    from export.factory.person import base_model

    return base_model()
