"""Error types: every bad input raises a `MetegsError` subclass naming the file/field and what was expected."""

from __future__ import annotations

from pathlib import Path


class MetegsError(Exception):
    """Base class of every error metegs raises for bad input or configuration."""


class DataError(MetegsError):
    """A data file or folder is missing, malformed or unsupported."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}" if path is not None else problem)


class ConfigError(MetegsError):
    """A configuration value or name is invalid."""


class PluginError(MetegsError):
    """A plugin or registered component cannot be loaded."""


class Interrupted(MetegsError):
    """The user stopped a command (Ctrl-C); the message says what was kept and how to go on."""

    exit_code = 130


class TrainingDiverged(MetegsError):
    """Training produced non-finite values; the message names them and a checkpoint to resume from."""
