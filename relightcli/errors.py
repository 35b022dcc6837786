"""Project exceptions. Each carries the exit code the CLI maps it to (the only place that exits).

Exit codes: 0 all ok, 1 some items failed, 2 usage, 3 missing model or dependency,
4 unreadable input; a signal stops a run with 128 + its number: 130 SIGINT (Ctrl-C), 143 SIGTERM
(docker stop) (the CLI's handlers, batch.Stopped).
"""

from __future__ import annotations

from pathlib import Path

EXIT_OK = 0
EXIT_ITEMS_FAILED = 1
EXIT_USAGE = 2
EXIT_MISSING = 3
EXIT_UNREADABLE = 4


class RelightError(Exception):
    """Base of every error a user can cause. The message names the file (when there is one)
    and says what to do about it."""

    exit_code = EXIT_ITEMS_FAILED

    def __init__(self, message: str, path: str | Path | None = None, fix: str | None = None):
        self.message = message  # without the path and the fix: a caller may restate it
        self.path = None if path is None else str(path)
        self.fix = fix
        text = message if self.path is None else f"{self.path}: {message}"
        if fix:
            text = f"{text} ({fix})"
        super().__init__(text)


class UsageError(RelightError):
    """Wrong arguments or options, or an output location that cannot be used."""

    exit_code = EXIT_USAGE


class OutputError(UsageError):
    """The output cannot be written (unwritable directory, would overwrite an input, exists)."""


class WriteError(RelightError):
    """Writing an output failed part-way (disk full, quota, I/O error): not a usage mistake,
    the item fails (exit 1) and nothing half-written is left."""

    exit_code = EXIT_ITEMS_FAILED


class MissingDependencyError(RelightError):
    """A model file or an optional package is missing or corrupt."""

    exit_code = EXIT_MISSING


class InputError(RelightError):
    """An input file cannot be read or decoded, or its content is unusable."""

    exit_code = EXIT_UNREADABLE


class NumericalError(RelightError):
    """A numerical stage failed to converge or produced non-finite values."""

    exit_code = EXIT_ITEMS_FAILED


class RelightWarning(UserWarning):
    """Something was repaired or assumed (NaN texels, an 8-bit map read as sRGB, ...).

    Library code emits these with `warnings.warn(..., RelightWarning)`; the CLI records them
    per item into the report instead of printing them.
    """
