"""Load a YAML file into a pydantic model, with errors that name the file, line and field.

    >>> from magrun.yamlio import load_yaml_model
    >>> spec = load_yaml_model("coils.yaml", CoilSystemSpec)   # doctest: +SKIP
    YamlModelError: coils.yaml:23: coil_types.small.turns: Input should be greater than 0

PyYAML's node tree keeps the position of every key and value; pydantic reports each error's
location as a path of keys and indices. Walking the path through the node tree gives the line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)


class YamlModelError(ValueError):
    """A YAML document that is unreadable or invalid; one ``file:line: field: message`` per line."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


def _line_of(root: yaml.Node | None, loc: tuple[int | str, ...]) -> int | None:
    """1-based line of the deepest node on ``loc`` that exists in the document."""
    node, line = root, (root.start_mark.line + 1) if root is not None else None
    for key in loc:
        nxt = None
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    # an unknown key is reported at the key itself; others at their value
                    nxt, line = v, k.start_mark.line + 1
                    break
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            nxt = node.value[key]
            line = nxt.start_mark.line + 1
        if nxt is None:
            break
        node = nxt
    return line


def _field_name(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(document)"


def parse_yaml_model(text: str, model: type[M], source: str) -> M:
    """Validate YAML ``text`` against ``model``; ``source`` names it in error messages."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data: Any = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise YamlModelError([f"{where}: not valid YAML: {problem}"]) from exc
    try:
        return model.model_validate(data if data is not None else {})
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = tuple(err["loc"])
            line = _line_of(root, loc)
            where = f"{source}:{line}" if line is not None else source
            problems.append(f"{where}: {_field_name(loc)}: {err['msg']}")
        raise YamlModelError(problems) from exc


def load_yaml_model(path: str | Path, model: type[M]) -> M:
    """Read and validate a YAML file; every problem raises :class:`YamlModelError`."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise YamlModelError([f"{path}: cannot read: {exc}"]) from exc
    return parse_yaml_model(text, model, str(path))
