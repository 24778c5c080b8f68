"""Answers kept in the machine's cache between processes (magrun.answers): computed once,
read back to the last bit, computed again for other inputs, other code or a damaged file."""

from __future__ import annotations

import math
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import pytest

from magrun import answers, trial
from magrun.field.coils import CoilSystem
from magrun.robot import load_robot


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(tmp_path))
    return tmp_path / "answers"


def _counted(numbers: tuple[float, ...]):
    calls: list[int] = []

    def compute() -> tuple[float, ...]:
        calls.append(1)
        return numbers

    return compute, calls


def test_an_answer_is_computed_once_and_read_back_to_the_last_bit(cache: Path) -> None:
    numbers = (math.pi / 7, 1e-300, -2.5e17, 0.1 + 0.2)
    compute, calls = _counted(numbers)
    assert answers.remembered("t", [b"a", b"b"], compute, 4) == numbers
    assert answers.remembered("t", [b"a", b"b"], compute, 4) == numbers  # from the file
    assert len(calls) == 1
    assert len(list(cache.glob("t-*.json"))) == 1
    assert not list(cache.glob(".*"))  # no temporary file left
    answers.remembered("t", [b"ab"], compute, 4)  # other inputs (not the same bytes joined)
    answers.remembered("t", [b"b", b"a"], compute, 4)
    assert len(calls) == 3


