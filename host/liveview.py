"""`monitor --plot`: a scrolling window of the last seconds per channel: Rp, I, T,
mE and mQ against the target band, with a mark at every stop.

matplotlib (already a dependency for the figures; no Qt to install), drawn with a
fixed layout: one line per channel per panel updated in place, the target band
as one polygon per channel, the stop marks as one line collection per panel.
Blitting: the axes, ticks and labels are drawn once into a background; a frame
restores it and draws only the traces, bands and stop marks. The y limits move
(a full redraw) only when the data leave them or shrink to under a third of them.
The same class draws on the Agg canvas (`interactive=False`: tests, no display)
and in a window (TkAgg or whatever backend matplotlib picks for the display)."""

from __future__ import annotations

import os
import sys

import hid_protocol as hp
import numpy as np

from .lsl.clock import Unwrap
from .protocol import STOP_WORDS, Telemetry

# channel colours (tab10 without red: red is kept for nothing, black for the stop marks)
COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd")
PANELS = ("Rp (kΩ)", "I (mA)", "T (µs)", "mE (mA²·ms)", "mQ (µC/kΩ)")
# the paper's settle threshold (NOTES.md): 2.5e-5 µC/kΩ = 25 fC/Ω around the target
MQ_BAND_FC_PER_OHM = 25
FIG_IN = (9.0, 9.0)
DPI = 90
# fixed layout (figure fractions), so a screenshot's panels are where the test looks
LEFT, RIGHT, TOP, BOTTOM, HSPACE = 0.11, 0.97, 0.93, 0.06, 0.12


def panel_fractions() -> list[tuple[float, float, float, float]]:
    """(x0, y0, x1, y1) of each panel's plotting area as fractions of the figure,
    top-left origin (screen convention), top panel first."""
    n = len(PANELS)
    h = (TOP - BOTTOM) / (n + (n - 1) * HSPACE)
    out = []
    for k in range(n):
        top = TOP - k * h * (1 + HSPACE)
        out.append((LEFT, 1 - top, RIGHT, 1 - (top - h)))
    return out


class _Ring:
    """The last `n` rows of 8 floats (time first), oldest first, without reallocating."""

    def __init__(self, n: int):
        self.a = np.empty((2 * n, 8))
        self.n = n
        self.end = 0

    def append(self, row) -> None:
        if self.end == len(self.a):  # full: keep the newest n-1 rows at the front
            self.a[: self.n - 1] = self.a[self.end - self.n + 1 : self.end]
            self.end = self.n - 1
        self.a[self.end] = row
        self.end += 1

    def since(self, t0: float) -> np.ndarray:
        v = self.a[max(0, self.end - self.n) : self.end]
        return v[np.searchsorted(v[:, 0], t0) :]


