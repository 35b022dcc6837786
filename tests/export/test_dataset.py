"""The on-disk dataset: format round trip, a tiny generated dataset, resume, determinism,
eval scene folders (export/factory/dataset.py, generate.py, eval_scenes.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from export.factory import dataset, generate, lighting, render
from relightcli.io.images import read_image

RES = 64
COUNTS = {"train": 2, "val": 1, "test": 1}
CONFIG = generate.GenerationConfig(
    seed=5, samples_per_person=2,
    settings=render.RenderSettings(resolution=RES, spp=8, target_error=None, ao_spp=4))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, makehuman_data):
    if not (lighting.hdri_dir() / "index.csv").is_file():
        pytest.skip("shared HDRIs not found")
    root = tmp_path_factory.mktemp("factory")
    summary = generate.generate(root, COUNTS, CONFIG)
    dataset.write_card(root, generate.build_card(root, COUNTS, CONFIG, "test", [summary]))
    return root, summary


def _contract_shape(shape):
    return tuple(RES if s in ("H", "W") else s for s in shape)


# --- format ------------------------------------------------------------------------------------

def test_hdr_arrays_round_trip_to_float16_precision(tmp_path):
    value = np.random.default_rng(0).exponential(50.0, (8, 8, 3)).astype(np.float32)
    dataset.write_sample(tmp_path, "train", "000000", {"shading_a": value}, {})
    dataset.write_card(tmp_path, {})
    loaded = dataset.open_dataset(tmp_path).load("train", "000000")["shading_a"]
    assert loaded == pytest.approx(value, rel=1e-3, abs=float(value.max()) * 1e-4)


def test_srgb_photo_round_trips_through_the_srgb_decode(tmp_path):
    photo = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, axis=2)
    dataset.write_sample(tmp_path, "val", "000003", {"input": photo}, {})
    dataset.write_card(tmp_path, {})
    data = dataset.open_dataset(tmp_path)
    from relightcli.io.images import srgb_to_linear
    assert np.array_equal(data.load("val", "000003")["input"], srgb_to_linear(photo / 255.0))


def test_reserved_array_names_are_refused(tmp_path):
    from relightcli.errors import UsageError
    with pytest.raises(UsageError):
        dataset.write_sample(tmp_path, "train", "x", {"a__scale": np.zeros(1)}, {})


def test_open_dataset_without_a_card_names_the_fix(tmp_path):
    from relightcli.errors import InputError
    with pytest.raises(InputError, match="generate"):
        dataset.open_dataset(tmp_path)


def test_split_counts_sum_to_the_count():
    counts = generate.split_counts(7, generate.parse_fractions("train=0.8,val=0.1,test=0.1"))
    assert counts == {"train": 5, "val": 1, "test": 1}  # largest remainders: 0.7, 0.7, 0.6


# --- a tiny generated dataset -------------------------------------------------------------------

def test_tiny_dataset_has_every_sample(tiny):
    data = dataset.open_dataset(tiny[0])
    assert {s: len(data.ids(s)) for s in dataset.SPLITS} == COUNTS


def test_tiny_dataset_round_trips_every_key_shape_and_dtype(tiny):
    loaded = dataset.open_dataset(tiny[0]).load("train", "000001")
    got = {k: (v.shape, v.dtype) for k, v in loaded.items()}
    want = {k: (_contract_shape(s), np.dtype(np.float32)) for k, s in dataset.CONTRACT.items()}
    assert got == want


def test_tiny_dataset_values_obey_the_contract(tiny):
    s = dataset.open_dataset(tiny[0]).load("test", "000000")
    inside = s["mask"] > 0.5
    assert np.linalg.norm(s["normal"][inside], axis=-1) == pytest.approx(1.0, abs=1e-5)
    assert 0 <= s["ao"].min() and s["ao"].max() <= 1 and 0 <= s["albedo"].min() <= s["albedo"].max() <= 1
    assert np.all(s["front_depth"][inside] >= s["back_depth"][inside])


def test_tiny_dataset_card_lists_splits_and_sources(tiny):
    card = dataset.open_dataset(tiny[0]).card
    assert card["counts_on_disk"] == COUNTS and card["seed"] == CONFIG.seed
    hdris = card["sources"]["hdri"]["splits"]
    assert not set(hdris["test"]) & set(hdris["train"])


def test_test_samples_use_test_hdris_only(tiny):
    meta = dataset.open_dataset(tiny[0]).meta("test", "000000")
    test_maps = set(lighting.hdri_splits()["test"])
    used = [meta["spec"][k]["name"] for k in ("lighting_a", "lighting_b", "background")]
    assert all(name == "sky" or name in test_maps for name in used)


def test_test_samples_use_test_poses_only(tiny):
    from export.factory.person import splits
    meta = dataset.open_dataset(tiny[0]).meta("test", "000000")
    assert meta["person"]["pose"] in splits()["pose"]["test"]


def test_second_run_renders_nothing_new(tiny):
    again = generate.generate(tiny[0], COUNTS, CONFIG)
    assert again["rendered"] == 0 and again["skipped"] == sum(COUNTS.values())


def test_same_seed_gives_the_same_arrays(tiny, tmp_path):
    generate.generate(tmp_path, {"val": 1}, CONFIG)
    first = dataset.open_dataset(tiny[0])
    dataset.write_card(tmp_path, {})
    second = dataset.open_dataset(tmp_path).load("val", "000000")
    for name, value in first.load("val", "000000").items():
        assert np.array_equal(value, second[name]), name


def test_eval_scene_folder_holds_the_ground_truth(tiny, tmp_path):
    from export.factory.eval_scenes import write_eval_scenes
    folder = write_eval_scenes(tiny[0], tmp_path, "test")[0]
    data = dataset.open_dataset(tiny[0])
    sample = data.load("test", "000000")
    import cv2
    stored = data.load_raw("test", "000000", "input")
    assert np.array_equal(cv2.imread(str(folder / "input.png"))[..., ::-1], stored)
    assert read_image(folder / "gt_shading.exr").rgb == pytest.approx(
        sample["shading_b"], rel=2e-3, abs=1e-3 * float(sample["shading_b"].max()))
    mask = read_image(folder / "gt_mask.png", srgb=False).rgb[..., 0]
    assert np.array_equal(mask > 0.5, sample["mask"] > 0.5)


def test_eval_target_is_lighting_b_as_the_shading_saw_it(tiny, tmp_path):
    from export.factory.eval_scenes import write_eval_scenes
    from relightcli.io.envmap import gaussian_pyramid_downsample
    folder = write_eval_scenes(tiny[0], tmp_path, "test")[0]
    target = read_image(folder / "target.hdr").rgb
    light_b = dataset.open_dataset(tiny[0]).load("test", "000000")["light_b"]
    # RGBE keeps ~1 % per texel; the 16x32 pyramid averages it
    assert gaussian_pyramid_downsample(target, 16) == pytest.approx(light_b, rel=0.02, abs=1e-6)


def test_generate_cli_writes_a_card(tmp_path, makehuman_data):
    code = generate.main(["--out", str(tmp_path), "--count", "0", "--resolution", "32"])
    card = json.loads((tmp_path / dataset.CARD_NAME).read_text())
    assert code == 0 and card["resolution"] == 32 and card["format_version"] == dataset.FORMAT_VERSION
    assert card["pose_variety"] == 0.0


def test_mixed_poses_reach_the_samples(tmp_path, makehuman_data):
    """--pose-variety goes to the card and to each sample's person, and the people mix poses
    of their own split only."""
    if not (lighting.hdri_dir() / "index.csv").is_file():
        pytest.skip("shared HDRIs not found")
    from export.factory.person import splits

    code = generate.main(["--out", str(tmp_path), "--count", "1", "--splits", "test=1", "--resolution", "32",
                          "--spp", "4", "--ao-spp", "2", "--target-error", "0", "--workers", "1",
                          "--pose-variety", "1"])
    data = dataset.open_dataset(tmp_path)
    person = data.meta("test", "000000")["person"]
    assert code == 0 and data.card["pose_variety"] == 1.0 and person["pose_variety"] == 1.0
    assert {name.split(" ")[0] for name in person["pose_mix"].values()} <= set(splits()["pose"]["test"])


def test_eval_scene_folder_loads_in_relight_eval(tiny, tmp_path):
    from export.factory.eval_scenes import write_eval_scenes
    from relightcli.evaluate import load_scene
    scene = load_scene(write_eval_scenes(tiny[0], tmp_path, "test")[0])
    assert scene.shading.shape == (RES, RES, 3) and scene.normal is not None


def test_interrupted_run_leaves_a_card_counting_what_is_on_disk(tmp_path, makehuman_data, monkeypatch):
    real = generate.render_group
    calls = []

    def render_then_interrupt(*args, **kwargs):
        if calls:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(generate, "render_group", render_then_interrupt)
    code = generate.main(["--out", str(tmp_path), "--count", "2", "--splits", "train=1,val=1",
                          "--resolution", "32", "--workers", "1", "--spp", "4", "--ao-spp", "4",
                          "--samples-per-person", "1"])
    card = json.loads((tmp_path / dataset.CARD_NAME).read_text())
    assert code == 130
    assert card["counts_on_disk"] == {"train": 1, "val": 0, "test": 0}
    assert card["runs"][-1]["interrupted"] and card["runs"][-1]["rendered"] == 1
