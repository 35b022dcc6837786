"""relightcli: single-image full-body human relighting (ECCV 2022, Ji et al.) on CPU."""

__version__ = "0.1.0"
