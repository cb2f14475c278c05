"""The files of a results folder: ``results.csv`` (``ResultsFile``, its columns, ``latest_rows``),
``run.json`` (the record of every invocation) and safe file names for cases and modes."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import time
from pathlib import Path
from typing import Any, Dict, Iterable, List, Tuple

import numpy as np

from ..io import json_compatible, write_text_atomically
from .errors import BenchmarkError
from .registry import METRIC_COLUMNS

IDENTITY_COLUMNS = ["suite", "tree", "case", "seed", "protocol", "target_kind", "mode", "preset", "steps",
                    "overrides", "config"]
COLUMNS = IDENTITY_COLUMNS + ["status", "error", "traceback_file"] + METRIC_COLUMNS + [
    "wall_s", "eval_s", "prepare_s", "device", "worker", "finished_at", "run_id"]  # run_id: its run.json record


# --- results.csv ----------------------------------------------------------------------------------
def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return repr(v) if math.isfinite(v) else "nan"
    return str(value)


class ResultsFile:
    """``results.csv``: rows appended and flushed one by one, so an interrupted run loses nothing."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.columns = list(COLUMNS)
        if self.path.exists() and self.path.stat().st_size > 0:
            with self.path.open(newline="", encoding="utf-8") as stream:
                header = next(csv.reader(stream), None)
            if not header or "case" not in header or "mode" not in header:
                raise BenchmarkError(f"{self.path} is not a benchmark results file (its header is {header!r}); "
                                     "choose another --out")
            # A file from another harness version keeps its own columns: rows stay aligned with its header.
            self.columns = header

    def rows(self) -> List[Dict[str, str]]:
        if not self.path.exists():
            return []
        with self.path.open(newline="", encoding="utf-8") as stream:
            reader = csv.DictReader(stream)
            # A row cut short by a crash mid-write has missing cells (None): not a finished row.
            return [r for r in reader if None not in r.values() and r.get("status") in ("ok", "failed")]

    def append(self, row: Dict[str, Any]) -> None:
        new = not self.path.exists() or self.path.stat().st_size == 0
        if not new:
            with self.path.open("rb") as stream:
                stream.seek(-1, os.SEEK_END)
                needs_newline = stream.read(1) not in (b"\n", b"\r")
        with self.path.open("a", newline="", encoding="utf-8") as stream:
            if not new and needs_newline:
                stream.write("\r\n")  # finish a line a crash left open, so this row starts afresh
            writer = csv.DictWriter(stream, fieldnames=self.columns, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow({c: _cell(row.get(c)) for c in self.columns})
            stream.flush()
            os.fsync(stream.fileno())


def _row_key(row: Dict[str, Any]) -> Tuple[str, str, str, str]:
    return (str(row.get("suite")), str(row.get("case")), str(row.get("mode")), str(row.get("config")))


def latest_rows(rows: Iterable[Dict[str, str]]) -> Dict[Tuple[str, str, str, str], Dict[str, str]]:
    """The last row written for each (suite, case, mode, config)."""
    out: Dict[Tuple[str, str, str, str], Dict[str, str]] = {}
    for row in rows:
        out[_row_key(row)] = row
    return out


# --- run.json and file names --------------------------------------------------------------------------
def safe_name(text: str) -> str:
    """``text`` (a case or mode name) as a file-name part: other characters become ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", str(text)).strip("_") or "case"


def _json_safe(value: Any) -> Any:
    return json_compatible(json.loads(json.dumps(value, default=str)))


def update_run_record(out: Path, record: Dict[str, Any]) -> None:
    """``run.json``: the invocations in order, this one last (replaced as it progresses)."""
    path = out / "run.json"
    runs: List[Dict[str, Any]] = []
    if path.exists():
        try:
            runs = json.loads(path.read_text(encoding="utf-8")).get("runs", [])
        except (ValueError, AttributeError):
            # Keep the unreadable file for the user instead of overwriting it.
            os.replace(path, path.with_name(f"run.json.unreadable-{int(time.time())}"))
            runs = []
    runs = [r for r in runs if r.get("run_id") != record["run_id"]] + [record]
    write_text_atomically(path, json.dumps(_json_safe({"runs": runs}), indent=2, allow_nan=False) + "\n")
