"""Reading config files: a YAML mapping, validated, with errors that name the file and the field."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)


def read_yaml_mapping(path: Path, what: str = "config") -> dict:
    """The top-level mapping of the YAML file ``path`` (``what`` names it in errors)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: a directory, not a {what} file")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such {what} file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not a text file (byte {e.start} is not UTF-8)") from None
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of {what} fields at the top level")
    return data


def validate_mapping(model: type[M], data: dict, path: Path | None = None) -> M:
    """``model`` validated from ``data``; the first error as ``<path>: <field.path>: <message>``."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = f"{path}: " if path is not None else ""
        raise ValueError(f"{where}{'.'.join(map(str, err['loc']))}: {err['msg']}") from None
