"""Load a YAML file into a pydantic model, with errors that name the file, line and field.

    >>> from magrun.yamlio import load_yaml_model
    >>> spec = load_yaml_model("coils.yaml", CoilSystemSpec)   # doctest: +SKIP
    YamlModelError: coils.yaml:23: coil_types.small.turns: Input should be greater than 0

PyYAML's node tree keeps the position of every key and value; pydantic reports each error's
location as a path of keys and indices. Walking the path through the node tree gives the line.
"""

from __future__ import annotations

import difflib
import json
import re
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from magrun.files import NotRegularFileError, open_binary

if typing.TYPE_CHECKING:
    from numpy.typing import NDArray

M = TypeVar("M", bound=BaseModel)

#: problems listed for one document: locating each walks the document, so a file of 50,000
#: unknown keys would take minutes; the rest are counted
MAX_PROBLEMS = 50


class YamlModelError(ValueError):
    """A YAML document that is unreadable or invalid; one ``file:line: field: message`` per line."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


def _locate(
    root: yaml.Node | None, loc: tuple[int | str, ...]
) -> tuple[int | None, tuple[int | str, ...]]:
    """1-based line of the deepest node on ``loc`` in the document, and ``loc`` as the user
    wrote it: parts that are not keys of the document (pydantic's tags of a discriminated
    union, e.g. ``workspace.spine_phantom.phantom``) are dropped, unless last (a missing key).
    An empty document is line 1.
    """
    node, line = root, (root.start_mark.line + 1) if root is not None else 1
    shown: list[int | str] = []
    for i, key in enumerate(loc):
        nxt = None
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    # an unknown key is reported at the key itself; others at their value
                    nxt, line = v, k.start_mark.line + 1
                    break
            if nxt is None and i + 1 < len(loc) and isinstance(key, str):
                continue  # a union tag, not a key: look for the next part here
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            nxt = node.value[key]
            line = nxt.start_mark.line + 1
        shown.append(key)
        if nxt is None:
            shown.extend(loc[i + 1 :])
            break
        node = nxt
    return line, tuple(shown)


#: what a key of a magrun document looks like; anything else is not echoed in an error (a file
#: that is not magrun's, say /etc/shadow named as a robots file, would be printed line by line)
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]{0,63}")


def _shown(part: str) -> str:
    return part if _KEY.fullmatch(part) else "(a key that is not a name)"


def _field_name(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        part = part if isinstance(part, int) else _shown(part)
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(document)"


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic models an annotation can hold (through unions, Annotated, lists, dicts)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models_in(arg)]


def _known_keys(model: type[BaseModel], parent: tuple[int | str, ...]) -> set[str]:
    """The keys the models at ``parent`` (a pydantic error location) accept."""
    models = [model]
    for part in parent:
        fields = [m.model_fields[part] for m in models if isinstance(part, str)
                  and part in m.model_fields]  # fmt: skip
        inner = [m for f in fields for m in _models_in(f.annotation)]
        if inner:
            models = inner
        # else: a list index, a dict key or a union's tag: the same models hold
    return {name for m in models for name in m.model_fields}


def _message(model: type[BaseModel], err: Any) -> str:
    """pydantic's message (a validator's own without pydantic's "Value error, " before it),
    with a "did you mean" for a misspelt key."""
    msg = str(err["msg"]).removeprefix("Value error, ")
    loc = tuple(err["loc"])
    if err["type"] == "extra_forbidden" and loc and isinstance(loc[-1], str):
        close = difflib.get_close_matches(loc[-1], _known_keys(model, loc[:-1]), n=1)
        if close:
            msg += f"; did you mean '{close[0]}'?"
    return msg


def parse_override(text: str) -> tuple[tuple[str, ...], Any]:
    """``KEY=VALUE`` with a dotted ``KEY`` (``controller.kalman.measurement_sigma_mm=0.5``):
    the key's parts and the value read as YAML (``0.5``, ``true``, ``null``, ``[3, 5]``,
    ``text``). Raises ``ValueError`` naming what is wrong."""
    key, sep, value = text.partition("=")
    parts = tuple(key.strip().split("."))
    if not sep or not all(parts):
        raise ValueError(f"--set {text!r}: expected KEY=VALUE with a dotted KEY, e.g. a.b=1")
    shown = text if len(text) <= 80 else text[:77] + "..."
    if len(value) > MAX_YAML_CHARS:
        raise ValueError(f"--set {shown!r}: the value is longer than {MAX_YAML_CHARS:,} characters")
    try:
        return parts, yaml.safe_load(value) if value.strip() else ""
    except yaml.YAMLError as exc:
        raise ValueError(f"--set {shown!r}: the value is not valid YAML") from exc
    except RecursionError as exc:  # PyYAML recurses once per nesting level
        raise ValueError(f"--set {shown!r}: the value is nested too deeply") from exc
    except ValueError as exc:  # an integer of more digits than Python converts
        raise ValueError(f"--set {shown!r}: the value is not valid YAML: {exc}") from exc


def _apply_overrides(data: Any, overrides: list[tuple[str, tuple[str, ...], Any]]) -> Any:
    """``data`` with each override set at its dotted path (mappings made where missing)."""
    for text, parts, value in overrides:
        if not isinstance(data, dict):
            raise YamlModelError([f"--set {text}: the document is not a mapping"])
        node = data
        for i, part in enumerate(parts[:-1]):
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                where = ".".join(parts[: i + 1])
                raise YamlModelError([f"--set {text}: {where} is a value, not a section"])
            node = child
        node[parts[-1]] = value
    return data


def _as_written(data: Any, loc: tuple[int | str, ...]) -> tuple[int | str, ...]:
    """``loc`` as the document (after the overrides) spells it: pydantic's tags of a
    discriminated union (``trajectory.out_and_back.speed_mm_s``) dropped, as :func:`_locate`
    drops them from the YAML nodes, unless last (a missing key)."""
    node, shown = data, []
    for i, key in enumerate(loc):
        if isinstance(node, dict) and isinstance(key, str) and key not in node and i + 1 < len(loc):
            continue  # a union tag: the next part is a key of this mapping
        shown.append(key)
        if isinstance(node, dict):
            node = node.get(key)
        elif isinstance(node, list) and isinstance(key, int) and 0 <= key < len(node):
            node = node[key]
        else:
            node = None
    return tuple(shown)


def _override_of(
    loc: tuple[int | str, ...], overrides: list[tuple[str, tuple[str, ...], Any]]
) -> tuple[str, str] | None:
    """The ``--set`` text an error at ``loc`` (union tags dropped: :func:`_as_written`) comes
    from, if one set that part, and the field to name."""
    shown = tuple(str(p) for p in loc)
    for text, parts, _ in overrides:
        n = min(len(parts), len(shown))
        if shown[:n] == parts[:n]:
            return text, _field_name(loc if len(loc) <= len(parts) else parts)
    return None


def validate_data(
    data: Any,
    model: type[M],
    source: str,
    context: dict[str, Any] | None = None,
    overrides: Sequence[str] = (),
    root: yaml.Node | None = None,
) -> M:
    """Validate ``data`` (a YAML or JSON document, as Python objects) with ``overrides``
    (``KEY=VALUE``, :func:`parse_override`) applied. Errors name ``source`` (and the line,
    given the document's YAML node tree ``root``), or the ``--set`` they come from."""
    parsed = []
    for text in overrides:
        try:
            parts, value = parse_override(text)
        except ValueError as exc:
            raise YamlModelError([str(exc)]) from exc
        parsed.append((text, parts, value))
    data = _apply_overrides(data if data is not None else {}, parsed)
    try:
        return model.model_validate(data, context=context)
    except RecursionError as exc:
        raise YamlModelError([f"{source}: nested too deeply to validate"]) from exc
    except ValidationError as exc:
        problems = []
        errors = exc.errors()
        for err in errors[:MAX_PROBLEMS]:  # each is located by a walk of the document
            loc = tuple(err["loc"])
            by = _override_of(_as_written(data, loc), parsed)
            if by is not None:
                problems.append(f"--set {by[0]}: {by[1]}: {_message(model, err)}")
                continue
            if root is not None:
                line, shown = _locate(root, loc)
                where = f"{source}:{line}"
            else:  # a JSON document (a recording's protocol): no lines, the same names
                where, shown = source, _as_written(data, loc)
            problems.append(f"{where}: {_field_name(shown)}: {_message(model, err)}")
        if len(errors) > MAX_PROBLEMS:
            problems.append(f"{source}: and {len(errors) - MAX_PROBLEMS:,} more problems")
        raise YamlModelError(problems) from exc


#: the largest YAML document magrun reads, characters (a protocol, a system, a robots file
#: is a few kB; this bounds the time and memory a hostile file can take)
MAX_YAML_CHARS = 4_000_000


def safe_yaml(text: str, source: str) -> tuple[yaml.Node | None, Any]:
    """The node tree (for the lines of errors) and the data of YAML ``text``: the one hardened
    reader of every YAML document magrun reads. Safe loader only (no tags that build Python
    objects), a size limit, and a :class:`YamlModelError` naming ``source`` (and the line
    where PyYAML knows it) for whatever is wrong: bad syntax, nesting too deep for the parser,
    a number too long to convert."""
    if len(text) > MAX_YAML_CHARS:
        problem = (
            f"{source}: not read: {len(text):,} characters, more than the "
            f"{MAX_YAML_CHARS:,} a YAML document may have"
        )
        raise YamlModelError([problem])
    try:
        root, data = _parse(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}:{mark.line + 1}" if mark is not None else source
        problem = getattr(exc, "problem", None) or str(exc)
        raise YamlModelError([f"{where}: not valid YAML: {problem}"]) from exc
    except RecursionError as exc:  # PyYAML's parser recurses once per nesting level
        raise YamlModelError([f"{source}: not valid YAML: nested too deeply"]) from exc
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise YamlModelError([f"{source}: not valid YAML: {exc}"]) from exc
    if root is not None:
        _refuse_duplicate_keys(root, source)
    return root, data


#: libyaml's parser (PyYAML's C extension: the same node tree and marks, 30 times faster than
#: the pure-Python one; it refuses nesting deeper than 1000 levels itself) with PyYAML's safe
#: constructor: no tags that build Python objects
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _parse(text: str) -> tuple[yaml.Node | None, Any]:
    """The node tree and the data of ``text``, parsed once (the data built from the tree, as
    ``yaml.safe_load`` builds it). A merge key (``<<``) is merged into the tree in place
    while the data is built, so where the text may hold one the data is built from a second
    parse and the tree stays as written, for the lines of errors."""
    loader = _LOADER(text)
    try:
        root = loader.get_single_node()
    finally:
        loader.dispose()
    if root is None:
        return None, None
    merges = "<<" in text
    loader = _LOADER(text if merges else "")
    try:
        return root, loader.construct_document(loader.get_single_node() if merges else root)
    finally:
        loader.dispose()


def _refuse_duplicate_keys(root: yaml.Node, source: str) -> None:
    """YAML requires a mapping's keys to be unique; PyYAML keeps the last silently, so a
    setting given twice (``seed: 1`` … ``seed: 7``) would run with a value the reader of the
    file's top did not expect. Walks the tree once (aliases are not re-entered)."""
    seen: set[int] = set()
    stack = [root]
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            keys: dict[str, int] = {}
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                    if key.value in keys:
                        raise YamlModelError(
                            [
                                f"{source}:{key.start_mark.line + 1}: {key.value}: given "
                                f"twice (first on line {keys[key.value]})"
                            ]
                        )
                    keys[key.value] = key.start_mark.line + 1
                stack += [key, value]
        elif isinstance(node, yaml.SequenceNode):
            stack += node.value


def safe_json(text: str, source: str, limit: int = MAX_YAML_CHARS) -> Any:
    """The data of JSON ``text``: the one hardened reader of the JSON magrun reads from
    files and recordings (a recorded protocol, a manifest, a model's or weights' metadata).
    A size limit, and a :class:`YamlModelError` naming ``source`` for whatever is wrong: bad
    syntax, nesting too deep for the decoder, a number too long to convert, NaN or infinity
    (not JSON, though Python's decoder takes them). An empty ``source`` names nothing (the
    caller's message names the file)."""
    at = f"{source}: " if source else ""
    if len(text) > limit:
        raise YamlModelError(
            [f"{at}not read: {len(text):,} characters, more than the {limit:,} allowed"]
        )

    def constant(name: str) -> Any:
        raise ValueError(f"{name} is not a JSON number")

    try:
        return json.loads(text, parse_constant=constant)
    except RecursionError as exc:  # the decoder recurses once per nesting level
        raise YamlModelError([f"{at}not valid JSON: nested too deeply"]) from exc
    except ValueError as exc:  # JSONDecodeError, an integer too long, NaN
        raise YamlModelError([f"{at}not valid JSON: {exc}"]) from exc


#: the most an .npz archive magrun reads may hold once unpacked, bytes (the shipped
#: reference maps and UNet weights are a few MB): a bound on a hostile archive's memory
MAX_NPZ_BYTES = 1 << 30


def check_npz(fh: typing.BinaryIO, written_by: str, limit: int = MAX_NPZ_BYTES) -> None:
    """Raise ``ValueError`` unless the open file ``fh`` is a zip archive (an ``.npz``) whose
    members unpack to at most ``limit`` bytes; ``written_by`` says which command writes one.
    Leaves ``fh`` at its start."""
    import zipfile

    if fh.read(4) != b"PK\x03\x04":
        raise ValueError(f"not an .npz archive ({written_by} writes one)")
    fh.seek(0)
    try:
        with zipfile.ZipFile(fh) as archive:
            size = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"not a readable .npz archive: {exc}") from exc
    if size > limit:
        raise ValueError(f"its arrays unpack to {size:,} bytes, more than the {limit:,} allowed")
    fh.seek(0)


