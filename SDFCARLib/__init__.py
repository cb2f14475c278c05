"""SDFCARLib — 3D coronary artery reconstruction from two X-ray angiography views (SDF-CAR).

Pure Python (torch, scikit-image, scipy): no Qt and no Slicer application, so the same
code runs in Slicer's Python, in scripts, on the command line and in tests.
"""

__version__ = "0.1.0"
