"""Analysis of magrun recordings: metrics, statistics, figures and reports.

It reads recordings (MCAP files and manifests) and shipped data files only and never imports
the control code, so it works on recordings made on any rig. Its modules arrive with the
analysis work (load, metrics, stats, figures, report); for now the package only reserves the
import name.
"""