def read_npz(path: str | Path, written_by: str) -> dict[str, NDArray[Any]]:
    """Every array of the ``.npz`` archive at ``path``, read into memory after
    :func:`check_npz` (a zip archive of bounded size) and without pickles; ``written_by``
    says which command writes one. Anything unreadable raises ``ValueError`` saying why."""
    import zipfile

    import numpy as np

    try:
        # open the file ourselves: np.load leaks its handle on a corrupt archive
        with open_binary(path) as fh:
            check_npz(fh, written_by)
            with np.load(fh, allow_pickle=False) as npz:
                return {name: np.asarray(npz[name]) for name in npz.files}
    except (OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"not a readable .npz archive: {exc}") from exc


def parse_yaml_model(
    text: str,
    model: type[M],
    source: str,
    context: dict[str, Any] | None = None,
    overrides: Sequence[str] = (),
) -> M:
    """Validate YAML ``text`` against ``model``; ``source`` names it in error messages.

    ``context`` reaches the model's validators (``ValidationInfo.context``), e.g. the folder
    that relative paths in the document are relative to. ``overrides`` (``KEY=VALUE``, a
    dotted key) replace values of the document before it is validated.
    """
    root, data = safe_yaml(text, source)
    if root is None:
        root = yaml.compose("{}", Loader=yaml.SafeLoader)
    return validate_data(data, model, source, context, overrides, root)


def load_yaml_model(
    path: str | Path,
    model: type[M],
    context: dict[str, Any] | None = None,
    overrides: Sequence[str] = (),
) -> M:
    """Read and validate a YAML file; every problem raises :class:`YamlModelError`."""
    return parse_yaml_model(read_text_file(path), model, str(path), context, overrides)


def read_text_file(path: str | Path, limit: int = MAX_YAML_CHARS) -> str:
    """The UTF-8 text of a regular file of at most ``limit`` characters, or a
    :class:`YamlModelError` naming it: a FIFO, a device or a folder is refused before it is
    read (:func:`open_binary`), and the read is bounded."""
    try:
        with open_binary(path) as fh:
            data = fh.read(4 * limit + 4)  # UTF-8: at most 4 bytes a character
        text = data.decode("utf-8")
    except NotRegularFileError as exc:
        raise YamlModelError([f"{path}: cannot read: not a regular file"]) from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise YamlModelError([f"{path}: cannot read: {exc}"]) from exc
    if len(text) > limit:
        raise YamlModelError([f"{path}: not read: more than the {limit:,} characters allowed"])
    return text
