"""`--lsl` for the commands that talk to a device (record, monitor) and for `sim`."""

from __future__ import annotations

import time

from . import require
from .streams import Feed, Tap, device_serial, open_streams

LINGER_S = 1.0  # after the last sample: time for connected inlets to take what is in flight


class LabLink:
    """Wraps the transport before the Device is built (so every report and command
    passes the tap); `start(meta, n)` opens the outlets once the device's metadata
    is known; `finish()` pushes the clock fit and lets the inlets drain."""

    def __init__(self, transport, url: str):
        self.pylsl = require()  # one clear line without pylsl, before anything is sent
        self.tap = Tap(transport, None, self.pylsl.local_clock)
        self.url = url
        self.streams = None
        self.feed: Feed | None = None

    def serial(self) -> str:
        return device_serial(self.tap.t, self.url)

    def start(self, meta: dict, n_channels: int) -> None:
        self.streams, self.feed, _ = open_streams(meta, n_channels, realtime=getattr(self.tap.t, "realtime", True))
        self.tap.feed = self.feed

    def finish(self) -> str:
        if self.feed is None:
            return ""
        self.feed.end()
        if self.streams.consumers():
            time.sleep(LINGER_S)
        words = (f"LSL: {self.streams.samples} samples on 'steadytouch telemetry' ({self.feed.clock.words()}), "
                 f"{self.streams.markers} markers")
        self.tap.feed = None
        self.streams.close()
        return words


def stream_run(meta: dict, n_channels: int, reports, auto_commands: list[bytes], wait_s: float, say) -> str:
    """`sim --lsl`: the outlets for one finished simulated run (virtual clock): wait up to
    wait_s for a recorder to connect, push every report, let it drain."""
    require()
    streams, feed, _ = open_streams(meta, n_channels, realtime=False)
    try:
        if wait_s > 0 and not streams.consumers():
            say(f"  LSL: waiting up to {wait_s:g} s for a recorder (e.g. LabRecorder) to connect to "
                f"'steadytouch telemetry' ({meta.get('serial')}) ...")
            end = time.monotonic() + wait_s
            while not streams.consumers() and time.monotonic() < end:
                time.sleep(0.05)
            if not streams.consumers():
                say("  LSL: no recorder connected; streaming anyway")
        for rep in auto_commands:
            feed.sent(rep)
        for rep in reports:
            feed.report(rep, 0.0)
        feed.end()
        if streams.consumers():
            time.sleep(LINGER_S)
        return f"  LSL: {streams.samples} samples, {streams.markers} markers ({feed.clock.words()})"
    finally:
        streams.close()
