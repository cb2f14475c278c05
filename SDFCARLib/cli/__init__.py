"""Command line: ``python -m SDFCARLib <command>`` (also installed as ``sdfcar``).

Commands
    reconstruct        the views' masks (or line integrals, two or more views) + GEOM.json or XA runs → result folder
    simulate           a label volume or centreline + GEOM.json → masks and line integrals
    evaluate           a prediction against a label: every metric, and the visual-hull baseline
    demo               reconstruct the bundled sample case and compare with its ground truth
    geometry-template  write a GEOM.json for a standard protocol or any view angles, as a starting point
    geometry           XA DICOM runs (one per view, any number) → GEOM.json, every value with its source tag
    segment            one XA DICOM frame (or a plain image) → vessel mask, frame and overlay PNGs
    analyse            a result folder → 3D-QCA: centrelines, diameters, lesions, best view
    benchmark          many simulated cases × modes → results.csv, summary.md (the paper's tables)

Exit status: 0 success; 2 bad input (one line ``error: …`` on stderr, no traceback unless
``--verbose``); 130 cancelled with Ctrl-C (nothing written); 1 an unexpected failure.
This interface is a contract other tools drive: add options, do not change existing ones.

Layout: ``parser`` (every command's options, ``main``), ``reconstruct`` (reconstruct, geometry,
demo, analyse), ``data`` (segment, simulate, evaluate, geometry-template), ``common`` (progress,
cancellation, tables). Modules that load torch are imported inside the commands that need them,
so that ``--help`` and the light commands start without it.
"""

from __future__ import annotations

from .common import metrics_table
from .parser import build_parser, main

__all__ = ["build_parser", "main", "metrics_table"]
