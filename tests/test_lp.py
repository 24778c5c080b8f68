"""The capability's linear programs straight to scipy's HiGHS (magrun.field.lp).

The direct path must give what :func:`scipy.optimize.milp` gives, bit for bit: on random
LPs of the capability's shape (feasible and not, zeros in the matrix), on every LP the
workspace map of an imported three-coil system with a background field solves, and after
a model HiGHS refuses.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_emns import SYNTHETIC

from magrun.field import capability, lp
from magrun.field.coils import CoilSystem
from magrun.field.mpem import import_mpem
from magrun.field.system import load_system
from magrun.robot import load_robot

pytestmark = pytest.mark.skipif(
    not lp.direct(), reason="this scipy has no HiGHS bindings magrun can use directly"
)


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


def _random_lp(rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """An LP of the capability's form: max the last variable over one inequality and
    three equalities, the currents boxed, a tenth of the matrix's entries zero."""
    a = rng.normal(size=(4, n + 1))
    a[rng.random(a.shape) < 0.1] = 0.0
    b = rng.normal(size=3) * rng.choice([0.01, 1.0, 100.0])
    cost = np.zeros(n + 1)
    cost[n] = -1.0
    limits = rng.uniform(0.5, 20.0, n)
    return (
        cost, a, np.r_[-np.inf, b], np.r_[rng.normal(), b], np.r_[-limits, 0.0],
        np.r_[limits, capability.SPEED_CAP],
    )  # fmt: skip


def test_random_lps_are_solved_as_milp_solves_them() -> None:
    rng = np.random.default_rng(20261201)
    solved = 0
    for k in range(600):
        problem = _random_lp(rng, n=3 + k % 8)
        direct = lp.solve_lp(*problem)
        assert _same(direct, lp.solve_lp(*problem, through_milp=True)), k
        solved += direct is not None
    # both outcomes are exercised: some LPs have a solution, some none
    assert 0 < solved < 600


def test_the_capability_maps_lps_are_solved_as_milp_solves_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every LP of a workspace map with a speed asked (its heading search included) on three
    unsymmetric coils with a background field, solved again through milp."""
    (tmp_path / "three.yaml").write_text(SYNTHETIC)
    folder = import_mpem(tmp_path / "three.yaml", tmp_path / "s", 0.0, (0.0, 0.0), 10e-3)
    coils = CoilSystem.load(folder)
    seen: list[tuple[Any, ...]] = []
    solve = lp.solve_lp

    def recording(*args: Any, **kwargs: Any) -> Any:
        seen.append(args)
        return solve(*args, **kwargs)

    monkeypatch.setattr(capability, "solve_lp", recording)
    model = load_system(folder).models[1]
    robot = load_robot("micro_magnet")
    capability.workspace_capability(model, robot, coils.max_current, 8e-3, 4, 6, speed=2e-3)
    answers = [solve(*args) for args in seen]
    assert len(seen) > 100
    assert any(x is not None for x in answers)
    for k, args in enumerate(seen):
        assert _same(answers[k], solve(*args, through_milp=True)), k


def test_a_refused_model_returns_nothing_and_leaves_no_stale_answer() -> None:
    """A NaN row bound: HiGHS refuses the model; the solver object the thread reuses must
    neither answer it with the previous LP's solution nor keep it for the next."""
    good = _random_lp(np.random.default_rng(3), n=8)
    first = lp.solve_lp(*good)
    assert first is not None
    bad = list(good)
    bad[2] = good[2].copy()
    bad[2][1] = np.nan
    assert lp.solve_lp(*bad) is None
    assert lp.solve_lp(*bad, through_milp=True) is None
    assert np.array_equal(lp.solve_lp(*good), first)
