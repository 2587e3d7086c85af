"""Telemetry recordings: one CSV row per pulse, a metadata header of `# key: value`
lines, flushed at least every second so an interrupted recording keeps all
but (at most) its last second and is still readable."""

from __future__ import annotations

import contextlib
import csv
import time
from pathlib import Path

from .protocol import Telemetry

FORMAT = "steadytouch recording 1"
COLUMNS = [
    "seq", "time_us", "channel", "i_ua", "t_us", "vp_mv", "rp_ohm", "status", "stop", "mode", "me_ua2ms",
    "mq_target_fc_per_ohm", "mq_last_fc_per_ohm", "next_i_ua", "next_t_us", "flags", "overruns", "loop_us",
    "sent_status", "ltau_q16",  # (firmware 0.4.0 on; `audit` replays sent_status where present)
]
REQUIRED = ["seq", "time_us", "channel", "i_ua", "t_us", "vp_mv", "rp_ohm", "status"]
MAX_CHANNELS = 4  # the protocol's channels 0..3


class RecordingError(ValueError):
    """A recording that cannot be read; the message names the file and line."""


class Recorder:
    """A recording written as it comes. A write that fails (a full disk, a removed drive) is a RecordingError
    naming the file, the reason and the rows saved in it (those of the last flush); the file is then closed."""

    def __init__(self, path: Path | str, meta: dict, flush_s: float = 1.0):
        self.path = Path(path)
        self.rows = 0
        self.saved = 0  # rows on disk: those of the last successful flush
        try:
            self.f = open(self.path, "w", newline="")
        except OSError as e:
            raise RecordingError(f"{self.path}: cannot create the recording ({e.strerror})") from None
        self.w = csv.writer(self.f)
        self.flush_s = flush_s
        with self._guard():
            self.f.write(f"# {FORMAT}\n")
            for k, v in meta.items():
                self.f.write(f"# {k}: {v}\n")
            self.w.writerow(COLUMNS)
            self.f.flush()
        self._last_flush = time.monotonic()

    @contextlib.contextmanager
    def _guard(self):
        try:
            yield
        except OSError as e:
            with contextlib.suppress(OSError):
                self.f.close()  # (what could not be written is dropped; the file holds what was flushed)
            raise RecordingError(f"{self.path}: cannot write ({e.strerror}): the recording stopped; "
                                 f"{self.saved} rows saved in it") from None

    def write(self, t: Telemetry) -> None:
        with self._guard():
            self.w.writerow([getattr(t, c) for c in COLUMNS])
            self.rows += 1
            now = time.monotonic()
            if now - self._last_flush >= self.flush_s:
                self.f.flush()
                self.saved = self.rows
                self._last_flush = now

    def close(self) -> None:
        if not self.f.closed:
            with self._guard():
                self.f.flush()
                self.saved = self.rows
                self.f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def write_recording(path: Path | str, tel: list[Telemetry], meta: dict) -> None:
    with Recorder(path, meta) as r:
        for t in tel:
            r.write(t)


CUT = "cut_at_line"  # metadata key read_recording(allow_cut=True) adds for a recording cut short


def read_recording(path: Path | str, allow_cut: bool = False) -> tuple[dict, list[dict]]:
    """(metadata, rows as dicts of ints); RecordingError naming the line on anything malformed.

    allow_cut: a recording cut short (killed while writing: its last line has no
    line end) gives its complete rows, and meta[CUT] = the line number of the cut row."""
    from .files import FileProblem, read_text_file

    path = Path(path)
    try:
        text = read_text_file(path, "recording")
    except FileProblem as e:
        raise RecordingError(str(e)) from None
    lines = text.splitlines()
    cut = None
    if allow_cut and text and not text.endswith(("\n", "\r")) and lines and not lines[-1].startswith("#"):
        cut = len(lines)
        lines = lines[:-1]
    meta: dict[str, str] = {}
    k = 0
    while k < len(lines) and lines[k].startswith("#"):
        key, sep, val = lines[k][1:].partition(":")
        if sep:
            meta[key.strip()] = val.strip()
        k += 1
    if k >= len(lines):
        raise RecordingError(f"{path}: no column header (is it a steadytouch recording?)")
    header = [h.strip() for h in lines[k].split(",")]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise RecordingError(f"{path} line {k + 1}: missing column(s) {', '.join(missing)}")
    channels = recording_channels(meta, path)
    rows = []
    for n, line in enumerate(lines[k + 1 :], start=k + 2):
        if not line.strip():
            continue
        cells = line.split(",")
        if len(cells) != len(header):
            what = "truncated" if n == len(lines) and len(cells) < len(header) else "malformed"
            raise RecordingError(f"{path} line {n}: {what} row ({len(cells)} of {len(header)} columns)")
        row = {}
        for h, c in zip(header, cells):
            c = c.strip()
            if not c.lstrip("-").isdigit() or c.count("-") > 1:
                raise RecordingError(f"{path} line {n}: column {h} is not a whole number")
            if len(c) > 11 or not -2**32 < int(c) < 2**32:
                raise RecordingError(f"{path} line {n}: column {h} = {c[:12]}{'...' if len(c) > 12 else ''} "
                                     "out of range (a 32-bit field)")
            row[h] = int(c)
        if row["channel"] not in channels:
            raise RecordingError(f"{path} line {n}: channel {row['channel']} is not one of the recording's channels "
                                 f"({_words(channels)})")
        rows.append(row)
    if not rows:
        raise RecordingError(f"{path}: no pulses recorded" + (f" (cut at line {cut})" if cut else ""))
    if cut:
        meta[CUT] = cut
    return meta, rows


def recording_channels(meta: dict, path="recording") -> range:
    """The channels a recording has: 0..n_channels-1 from its header (`record` writes it), else the protocol's
    0..3 (a header without it). A row on another channel is refused: it cannot be replayed or plotted."""
    if "n_channels" not in meta:
        return range(MAX_CHANNELS)
    n = meta_int(meta, "n_channels", path)
    if not 1 <= n <= MAX_CHANNELS:
        raise RecordingError(f"{path}: metadata 'n_channels' = {n} out of range [1, {MAX_CHANNELS}]")
    return range(n)


def _words(channels: range) -> str:
    if len(channels) == 1:
        return f"it has channel {channels[0]} only"
    return f"it has channels {channels[0]}..{channels[-1]}"


def meta_int(meta: dict, key: str, path="recording") -> int:
    try:
        return int(meta[key])
    except KeyError:
        raise RecordingError(f"{path}: metadata '{key}' missing from the header") from None
    except ValueError:
        raise RecordingError(f"{path}: metadata '{key}' is not a whole number: {meta[key]!r}") from None
