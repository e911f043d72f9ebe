"""Errors that the user can cause, reported as one line by the CLI."""
from __future__ import annotations

from pathlib import Path


class NeuralSlicerError(Exception):
    """Base class of the errors this package raises on purpose."""


class InputError(NeuralSlicerError):
    """Bad user input: names where (a file, a line, a key) and what is wrong."""

    def __init__(self, where: str | Path, message: str) -> None:
        self.where = str(where)
        self.message = message
        super().__init__(f"{self.where}: {message}")


class PlanError(NeuralSlicerError):
    """A print the machine cannot execute as planned (a pose beyond its axis limits): says where and why."""
