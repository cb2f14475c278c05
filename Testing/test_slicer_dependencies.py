"""Every third-party module SDFCAR imports inside Slicer is bundled with Slicer or in REQUIREMENTS.

Slicer's Python holds only what Slicer bundles until the module installs ``REQUIREMENTS``
(SDFCAR/SDFCAR.py) on the first Apply or Sample Data load. A module missing from both fails
only at the end of a reconstruction (the worker writes its results) or when the sample case
loads, so three checks, from cheap to faithful:

1. static: the imports of every SDFCARLib module reachable from the worker's entry point
   (``python -m SDFCARLib.jobs worker``) and from SDFCAR.py, function-level imports included;
2. blocked imports: the worker and the module's library calls run in a subprocess whose import
   system refuses, and records, any third-party module SDFCARLib imports that is neither bundled
   nor required — even one whose ImportError the code catches;
3. a fresh virtual environment (no site packages) holding only the distributions of the Slicer
   bundle and of REQUIREMENTS with their dependencies (linked from this environment's installed
   copies, so it takes seconds and no network) runs the worker end to end on a tiny case.

Check 3 does not ask pip to resolve REQUIREMENTS; the test that maps each requirement's
distribution to its import name covers what pip needs. With SDFCAR_PIP_VENV_TEST=1 a last test
builds the environment with pip instead (about 1.5 min and 1.2 GB the first time; kept under the
temporary folder, or SDFCAR_SLICER_VENV_DIR, keyed by the package list, and reused);
SDFCAR_TORCH_SPEC chooses the torch build (default: the version installed here).
"""

from __future__ import annotations

import ast
import hashlib
import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "SDFCAR" / "SDFCAR.py"
LIBRARY = ROOT / "SDFCARLib"
WORKER_ENTRY = "SDFCARLib.jobs"  # ReconstructionJob.launch runs "python -m SDFCARLib.jobs worker DIR"

# What every supported Slicer (5.4.0 to main) bundles in its Python, by import name. Python
# packages: the pinned requirements of SuperBuild/External_python-*.cmake at v5.4.0, v5.6.2,
# v5.8.1, v5.10.0, v5.12.3 and main (numpy, scipy, pydicom, Pillow, requests, packaging and
# their dependencies; the extension manager's GitPython, PyGithub, … are left out: nothing here
# should lean on them). The application's own modules: VTK and MRML (vtk, slicer), PythonQt
# (qt, ctk), scripted modules (SampleData), and PyTorchUtils from the PyTorch extension that
# EXTENSION_DEPENDS names (always guarded: it may be absent).
SLICER_BUNDLED = {
    "numpy": "numpy", "scipy": "scipy", "pydicom": "pydicom", "PIL": "pillow", "requests": "requests",
    "packaging": "packaging", "urllib3": "urllib3", "idna": "idna", "certifi": "certifi",
    "charset_normalizer": "charset-normalizer", "six": "six", "pyparsing": "pyparsing",
    "vtk": "vtk", "slicer": "slicer-core",  # headless stand-ins for Slicer's VTK and MRML
}
SLICER_APPLICATION_MODULES = {"qt", "ctk", "SampleData", "PyTorchUtils"}

# Imports in modules the worker or the module reach, on code paths they never take (the
# blocked-import run below would record them if they did). (importing module, top-level name): why.
NOT_ON_SLICER_PATHS = {
    ("SDFCARLib.io", "tifffile"): "read_image of .tif files: command line only (the module reads frames from the scene)",
    ("SDFCARLib.io", "nibabel"): "read_volume of NIfTI files: command line and benchmark only",
}


# Imports on Slicer paths whose absence the code handles, so they are not asked for: (importing
# module, top-level name): what is lost without them. The blocked-import run of the analysis below
# checks that the code really goes on without them.
OPTIONAL_ON_SLICER_PATHS = {
    ("SDFCARLib.analysis.outputs", "matplotlib"): "the 3D-QCA's PNG figures; analyse_result_dir skips them and says so "
                                                  "in analysis.json (Slicer plots the diameters itself)",
}


