"""export.factory.merge: one dataset that is the union of several, by links."""

import numpy as np
import pytest

from export.factory import dataset, merge
from export.train.fake_data import write_fake_dataset
from relightcli.errors import UsageError


def test_merge_links_every_sample_under_a_source_prefix(tmp_path):
    a = write_fake_dataset(tmp_path / "a", {"train": 3, "val": 1}, size=16, seed=0)
    b = write_fake_dataset(tmp_path / "b", {"train": 2}, size=16, seed=1)
    card = merge.merge(tmp_path / "ab", [a, b])
    data = dataset.open_dataset(tmp_path / "ab")
    assert data.ids("train") == ["0_train_0000", "0_train_0001", "0_train_0002", "1_train_0000", "1_train_0001"]
    assert data.ids("val") == ["0_val_0000"]
    assert card["counts_on_disk"] == {"train": 5, "val": 1, "test": 0}
    assert [m["prefix"] for m in card["merged"]] == ["0_", "1_"]
    # The same ids in both sources stay two samples: each link reads its own source's bytes
    same_id = dataset.open_dataset(b).load("train", "train_0000")["albedo"]
    np.testing.assert_array_equal(data.load("train", "1_train_0000")["albedo"], same_id)
    assert not np.array_equal(data.load("train", "0_train_0000")["albedo"], same_id)
    # Resumable: a second run keeps the links and the counts
    assert merge.merge(tmp_path / "ab", [a, b])["counts_on_disk"]["train"] == 5


def test_merge_refuses_mixed_resolutions(tmp_path):
    a = write_fake_dataset(tmp_path / "a", {"train": 1}, size=16)
    b = write_fake_dataset(tmp_path / "b", {"train": 1}, size=32)
    with pytest.raises(UsageError, match="resolution"):
        merge.merge(tmp_path / "ab", [a, b])
