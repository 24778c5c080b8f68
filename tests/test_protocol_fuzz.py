"""Hostile protocol files: whatever the YAML, the only failure is a clean validation error.

Three generators (hypothesis): the shipped protocols with one field replaced by an arbitrary
YAML value (wrong types, huge or non-finite numbers, nested junk), arbitrary YAML documents,
and arbitrary text. Every outcome must be a :class:`Protocol` or a :class:`YamlModelError`
whose every line names the file (and a line number for documents that parse as YAML).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from magrun.cli import cli
from magrun.protocol import MAX_TRIALS, Protocol
from magrun.yamlio import YamlModelError, parse_yaml_model

PROTOCOLS = Path(__file__).resolve().parents[1] / "protocols"
SHIPPED = {p.stem: yaml.safe_load(p.read_text()) for p in sorted(PROTOCOLS.glob("*.yaml"))}
SOURCE = "fuzz.yaml"


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path into a document (dict keys and list indices), the root excluded."""
    out = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out.append((*prefix, k))
            out.extend(_paths(v, (*prefix, k)))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out.append((*prefix, i))
            out.extend(_paths(v, (*prefix, i)))
    return out


FIELDS = sorted({(name, path) for name, doc in SHIPPED.items() for path in _paths(doc)}, key=str)

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=30),
    st.sampled_from(["phantoms/spine_l3l4.yaml", "/dev/null", ".", "..", "s_curve", "proposed"]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=10), inner, max_size=5)
    ),
    max_leaves=15,
)


def _check(text: str) -> None:
    problems: list[str] | None = None
    try:
        parse_yaml_model(text, Protocol, SOURCE, context={"base_dir": str(PROTOCOLS)})
    except YamlModelError as exc:  # the one allowed failure; anything else fails the test
        problems = exc.problems
    if problems is not None:
        assert problems
        assert all(line.startswith(SOURCE) for line in problems)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(field=st.sampled_from(FIELDS), value=values)
def test_a_shipped_protocol_with_any_field_replaced(field: tuple[str, tuple], value: Any) -> None:
    name, path = field
    doc = copy.deepcopy(SHIPPED[name])
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    _check(yaml.safe_dump(doc, allow_unicode=True))


@settings(max_examples=200, deadline=None)
@given(doc=st.dictionaries(st.sampled_from([*Protocol.model_fields, "x"]), values, max_size=8))
def test_any_document_with_protocol_keys(doc: dict[str, Any]) -> None:
    _check(yaml.safe_dump(doc, allow_unicode=True))


@settings(max_examples=300, deadline=None)
@given(text=st.text(max_size=400))
def test_any_text(text: str) -> None:
    _check(text)


def test_hostile_yaml_constructs_are_refused_cleanly() -> None:
    """Python object tags never construct anything; alias bombs and deep nesting end cleanly."""
    for text in (
        "!!python/object/apply:os.system ['echo hacked']\n",
        "name: !!python/name:os.system\n",
        "a: &a [*a]\n",
        "x: " + "[" * 5000 + "]" * 5000 + "\n",
        'a: &a ["x","x","x","x","x","x","x","x","x"]\n'
        + "".join(f"{c}: &{c} [*{p},*{p},*{p},*{p},*{p},*{p},*{p},*{p},*{p}]\n"
                  for p, c in zip("abcdefg", "bcdefgh", strict=True)),
    ):  # fmt: skip
        with pytest.raises(YamlModelError):
            parse_yaml_model(text, Protocol, SOURCE)


def test_a_huge_sweep_is_refused_before_anything_runs(tmp_path: Path) -> None:
    doc = copy.deepcopy(SHIPPED["rate"])
    doc["sweep"] = {
        "tracking_rate_hz": [r / 4 for r in range(1, 101)],  # 0.25 … 25 Hz
        "noise_sigma_mm": [i / 10 for i in range(50)],
    }
    doc.pop("conditions", None)
    path = tmp_path / "huge.yaml"
    path.write_text(yaml.safe_dump(doc))
    n = 100 * 50 * len(doc["methods"]) * doc["trials"]
    assert n > MAX_TRIALS
    with pytest.raises(YamlModelError, match=f"{n:,} trials"):
        parse_yaml_model(path.read_text(), Protocol, str(path))
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["run", str(path), "--out", str(out)])
    assert result.exit_code == 2
    assert "split it into several protocol files" in result.output
    assert not out.exists()
