"""A run's configuration: ``BenchmarkConfig`` (its identity hash and reproducing command line),
``--set`` overrides, the suite's cases (``build_cases``) and the checks made before any work."""

from __future__ import annotations

import hashlib
import json
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional, Tuple

from .. import __version__
from .cases import (PROCEDURAL_SUITES, CaseSpec, GridOptions, default_centreline, label_volume_files, parse_suite,
                    protocol_geometry, volume_stem)
from .errors import BenchmarkError
from .registry import HULL
from ..settings import MODES, PROTOCOLS, ReconstructionError, make_settings, parse_setting_overrides

# Bump when a change to this harness changes what a row means; it enters the config hash.
HARNESS_VERSION = 1

DEFAULT_MODES = ("sdfcar", "neca", "occ-combined", "sdf-occ")

# Settings the harness sets itself; --set must not fight them.
_RESERVED_SETTINGS = {
    "mode": "choose modes with --modes",
    "seed": "seeds are fixed per case; choose the first with --seed",
    "steps": "use --steps",
    "preset": "use --preset",
    "threads": "use --threads-per-worker",
}


@dataclass
class BenchmarkConfig:
    suite: str
    out: Path
    modes: Tuple[str, ...] = DEFAULT_MODES
    preset: str = "fast"
    protocol: str = "paper"
    cases: Optional[int] = None  # None: 10 procedural, 1 for 721a, every file of a folder
    seed: int = 0
    steps: Optional[int] = None
    overrides: Dict[str, Any] = field(default_factory=dict)
    grid: GridOptions = field(default_factory=GridOptions)
    centreline: Optional[Path] = None
    scheduler: Optional[str] = None
    workers: Optional[int] = None
    threads_per_worker: int = 1
    overlays: int = 3
    retry_failed: bool = False
    progress: bool = True

    def identity(self) -> Dict[str, Any]:
        """What, besides the case and mode, determines a row's numbers.

        The preset is resolved into its settings, so that retuned preset values make new rows
        instead of resuming from rows computed with the old ones.
        """
        settings = make_settings(self.preset, steps=self.steps, **self.overrides).to_dict()
        for name in ("mode", "seed", "threads"):  # per row, or not affecting the numbers
            settings.pop(name, None)
        return {"harness": HARNESS_VERSION, "sdfcar": __version__, "protocol": self.protocol, "preset": self.preset,
                "steps": self.steps, "overrides": dict(sorted(self.overrides.items())), "grid": self.grid.to_dict(),
                "seed": self.seed, "settings": settings}

    def config_id(self) -> str:
        text = json.dumps(self.identity(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:10]

    def command_line(self) -> str:
        """The full command (defaults spelled out) that reproduces this run."""
        parts = ["python", "-m", "SDFCARLib", "benchmark", "--suite", self.suite, "--modes", ",".join(self.modes),
                 "--preset", self.preset, "--protocol", self.protocol, "--seed", str(self.seed), "--out", str(self.out)]
        if self.cases is not None:
            parts += ["--cases", str(self.cases)]
        if self.steps is not None:
            parts += ["--steps", str(self.steps)]
        for key, value in sorted(self.overrides.items()):
            parts += ["--set", f"{key}={json.dumps(value)}"]
        g = self.grid
        if g.volume_shape:
            parts += ["--volume-shape", *map(str, g.volume_shape)]
        if g.spacing_mm:
            parts += ["--spacing-mm", repr(g.spacing_mm)]
        if g.detector_shape:
            parts += ["--detector-shape", *map(str, g.detector_shape)]
        if g.detector_spacing_mm:
            parts += ["--detector-spacing-mm", repr(g.detector_spacing_mm)]
        if self.centreline is not None and self.suite == "721a":
            parts += ["--centreline", str(self.centreline)]
        return " ".join(shlex.quote(p) for p in parts)


def parse_overrides(items: Optional[Iterable[str]]) -> Dict[str, Any]:
    """``["learning_rate=1e-3", "device=cuda"]`` → typed optimiser overrides, checked against ``Settings``."""
    try:
        return parse_setting_overrides(items, reserved=_RESERVED_SETTINGS)
    except ReconstructionError as error:
        raise BenchmarkError(str(error)) from None


def build_cases(config: BenchmarkConfig) -> List[CaseSpec]:
    """The suite's cases in a fixed order, with their seeds."""
    kind, folder = parse_suite(config.suite)
    n = config.cases
    if n is not None and n < 1:
        raise BenchmarkError(f"--cases must be at least 1, got {n}")
    if kind in PROCEDURAL_SUITES:
        count = 10 if n is None else n
        prefix = kind.upper()
        return [CaseSpec(kind, f"{prefix}-{config.seed + i}", kind, config.seed + i, i) for i in range(count)]
    if kind == "721a":
        path = Path(config.centreline) if config.centreline else default_centreline()
        if not path.is_file():
            raise BenchmarkError(f"the 721a suite needs the 721A centreline (legacy VTK with radii); it is not at {path}: "
                                 "give its path with --centreline")
        count = 1 if n is None else n
        return [CaseSpec("721a", f"721A-s{config.seed + i}", "lad", config.seed + i, i, str(path.resolve())) for i in range(count)]
    cases: List[CaseSpec] = []
    for path in label_volume_files(folder):
        for tree in ("lad", "rca"):
            index = len(cases)
            cases.append(CaseSpec(config.suite, f"{volume_stem(path)}-{tree}", tree, config.seed + index, index,
                                  str(path.resolve()), tree))
    return cases if n is None else cases[:n]


def check_config(config: BenchmarkConfig) -> List[CaseSpec]:
    """Validate everything before any work (bad input changes nothing on disk); the cases."""
    if not config.modes:
        raise BenchmarkError(f"--modes is empty; choose from {', '.join(MODES)}")
    unknown = [m for m in config.modes if m not in MODES and m != HULL]
    if unknown:
        raise BenchmarkError(f"unknown mode(s) {', '.join(unknown)} in --modes; choose from {', '.join(MODES)} "
                             "(the visual hull baseline is always included)")
    if len(set(config.modes)) != len(config.modes):
        raise BenchmarkError(f"--modes lists a mode twice: {','.join(config.modes)}")
    if config.protocol not in PROTOCOLS:
        raise BenchmarkError(f"unknown protocol {config.protocol!r}; choose one of {', '.join(PROTOCOLS)}")
    if config.steps is not None and config.steps < 1:
        raise BenchmarkError(f"--steps must be at least 1, got {config.steps}")
    if config.workers is not None and config.workers < 1:
        raise BenchmarkError(f"--workers must be at least 1, got {config.workers}")
    if config.threads_per_worker < 1:
        raise BenchmarkError(f"--threads-per-worker must be at least 1, got {config.threads_per_worker}")
    if config.overlays < 0:
        raise BenchmarkError(f"--overlays must be 0 or more, got {config.overlays}")
    for mode in config.modes:
        if mode != HULL:
            try:
                make_settings(config.preset, mode=mode, steps=config.steps, **config.overrides)
            except (ValueError, TypeError) as exc:
                raise BenchmarkError(f"the optimiser settings are invalid: {exc}") from None
    device = str(config.overrides.get("device", "auto"))
    if device.startswith("cuda") and config.scheduler is None:  # a --scheduler's workers may have a GPU this one lacks
        import torch

        if not torch.cuda.is_available():
            raise BenchmarkError(f"--set device={device}: this machine has no CUDA GPU for the local cluster's workers; "
                                 "use --set device=cpu (or auto), or a --scheduler whose workers have one")
    kind, _ = parse_suite(config.suite)
    try:
        protocol_geometry(config.protocol, kind, config.grid)
    except ValueError as exc:
        raise BenchmarkError(f"the grid/detector overrides give an invalid geometry: {exc}") from None
    out = Path(config.out)
    if out.exists() and not out.is_dir():
        raise BenchmarkError(f"--out {out} is a file; give a folder")
    cases = build_cases(config)  # the user's own mistakes first, then what the machine lacks
    for extra in ("matplotlib", "distributed"):
        try:
            __import__(extra)
        except ImportError:
            raise BenchmarkError(f"the benchmark needs {extra}: pip install 'SDFCARLib[bench]' "
                                 "(dask[distributed] and matplotlib)") from None
    return cases
