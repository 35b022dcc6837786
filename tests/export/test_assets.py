"""Archive extraction into the cache: once, atomically, with a clear error when missing."""

import tarfile

import pytest

from export.factory import assets
from relightcli.errors import MissingDependencyError


@pytest.fixture
def fake_data(tmp_path, monkeypatch):
    data = tmp_path / "data"
    (data / "payload" / "makehuman" / "data").mkdir(parents=True)
    (data / "payload" / "makehuman" / "data" / "hello.txt").write_text("hi")
    with tarfile.open(data / assets.ARCHIVES["core"], "w:xz") as tar:
        tar.add(data / "payload" / "makehuman", arcname="makehuman")
    monkeypatch.setenv("RELIGHT_MAKEHUMAN_DATA", str(data))
    monkeypatch.setenv("RELIGHT_CACHE", str(tmp_path / "cache"))
    return tmp_path


def test_extracts_once_into_the_cache(fake_data):
    path = assets.core_path("hello.txt")
    assert path.read_text() == "hi"
    assert path.is_relative_to(fake_data / "cache" / "makehuman")
    path.write_text("changed")  # a second call must not extract again
    assert assets.core_path("hello.txt").read_text() == "changed"
    cache = fake_data / "cache" / "makehuman"
    assert [p.name for p in cache.iterdir() if p.name.startswith(".")] == []  # no temp dirs


def test_missing_archive_names_the_file(fake_data):
    with pytest.raises(MissingDependencyError, match="makehuman_assets.tar.xz"):
        assets.asset_path("poses/sit01.bvh")


def test_unknown_archive_is_rejected():
    with pytest.raises(ValueError, match="unknown archive"):
        assets.extracted("extras")
