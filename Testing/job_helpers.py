"""The job tests' tiny case, and waiting on worker processes: whether one still runs, polling for a condition."""

from __future__ import annotations

import os
import time

import numpy as np

from SDFCARLib.geometry import CArmView, Geometry, VolumeGrid
from SDFCARLib.phantoms import Branch, CentrelineTree, make_case


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def wait_for(predicate, timeout: float, interval: float = 0.05) -> bool:
    """Poll ``predicate`` until it holds or ``timeout`` seconds pass; its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(interval)
    return predicate()


def tiny_job_case():
    """A tube in a 24³ grid of 2 mm seen from LAO 30 and RAO 30 on 64² detectors: a run of a few seconds."""
    grid = VolumeGrid((24, 24, 24), (2.0, 2.0, 2.0))
    views = [CArmView(a, 0.0, 1000.0, 750.0, (1.0, 1.0), (64, 64)) for a in (30.0, -30.0)]
    tube = CentrelineTree([Branch(np.array([[-12.0, 0, -10], [10.0, 4, 12]]), np.array([3.0, 2.5]))])
    return make_case(tube, Geometry(grid, views))