# Telling the standard library apart needs sys.stdlib_module_names (Python 3.10+).
needs_stdlib_names = pytest.mark.skipif(not hasattr(sys, "stdlib_module_names"), reason="needs Python 3.10+ (sys.stdlib_module_names)")


def requirements():
    """REQUIREMENTS of SDFCAR.py (a literal dict: the module cannot be imported without Slicer)."""
    for node in ast.parse(SCRIPT.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "REQUIREMENTS" for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError("SDFCAR.py has no REQUIREMENTS = {...}")


def allowed_imports():
    return set(SLICER_BUNDLED) | SLICER_APPLICATION_MODULES | set(requirements())


# --- 1. static -------------------------------------------------------------------------------------------
def _module_file(name):
    base = ROOT.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _imports(path: Path, name: str):
    """(imported module, line) of every import statement in ``path``, relative ones resolved;
    ``from a import b`` also yields ``a.b`` (b may be a submodule)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                module = ".".join(parts + ([node.module] if node.module else []))
            else:
                module = node.module
            yield module, node.lineno
            for alias in node.names:
                yield f"{module}.{alias.name}", node.lineno


def _is_stdlib(top: str) -> bool:
    return top in sys.stdlib_module_names or top == "__future__"


def third_party_imports(start_modules):
    """{(importing module, top-level name): line} over the SDFCARLib modules reachable from ``start_modules``."""
    seen, todo, found = set(), list(start_modules), {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for module, line in _imports(_module_file(name), name):
            parts = module.split(".")
            if parts[0] == "SDFCARLib":
                todo += [".".join(parts[:i]) for i in range(1, len(parts) + 1) if _module_file(".".join(parts[:i]))]
            elif not _is_stdlib(parts[0]):
                found.setdefault((name, parts[0]), line)
    return found, seen


def module_library_imports():
    """The SDFCARLib modules SDFCAR.py imports (inside its functions)."""
    return sorted({m for m, _ in _imports(SCRIPT, "SDFCAR") if m.startswith("SDFCARLib") and _module_file(m)})


@needs_stdlib_names
def test_every_import_on_slicer_paths_is_bundled_or_required():
    allowed = allowed_imports()
    found, seen = third_party_imports([WORKER_ENTRY, "SDFCARLib"] + module_library_imports())
    assert {"SDFCARLib.jobs", "SDFCARLib.optimiser", "SDFCARLib.outputs", "SDFCARLib.io", "SDFCARLib.sample_data"} <= seen
    missing = {f"{module}:{line} imports {top}" for (module, top), line in found.items()
               if top not in allowed and (module, top) not in NOT_ON_SLICER_PATHS and (module, top) not in OPTIONAL_ON_SLICER_PATHS}
    assert not missing, ("imported inside Slicer but neither bundled with Slicer nor in SDFCAR.py's REQUIREMENTS "
                         f"(add the pip name there): {sorted(missing)}")
    # The module itself imports only what Slicer provides (everything else lazily through SDFCARLib).
    own = {m.split(".")[0] for m, _ in _imports(SCRIPT, "SDFCAR")} - {"SDFCARLib"}
    assert {t for t in own if not _is_stdlib(t)} <= set(SLICER_BUNDLED) | SLICER_APPLICATION_MODULES


@needs_stdlib_names
def test_exemptions_are_still_needed():
    found, _ = third_party_imports([WORKER_ENTRY, "SDFCARLib"] + module_library_imports())
    stale = (set(NOT_ON_SLICER_PATHS) | set(OPTIONAL_ON_SLICER_PATHS)) - set(found)
    assert not stale, f"remove these from NOT_ON_SLICER_PATHS, nothing imports them any more: {sorted(stale)}"


def test_requirements_are_the_one_list():
    reqs = requirements()
    assert {"torch", "skimage", "nrrd", "imageio"} <= set(reqs)
    assert not set(reqs) & set(SLICER_BUNDLED), "bundled with Slicer: do not ask to install it"
    # No second list to drift apart: requirements.txt was never read by the code.
    assert not (ROOT / "SDFCAR" / "Resources" / "requirements.txt").exists()
    text = SCRIPT.read_text(encoding="utf-8")
    for name in ("SAMPLE_REQUIREMENTS", "VESSELNESS_REQUIREMENTS", "ANALYSIS_REQUIREMENTS"):
        listed = ast.literal_eval(text.split(f"\n{name} = ", 1)[1].split("\n", 1)[0])
        assert set(listed) <= set(reqs), name


def test_each_requirement_provides_its_import_name():
    """pip installs the distribution named on the right; the code imports the name on the left."""
    provided = importlib.metadata.packages_distributions()
    not_installed = []
    for module, requirement in requirements().items():
        distributions = {d.lower().replace("_", "-") for d in provided.get(module, [])}
        if not distributions:  # checked wherever it is installed; one missing here does not stop the others
            not_installed.append(requirement)
            continue
        assert requirement.lower() in distributions, f"REQUIREMENTS[{module!r}] = {requirement!r}, but {module} comes from {distributions}"
    if len(not_installed) == len(requirements()):
        pytest.skip(f"none of {', '.join(not_installed)} is installed here, so no import name can be checked")


# --- 2. blocked imports ----------------------------------------------------------------------------------
BLOCKER = textwrap.dedent('''
    import importlib.abc, json, os, sys
    ALLOWED = set(json.loads(os.environ["SDFCAR_ALLOWED_IMPORTS"])) | {"SDFCARLib"}
    LOG = os.environ["SDFCAR_BLOCKED_LOG"]
    STDLIB = set(sys.stdlib_module_names) | {"__future__"}

    def importer():
        frame = sys._getframe(2)
        while frame is not None:
            name = frame.f_globals.get("__name__", "")
            if not (name.startswith("importlib") or frame.f_code.co_filename.startswith("<frozen")):
                return name, frame.f_lineno
            frame = frame.f_back
        return "", 0

    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname, path=None, target=None):
            if "." in fullname or fullname in STDLIB or fullname in ALLOWED:
                return None
            name, line = importer()
            if not (name.startswith("SDFCARLib") or name in ("__main__", "SDFCAR")):
                return None  # a dependency of an allowed package: pip brings it along
            with open(LOG, "a") as log:
                log.write(f"{name}:{line} imports {fullname}\\n")
            raise ModuleNotFoundError(f"{fullname} is neither bundled with Slicer nor in REQUIREMENTS", name=fullname)

    sys.meta_path.insert(0, Block())
''')


def _run_blocked(tmp_path, body: str, *args):
    script = tmp_path / "blocked_run.py"
    script.write_text(BLOCKER + textwrap.dedent(body), encoding="utf-8")
    log = tmp_path / "blocked.log"
    env = dict(os.environ, SDFCAR_ALLOWED_IMPORTS=json.dumps(sorted(allowed_imports())), SDFCAR_BLOCKED_LOG=str(log),
               PYTHONPATH=os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]))
    out = subprocess.run([sys.executable, str(script), *map(str, args)], capture_output=True, text=True, env=env, timeout=600)
    blocked = log.read_text().splitlines() if log.exists() else []
    return out, blocked


TINY = {"steps": 3, "levels": 4, "log2_table_size": 12, "width": 16, "depth": 2, "threads": 1, "seed": 0}


@needs_stdlib_names
def test_blocked_imports_the_worker(tmp_path, tiny_geometry, tiny_case):
    from SDFCARLib.jobs import prepare_job

    job_dir = prepare_job(tmp_path / "job", tiny_geometry, tiny_case.masks, TINY, name="blocked")
    out, blocked = _run_blocked(tmp_path, '''
        import runpy
        sys.argv = ["SDFCARLib.jobs", "worker", sys.argv[1]]
        try:
            runpy.run_module("SDFCARLib.jobs", run_name="__main__", alter_sys=True)
        except SystemExit as exc:
            sys.exit(exc.code)
    ''', job_dir)
    status = json.loads((job_dir / "status.json").read_text())
    assert not blocked, f"the worker imports modules Slicer lacks: {blocked}"
    assert out.returncode == 0 and status["state"] == "finished", (status, out.stderr[-3000:])


@needs_stdlib_names
def test_blocked_imports_the_modules_library_calls(tmp_path):
    """What the module's own process runs: the sample case, vesselness, inputs' checks, DICOM tags,
    the views' parameters, the QA overlays and the 3D-QCA nodes."""
    out, blocked = _run_blocked(tmp_path, '''
        import numpy as np
        from SDFCARLib.sample_data import load_sample_case
        from SDFCARLib.angiogram import simulate_angiogram
        from SDFCARLib.masks import angiogram_mask
        from SDFCARLib.jobs import prepare_job
        import SDFCARLib.dicom, SDFCARLib.selftest, SDFCARLib.mrml
        import SDFCARLib.analysis.mrml_nodes, SDFCARLib.mrml.parameter_views, SDFCARLib.mrml.qa_overlays
        case = load_sample_case()
        frame, _ = simulate_angiogram(2.0 * case.masks[0], 0.278, 0)
        angiogram_mask(frame, 0.278, 1.32)
        prepare_job(sys.argv[1], case.geometry, case.masks, {"steps": 1})
    ''', tmp_path / "job")
    assert not blocked, f"the module imports modules Slicer lacks: {blocked}"
    assert out.returncode == 0, out.stderr[-3000:]


@needs_stdlib_names
def test_blocked_imports_the_analysis_worker(tmp_path):
    """The module's Analyse runs `python -m SDFCARLib.jobs analyse`: it needs nothing Slicer lacks,
    and without the optional matplotlib it still finishes (without the figures)."""
    from test_analysis import _result_folder

    from SDFCARLib.jobs import prepare_analysis_job

    folder, _ = _result_folder(tmp_path)
    job_dir = prepare_analysis_job(tmp_path / "qca", folder, options={"view_step_deg": 30.0})
    out, blocked = _run_blocked(tmp_path, '''
        import runpy
        sys.argv = ["SDFCARLib.jobs", "analyse", sys.argv[1]]
        try:
            runpy.run_module("SDFCARLib.jobs", run_name="__main__", alter_sys=True)
        except SystemExit as exc:
            sys.exit(exc.code)
    ''', job_dir)
    status = json.loads((job_dir / "status.json").read_text())
    optional = {top for _, top in OPTIONAL_ON_SLICER_PATHS}
    assert all(line.rsplit(" ", 1)[-1] in optional for line in blocked), f"the analysis imports modules Slicer lacks: {blocked}"
    assert out.returncode == 0 and status["state"] == "finished", (status, out.stderr[-3000:])
    notes = json.loads(Path(status["outputs"]["analysis.json"]).read_text())["notes"]
    assert any("figures skipped" in n for n in notes)


@needs_stdlib_names
def test_the_blocker_blocks(tmp_path):
    """Guard for the check itself: an import Slicer lacks, made by SDFCARLib, is refused and recorded."""
    out, blocked = _run_blocked(tmp_path, '''
        import types
        module = types.ModuleType("SDFCARLib.fake")
        exec("try:\\n    import nibabel\\nexcept ImportError:\\n    pass", module.__dict__)
    ''')
    assert out.returncode == 0, out.stderr
    assert blocked and blocked[0].endswith("imports nibabel")


# --- 3. a fresh environment with only the Slicer bundle and REQUIREMENTS -------------------------------------
def _distribution_closure(names, optional=()):
    """The installed distributions ``names`` need (themselves and their non-extra requirements).
    Names in ``optional`` that are not installed here are left out: leaving a bundled package out
    can only make the worker fail, never pass wrongly."""
    from packaging.requirements import Requirement

    found, todo = {}, list(names) + list(optional)
    while todo:
        name = todo.pop()
        key = name.lower().replace("_", "-")
        if key in found:
            continue
        try:
            dist = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError:
            if name in optional:
                continue
            raise AssertionError(f"{name} is not installed in this environment; install it to run this test") from None
        found[key] = dist
        for text in dist.requires or []:
            requirement = Requirement(text)
            if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
                todo.append(requirement.name)
    return found


def _link_environment(venv: Path, distributions) -> Path:
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    for dist in distributions.values():
        tops = {Path(str(f)).parts[0] for f in dist.files or [] if not str(f).startswith("..")}
        for top in tops:
            source = Path(dist.locate_file(top))
            if source.exists() and not (site / top).exists():
                (site / top).symlink_to(source, target_is_directory=source.is_dir())
    return python


def _run_worker_in(python, tmp_path, tiny_geometry, tiny_case, monkeypatch):
    from SDFCARLib.jobs import ReconstructionJob, prepare_job

    # The environment really is bare: what this suite installs besides (pytest, kornia) is absent.
    probe = subprocess.run([str(python), "-c", "import importlib.util as u; print(u.find_spec('pytest'), u.find_spec('kornia'))"],
                           capture_output=True, text=True, env={"PATH": os.environ.get("PATH", "")})
    assert probe.stdout.split() == ["None", "None"], probe
    monkeypatch.delenv("PYTHONPATH", raising=False)
    monkeypatch.delenv("PYTHONHOME", raising=False)
    job_dir = prepare_job(tmp_path / "job", tiny_geometry, tiny_case.masks, TINY, name="fresh")
    job = ReconstructionJob.launch(job_dir, python=str(python))
    state = job.wait(300)
    log = (job_dir / "worker.log").read_text(errors="replace")
    assert state == "finished", f"{state}: {job._status()}\n{log[-3000:]}"
    outputs = job.result()
    assert Path(outputs["segmentation"]).is_file() and Path(outputs["surface"]).is_file()
    report = json.loads(Path(outputs["report"]).read_text())
    assert not [w for w in report.get("warnings", []) if "missing" in w or "not available" in w], report["warnings"]


@pytest.mark.skipif(os.name == "nt", reason="links the installed packages with symlinks")
def test_worker_runs_in_an_environment_with_only_slicer_and_requirements(tmp_path, tiny_geometry, tiny_case, monkeypatch):
    distributions = _distribution_closure(list(requirements().values()), optional=list(SLICER_BUNDLED.values()))
    python = _link_environment(tmp_path / "venv", distributions)
    _run_worker_in(python, tmp_path, tiny_geometry, tiny_case, monkeypatch)


def _pip_environment() -> Path:
    torch = os.environ.get("SDFCAR_TORCH_SPEC") or f"torch=={importlib.metadata.version('torch')}"
    packages = [torch if r == "torch" else r for r in requirements().values()] + list(SLICER_BUNDLED.values())
    key = hashlib.sha256(json.dumps([sys.version, packages]).encode()).hexdigest()[:16]
    venv = Path(os.environ.get("SDFCAR_SLICER_VENV_DIR") or tempfile.gettempdir()) / f"sdfcar-slicer-venv-{key}"
    python = venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    if not (venv / ".complete").exists():
        shutil.rmtree(venv, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
        out = subprocess.run([str(python), "-m", "pip", "install", *packages], capture_output=True, text=True, timeout=3600)
        assert out.returncode == 0, f"pip could not install {packages}:\n{out.stdout[-2000:]}{out.stderr[-3000:]}"
        (venv / ".complete").touch()
    return python


@pytest.mark.skipif(os.environ.get("SDFCAR_PIP_VENV_TEST") != "1", reason="set SDFCAR_PIP_VENV_TEST=1 to build the environment with pip")
def test_worker_runs_in_a_pip_built_environment(tmp_path, tiny_geometry, tiny_case, monkeypatch):
    _run_worker_in(_pip_environment(), tmp_path, tiny_geometry, tiny_case, monkeypatch)
