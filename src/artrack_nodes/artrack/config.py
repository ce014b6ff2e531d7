"""Configuration files: where config/ is, and YAML -> dataclass with checked keys."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, TypeVar

import yaml

from .errors import InputError

T = TypeVar("T")

#: libyaml's C parser where PyYAML was built with it: the same documents as yaml.SafeLoader, 10-20x
#: faster (config/skeleton.yaml 50 -> 2.5 ms, body_model.yaml 53 -> 6), which every node pays at start-up
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load(text)``, with the C parser when available (raises yaml.YAMLError likewise)."""
    return yaml.load(text, Loader=_SAFE_LOADER)  # noqa: S506 (a safe loader)


def yaml_error_text(exc: yaml.YAMLError) -> str:
    """One line for a YAML syntax error: what is wrong and where, e.g. "did not find expected ','
    or '}' at line 3, column 1" (str(exc) spans several lines and names no file)."""
    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    what = " ".join(str(getattr(exc, "problem", None) or type(exc).__name__).split())
    return what + where


def config_dir() -> Path:
    """The config/ folder: $ARTRACK_CONFIG_DIR, the source tree's, or the installed share/ copy."""
    env = os.environ.get("ARTRACK_CONFIG_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "config" / "body_model.yaml").is_file():
            return parent / "config"
        if (parent / "share" / "artrack_nodes" / "config").is_dir():
            return parent / "share" / "artrack_nodes" / "config"
    raise InputError("cannot find the config/ folder; set ARTRACK_CONFIG_DIR")


def config_path(name_or_path: str | os.PathLike | None, default_name: str) -> Path:
    """A path as given, or config/<default_name> when empty."""
    if name_or_path:
        return Path(name_or_path)
    return config_dir() / default_name


def read_yaml(path: str | os.PathLike) -> dict[str, Any]:
    """The top-level mapping of a YAML file ({} when empty); a missing, unreadable or invalid file, or a
    top level that is not a mapping, is an InputError of one line naming the file."""
    p = Path(path)
    try:
        data = parse_yaml(p.read_text())
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a directory, not a YAML file") from None
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a text file (not UTF-8)") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{p}: not valid YAML ({yaml_error_text(exc)})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{p}: top level must be a mapping")
    return data


def require_bool(value: Any, subject: str) -> None:
    """InputError ``"<subject> must be true or false"`` unless ``value`` is a bool: a switch
    must be a YAML true / false (``bool("false")`` is True, and a string would be truthy)."""
    if not isinstance(value, bool):
        raise InputError(f"{subject} must be true or false (got {value!r})")


def dataclass_from_dict(cls: type[T], data: dict[str, Any], where: str) -> T:
    """Build dataclass ``cls`` from ``data``; an unknown key is an InputError naming it."""
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise InputError(f"{where}: unknown field '{unknown[0]}' (known: {', '.join(sorted(names))})")
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if isinstance(f.default, bool) and f.name in data:
            require_bool(data[f.name], f"{where}: field '{f.name}'")
    return cls(**data)


def load_dataclass_yaml(path: str | os.PathLike, cls: type[T], section: str | None = None) -> T:
    """Dataclass ``cls`` from a YAML file (or its ``section`` mapping), every key checked
    (:func:`dataclass_from_dict`)."""
    data = read_yaml(path)
    if section is not None:
        data = data.get(section, {}) or {}
    return dataclass_from_dict(cls, data, f"{Path(path).name}" + (f" [{section}]" if section else ""))
