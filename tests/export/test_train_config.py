"""Training configs: the shipped files load, the paper's rates are the defaults, typos are refused."""

import json

import pytest

from export.train.config import (ALL_NETS, CONFIG_DIR, PAPER_LOSS, ConfigError, TrainConfig, load_config,
                                 merge_overrides)


@pytest.mark.parametrize("net", ALL_NETS)
@pytest.mark.parametrize("size", ["small", "paper"])
def test_shipped_config_loads(net, size):
    config = load_config(CONFIG_DIR / f"{net}_{size}.json")
    assert (config.net, config.size) == (net, size)
    assert config.loss == PAPER_LOSS[net]


@pytest.mark.parametrize("net", ALL_NETS)
def test_paper_config_uses_the_paper_learning_rates(net):
    config = load_config(CONFIG_DIR / f"{net}_paper.json")
    assert (config.lr, config.lr_disc) == (1e-5, 1e-6)


def test_closeup_config_loads_with_a_cosine_schedule():
    config = load_config(CONFIG_DIR / "face_refine_small_closeup.json")
    assert (config.net, config.size, config.lr_schedule) == ("face_refine", "small", "cosine")


def test_unknown_lr_schedule_is_refused():
    with pytest.raises(ConfigError, match="lr_schedule"):
        TrainConfig(net="face_refine", lr_schedule="step")


def test_defaults_are_the_paper_learning_rates():
    config = TrainConfig(net="delight")
    assert (config.lr, config.lr_disc) == (1e-5, 1e-6)


def test_unknown_key_is_refused(tmp_path):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"net": "ao", "learning_rate": 1e-3}))
    with pytest.raises(ConfigError, match="learning_rate"):
        load_config(path)


def test_unknown_loss_term_is_refused():
    with pytest.raises(ConfigError, match="adversarial"):
        TrainConfig(net="ao", loss={"adversarial": 1.0})


def test_missing_config_file_names_the_config_dir(tmp_path):
    with pytest.raises(ConfigError, match="configs"):
        load_config(tmp_path / "nope.json")


def test_overrides_merge_nested_loss_weights():
    config = TrainConfig(net="delight").with_overrides(merge_overrides(["loss.l1=2", "lr=1e-4", "crop=null"]))
    assert config.loss == {**PAPER_LOSS["delight"], "l1": 2}
    assert config.lr == 1e-4 and config.crop is None
