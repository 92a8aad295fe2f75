"""Strict YAML helpers: every problem names the file, the key path and what is wrong."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from cfrace.errors import ConfigError


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":      # `<<: *base`: merged keys may be overridden
                continue
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} is given twice", key_node.start_mark)
            seen.add(key if isinstance(key, (str, int, float, bool)) else id(key_node))
        return super().construct_mapping(node, deep)


def load_yaml(path: Path) -> dict:
    """Read a YAML mapping from ``path`` or raise ConfigError with file and problem."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a YAML text file (byte {exc.start} is not UTF-8)") from None
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}:{where} invalid YAML: {problem}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data


def open_named(name_or_path: str | Path, folder: Path, what: str) -> "Reader":
    """A Reader of ``folder/NAME.yaml`` (a name) or of the path given; ConfigError naming the known
    files of ``folder`` when there is no such file. ``what``: "drone profile", "track", ..."""
    from cfrace.paths import resolve_named

    path = resolve_named(name_or_path, folder, ".yaml")
    if not path.exists():
        known = ", ".join(sorted(p.stem for p in folder.glob("*.yaml")))
        raise ConfigError(f"{path}: no such {what} file (known: {known})")
    return Reader(path, load_yaml(path))


class Reader:
    """Walks a YAML mapping, checking keys and values, raising one-line ConfigErrors."""

    def __init__(self, path: Path | str, data: dict, prefix: str = ""):
        self.path = str(path)
        self.data = data
        self.prefix = prefix
        self.used: set[str] = set()

    def _key(self, key: str) -> str:
        return f"{self.prefix}{key}"

    def fail(self, key: str, problem: str) -> ConfigError:
        return ConfigError(f"{self.path}: key '{self._key(key)}': {problem}")

    def has(self, key: str) -> bool:
        return key in self.data

    def file_name(self, folder: Path) -> str:
        """The ``name`` key; in ``folder`` (where files are found by name) it must be the file's name."""
        name = self.string("name")
        path = Path(self.path)
        if path.parent.resolve() == Path(folder).resolve() and name != path.stem:
            raise self.fail("name", f"'{name}' is not the file's name '{path.stem}': files in {folder.name}/ "
                                    "are found by their file name, so the two must be equal")
        return name

    def raw(self, key: str, default: Any = ...) -> Any:
        if key not in self.data:
            if default is ...:
                raise self.fail(key, "missing")
            return default
        self.used.add(key)
        return self.data[key]

    def number(self, key: str, default: Any = ..., *, min: float | None = None,
               max: float | None = None, positive: bool = False) -> float:
        value = self.raw(key, default)
        return self.check_number(key, value, min=min, max=max, positive=positive)

    def check_number(self, key: str, value: Any, *, min: float | None = None,
                     max: float | None = None, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, f"expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(key, f"must be finite, got {value}")
        if positive and value <= 0:
            raise self.fail(key, f"must be > 0, got {value}")
        if min is not None and value < min:
            raise self.fail(key, f"must be >= {min}, got {value}")
        if max is not None and value > max:
            raise self.fail(key, f"must be <= {max}, got {value}")
        return value

    def vector(self, key: str, length: int | None, default: Any = ..., **kw) -> tuple[float, ...]:
        value = self.raw(key, default)
        return self.check_vector(key, value, length, **kw)

    def check_vector(self, key: str, value: Any, length: int | None, **kw) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)):
            raise self.fail(key, f"expected a list of {length or 'some'} numbers, got {value!r}")
        if length is not None and len(value) != length:
            raise self.fail(key, f"expected {length} numbers, got {len(value)}")
        return tuple(self.check_number(f"{key}[{i}]", v, **kw) for i, v in enumerate(value))

    def string(self, key: str, default: Any = ...) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"expected a non-empty string, got {value!r}")
        return value

    def mapping(self, key: str, default: Any = ...) -> "Reader":
        value = self.raw(key, default)
        if not isinstance(value, dict):
            raise self.fail(key, f"expected a mapping, got {type(value).__name__}")
        return Reader(self.path, value, prefix=f"{self._key(key)}.")

    def sequence(self, key: str, default: Any = ...) -> list:
        value = self.raw(key, default)
        if not isinstance(value, list):
            raise self.fail(key, f"expected a list, got {type(value).__name__}")
        return value

    def child(self, key: str, value: Any) -> "Reader":
        if not isinstance(value, dict):
            raise self.fail(key, f"expected a mapping, got {type(value).__name__}")
        return Reader(self.path, value, prefix=f"{self._key(key)}.")

    def done(self) -> None:
        """Raise on any key that was not read (unknown keys are errors)."""
        unknown = sorted(str(k) for k in self.data if k not in self.used)
        if unknown:
            raise self.fail(unknown[0], "unknown key")


def read_named(name_or_path: str | Path, folder: Path, what: str) -> Reader:
    """A Reader over ``folder/NAME.yaml`` (or a path); ConfigError listing the known names when missing."""
    from cfrace.paths import resolve_named

    path = resolve_named(name_or_path, folder, ".yaml")
    if not path.exists():
        known = ", ".join(sorted(p.stem for p in folder.glob("*.yaml")))
        raise ConfigError(f"{path}: no such {what} (known: {known})")
    return Reader(path, load_yaml(path))