class LivePlot:
    _window_errors: tuple = ()  # errors of a window that changed under a frame (Tk's TclError)

    def __init__(self, seconds: float = 10.0, interactive: bool = True, capacity: int = 4096):
        if interactive and sys.platform.startswith("linux") and not (
                os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise RuntimeError("--plot needs a display (no DISPLAY is set); the terminal view works without one")
        import matplotlib

        if not interactive:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure

            self.plt = None
            self.fig = Figure(figsize=FIG_IN, dpi=DPI)
            FigureCanvasAgg(self.fig)
        else:
            if matplotlib.get_backend().lower() == "agg":
                matplotlib.use("TkAgg")  # pyplot defaulted to Agg (no display when it was first imported)
            import matplotlib.pyplot as plt

            self.plt = plt
            # not plt.ion(): interactive mode redraws the whole stale figure after every change
            where = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
            try:
                self.fig = plt.figure(figsize=FIG_IN, dpi=DPI)
            except ImportError as e:  # DISPLAY set, but no server answers there (matplotlib: "headless")
                raise RuntimeError(f"--plot needs a display: {where} is set but none could be opened ({e}); "
                                   "the terminal view works without one") from None
            if plt.get_backend().lower() == "agg":  # pyplot fell back to drawing off-screen: no window would open
                plt.close(self.fig)
                raise RuntimeError(f"--plot needs a display: {where} is set but none could be opened (matplotlib "
                                   "fell back to its off-screen backend: no display answered, or this Python has no "
                                   "tkinter); the terminal view works without one")
            try:
                self.fig.canvas.manager.set_window_title("steadytouch monitor")
            except AttributeError:
                pass
            self._catch_tk_interrupts()
            plt.show(block=False)
        self.fig.subplots_adjust(left=LEFT, right=RIGHT, top=TOP, bottom=BOTTOM, hspace=HSPACE)
        self.ax = self.fig.subplots(len(PANELS), 1, sharex=True)
        for a, lab in zip(self.ax, PANELS):
            a.set_ylabel(lab, fontsize=8)
            a.tick_params(labelsize=7)
            a.grid(alpha=0.3)
            a.set_xlim(-seconds, 0)
        self.ax[-1].set_xlabel("time (s, 0 = the newest pulse; device clock)", fontsize=8)
        self.title = self.fig.suptitle("steadytouch monitor", fontsize=9, y=0.995)
        self.seconds = seconds
        self.unwrap = Unwrap()
        self.data: dict[int, _Ring] = {}
        self.capacity = capacity
        self.lines: dict[int, list] = {}
        self.bands: dict[int, object] = {}
        self.stops: list[tuple[float, int, str]] = []
        self.last_stop: dict[int, int] = {}
        self.now_s = 0.0
        self.draws = 0
        from matplotlib.collections import LineCollection

        self.marks = []
        for a in self.ax:
            lc = LineCollection([], colors="k", linewidths=1.2, linestyles="--", transform=a.get_xaxis_transform(),
                                animated=True)
            a.add_collection(lc)
            self.marks.append(lc)
        self.mark_text = []
        self.background = None
        self.full_draws = 0
        self.fig.canvas.mpl_connect("draw_event", self._on_draw)
        if self.plt is not None:
            # the window's first draw takes about a second (fonts, mapping the window): do it now,
            # before any device is opened, so it cannot starve the keep-alive of an armed device
            self.draw()

    def _catch_tk_interrupts(self) -> None:
        """Ctrl-C / SIGTERM (cli.Terminated) that lands in one of Tk's own callbacks (a redraw on
        expose) is caught and printed by Tk, and the monitor would run on: keep it and raise it
        from draw() instead, so the monitor stops (and disarms) as it should."""
        self._pending_interrupt = None
        try:
            root = self.fig.canvas.get_tk_widget()._root()
        except AttributeError:  # not a Tk backend
            return
        import tkinter

        self._window_errors = (tkinter.TclError,)
        report = root.report_callback_exception

        def report_or_keep(exc, val, tb):
            if issubclass(exc, KeyboardInterrupt):
                self._pending_interrupt = val
            else:
                report(exc, val, tb)

        root.report_callback_exception = report_or_keep

    def set_meta(self, meta: dict) -> None:
        """The device's soft limits as grey lines on I and T; its name in the title."""
        self.title.set_text(f"steadytouch monitor: {meta.get('device', '')}  mode {meta.get('mode', '?')}  "
                            f"firmware {meta.get('firmware', '?')}")
        self.background = None  # the title and limit lines are in the background
        for key, ax, scale in (("i_min_ua", 1, 1e3), ("i_max_ua", 1, 1e3), ("t_min_us", 2, 1), ("t_max_us", 2, 1)):
            if key in meta:
                self.ax[ax].axhline(float(meta[key]) / scale, color="0.6", lw=0.8, ls=":")

    def add(self, t: Telemetry) -> None:
        s = self.unwrap(t.time_us) / 1e6
        self.now_s = max(self.now_s, s)
        stop = t.stop
        if stop not in (hp.STOP_NONE, hp.STOP_IDLE) and self.last_stop.get(t.channel) != stop:
            self.stops.append((s, t.channel, STOP_WORDS.get(stop, str(stop))))
        self.last_stop[t.channel] = stop
        if t.i_ua:
            ring = self.data.get(t.channel)
            if ring is None:
                ring = self.data[t.channel] = _Ring(self.capacity)
            ring.append((s, t.rp_ohm / 1e3, t.i_ua / 1e3, t.t_us, t.i_ua * t.i_ua * t.t_us / 1e9, t.me_ua2ms / 1e6,
                         t.mq_last_fc_per_ohm / 1e6, t.mq_target_fc_per_ohm / 1e6))

    def _new_channel(self, ch: int) -> None:
        c = COLOURS[ch % len(COLOURS)]
        lines = [a.plot([], [], lw=1.4, color=c, animated=True)[0] for a in self.ax]
        lines.append(self.ax[3].plot([], [], lw=1.0, ls="--", color=c, animated=True)[0])  # the calibrated mE
        self.lines[ch] = lines
        handles = [self.lines[k][0] for k in sorted(self.lines)]
        if getattr(self, "legend", None) is not None:
            self.legend.remove()
        self.legend = self.fig.legend(handles, [f"ch{k}" for k in sorted(self.lines)], loc="upper right",
                                      ncol=4, fontsize=7, frameon=False, bbox_to_anchor=(RIGHT, 0.985))
        self.background = None  # the legend is part of the background

    def update(self) -> None:
        """Move the data into the artists (no drawing)."""
        lo = self.now_s - self.seconds
        for ch, ring in sorted(self.data.items()):
            if ch not in self.lines:
                self._new_channel(ch)
            a = ring.since(lo)  # (may be empty: a channel that stopped pulsing a window ago)
            x = a[:, 0] - self.now_s
            ln = self.lines[ch]
            for k in range(5):
                ln[k].set_data(x, a[:, k + 1] if k < 4 else a[:, 6])
            ln[5].set_data(x, a[:, 5])
            band = MQ_BAND_FC_PER_OHM / 1e6
            verts = np.concatenate([np.column_stack([x, a[:, 7] - band]), np.column_stack([x[::-1], a[::-1, 7] + band])])
            if ch not in self.bands:
                from matplotlib.collections import PolyCollection

                self.bands[ch] = PolyCollection([verts], facecolors=COLOURS[ch % 4], alpha=0.25, linewidths=0,
                                                animated=True)
                self.ax[4].add_collection(self.bands[ch], autolim=False)
            else:
                self.bands[ch].set_verts([verts])
        segs = [[(s - self.now_s, 0), (s - self.now_s, 1)] for s, _, _ in self.stops if s >= lo]
        for lc in self.marks:
            lc.set_segments(segs)
        for tx in self.mark_text:
            tx.remove()
        groups: list[list] = []  # stops of the same kind within 0.1 s share one label: "ch0,1 ELECTRODE OFF"
        for s, ch, w in self.stops:
            if s < lo:
                continue
            if groups and groups[-1][2] == w and s - groups[-1][0] < 0.1:
                groups[-1][1].append(ch)
            else:
                groups.append([s, [ch], w])
        self.mark_text = [self.ax[0].text(s - self.now_s, 1.02, f"ch{','.join(map(str, sorted(chs)))} {w}",
                                          transform=self.ax[0].get_xaxis_transform(), fontsize=6, ha="right",
                                          va="bottom", animated=True)
                          for s, chs, w in groups[-4:]]
        for k, a in enumerate(self.ax):
            ys = [ln.get_ydata() for ln in (self.lines[c][k] for c in self.lines) if len(ln.get_ydata())]
            if k == 3:
                ys += [self.lines[c][5].get_ydata() for c in self.lines if len(self.lines[c][5].get_ydata())]
            if k == 4:
                ys += [np.asarray(b.get_paths()[0].vertices[:, 1]) for b in self.bands.values() if b.get_paths()]
            ys = [y for y in ys if len(y)]
            if ys:
                y = np.concatenate(ys)
                y0, y1 = float(y.min()), float(y.max())
                lo_, hi_ = a.get_ylim()
                pad = max((y1 - y0) * 0.15, abs(y1) * 0.01, 1e-9)
                if y0 < lo_ or y1 > hi_ or (hi_ - lo_) > 3 * (y1 - y0 + 2 * pad):
                    a.set_ylim(y0 - pad, y1 + pad)
                    self.background = None  # new ticks: a full redraw

    def _animated(self):
        for k, a in enumerate(self.ax):
            for ch in sorted(self.lines):
                if ch in self.bands and k == 4:
                    yield a, self.bands[ch]
                yield a, self.lines[ch][k]
                if k == 3:
                    yield a, self.lines[ch][5]
            yield a, self.marks[k]
        for tx in self.mark_text:
            yield self.ax[0], tx

    def _on_draw(self, event) -> None:
        """After every full draw (ours, or the window's own on expose/resize): keep the
        background, put the traces on it."""
        c = self.fig.canvas
        self.background = c.copy_from_bbox(self.fig.bbox)
        for a, art in self._animated():
            a.draw_artist(art)

    def draw(self) -> bool:
        """One frame; False once the window was closed."""
        if self.plt is not None and not self.plt.fignum_exists(self.fig.number):
            return False
        self.update()
        c = self.fig.canvas
        try:
            if self.background is None:
                c.draw()  # the draw_event puts the traces on
                self.full_draws += 1
            else:
                c.restore_region(self.background)
                for a, art in self._animated():
                    a.draw_artist(art)
            c.blit(self.fig.bbox)
        except self._window_errors:
            # the window was resized or re-mapped under us (Tk replaced its image: "TclError: pyimageN"):
            # the next frame is a full draw at the new size
            self.background = None
        if self.plt is not None:
            c.flush_events()
            if getattr(self, "_pending_interrupt", None) is not None:
                e, self._pending_interrupt = self._pending_interrupt, None
                raise e
        self.draws += 1
        return True

    def rgb(self) -> np.ndarray:
        """The figure as an H x W x 3 uint8 array (the Agg canvas, as last drawn)."""
        if self.background is None:
            self.draw()
        return np.asarray(self.fig.canvas.buffer_rgba())[:, :, :3].copy()

    def close(self) -> None:
        if self.plt is not None:
            self.plt.close(self.fig)
