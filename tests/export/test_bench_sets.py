"""bench/sets.py: each working set's commands, as the docs give them."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import sets  # noqa: E402


def test_the_validation_set_is_the_documented_command_with_the_workers_added():
    generate, scenes = (command[1:] for command in sets.commands("val60", workers=1))
    assert " ".join(generate) == ("-m export.factory.generate --out data/factory512val60 --count 60 --splits val=1 "
                                  "--resolution 512 --seed 21 --spp 128 --target-error 0.03 --bounces 2 "
                                  "--samples-per-person 1 --workers 1")
    assert scenes == ["-m", "export.factory.eval_scenes", "data/factory512val60", "data/evalval512p60", "--split", "val"]


def test_the_mixed_pose_set_differs_from_its_twin_only_by_its_poses_and_folders():
    plain, mixed = (sets.commands(name, 2)[0] for name in ("val60", "val60m"))
    assert mixed[mixed.index("--pose-variety") + 1] == "0.5"
    drop = {"--pose-variety", "0.5", "data/factory512val60", "data/factory512val60m"}
    assert [a for a in plain if a not in drop] == [a for a in mixed if a not in drop]


def test_only_the_generator_takes_workers():
    for name in sets.SETS:
        for command in sets.commands(name, 2):
            assert ("--workers" in command) == ("export.factory.generate" in command)