def test_changed_code_or_a_damaged_file_computes_it_again(
    cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    compute, calls = _counted((1.5, 2.5))
    answers.remembered("t", [b"x"], compute, 2)
    (path,) = cache.glob("t-*.json")
    damaged_files = ["[1.5, ", '["1.5", 2.5]', "[NaN, 1.0]", "{}", "[1.5]", "[1.5, 2.5, 3.5]",
                     "[" * 100_000 + "]" * 100_000]  # fmt: skip
    for damaged in damaged_files:
        path.write_text(damaged)
        assert answers.remembered("t", [b"x"], compute, 2) == (1.5, 2.5)
    assert len(calls) == 1 + len(damaged_files)
    assert path.read_text() == "[1.5, 2.5]"  # replaced by the computed answer
    monkeypatch.setattr(answers, "package_digest", lambda: "another version of magrun")
    answers.remembered("t", [b"x"], compute, 2)
    assert len(calls) == 2 + len(damaged_files)
    with pytest.raises(ValueError, match="3 numbers computed where 2 are kept"):
        answers.remembered("u", [b"x"], _counted((1.0, 2.0, 3.0))[0], 2)
    compute_nan, _ = _counted((math.nan,))
    assert math.isnan(answers.remembered("n", [b"x"], compute_nan, 1)[0])
    assert not list(cache.glob("n-*"))  # not kept: a NaN is no answer to read back


def test_a_system_file_changed_by_content_is_another_input(tmp_path: Path) -> None:
    folder = tmp_path / "system"
    folder.mkdir()
    (folder / "maps.txt").write_text("1 2 3")
    before = answers.files_digest(folder)
    (folder / "maps.txt").write_text("1 2 4")
    assert answers.files_digest(folder) != before
    assert answers.files_digest(folder / "maps.txt") == answers.files_digest(folder)
    assert answers.files_digest(None) != before
    os.mkfifo(folder / "pipe")  # not a file: not read (reading it would wait for a writer)
    assert answers.files_digest(folder) == answers.files_digest(folder / "maps.txt")


def test_the_typical_wrench_from_the_cache_is_the_computed_one(
    cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A second process's answer (the process's own memory cleared) comes from the file, not
    the linear programs, and equals the computed one exactly; other limits are computed."""
    coils, robot = CoilSystem.load(), load_robot("drug_delivery")
    monkeypatch.setattr(trial, "_WRENCH", {})
    computed = trial.typical_wrench(coils, robot)
    monkeypatch.setattr(trial, "_WRENCH", {})

    def no_lp(*args: object, **kwargs: object) -> None:
        raise AssertionError("computed again")

    monkeypatch.setattr("magrun.field.capability.workspace_capability", no_lp)
    assert trial.typical_wrench(coils, robot) == computed
    weaker = cast(CoilSystem, SimpleNamespace(folder=None, max_current=coils.max_current / 2))
    with pytest.raises(AssertionError, match="computed again"):
        trial.typical_wrench(weaker, robot)


def test_the_planned_headings_and_the_reach_from_the_cache_are_the_computed_ones(
    cache: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """On three coils that cannot hold the S's own heading, a second process's planned
    reference (its memory cleared) is built from the kept heading offsets, not the linear
    programs, and equals the computed one to the last bit, as does its factor; the reference
    is reachable, and that verdict too comes from the file. A reference the coils cannot
    follow is not kept: its error is found again, with the same message, every time."""
    import numpy as np
    from test_capability import ROBOT, TRI

    from magrun.field.capability import held_reference
    from magrun.field.lut import LookupTableFieldModel
    from magrun.field.mpem import import_mpem
    from magrun.scene import s_trajectory

    (tmp_path / "tri.yaml").write_text(TRI)
    folder = import_mpem(tmp_path / "tri.yaml", tmp_path / "tri", 0.0, (0.0, 0.0), 10e-3)
    coils = CoilSystem.load(folder)
    reference = s_trajectory(size=8e-3, speed=0.5e-3)
    for memory in ("_PLANNED", "_REACH"):
        monkeypatch.setattr(trial, memory, {})
    trial.check_reach(coils, reference, ROBOT)
    computed = []  # what the linear programs gave, and for what

    def held(model: Any, *args: Any) -> Any:
        computed.append((model, args, held_reference(model, *args)))
        return computed[-1][-1]

    monkeypatch.setattr("magrun.field.capability.held_reference", held)
    planned, factor = trial.planned_reference(coils, reference, ROBOT)
    assert planned is not reference  # headings turned: the offsets matter
    ((model, args, direct),) = computed
    assert isinstance(model, LookupTableFieldModel)  # the system's own tables
    assert model.coils.folder == coils.folder
    assert args == (ROBOT, coils.max_current, reference)
    assert np.array_equal(planned.poses, direct.trajectory.poses)
    assert factor == direct.median_factor
    for memory in ("_PLANNED", "_REACH"):
        monkeypatch.setattr(trial, memory, {})

    def no_lp(*args: object, **kwargs: object) -> None:
        raise AssertionError("computed again")

    monkeypatch.setattr("magrun.field.capability.held_reference", no_lp)
    monkeypatch.setattr("magrun.field.capability.trajectory_capability", no_lp)
    trial.check_reach(coils, reference, ROBOT)
    again, factor_again = trial.planned_reference(coils, reference, ROBOT)
    assert factor_again == factor
    # a kept verdict that is not one, or headings of another count, are checked again
    (verdict,) = cache.glob("reachable-*.json")
    (headings,) = cache.glob("planned_headings-*.json")
    verdict.write_text("[0.5]")
    headings.write_text("[8.0, 0.1, 0.2]")
    for memory in ("_PLANNED", "_REACH"):
        monkeypatch.setattr(trial, memory, {})
    with pytest.raises(AssertionError, match="computed again"):
        trial.check_reach(coils, reference, ROBOT)
    with pytest.raises(AssertionError, match="computed again"):
        trial.planned_reference(coils, reference, ROBOT)
    assert np.array_equal(again.t, planned.t)
    assert np.array_equal(again.poses, planned.poses)

    monkeypatch.undo()
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(cache.parent))
    fast = s_trajectory(size=8e-3, speed=50e-3)
    messages = []
    for _ in range(2):
        monkeypatch.setattr(trial, "_REACH", {})
        with pytest.raises(trial.RunError) as err:
            trial.check_reach(coils, fast, ROBOT)
        messages.append(str(err.value))
    assert messages[0] == messages[1]
    assert len(list(cache.glob("reachable-*.json"))) == 1  # the reachable S's alone


def test_a_reference_whose_headings_hold_is_planned_as_itself(
    cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the coils hold a reference's own headings, its planned reference is the very
    object asked about, also for a second trial's equal reference: a trial knows its
    headings were turned by comparing the two objects (a remembered equal object once made
    the second trial of a protocol tune its NMPC for turned headings)."""
    from magrun.scene import s_trajectory

    coils, robot = CoilSystem.load(), load_robot("magnet")
    monkeypatch.setattr(trial, "_PLANNED", {})
    for _ in range(2):  # computed, then remembered in the process
        reference = s_trajectory()
        planned, factor = trial.planned_reference(coils, reference, robot)
        assert planned is reference
        assert factor > 1.0
    monkeypatch.setattr(trial, "_PLANNED", {})
    reference = s_trajectory()
    assert trial.planned_reference(coils, reference, robot)[0] is reference  # from the file
