"""Compiling ahead what a campaign's trials would compile on first use (``magrun build``).

A trial compiles two things the first time a machine runs it, into the user cache
(:func:`magrun.compiled.cache_dir`): the NMPC's C kernel and the CasADi functions around it
(one library per distinct problem: system, robot, horizon, tuning; keyed by the generated
source, :mod:`magrun.compiled`), and the simulated plant's Numba loop (once per machine,
:mod:`magrun.rigs.kernel`). Both take seconds to a minute, spent in the first trial that
needs them. :func:`build` spends them ahead: for each distinct controller configuration of
the given protocols (every method and condition, quick runs included) it assembles the trial
as ``magrun run`` does and runs its first ticks on the simulated rig, nothing recorded. What
is cached already is loaded, not rebuilt, so a second build is quick.

Without a C compiler (``cc``, or ``$CC``) nothing can be compiled: the NMPC then runs in
CasADi's virtual machine (the same results, several times slower) and :func:`build` says so
(:attr:`BuildReport.compiler`).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from magrun.compiled import CC, CompileWarning, cache_dir, compilation_enabled
from magrun.protocol import Protocol, Trial
from magrun.trial import assemble, controller_tuning, system_of, trial_threads

#: control ticks each variant runs: the first tick builds the plan, the second reuses it
TICKS = 2


@dataclass
class BuildReport:
    """What :func:`build` did: the variants it ran, per protocol, and what went wrong."""

    variants: dict[str, int] = field(default_factory=dict)  # protocol name → variants built
    seconds: float = 0.0
    compiler: bool = True  # a C compiler was there (and MAGRUN_COMPILE is not 0)
    warnings: list[str] = field(default_factory=list)  # compile failures, one line each


def variants(protocol: Protocol, quick: bool = False) -> list[Trial]:
    """One trial per distinct controller configuration of ``protocol`` (method, tuning and
    the condition's part of it; quick runs' conditions included, or with ``quick`` only
    those), shortened to :data:`TICKS` control ticks."""
    system = system_of(protocol)
    short = protocol.model_copy(update={"duration_s": (TICKS - 1) / protocol.controller.rate_hz})
    seen: set[tuple[str, str]] = set()
    out = []
    trials = protocol.expand(quick=True) if quick else protocol.expand()
    for trial in [*trials, *protocol.expand(quick=True)]:
        if trial.index:
            continue
        _, _, config, *_ = controller_tuning(trial, system)
        key = (trial.method, repr(config))
        if key in seen:
            continue
        seen.add(key)
        out.append(trial.model_copy(update={"protocol": short, "quick": False}))
    return out


def build(
    protocols: Sequence[Protocol],
    quick: bool = False,
    progress: Callable[[str, int, int], None] | None = None,
) -> BuildReport:
    """Compile (or load from the cache) everything the trials of ``protocols`` (with
    ``quick``: their quick runs) compile, by assembling each of their :func:`variants` and
    running its first ticks; ``progress`` gets (protocol name, variants done, of it)."""
    report = BuildReport(compiler=compilation_enabled())
    t0 = time.perf_counter()
    for protocol in protocols:
        trials = variants(protocol, quick)
        for k, trial in enumerate(trials):
            with warnings.catch_warnings(record=True) as caught, trial_threads(1):
                warnings.simplefilter("always", CompileWarning)
                assemble(trial).run()
            for w in caught:
                if issubclass(w.category, CompileWarning):
                    line = str(w.message).splitlines()[0]
                    if line not in report.warnings:
                        report.warnings.append(line)
                else:
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            if progress is not None:
                progress(protocol.name, k + 1, len(trials))
        report.variants[protocol.name] = len(trials)
    report.seconds = time.perf_counter() - t0
    return report


def where() -> str:
    """The cache folder and the compiler, for messages."""
    return f"{cache_dir()} (compiler: {CC})"
