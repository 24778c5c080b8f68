"""Analysis of magrun recordings: metrics, statistics, the paper's figures and a report.

It reads recordings (MCAP files and manifests) and data files only and never imports magrun's
control code, so it works on recordings made on any rig::

    import analysis
    data = analysis.load("recordings")            # Dataset: .trials, .samples, .problems
    analysis.write_results(data, "figures/results.csv")
    analysis.figures.draw_all(data, "figures")

Modules: :mod:`~analysis.load` (MCAP → pandas), :mod:`~analysis.metrics`,
:mod:`~analysis.stats`, :mod:`~analysis.figures`, :mod:`~analysis.report`,
:mod:`~analysis.replays` (``magrun replay``'s outputs beside the recordings).
"""

from analysis import figures, metrics, report, stats
from analysis.load import Dataset, Recording, RecordingError, load, read_recording
from analysis.report import results_table, write_results

__all__ = [
    "Dataset",
    "Recording",
    "RecordingError",
    "figures",
    "load",
    "metrics",
    "read_recording",
    "report",
    "results_table",
    "stats",
    "write_results",
]
