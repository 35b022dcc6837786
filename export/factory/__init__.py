"""Synthetic data factory: MakeHuman bodies, poses, clothes and synthetic albedo.

`build_person(seed, split)` is the entry point; see `person.py` for the output contract.
"""

from .person import PART_NAMES, SPLITS, Person, build_person, splits

__all__ = ["PART_NAMES", "SPLITS", "Person", "build_person", "splits"]
