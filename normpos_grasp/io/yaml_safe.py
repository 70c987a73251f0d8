"""Bounded YAML for the files a user hands the product (cells, grippers, templates).

`yaml.safe_load` builds no Python objects, but it still expands aliases: a 1.3 kB file of nested anchors and
aliases ("billion laughs") grows to gigabytes once a value is turned into text. This loader refuses what a
configuration file never needs and an attacker or a slip can abuse:

- anchors, aliases (`&a`, `*a`) and merge keys (`<<:`): write values out instead;
- duplicate keys in one mapping (plain YAML keeps the last one silently: a typo'd override would win);
- files over `MAX_BYTES` and collections nested deeper than `MAX_DEPTH`.

Every problem, syntax errors included, is a `YamlError` whose message is one line, `file:line:col: problem`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from normpos_grasp.errors import InputError

MAX_BYTES = 1 << 20  # 1 MiB: cell, gripper and template files are a few kB
MAX_DEPTH = 32  # nesting of mappings / sequences; the deepest schema (cell poses) uses 4


class YamlError(InputError, yaml.YAMLError):
    """A YAML file is malformed or uses a refused feature; `line` and `column` are 1-based (0 when unknown).

    It is also a `yaml.YAMLError`, so code that caught PyYAML's errors keeps catching it."""

    def __init__(self, message: str, line: int = 0, column: int = 0) -> None:
        super().__init__(message)
        self.line = line
        self.column = column


def _where(source: str, mark: Any) -> tuple[str, int, int]:
    if mark is None:
        return source, 0, 0
    line, col = int(mark.line) + 1, int(mark.column) + 1
    return f"{source}:{line}:{col}", line, col


def _error(source: str, mark: Any, problem: str) -> YamlError:
    where, line, col = _where(source, mark)
    return YamlError(f"{where}: {' '.join(problem.split())}", line, col)


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader that refuses anchors, aliases, merge keys, duplicate keys and deep nesting."""

    source = "<yaml>"

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise _error(
                self.source,
                event.start_mark,
                f"alias *{event.anchor} refused: aliases and anchors are not "
                "allowed in this file (they can expand without bound); write the value out",
            )
        anchor = getattr(event, "anchor", None)
        if anchor is not None:
            raise _error(
                self.source,
                event.start_mark,
                f"anchor &{anchor} refused: anchors and aliases are not allowed "
                "in this file (they can expand without bound); write the value out",
            )
        nested = isinstance(event, yaml.SequenceStartEvent | yaml.MappingStartEvent)
        if nested:
            self._depth += 1
            if self._depth > MAX_DEPTH:
                raise _error(self.source, event.start_mark, f"nested deeper than {MAX_DEPTH} levels")
        try:
            return super().compose_node(parent, index)
        finally:
            if nested:
                self._depth -= 1

    def flatten_mapping(self, node: Any) -> None:
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                raise _error(
                    self.source, key_node.start_mark, "merge key '<<' refused: write the keys out in this mapping"
                )
            if isinstance(key_node, yaml.ScalarNode):
                key = (key_node.tag, key_node.value)
                if key in seen:
                    first = seen[key]
                    raise _error(
                        self.source,
                        key_node.start_mark,
                        f"duplicate key {key_node.value!r} (first at line {first.line + 1}); give each key once",
                    )
                seen[key] = key_node.start_mark
        super().flatten_mapping(node)


def load_yaml(text: str, source: str = "<yaml>") -> Any:
    """Parse one YAML document from `text` with the bounds above; `source` names it in errors (a path)."""
    if len(text) > MAX_BYTES:
        raise YamlError(f"{source}: {len(text)} characters, more than the {MAX_BYTES} accepted for this file")
    loader_cls = type("_Loader", (_BoundedLoader,), {"source": source})
    loader = loader_cls(text)
    try:
        return loader.get_single_data()
    except YamlError:
        raise
    except yaml.MarkedYAMLError as exc:
        problem = exc.problem or "invalid YAML"
        if exc.context:
            problem = f"{problem} ({exc.context})"
        raise _error(source, exc.problem_mark or exc.context_mark, f"not valid YAML: {problem}") from exc
    except yaml.YAMLError as exc:
        raise YamlError(f"{source}: not valid YAML: {' '.join(str(exc).split())}") from exc
    finally:
        loader.dispose()


def load_yaml_file(path: str | Path) -> Any:
    """Read `path` as UTF-8 (at most `MAX_BYTES`) and parse it with `load_yaml`; every failure is a `YamlError`."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_BYTES:
            raise YamlError(f"{p}: {size} bytes, more than the {MAX_BYTES} accepted for this file")
        text = p.read_bytes().decode("utf-8")
    except OSError as exc:
        raise YamlError(f"cannot read {p}: {exc.strerror or exc}; check the path") from exc
    except UnicodeDecodeError as exc:
        raise YamlError(f"{p}: not UTF-8 text (byte {exc.start}); save the file as UTF-8") from exc
    return load_yaml(text, str(p))
