"""Errors that the user can cause, reported as one line by the CLI."""
from __future__ import annotations

import difflib
from collections.abc import Sequence
from pathlib import Path
from typing import Any, get_args


class NeuralSlicerError(Exception):
    """Base class of the errors this package raises on purpose."""


class InputError(NeuralSlicerError):
    """Bad user input: names where (a file, a line, a key) and what is wrong."""

    def __init__(self, where: str | Path, message: str) -> None:
        self.where = str(where)
        self.message = message
        super().__init__(f"{self.where}: {message}")

    def __reduce__(self) -> tuple[type, tuple[str, str], dict]:
        """Pickled with its two arguments (a step's own process sends its error back to the run)."""
        return type(self), (self.where, self.message), self.__dict__


class PlanError(NeuralSlicerError):
    """A print the machine cannot execute as planned (a pose beyond its axis limits): says where and why."""


def _section_models(annotation: Any) -> list[type]:
    """The pydantic model classes an annotation holds (``Model``, ``Model | None``, ``list[Model]``, ...)."""
    if isinstance(annotation, type) and hasattr(annotation, "model_fields"):
        return [annotation]
    return [m for arg in get_args(annotation) for m in _section_models(arg)]


def _type_tag(model: type) -> Any:
    """The annotation of a model's ``type`` field (``Literal["mesh"]`` in a tagged union), or None."""
    field = model.model_fields.get("type")
    return field.annotation if field is not None else None


def _walk(model: type, loc: Sequence[str | int]) -> tuple[type | None, list[str | int]]:
    """The model class of the section that holds the last key of a pydantic error's ``loc`` (None where the walk
    leaves the models), and ``loc`` without the class names pydantic puts in the paths of union members."""
    models: list[type] = [model]
    path: list[str | int] = []
    for n, part in enumerate(loc):
        if isinstance(part, int):
            path.append(part)
            continue
        named = [m for m in models if m.__name__ == part or part in get_args(_type_tag(m))]
        if named and n < len(loc) - 1:
            models = named           # a union member: ``network.NetworkConfig.width``, ``components.0.mesh.file``
            continue
        path.append(part)
        if n == len(loc) - 1:
            break
        field = next((m.model_fields[part] for m in models if part in m.model_fields), None)
        models = _section_models(field.annotation) if field is not None else []
    return (models[0] if models else None), path


def error_key(model: type, loc: Sequence[str | int]) -> str:
    """A pydantic error's ``loc`` as the dotted key a user wrote (``neural.network.width``)."""
    return ".".join(str(p) for p in _walk(model, loc)[1]) or "(top level)"


def unknown_key_message(model: type, loc: Sequence[str | int]) -> str:
    """One line for an unknown key at ``loc`` of the pydantic ``model``: the key, its section and the nearest
    valid name (``difflib.get_close_matches``), or every valid name when none is close."""
    section_model, path = _walk(model, loc)
    names = [str(p) for p in path if not isinstance(p, int)]
    key, section = (names[-1], names[:-1]) if names else ("?", [])
    if section_model is None:
        return f"unknown key {key!r}"
    valid = [f.alias or name for name, f in section_model.model_fields.items()]
    where = f"in section {'.'.join(section)!r}" if section else "at the top level"
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"valid keys: {', '.join(valid)}"
    return f"unknown key {key!r} {where}; {hint}"


def validation_error_line(model: type, errors: list[dict]) -> tuple[str, str]:
    """The dotted key and the message of the error to report of a pydantic ``model``'s validation ``errors``: an
    unknown key first, with its nearest valid name (a union's other members only say "not a string")."""
    unknown = [e for e in errors if e["type"] == "extra_forbidden"]
    err = (unknown or errors)[0]
    msg = unknown_key_message(model, err["loc"]) if unknown else err["msg"]
    return error_key(model, err["loc"]), msg
