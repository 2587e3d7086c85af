"""Files in and out, for user mistakes to end in one clear line.

- `Outputs`: every file a command writes goes to a temporary name in the same
  folder and is renamed over the final name only when the whole command
  succeeded (`os.replace`: atomic on one file system). A failed or interrupted
  run leaves no new or half-written file behind, and an old file is kept.
- `read_text_file` / `csv_rows`: a text CSV or an error naming the file (binary
  data, unreadable, fields longer than the csv module's limit).
- `refuse_existing`: an output that exists already is replaced only when the user
  said so (`--overwrite`): a previous session or recording is never lost by a
  repeated command.
- `finite`: no NaN or Infinity reaches a JSON file or a table.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path


class FileProblem(ValueError):
    """An input or output file problem; the message names the file."""


class Outputs:
    """with Outputs() as out: p = out.path("x.csv"); write p ... -> renamed at the end."""

    def __init__(self):
        self._files: list[tuple[Path, Path]] = []

    def path(self, final: Path | str) -> Path:
        final = Path(final)
        writable_file(final)
        tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp{final.suffix}")
        self._files.append((tmp, final))
        return tmp

    def commit(self) -> None:
        for tmp, final in self._files:
            os.replace(tmp, final)
        self._files = []

    def discard(self) -> None:
        for tmp, _ in self._files:
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
        self._files = []

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.commit()
        else:
            self.discard()
        return False


def writable_file(path: Path | str, example: str = "out.csv") -> None:
    """FileProblem if path cannot be an output file: a folder, a device or other non-regular file (never replaced,
    even with --overwrite), or a name in a folder that does not exist."""
    path = Path(path)
    if path.is_dir():
        raise FileProblem(f"{path} is a folder: give a file name for the output, e.g. {path / example}")
    if os.path.lexists(path) and not path.is_file():
        raise FileProblem(f"{path} is not a regular file (a device, pipe or link to none): give a file name")
    parent = path.parent
    if not parent.is_dir():
        raise FileProblem(f"{path}: the folder {parent} does not exist" if not parent.exists() else
                          f"{path}: {parent} is not a folder")


def out_folder(path: Path | str, flag: str = "--out", create: bool = True) -> Path:
    """The output folder path, created if needed (create); FileProblem naming it if it is a file or cannot be
    created. create=False: only the check, before a command's work (the folder is made when it writes)."""
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():
        raise FileProblem(f"{flag} {path}: not a folder (a file of that name exists): {flag} names the folder "
                          "the outputs go to")
    if not create:
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FileProblem(f"{flag} {path}: cannot create the folder ({e.strerror})") from None
    return path


def refuse_existing(paths, overwrite: bool, instead: str = "choose another --out") -> None:
    """FileProblem naming every one of paths that exists already, unless overwrite (the command's --overwrite);
    one that cannot be an output file at all (a folder, a device) is refused either way (writable_file).
    Called before the command does its work: nothing is measured or simulated for a file it may not write."""
    for p in paths:
        if os.path.lexists(p) and not Path(p).is_file():
            writable_file(p)
    if overwrite:
        return
    there = [str(p) for p in paths if os.path.lexists(p)]
    if there:
        names = there[0] if len(there) == 1 else ", ".join(there[:-1]) + " and " + there[-1]
        raise FileProblem(f"{names} already exist{'s' if len(there) == 1 else ''}: --overwrite replaces "
                          f"{'it' if len(there) == 1 else 'them'} ({instead})")


def read_text_file(path: Path | str, what: str = "file") -> str:
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FileProblem(f"{path}: no such {what}") from None
    except IsADirectoryError:
        raise FileProblem(f"{path}: is a folder, not a {what}") from None
    except OSError as e:
        raise FileProblem(f"{path}: cannot read ({e.strerror})") from None
    if b"\0" in data[:65536]:
        raise FileProblem(f"{path}: a binary file, not a text {what}")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise FileProblem(f"{path}: not a UTF-8 text {what} (bad byte at offset {e.start})") from None


def csv_rows(path: Path | str, text: str) -> list[list[str]]:
    """All rows of CSV text; FileProblem naming the file and row on a CSV error."""
    rows = []
    r = csv.reader(text.splitlines())
    try:
        for row in r:
            rows.append(row)
    except csv.Error as e:
        raise FileProblem(f"{path} row {r.line_num}: not a valid CSV row ({e})") from None
    return rows


def finite(obj, where: str = "result"):
    """obj unchanged if every float in it is finite; FileProblem naming the first that is not."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise FileProblem(f"{where} is {obj}: the data are degenerate (identical or constant values?)")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            finite(v, f"{where}.{k}")
    elif isinstance(obj, (list, tuple)):
        for k, v in enumerate(obj):
            finite(v, f"{where}[{k}]")
    return obj


def dump_json(obj, where: str = "result") -> str:
    """JSON text with no NaN/Infinity (checked first, and refused by json itself)."""
    return json.dumps(finite(obj, where), indent=1, allow_nan=False)
