"""`steadytouch` command line: simulate, monitor, record, audit, plot, flash and
command a stimulator. User mistakes end in one line on stderr, never a traceback."""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import signal
import statistics
import sys
import time
import warnings
from pathlib import Path

import hid_protocol as hp
import sensation_core as sc

from . import __version__
from .device import Device, DeviceError, vmon_warning
from .files import FileProblem, Outputs, dump_json, out_folder, refuse_existing, writable_file
from .protocol import (FW_OWN_LIMITS, STOP_WORDS, VMON_STATE_WORDS, CalInfo, Commands, Info, Telemetry, check_calibration,
                       held_reason)
from .record import CUT, Recorder, RecordingError, read_recording, write_recording
from .simrun import Calib, SimError, default_limits, run_firmware, scenario_keys
from .transport import DEFAULT_URL, Disconnected, TransportError, open_transport

# what a user can act on (FlashError, SimError and the session's errors are RuntimeErrors)
USER_ERRORS = (SimError, TransportError, DeviceError, RecordingError, ValueError, OSError, RuntimeError)
MODES = {"akhtar": sc.MODE_AKHTAR, "fast": sc.MODE_FAST, "open": sc.MODE_OPEN_LOOP,
         "charge": sc.MODE_CONSTANT_CHARGE, "energy": sc.MODE_CONSTANT_ENERGY, "pwlinear": sc.MODE_PULSE_WIDTH_LINEAR}
MODE_WORDS = {v: k for k, v in MODES.items()}


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP: stop like Ctrl-C (the device is disarmed on the way out)."""


def say(*a):
    print(*a, flush=True)


def _warn_vmon(info) -> None:
    """One line on stderr when the board ignored its stored correction at boot (device.vmon_warning)."""
    w = vmon_warning(info.vmon_state)
    if w:
        print(f"steadytouch: {w}", file=sys.stderr, flush=True)


def _finite(name, v, lo=-math.inf, hi=math.inf):
    """A float option within [lo, hi] (NaN and infinities refused), else one clear line."""
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ValueError(f"--{name.replace('_', '-')} {v} out of range: a number in [{lo:g}, {hi:g}]")
    return v


def _seconds(a) -> float:
    """--seconds: a duration in (0, 1e9] s; left out, the command runs until Ctrl-C (0 here, as Progress takes it).
    An explicit 0 is refused: a stimulator runs for a duration the user gave, or until they stop it, never for
    'forever' by a number that reads as 'none'."""
    if a.seconds is None:
        return 0.0
    v = a.seconds
    if not (math.isfinite(v) and 0 < v <= 1e9):
        raise ValueError(f"--seconds {v:g} out of range: a number of seconds in (0, 1e9]; leave --seconds out to "
                         "run until Ctrl-C")
    return v


# ---------------------------------------------------------------- sim
def phase_table(keys, duration_s, runs: dict[str, list[Telemetry]]) -> list[str]:
    bounds = [k[0] for k in keys] + [duration_s]
    names = list(runs)
    head = f"{'phase (s)':>13} | {'contact':>7} | {'Rp range kohm':>15} | " + " | ".join(
        f"{'mQ err ' + n:>17}" for n in names)
    lines = [head, "-" * len(head)]
    ref = runs[names[0]]
    for k in range(len(bounds) - 1):
        lo, hi = bounds[k], bounds[k + 1]
        if hi - lo < 0.9:
            continue  # a ramp between two holds
        settled_from = lo + min(1.0, (hi - lo) / 2)  # judge the hold after it had time to settle
        cells = []
        for n in names:
            w = [t for t in runs[n] if settled_from <= t.time_us / 1e6 < hi and t.i_ua and t.channel == 0]
            if not w:
                cells.append(f"{'stopped':>17}")
                continue
            err = abs(statistics.median(t.mq_last_fc_per_ohm - t.mq_target_fc_per_ohm for t in w))
            rel = err / max(1, w[0].mq_target_fc_per_ohm)
            bound = any(t.status & sc.ST_BOUND_MASK for t in w)
            cells.append(f"{err / 1e6:9.2e} (bound)" if bound else f"{err / 1e6:9.2e} {rel:6.1%} ")
        w = [t for t in ref if lo <= t.time_us / 1e6 < hi and t.i_ua and t.channel == 0]
        rp = f"{min(t.rp_ohm for t in w) / 1e3:6.1f}-{max(t.rp_ohm for t in w) / 1e3:6.1f}" if w else "-"
        lines.append(f"{lo:6.1f}-{hi:6.1f} | {keys[k][1]:7.2f} | {rp:>15} | " + " | ".join(cells))
    return lines


def sim_meta(a, cal: Calib, m: str, info: Info | None = None) -> dict:
    """A simulated run's header. Its firmware: the version the simulated device reports (GET_INFO), not the host
    package's. Its limits: the device's own (info: the GET_INFO its --auto start answers; the
    realistic board without a DAC gain holds them, `audit` replays with them), else board_config's."""
    lim = default_limits() if info is None else {
        "i_min_ua": info.i_min_ua, "i_max_ua": info.i_max_ua, "t_min_us": info.t_min_us, "t_max_us": info.t_max_us,
        "q_max_pc": info.q_max_pc}
    if info is not None:
        firmware = info.firmware  # what the simulated device said, as `info --device sim://...` shows it
    else:
        from .flash import fw_version

        firmware = fw_version()  # firmware/stim.py's FW_VERSION: the one place the version is kept
    return {"firmware": firmware, "board": "sim", "device": f"sim://{a.scenario}" + ("?board=ideal" if getattr(a, "ideal_board", False) else ""), "scenario": a.scenario,
            "n_channels": a.channels, "mode": m, "i0_ua": cal.i0_ua, "t0_us": cal.t0_us, "x_star_ohm": cal.x_star_ohm,
            "y_star_pc": cal.y_star_pc, **lim, "started": time.strftime("%Y-%m-%dT%H:%M:%S")}


def cmd_sim(a) -> int:
    keys, duration = scenario_keys(a.scenario)
    check_calibration(a.i0_ua, a.t0_us, a.x_star_ohm, a.y_star_pc)  # before the VM starts
    _lab_check(a)
    _finite("lsl_wait", a.lsl_wait, 0, 3600)
    cal = Calib(a.i0_ua, a.t0_us, a.x_star_ohm, a.y_star_pc)
    with open_transport(f"sim://steady?channels={a.channels}" + ("&board=ideal" if a.ideal_board else "")) as t:
        # the simulated board's own soft limits (held without a DAC gain in its flash), as `calibrate` checks them
        _within_soft_limits(Device(t).info(), cal.i0_ua, cal.t0_us, "--i0-ua", sim=True)
    modes = ["akhtar", "open"] if a.mode == "both" else [a.mode]
    out = Path(a.out)
    stem = Path(a.scenario).stem
    out_folder(out, create=False)
    refuse_existing([out / f"{stem}-{m}.csv" for m in modes] + ([] if a.no_plot else [out / f"{stem}.png"]),
                    a.overwrite)
    out_folder(out)
    files: list[Path] = []  # each run's file, written (atomically) as the run completes
    try:
        return _sim(a, keys, duration, cal, modes, out, files)
    except KeyboardInterrupt:  # every completed run's file is kept: say which
        say(f"interrupted: kept {', '.join(map(str, files))} (the runs that completed)" if files else
            "interrupted: no run was complete, no file written")
        raise


def _sim(a, keys, duration, cal, modes, out, files: list[Path]) -> int:
    from .progress import Progress

    runs = {}
    stem = Path(a.scenario).stem
    for m in modes:
        t0 = time.perf_counter()
        say(f"running {a.scenario} ({duration:.0f} s simulated, {a.channels} channel(s), mode {m}) in the MicroPython VM ...")
        prog = Progress(f"sim {m}")

        def show(t_s, prog=prog):
            prog.work(t_s, duration)
            prog.tick(f"{t_s:.1f} of {duration:.0f} s simulated")

        def seen(reps, prog=prog):
            for r in reps:
                if isinstance(r, Telemetry):
                    prog.add(r)

        try:
            reps = run_firmware(a.scenario, m, cal, a.channels, a.seed, progress=show, ideal=a.ideal_board,
                                on_reports=seen)
        except KeyboardInterrupt:  # an unfinished run writes no file; say how far it got
            say(prog.summary(f"{prog.work_done:.1f} of {duration:.0f} s simulated; interrupted: no file for the "
                             f"{m} run"))
            raise
        prog.clear()
        bad = [r for r in reps if not isinstance(r, Telemetry) and not r.ok]
        if bad:
            raise SimError(f"the device refused: {bad[0].words()}")
        tel = [r for r in reps if isinstance(r, Telemetry)]
        info = next((r for r in reps if isinstance(r, Info)), None)
        path = out / f"{stem}-{m}.csv"
        with Outputs() as outputs:  # a temporary name renamed over the final one: complete or absent
            write_recording(outputs.path(path), tel, sim_meta(a, cal, m, info))
        runs[m] = tel
        files.append(path)
        done = Progress(f"  sim {m}", clock=prog.clock)  # the summary, from every report of the run
        done.t0 = prog.t0
        for t in tel:
            done.add(t)
        say(done.summary(f"{duration:.0f} s simulated -> {path}"))
        if a.lsl:
            from .lsl.link import stream_run

            c = Commands()
            auto = [c.set_mode(MODES[m]), c.calibrate(cal.i0_ua, cal.t0_us, cal.x_star_ohm, cal.y_star_pc),
                    c.arm()]  # what the simulated board's --auto did, for the markers
            auto = [r[:1] + b"\0" + r[2:] for r in auto]  # its commands carry tag 0
            meta = dict(sim_meta(a, cal, m, info), serial=f"sim-{stem}-{m}", n_channels=a.channels)
            say(stream_run(meta, a.channels, reps, auto, a.lsl_wait, say))
    if not a.no_plot:
        from .plot import fig5

        recs = [("with the controller" if m == "akhtar" else "open loop", *read_recording(files[k]))
                for k, m in enumerate(modes)]
        png = out / f"{stem}.png"
        with Outputs() as outputs:
            fig5(recs, outputs.path(png))
        files.append(png)
        say(f"  figure (the paper's Fig. 5 layout) -> {png}")
    say("")
    say("mQ error: |median(measured - target)| over each hold, in uC/kohm (the paper's settle threshold: 2.5e-05);")
    say("(bound) = the law needs I or T beyond its limits, which are held (paper, Discussion)")
    for line in phase_table(keys, duration, runs):
        say(line)
    return 0


# ------------------------------------------------------------ devices
def cmd_info(a) -> int:
    with open_transport(a.device) as t:
        d = Device(t)
        i = d.info()
        say(f"{a.device}: steadytouch firmware {i.firmware} on {i.board}, {i.n_channels} channel(s)")
        say(f"  hard limits: I <= {i.hard_i_max_ua} uA, T <= {i.hard_t_max_us} us, Q <= {i.hard_q_max_pc} pC, "
            f"compliance {i.compliance_mv / 1000:g} V" + (" (held)" if i.held else " (lowered)" if i.dac_low else ""))
        if not i.reports_held_limits:
            say(f"  firmware {i.firmware} reports the board's nominal hard limits even where they are held (a "
                "channel with no DAC gain latches above x 0.965 at the gate): `steadytouch flash` updates it")
        own = d.own_limits() if i.reports_held_limits else None  # GET_INFO page 1 (None: firmware before it)
        if i.held:
            say(f"  held: {held_reason(i.dac_gain_applied, i.nominal)}")
        elif i.dac_low:
            low = [f"ch{ch} {c.dac_gain_ppm / 1e6:.4f}" for ch in range(i.n_channels)
                   for c in [d.calibration(ch)] if 0 < c.dac_gain_ppm < hp.VMON_DAC_PPM_MAX]
            mine = "; the board's own: I {} uA, Q {} pC".format(*i.nominal) if i.nominal else ""
            say(f"  lowered: the board's own limits x the lowest DAC gain measured / {hp.VMON_DAC_PPM_MAX / 1e6:g} "
                f"({', '.join(low)}): the current delivered stays within the board's own whatever the DAC's true "
                f"gain in its window{mine}")
        if (i.held or i.dac_low) and own is None:
            say(f"  firmware {i.firmware} does not report the board's own limits beside the lowered ones (GET_INFO "
                f"page 1, firmware {'.'.join(map(str, FW_OWN_LIMITS))} on): `steadytouch flash` updates it")
        soft = f"  soft limits: I {i.i_min_ua}-{i.i_max_ua} uA, T {i.t_min_us}-{i.t_max_us} us, Q <= {i.q_max_pc} pC"
        if own is not None and (own.i_min_ua, own.i_max_ua, own.q_max_pc) != (i.i_min_ua, i.i_max_ua, i.q_max_pc):
            soft += (f" (set: I {own.i_min_ua}-{own.i_max_ua} uA, Q <= {own.q_max_pc} pC; lowered to the hard "
                     "limits in force, `steadytouch limits` or `selftest --scope` sets them again)")
        say(soft)
        say(f"  mode {MODE_WORDS.get(i.mode, i.mode)}, {i.rate_hz} Hz, "
            f"keep-alive {'off' if not i.keepalive_ms else str(i.keepalive_ms) + ' ms'}")
        for ch in range(i.n_channels):
            c = d.calibration(ch)
            if c.calibrated:
                rp0 = f", Rp0 {c.rp0_ohm} ohm" if c.rp0_ohm else ""
                say(f"  ch{ch}: I0 {c.i0_ua} uA, T0 {c.t0_us} us, x* {c.x_star_ohm} ohm, y* {c.y_star_pc} pC{rp0}"
                    + (" (armed)" if c.flags & 2 else ""))
            else:
                say(f"  ch{ch}: not calibrated")
            if c.vmon_gain_ppm or c.dac_gain_ppm:  # steadytouch selftest's correction
                dac = f"DAC gain {c.dac_gain_ppm / 1e6:.4f}" if c.dac_gain_ppm else "DAC gain not measured"
                if c.dac_gain_ppm and not i.dac_gain_applied:  # what the device itself says (GET_INFO's flags)
                    dac = (f"DAC gain {c.dac_gain_ppm / 1e6:.4f} stored, not applied: this board has no "
                           "gain-corrected DAC")
                mon = (f"monitor gain {c.vmon_gain_ppm / 1e6:.4f} offset {c.vmon_offset_mv:+d} mV"
                       if c.vmon_gain_ppm else "monitor uncorrected")
                say(f"  ch{ch}: {mon}, {dac}")
            if c.skin_rs_ohm or c.skin_beta_q16 or c.skin_cp_pf:  # (firmware 0.4.1 on: MODE_FAST's model)
                tau = ("tau not read" if c.skin_tau_q16 == sc.SKIN_TAU_OFF else
                       f"tau read x {2 ** (c.skin_tau_q16 / 65536):.3f} (rule 7)")
                say(f"  ch{ch}: skin model Rs {c.skin_rs_ohm} ohm, beta {c.skin_beta_q16 / 65536:.3f}, "
                    f"Cp {c.skin_cp_pf} pF; {tau}")
        say(f"  correction: {VMON_STATE_WORDS.get(i.vmon_state, i.vmon_state)}")
    return 0


_BUILDERS = {"limits": "set_limits", "mode": "set_mode", "skin": "set_skin", "calibrate": "calibrate",
             "arm": "arm", "disarm": "disarm"}


def _precheck(fn_name, *args):
    """Build the command once, unsent: an argument out of range is one clear line before the device is opened."""
    getattr(Commands(), _BUILDERS[fn_name])(*args)


def _simple(fn_name, *args_from):
    def run(a) -> int:
        _precheck(fn_name, *[f(a) for f in args_from])
        with open_transport(a.device) as t:
            d = Device(t)
            ack = getattr(d, fn_name)(*[f(a) for f in args_from])
            say(f"{a.device}: {ack.words()}")
        return 0

    return run


def _channel(a):
    return hp.CH_ALL if a.channel is None else a.channel


def cmd_arm(a) -> int:
    """Arm, keep the device alive while this runs, disarm on exit (Ctrl-C, SIGTERM, --seconds,
    or every armed channel stopped by the device)."""
    ch = _channel(a)
    _precheck("arm", ch)
    a.seconds = _seconds(a)
    from .progress import Progress

    prog = Progress("arm", a.seconds)
    with open_transport(a.device) as t:
        d = Device(t)
        info = d.info()
        _warn_vmon(info)
        n = info.n_channels
        chans = set(range(n)) if ch == hp.CH_ALL else {ch}
        stopped: dict[int, int] = {}
        t_end = time.monotonic() + a.seconds if a.seconds else None
        try:
            with d.live(arm=ch):
                why = (f"the device stops by itself {d.ka_ms} ms after the host goes silent" if d.ka_ms
                       else "keep-alive off: a virtual-clock simulation")
                say(f"{a.device}: arm: ok; stimulating while this runs (Ctrl-C disarms; {why})")
                while (t_end is None or time.monotonic() < t_end) and not chans <= set(stopped):
                    rep = d.read(0.25)
                    if isinstance(rep, Telemetry) and rep.channel in chans:
                        prog.add(rep)
                        if not rep.armed:
                            stopped[rep.channel] = rep.stop
                    prog.tick(f"{d.lost} reports lost")
        except KeyboardInterrupt:
            pass
        say(prog.summary(f"{d.lost} reports lost"))
        for c, why in sorted(stopped.items()):
            say(f"  ch{c}: {STOP_WORDS.get(why, why)}")
        say(_disarm_words(d, a.device))
    return 1 if any(w not in (hp.STOP_DISARMED, hp.STOP_NONE) for w in stopped.values()) else 0


class _Asks:
    """The responder, with the status line cleared before each question (the person's
    prompt is drawn on the same terminal line)."""

    def __init__(self, responder, prog):
        self.r, self.prog = responder, prog

    def __getattr__(self, name):
        return getattr(self.r, name)

    def key(self, **kw) -> str:
        self.prog.clear()
        return self.r.key(**kw)


def _guided_session_class():
    from .session import T_STEPS_US, Session

    class GuidedSession(Session):
        """The guided session with its progress: steps matched of all (per level each T step after the
        reference, and the re-check), the points matched so far (kept if the session is cut short)."""

        def __init__(self, dev, responder, prog, n_levels, **kw):
            super().__init__(dev, responder, **kw)
            self.prog, self.level = prog, ""
            self.steps, self.total = 0, n_levels * len(T_STEPS_US)
            self.rows: list[dict] = []
            prog.work(0, self.total)

        def where(self) -> str:
            return f"{self.steps} of {self.total} steps matched" + (f", level {self.level}" if self.level else "")

        def match(self, ref, t_us, i_start, level):
            self.level = level
            got = super().match(ref, t_us, i_start, level)
            self.steps += 1
            self.prog.work(self.steps, self.total)
            return got

        def _row(self, level, p):
            row = super()._row(level, p)
            self.rows.append(row)
            return row

    return GuidedSession


def cmd_calibrate_interactive(a) -> int:
    from . import fit as F
    from .participant import write_rows
    from .progress import Progress, Watch
    from .session import KeyboardResponder, SimResponder, Stopped

    _GuidedSession = _guided_session_class()

    _finite("present_s", a.present_s, 0.05, 60)
    for k in ("weak_ua", "strong_ua"):
        if not 1 <= getattr(a, k) <= sc.I_LIMIT_UA:
            raise ValueError(f"--{k.replace('_', '-')} {getattr(a, k)} out of range: 1..{sc.I_LIMIT_UA} uA")
    responder = SimResponder(a.seed) if a.participant == "sim" else KeyboardResponder()
    out = Path(a.out)
    out_folder(out, create=False)
    refuse_existing([out / n for n in ("session.csv", "calibration.json", "session-partial.csv")], a.overwrite)
    levels = {"weak": a.weak_ua, "strong": a.strong_ua}
    prog = Progress("calibrate")
    with open_transport(a.device) as t:
        d = Device(t)
        _levels_within_hard_limits(d.info(), levels)
        s = _GuidedSession(Watch(d, prog, lambda: s.where()), _Asks(responder, prog), prog, len(levels), channel=a.channel or 0,
                           present_s=a.present_s, log=lambda text: (prog.clear(), say(text)))
        say(f"guided calibration on {a.device}, channel {a.channel or 0} (q stops at once)")
        try:
            with d.live():  # keep-alive while presenting; DISARM however the session ends
                res = s.run(levels)
        except (Stopped, KeyboardInterrupt) as e:  # q, Ctrl-C, SIGTERM: the matches made so far are kept
            kept = ""
            if s.rows:
                out_folder(out)
                with Outputs() as o:
                    write_rows(o.path(out / "session-partial.csv"), s.rows)
                kept = f"; the {len(s.rows)} points matched so far -> {out / 'session-partial.csv'} (not fitted)"
            say(prog.summary(f"{s.where()}; {'stopped' if isinstance(e, Stopped) else 'interrupted'}, "
                             f"nothing was sent{kept}"))
            say(_disarm_words(d, a.device))
            if isinstance(e, Stopped):
                return 1
            raise
        say(prog.summary(s.where()))
        out_folder(out)
        data = out / "session.csv"
        with Outputs() as o:  # the measured session is kept even if the fit fails
            write_rows(o.path(data), res.rows)
        fitres = F.fit(F.load(data), device_range=True)
        cal = dict(fitres.calibration(), source=str(data))
        with Outputs() as o:
            o.path(out / "calibration.json").write_text(dump_json(cal, "calibration") + "\n")
        say(f"{res.presentations} presentations; data -> {data}")
        say(f"fit: x* = {fitres.x_star_ohm:.0f} ohm, y* = {fitres.y_star_pc:.0f} pC, mean r2 Q-Rp {fitres.mean_r2_q:.3f}, "
            f"Ep-Rp {fitres.mean_r2_ep:.3f} -> {out / 'calibration.json'}")
        weak = [r for r in res.rows if r["condition"] == "weak"]
        op = next(r for r in weak if r["t_us"] == a.t0_us) if any(r["t_us"] == a.t0_us for r in weak) else weak[len(weak) // 2]
        send = a.send or (a.participant != "sim" and input(
            f"send the calibration (I0 {op['i_ua']} uA, T0 {op['t_us']} us, x* {cal['x_star_ohm']}, y* {cal['y_star_pc']})? [y/N] ")
            .strip().lower() == "y")
        if send:
            check_calibration(op["i_ua"], op["t_us"], cal["x_star_ohm"], cal["y_star_pc"])
            d.mode(sc.MODE_AKHTAR)
            ack = d.calibrate(op["i_ua"], op["t_us"], cal["x_star_ohm"], cal["y_star_pc"], hp.CH_ALL)
            say(f"{a.device}: {ack.words()} (I0 {op['i_ua']} uA, T0 {op['t_us']} us, x* {cal['x_star_ohm']} ohm, "
                f"y* {cal['y_star_pc']} pC); `steadytouch arm` starts stimulating")
    return 0


def _levels_within_hard_limits(i: Info, levels: dict[str, int]) -> None:
    """A reference level the board can never deliver at 200 us (above the hard limits it reports, e.g. held for
    want of a DAC gain): one line before anything is presented. (Within them, the session keeps to the soft limits.)"""
    from .session import T_STEPS_US

    t_us = T_STEPS_US[0]
    top = min(i.hard_i_max_ua, i.hard_q_max_pc // t_us)
    for k, v in levels.items():
        if v > top:
            raise ValueError(f"--{k}-ua {v} out of range: the device accepts at most {top} uA at {t_us} us"
                             + _why_not_higher(i, True))


def cmd_calibrate(a) -> int:
    if a.interactive:
        return cmd_calibrate_interactive(a)
    vals = {"i0_ua": a.i0_ua, "t0_us": a.t0_us, "x_star_ohm": a.x_star_ohm, "y_star_pc": a.y_star_pc}
    if a.from_file:
        data = _calibration_json(a.from_file)
        for k in vals:
            if vals[k] is None and k in data:
                vals[k] = _json_number(a.from_file, data, k, whole=True)
    missing = [k for k, v in vals.items() if v is None]
    if missing:
        raise ValueError("calibrate needs " + ", ".join("--" + k.replace("_", "-") for k in missing)
                         + " (or --from calibration.json)")
    _precheck("calibrate", vals["i0_ua"], vals["t0_us"], vals["x_star_ohm"], vals["y_star_pc"], _channel(a))
    with open_transport(a.device) as t:
        d = Device(t)
        info = d.info()
        _warn_vmon(info)
        _within_soft_limits(info, vals["i0_ua"], vals["t0_us"])
        ack = d.calibrate(vals["i0_ua"], vals["t0_us"], vals["x_star_ohm"], vals["y_star_pc"], _channel(a))
        say(f"{a.device}: {ack.words()} (I0 {vals['i0_ua']} uA, T0 {vals['t0_us']} us, "
            f"x* {vals['x_star_ohm']} ohm, y* {vals['y_star_pc']} pC; Rp0 is measured on the first pulse after arm)")
    return 0


def _why_not_higher(i: Info, beyond_hard: bool, sim: bool = False) -> str:
    """Why a value above the device's soft limits is refused: the hard limits it reports (held for want of a DAC
    gain: say so and how to lift it), or soft limits `steadytouch limits` may raise (sim: board_config's)."""
    if beyond_hard and i.held:
        return f"; {held_reason(i.dac_gain_applied, i.nominal)}"
    if beyond_hard:
        return " (the board's hard limits)"
    if sim:
        return " (the simulated board's, firmware/board_config.py)"
    return " (`steadytouch limits` changes them, within the board's hard limits)"


def _within_soft_limits(i: Info, i0_ua: int, t0_us: int, name: str = "i0_ua", sim: bool = False) -> None:
    """The device's own soft limits (read back from it), checked before the calibration is sent."""
    t_name = "--t0-us" if sim else "t0_us"
    if not i.i_min_ua <= i0_ua <= i.i_max_ua:
        raise ValueError(f"{name}={i0_ua} out of range: the device's soft limits are {i.i_min_ua}..{i.i_max_ua} uA"
                         + _why_not_higher(i, i0_ua > i.hard_i_max_ua, sim))
    if not i.t_min_us <= t0_us <= i.t_max_us:
        raise ValueError(f"{t_name}={t0_us} out of range: the device's soft limits are {i.t_min_us}..{i.t_max_us} us"
                         + _why_not_higher(i, False, sim))
    if i0_ua * t0_us > i.q_max_pc:
        raise ValueError(f"{name}*{t_name}={i0_ua * t0_us} pC out of range: the device's charge limit is {i.q_max_pc} "
                         "pC" + (_why_not_higher(i, True) if i0_ua * t0_us > i.hard_q_max_pc else ""))


def _calibration_json(path) -> dict:
    from .files import read_text_file

    try:
        data = json.loads(read_text_file(path, "calibration JSON"))
    except json.JSONDecodeError as e:
        raise FileProblem(f"{path}: not a readable calibration JSON ({e})") from None
    if not isinstance(data, dict):
        raise FileProblem(f"{path}: a calibration JSON is an object with x_star_ohm and y_star_pc, "
                          f"not a {type(data).__name__}")
    return data


def _json_number(path, data: dict, key: str, whole=False):
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise FileProblem(f"{path}: {key} must be a finite number, not {v!r}")
    if whole:
        if abs(v) >= 2**31:
            raise FileProblem(f"{path}: {key} = {v} out of range (|x| < 2**31)")
        return int(round(v))
    return float(v)


# ------------------------------------------------------------ record / monitor
def device_meta(d: Device, url: str) -> dict:
    i: Info = d.info()
    _warn_vmon(i)
    meta = {"firmware": i.firmware, "board": i.board, "device": url, "i_min_ua": i.i_min_ua,
            "i_max_ua": i.i_max_ua, "t_min_us": i.t_min_us, "t_max_us": i.t_max_us, "q_max_pc": i.q_max_pc,
            "hard_i_max_ua": i.hard_i_max_ua, "hard_q_max_pc": i.hard_q_max_pc, "rate_hz": i.rate_hz}
    meta.update({"hard_t_max_us": i.hard_t_max_us, "compliance_mv": i.compliance_mv, "n_channels": i.n_channels,
                 "mode": MODE_WORDS.get(i.mode, i.mode)})  # (the LSL stream's metadata too)
    for ch in range(i.n_channels):
        c: CalInfo = d.calibration(ch)
        if c.calibrated:
            meta.update({f"ch{ch}_i0_ua": c.i0_ua, f"ch{ch}_t0_us": c.t0_us, f"ch{ch}_x_star_ohm": c.x_star_ohm,
                         f"ch{ch}_y_star_pc": c.y_star_pc, f"ch{ch}_rp0_ohm": c.rp0_ohm})
            if i.reports_skin:  # (MODE_FAST's model: `audit` replays it; 0 0 0 none)
                meta.update({f"ch{ch}_skin_rs_ohm": c.skin_rs_ohm, f"ch{ch}_skin_beta_q16": c.skin_beta_q16,
                             f"ch{ch}_skin_cp_pf": c.skin_cp_pf})
            if i.reports_tau:  # (rule 7's tau gain: off or the one SET_SKIN gave)
                meta[f"ch{ch}_skin_tau_q16"] = c.skin_tau_q16
    meta["started"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    return meta


def _disarm_words(d: Device, url: str) -> str:
    if d.disarmed:
        return f"{url}: disarmed"
    return (f"{url}: could not confirm the DISARM (the device is gone or silent); "
            "a board stops by itself after its keep-alive timeout")


def cmd_record(a) -> int:
    """Telemetry to a CSV streamed as it comes (flushed every second: a killed
    recording keeps all but its last second); the device is kept alive while
    recording and disarmed at the end, however the recording ends."""
    from .progress import Progress

    out = Path(a.file)
    a.seconds = _seconds(a)
    writable_file(out, "recording.csv")
    refuse_existing([out], a.overwrite, "choose another file name")
    _finite("lsl_wait", a.lsl_wait, 0, 3600)
    _lab_check(a)
    with open_transport(a.device) as t:
        link = _lab_link(t, a)
        d = Device(link.tap if link else t)
        meta = device_meta(d, a.device)
        _lab_start(link, meta, d, a.lsl_wait)
        rec = Recorder(out, meta)
        say(f"recording {a.device} -> {out}  (Ctrl-C to stop)")
        t_end = time.monotonic() + a.seconds if a.seconds else None
        prog = Progress("record", a.seconds)
        lost_device = cannot_write = None
        try:
            with d.live(arm=hp.CH_ALL if a.arm else None), _lab_samples(link), _stop_between_reports() as stop:
                while not stop and (t_end is None or time.monotonic() < t_end):
                    try:
                        rep = d.read(0.5)
                    except Disconnected as e:
                        lost_device = e
                        break
                    if isinstance(rep, Telemetry):
                        try:
                            rec.write(rep)
                        except RecordingError as e:  # a full disk: stop (and disarm), say what the file holds
                            cannot_write = e
                            break
                        prog.add(rep)
                    prog.tick(f"{d.lost} reports lost")
        except KeyboardInterrupt:
            pass
        finally:
            try:
                rec.close()
            except RecordingError as e:
                cannot_write = cannot_write or e
        bad = f", {d.bad} undecodable reports skipped" if d.bad else ""
        say(prog.summary(f"{d.lost} reports lost{bad}"))
        say(f"saved {rec.saved} rows to {out}")
        say(_disarm_words(d, a.device))
        _lab_finish(link)
        if cannot_write is not None:
            print(f"steadytouch: {cannot_write}", file=sys.stderr)
            return 1
        if lost_device is not None:
            print(f"steadytouch: device lost: {lost_device}", file=sys.stderr)
            return 1
    return 0


@contextlib.contextmanager
def _stop_between_reports():
    """Ctrl-C, SIGTERM or SIGHUP inside a recording loop end it between two reports (a flag
    the loop checks, within its 0.5 s read), never between a report's LSL sample (the tap
    pushes it as it is read) and its CSV row: the CSV holds every sample LSL sent (found by
    tests/lab/test_lsl.py: one sample on LSL and not in the CSV). Outside the loop (the
    disarm after it) the signals act as before."""
    import threading

    stop: list[int] = []
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
            if sig is not None and signal.getsignal(sig) not in (signal.SIG_IGN, None):
                old[sig] = signal.signal(sig, lambda signum, frame: stop.append(signum))
    try:
        yield stop
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _lab_check(a) -> None:
    """--lsl without pylsl: one line saying how to get it, before the device is opened."""
    if getattr(a, "lsl", False):
        from .lsl import require

        require()


def _lab_link(t, a):
    if not getattr(a, "lsl", False):
        return None
    from .lsl.link import LabLink

    return LabLink(t, a.device)


def _lab_start(link, meta: dict, d: Device, wait_s: float = 0.0) -> None:
    """Open the outlets; with --lsl-wait, wait (keeping the device alive) for a recorder to connect."""
    if link is None:
        return
    meta["serial"] = link.serial()
    link.start(meta, int(meta["n_channels"]))
    say("LSL: streaming 'steadytouch telemetry' (StimTelemetry) and 'steadytouch markers' (Markers)")
    if wait_s > 0 and not link.streams.consumers():
        say(f"LSL: waiting up to {wait_s:g} s for a recorder (e.g. LabRecorder) to connect ...")
        feed, link.tap.feed = link.tap.feed, None  # the LSL stream starts with the recording, not before
        try:
            if d.t.realtime:
                d.keep_alive()  # (its ack's wait reads reports too: none of them is on the stream)
            end = time.monotonic() + wait_s
            while not link.streams.consumers() and time.monotonic() < end:
                d.read(0.05)
        finally:
            link.tap.feed = feed
        if not link.streams.consumers():
            say("LSL: no recorder connected; going on")


@contextlib.contextmanager
def _lab_samples(link):
    """Pulses go on the LSL stream while the recording loop runs (the CSV's rows); the markers
    of what follows (the closing DISARM) still go out."""
    try:
        yield
    finally:
        if link is not None and link.feed is not None:
            link.feed.samples = False


def _lab_finish(link) -> None:
    if link is not None:
        say(link.finish())


def cmd_monitor(a) -> int:
    from .monitor import LivePlot, MonitorState
    from .progress import Progress

    state = MonitorState()
    tty = sys.stdout.isatty()
    a.seconds = _seconds(a)
    _finite("lsl_wait", a.lsl_wait, 0, 3600)
    _lab_check(a)
    live = LivePlot() if a.plot else None
    prog = Progress("monitor", a.seconds)
    with open_transport(a.device) as t:
        link = _lab_link(t, a)
        d = Device(link.tap if link else t)
        if link or live:
            meta = device_meta(d, a.device)
            _lab_start(link, meta, d, a.lsl_wait)
            if live:
                live.set_meta(meta)
        t_end = time.monotonic() + a.seconds if a.seconds else None
        next_draw = 0.0
        lost = None
        try:
            with d.live(arm=hp.CH_ALL if a.arm else None):  # keep-alive; DISARM however it ends
                while t_end is None or time.monotonic() < t_end:
                    rep = d.read(0.05)
                    if isinstance(rep, Telemetry):
                        state.add(rep)
                        prog.add(rep)
                        if live:
                            live.add(rep)
                    now = time.monotonic()
                    if now >= next_draw:
                        next_draw = now + 0.1  # 10 screens a second
                        if live:
                            d.feed()  # a redraw can take most of the keep-alive timeout on a busy machine
                        if live and not live.draw():
                            break  # the window was closed
                        if live:
                            _raise_lost_signal()
                        screen = state.render(a.device, d.lost)
                        if tty:
                            sys.stdout.write("\x1b[H\x1b[2J" + screen + "\n" + prog.line() + "\n")
                            sys.stdout.flush()
        except KeyboardInterrupt:
            pass
        except Disconnected as e:
            lost = e
        if not tty or lost:
            say(state.render(a.device, d.lost))
        say(prog.summary(f"{d.lost} reports lost" + (f", {live.draws} plot redraws" if live else "")))
        if d.disarmed is not None:
            say(_disarm_words(d, a.device))
        _lab_finish(link)
        if lost:
            print(f"steadytouch: device lost: {lost}", file=sys.stderr)
            return 1
    return 0


# ------------------------------------------------------------ files
def cmd_audit(a) -> int:
    from .audit import audit

    meta, rows = read_recording(a.file, allow_cut=True)
    r = audit(meta, rows, a.file)
    if CUT in meta:
        say(f"{a.file}: cut short at line {meta[CUT]} (an interrupted recording): auditing its {len(rows)} complete rows")
    for m in r.mismatches[:20]:
        say(f"  row {m.line} (seq {m.seq}, ch{m.channel}): device sent I,T = {m.recorded}, the reference gives {m.expected}")
    if len(r.mismatches) > 20:
        say(f"  ... and {len(r.mismatches) - 20} more")
    if r.checked == 0:
        say(f"{a.file}: no pulse could be replayed: the recording has no calibration pulse and its header no Rp0")
        return 1
    if r.mismatches and r.no_skin:
        say(f"{a.file}: its header has no skin model (firmware before 0.4.1 does not report it): MODE_FAST's pulses were "
            "replayed without the one the device had, so they can differ (`steadytouch flash` updates the board)")
    verdict = "bit-exact" if not r.mismatches else f"{len(r.mismatches)} MISMATCH(ES)"
    say(f"{a.file}: {r.checked} pulses replayed through sensation_core: {verdict}"
        + (f" ({r.skipped} before a calibration was known, skipped)" if r.skipped else ""))
    return 1 if r.mismatches else 0


def cmd_plot(a) -> int:
    from .plot import fig5, planes

    if not 0 <= a.channel <= 3:
        raise ValueError(f"--channel {a.channel} out of range: 0..3")
    recs = []
    for f in a.files:
        meta, rows = read_recording(f, allow_cut=True)
        title = {"akhtar": "with the controller", "open": "open loop"}.get(meta.get("mode", ""), meta.get("mode") or Path(f).stem)
        recs.append((title, meta, rows))
        if not any(r["channel"] == a.channel and r["i_ua"] > 0 for r in rows) and (a.planes or len(a.files) == 1):
            raise RecordingError(f"{f}: no pulses on channel {a.channel}: nothing to plot")
    if not any(any(r["channel"] == a.channel and r["i_ua"] > 0 for r in rows) for _, _, rows in recs):
        raise RecordingError(f"no pulses on channel {a.channel} in any of the recordings: nothing to plot")
    out = Path(a.out or Path(a.files[0]).with_suffix(".png"))
    p = out.with_name(out.stem + "-planes.png")
    for f in (out, p) if a.planes else (out,):
        writable_file(f, Path(a.files[0]).stem + ".png")
    if out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise FileProblem(f"--out {out}: a figure's file name ends in .png (or .pdf, .svg)")
    refuse_existing([out] + ([p] if a.planes else []), a.overwrite)
    with Outputs() as o:
        fig5(recs, o.path(out), a.channel)
        if a.planes:
            planes(recs[0][1], recs[0][2], o.path(p), a.channel)
    say(f"figure -> {out}")
    if a.planes:
        say(f"planes -> {p}")
    return 0


def cmd_devices(a) -> int:
    from .transport import _hid_module

    found = 0
    try:
        mod = _hid_module()
        for dinfo in mod.enumerate(hp.VID, hp.PID):
            found += 1
            say(f"hid://{dinfo['vendor_id']:04x}:{dinfo['product_id']:04x}/{dinfo.get('serial_number') or ''}  "
                f"{dinfo.get('product_string') or ''}")
    except Exception as e:  # no HID backend on this machine
        say(f"(HID not available: {e})")
    from serial.tools import list_ports

    for p in list_ports.comports():
        if p.vid == 0x2E8A:
            found += 1
            say(f"{p.device}  MicroPython REPL (USB {p.vid:04x}:{p.pid:04x}) - flash with `steadytouch flash --port {p.device}`")
    if not found:
        say("no steadytouch board or Pico found; `sim://peel` runs the simulator")
    return 0


def cmd_flash(a) -> int:
    from . import flash as F

    if a.build_only:
        b = F.build(Path(a.build_dir))
        say(f"compiled {len(b.files)} files for the RP2040 into {a.build_dir} (the board also needs the pinned "
            "USB libraries: `steadytouch flash` installs them)")
        return 0
    F.flash(F.Options(port=a.port, build_dir=Path(a.build_dir), lib_dir=a.lib_dir, online=a.online,
                      dry_run=a.dry_run, boot_timeout_s=a.boot_timeout_s, device=a.device,
                      hid_check=not a.no_hid_check, ignore_stored_correction=a.ignore_stored_correction), say=say)
    return 0


# ------------------------------------------------------------ calibration data
def cmd_fit(a) -> int:
    from . import fit as F

    out = Path(a.out)
    out_folder(out, create=False)
    refuse_existing([out / "calibration.json", out / "fit.png"], a.overwrite)
    sets = F.load(a.file)
    res = F.fit(sets)
    cal = dict(res.calibration(), source=str(a.file))
    q_min = min(float(s.q_pc.min()) for s in sets)
    if not (sc.X_STAR_MIN_OHM <= cal["x_star_ohm"] <= 0 and 0 <= cal["y_star_pc"] < q_min):
        raise F.DataError(f"{a.file}: the convergence point (x*, y*) = ({cal['x_star_ohm']} ohm, {cal['y_star_pc']} pC) "
                          f"is outside what the device accepts (x* in {sc.X_STAR_MIN_OHM}..0 ohm, 0 <= y* < the smallest "
                          f"Q, {q_min:.0f} pC): these data give no usable calibration")
    report = dump_json({"calibration": cal, "by_condition": res.by_condition, "per_set": res.per_set}, "fit")
    if a.json:
        print(report)
    else:
        say(f"{a.file}: {res.n_sets} participant x condition data sets")
        say(f"convergence point: x* = {res.x_star_ohm:.0f} ohm, y* = {res.y_star_pc:.0f} pC "
            f"({res.x_star_ohm / 1e3:.2f} kohm, {res.y_star_pc / 1e6:.3f} uC); mean r2 Q-Rp {res.mean_r2_q:.3f}, "
            f"Ep-Rp {res.mean_r2_ep:.3f}")
        say("one-tailed Wilcoxon signed-rank test of r2 > 0.7 per condition, Holm-Bonferroni corrected:")
        for line in F.table(res):
            say("  " + line)
    out_folder(out)
    png = out / "fit.png"
    with Outputs() as o:
        o.path(out / "calibration.json").write_text(dump_json(cal, "calibration") + "\n")
        F.figure(sets, res, o.path(png))
    if not a.json:
        say(f"wrote {out / 'calibration.json'} and {png}")
    return 0


def cmd_skin(a) -> int:
    args, tau = _skin_fit(a.file, a.send)
    if a.send:
        Commands().set_skin(*args, _channel(a), tau)  # (a value out of range: one line before the device is opened)
        with open_transport(a.device) as t:
            _send_skin(Device(t), args, _channel(a), tau, a.device)
    return 0


def _skin_fit(path, send: bool) -> tuple[tuple, int]:
    """`skin`'s fit of a pulses or sweeps CSV, said: (set_skin's args, rule 7's tau gain)."""
    from . import skin

    sweeps = skin.load_sweeps(path)
    whole, cut = skin.whole_sweeps(sweeps)  # a sweep cut short (an interrupted `sweep`, then `sweep --more`): left out
    for k in cut:
        say(f"{path}: sweep {k + 1} of {len(sweeps)} has {len(sweeps[k])} of its {len(whole[0])} pulses (an "
            "interrupted recording): left out")
    sweeps = whole
    if len(sweeps) > 1:  # repeated sweeps: the averaged fit, its uncertainty, and whether to send it
        i0, t0 = int(sweeps[0][0][0]), int(sweeps[0][0][1])
        f = skin.fit_sweeps(sweeps, i0, t0)
        m = f.model
        say(f"{path}: {f.sweeps} sweeps averaged: Rs {m.rs_ohm} ohm, beta {m.beta:.4f} (Q.16 {m.beta_q16}), "
            f"Cp {m.cp_pf} pF; Rp shape known to {f.shape_sd:.2%} (1 sd) around I0 {i0} uA, T0 {t0} us; "
            f"worst misfit {m.worst_misfit:.3%}")
        if not f.trusted:
            say(f"not trusted: {f.why}; MODE_FAST runs model-free" + (" (the device's model is removed)" if send else ""))
            if f.shape_sd > skin.TRUST_SHAPE_SD:
                if (n := skin.sweeps_for_trust(f)) is not None:
                    say(f"more sweeps narrow the shape's uncertainty (about 1/sqrt(n)): about {n} in all should bring "
                        f"it within {skin.TRUST_SHAPE_SD:.0%}; record {n - f.sweeps} more of the same pulses on this "
                        "electrode and fit them all again (`steadytouch sweep --more`, docs/calibration.md)")
                else:
                    say(f"more sweeps would not help enough: it would take more than {skin.SWEEPS_MOST} to bring it "
                        f"within {skin.TRUST_SHAPE_SD:.0%}; this electrode's Rp is read too noisily for a model "
                        "(check the contact and the leads, docs/calibration.md)")
        args = f.args()
        tau = _skin_tau(path, f.model) if f.trusted else sc.SKIN_TAU_OFF
    else:
        m = skin.fit(sweeps[0])
        say(f"{path}: Rs {m.rs_ohm} ohm, beta {m.beta:.4f} (Q.16 {m.beta_q16}), Cp {m.cp_pf} pF; "
            f"worst misfit {m.worst_misfit:.3%} over the pulses")
        if m.worst_misfit > 0.02:
            say("warning: the model misses some pulses by more than 2 %: MODE_FAST's model jumps will be rough")
        say("one sweep: its uncertainty is unknown; repeated sweeps (a `sweep` column) let the fit judge itself")
        args = m.args()
        tau = sc.SKIN_TAU_OFF
        if skin.load_taus(path) is not None:
            say("tau not used (rule 7): its gain is measured only on repeated sweeps the model is trusted on")
    return args, tau


def _send_skin(d: Device, args, ch, tau: int, url: str) -> None:
    """SET_SKIN on an open device, said (a firmware that does not read tau gets the model without the gain)."""
    if tau != sc.SKIN_TAU_OFF and not (i := d.info()).reports_tau:  # (its SET_SKIN ignores the gain's bytes)
        say(f"{url}: firmware {i.firmware} does not read tau (rule 7: firmware 0.5.0 on, `steadytouch "
            "flash`): the model is sent without the gain")
        tau = sc.SKIN_TAU_OFF
    ack = d.skin(*args, ch=ch, tau_q16=tau)
    say(f"{url}: {ack.words()}")


def cmd_sweep(a) -> int:
    """Calibration sweeps on one channel (host/sweep.py), written as read; then `skin`'s fit, --send sets it."""
    from . import skin
    from . import sweep as S

    lo, hi = S.SWEEPS_RANGE
    if not lo <= a.sweeps <= hi:
        raise ValueError(f"--sweeps {a.sweeps} out of range: {lo}..{hi} (3 or more tell the fit's uncertainty; "
                         f"{skin.RECOMMENDED_SWEEPS} recommended)")
    for k in ("i0_ua", "t0_us"):
        v = getattr(a, k)
        if v is not None and not 1 <= v <= (sc.I_LIMIT_UA if k == "i0_ua" else 10**6):
            raise ValueError(f"--{k.replace('_', '-')} {v} out of range: 1..{sc.I_LIMIT_UA if k == 'i0_ua' else 10**6}")
    out = Path(a.csv)
    if a.more:
        if not out.is_file():
            raise FileProblem(f"{out}: --more adds sweeps to a file `sweep` wrote; there is none")
        have = skin.load_sweeps(out)
        first, (i0, t0) = len(have), (int(have[0][0][0]), int(have[0][0][1]))
        if a.i0_ua not in (None, i0) or a.t0_us not in (None, t0):
            raise ValueError(f"--more: {out} holds sweeps of {i0} uA x {t0} us; more must be of the same pulses")
    else:
        refuse_existing([out], a.overwrite, "choose another file, or --more to add sweeps to it")
        first, i0, t0 = 0, a.i0_ua, a.t0_us
    ch = a.channel
    url = a.device
    if url.startswith("sim://") and "frames=" not in url:  # the scenario's own length is too short for the sweeps:
        url += ("&" if "?" in url else "?") + f"frames={skin.SWEEPS_MOST * 12 * 25}"  # 0.5 s a pulse, 60 sweeps
    with open_transport(url) as t:
        d = Device(t)
        info = d.info()
        _warn_vmon(info)
        if not 0 <= ch < info.n_channels:
            raise ValueError(d._no_such_channel("--channel", ch))
        cal = d.calibration(ch)
        if i0 is None or t0 is None:
            if not cal.calibrated:
                raise ValueError(f"sweep needs --i0-ua and --t0-us: channel {ch} is not calibrated (its operating "
                                 "pulse is the sweep's centre)")
            i0, t0 = i0 or cal.i0_ua, t0 or cal.t0_us
        pts = S.points(i0, t0, info)
        say(f"sweep on {a.device}, channel {ch}: {len(pts)} pulses on the mE curve of {i0} uA x {t0} us "
            f"({min(p[1] for p in pts)}..{max(p[1] for p in pts)} us), {a.sweeps} sweeps"
            f"{f' after the {first} in {out}' if first else ''}"
            f"{f', more while the fit asks (up to {skin.SWEEPS_MOST} in all)' if a.until_trusted else ''}; "
            "every channel is disarmed first; the mode and this channel's calibration are put back after (disarmed)")
        d.disarm()
        done = first
        try:
            d.mode(sc.MODE_OPEN_LOOP)
            with open(out, "a" if first else "w") as f:
                if not first:
                    f.write(",".join(S.FIELDS) + "\n")
                want = first + a.sweeps
                while True:
                    for k in range(done, want):
                        S.run(d, ch, pts, k, f)
                        done += 1
                        say(f"  sweep {k + 1} of {want}: {len(pts)} pulses read")
                    fit = skin.fit_sweeps(skin.whole_sweeps(skin.load_sweeps(out))[0], i0, t0)
                    n = skin.sweeps_for_trust(fit) if a.until_trusted else None
                    if n is None:
                        break
                    say(f"  the shape is known to {fit.shape_sd:.2%}: about {n} sweeps in all should bring it within "
                        f"{skin.TRUST_SHAPE_SD:.0%}; {n - done} more")
                    want = n
        except KeyboardInterrupt:
            say(f"sweep: interrupted after {done} whole sweeps; every reading taken is in {out} "
                "(`steadytouch skin` leaves a sweep cut short out; `sweep --more` adds to the file)")
            raise
        finally:
            try:
                d.disarm()
                d.mode(info.mode)
                if cal.calibrated:
                    d.calibrate(cal.i0_ua, cal.t0_us, cal.x_star_ohm, cal.y_star_pc, ch=ch)
            except (DeviceError, TransportError) as e:
                say(f"{a.device}: could not put the mode and channel {ch}'s calibration back ({e}): set them again "
                    "(`steadytouch mode`, `steadytouch calibrate`) before arming")
        say(f"wrote {done - first} sweeps to {out} ({done} in all)")
        args, tau = _skin_fit(out, a.send)
        if a.send:
            _send_skin(d, args, ch, tau, a.device)
    return 0


def _skin_tau(path, model) -> int:
    """Rule 7's tau gain from the sweeps' ltau_q16 column (skin.tau_gain), said; sc.SKIN_TAU_OFF when the file has
    none or it is not trusted."""
    from . import skin

    taus = skin.load_taus(path)
    if taus is None:
        say("no ltau_q16 column: tau not used (rule 7; `record` writes the decay's tau after each pulse)")
        return sc.SKIN_TAU_OFF
    g = skin.tau_gain(model, taus)
    if not g.trusted:
        say(f"tau not used (rule 7): {g.why}")
        return sc.SKIN_TAU_OFF
    say(f"tau read on {g.reads} pulses: the monitor reads it x {2 ** g.gain_oct:.3f} (spread {g.spread_oct:.3f} "
        f"octave, slope {g.slope:.3f}); MODE_FAST's jumps anchor on it (rule 7)")
    return g.q16


def cmd_validate(a) -> int:
    from . import fit as F

    if a.calibration:
        c = _calibration_json(a.calibration)
        missing = [k for k in ("x_star_ohm", "y_star_pc") if k not in c]
        if missing:
            raise F.DataError(f"{a.calibration}: needs x_star_ohm and y_star_pc (missing {', '.join(missing)})")
        x, y = _json_number(a.calibration, c, "x_star_ohm"), _json_number(a.calibration, c, "y_star_pc")
    else:
        x, y = a.x_star_ohm, a.y_star_pc
    _finite("x_star_ohm", x, sc.X_STAR_MIN_OHM, 0)
    _finite("y_star_pc", y, 0, sc.Q_LIMIT_PC)
    sets = F.load(a.file, exp2=True)
    r = F.validate(sets, x, y)
    if a.json:
        print(dump_json(r, "validate"))
        return 0
    say(f"{a.file}: {len(sets)} trials; the controller's lines from each trial's initial point with "
        f"(x*, y*) = ({x:.0f} ohm, {y:.0f} pC)")
    say(f"mean r2 of the chosen points: Ep-Rp {r['mean_r2_ep']:.3f}, Q-Rp {r['mean_r2_q']:.3f}")
    for c, v in sorted(r["by_condition"].items()):
        say(f"  {c:<24} n={v['n']:>3}  Ep {v['mean_r2_ep']:.3f} (Z {F._z(v['ep']['z']).strip()}, p {v['ep']['p_holm']:.4f})  "
            f"Q {v['mean_r2_q']:.3f} (Z {F._z(v['q']['z']).strip()}, p {v['q']['p_holm']:.4f})")
    return 0


def cmd_synth(a) -> int:
    from .participant import SimParticipant, write_rows

    if not 1 <= a.participants <= 1000:
        raise ValueError(f"--participants {a.participants} out of range: 1..1000")
    if not 0 <= a.seed < 2**32:
        raise ValueError(f"--seed {a.seed} out of range: 0..{2**32 - 1}")
    _finite("x_star_ohm", a.x_star_ohm, sc.X_STAR_MIN_OHM, 0)
    _finite("y_star_pc", a.y_star_pc, 0, 1e6)
    _finite("rp_noise", a.rp_noise, 0, 0.5)
    out = Path(a.out)
    out_folder(out, create=False)
    refuse_existing([out / "exp1.csv", out / "exp2.csv"], a.overwrite)
    sp = SimParticipant(a.seed, a.x_star_ohm, a.y_star_pc, a.rp_noise)
    out_folder(out)
    with Outputs() as o:
        write_rows(o.path(out / "exp1.csv"), sp.exp1_rows(a.participants))
        write_rows(o.path(out / "exp2.csv"), sp.exp2_rows(a.participants))
    say(f"simulated {a.participants} participants (true x* {a.x_star_ohm} ohm, y* {a.y_star_pc} pC): "
        f"{out / 'exp1.csv'} (Exp. 1), {out / 'exp2.csv'} (Exp. 2)")
    return 0


def _interruptible(prog, run, d: Device, url: str, kept: str):
    """run(); on Ctrl-C or SIGTERM the summary so far, what is kept and whether the device
    acknowledged its DISARM, then the interruption goes on (exit 130 / 143)."""
    try:
        return run()
    except KeyboardInterrupt:
        say(prog.summary(f"interrupted: {kept}"))
        say(_disarm_words(d, url))
        raise


def cmd_selftest(a) -> int:
    """Self-test and monitor correction on a dummy load (host/selftest.py)."""
    from .progress import Progress, Watch
    from . import selftest as st

    _finite("load-ohm", a.load_ohm, *st.LOAD_OHM_RANGE)
    if a.pulses < 2 or a.pulses > 100:
        raise st.SelfTestError(f"--pulses {a.pulses} out of range [2, 100]")
    if a.save_dir is not None:
        refuse_existing([Path(a.save_dir) / st.CAL_FILE], a.overwrite, "choose another --save-dir")
    url = a.device
    if url.startswith(("sim://", "emu://")) and "load=" not in url:  # the simulated resistor in place of the electrodes
        url += ("&" if "?" in url else "?") + f"load={a.load_ohm}"

    def measure(d, pts, chans, label, kept):  # st.measure with the status line and a clean Ctrl-C
        prog = Progress(label, total_pulses=len(pts) * a.pulses * len(chans))
        rows = _interruptible(prog, lambda: st.measure(Watch(d, prog), pts, chans, a.pulses), d, a.device, kept)
        say(prog.summary())
        return rows

    return st.run(url, a.load_ohm, a.channel, a.pulses, not a.no_store, a.save_dir, say, open_transport, a.scope,
                  measure_with=measure)


# ------------------------------------------------------------ parser
OVERWRITE_HELP = "replace output files that exist already (default: refuse, naming them)"


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors in one line (and a pointer to --help)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    raw = argparse.RawDescriptionHelpFormatter
    p = _Parser(prog="steadytouch", description="Constant-sensation electrotactile stimulation: host tools.")
    p.add_argument("--version", action="version", version=f"steadytouch {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    def add(name, fn, help, examples, device=True):
        s = sub.add_parser(name, help=help, description=help, formatter_class=raw, epilog="examples:\n" + examples)
        if device:
            s.add_argument("--device", default=DEFAULT_URL, help=f"device URL: hid://VID:PID[/SERIAL] (the board), sim://SCENARIO (the firmware in the VM) or emu://?scenario=NAME (the rp2 firmware on an emulated Pico) (default {DEFAULT_URL})")
        s.set_defaults(func=fn)
        return s

    s = add("sim", cmd_sim, "run the firmware in the MicroPython VM against a simulated electrode",
            "  steadytouch sim peel\n  steadytouch sim gel --mode akhtar --out runs/\n"
            "  steadytouch sim peel --out runs/ --overwrite   (replace the files of an earlier run)\n"
            "  steadytouch sim my-disturbance.csv   (columns time_s,contact,hydration)", device=False)
    s.add_argument("scenario", nargs="?", default="peel", help="steady, peel, gel, gel-step, exercise, off, or a .csv file")
    s.add_argument("--mode", choices=list(MODES) + ["both"], default="both",
                   help="controller mode (default: both = akhtar and open loop, side by side)")
    s.add_argument("--channels", type=int, choices=[1, 2, 3, 4], default=1)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--out", default="out", help="folder for the CSV and PNG files (default: out/)")
    s.add_argument("--no-plot", action="store_true", help="skip the PNG")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s.add_argument("--ideal-board", action="store_true", help="the ideal board instead of the one with the real "
                   "parts' errors (DAC steps, ADC noise and DNL, monitor gain/offset; docs/simulation.md)")
    s.add_argument("--lsl", action="store_true", help="also stream each run on Lab Streaming Layer (docs/lab.md)")
    s.add_argument("--lsl-wait", type=float, default=30.0,
                   help="with --lsl: seconds to wait for a recorder to connect before streaming a run (default 30)")
    for k, v in (("--i0-ua", 1000), ("--t0-us", 1000), ("--x-star-ohm", -1670), ("--y-star-pc", 186000)):
        s.add_argument(k, type=int, default=v)

    s = add("monitor", cmd_monitor, "live view of a device's telemetry (10 screens a second); keeps the device alive, "
            "disarms it on exit",
            "  steadytouch monitor\n  steadytouch monitor --arm --seconds 30\n"
            "  steadytouch monitor --device 'sim://peel?auto=1000,1000,-1670,186000'")
    s.add_argument("--seconds", type=float, help="stop after this long, in (0, 1e9] s (left out: until Ctrl-C)")
    s.add_argument("--arm", action="store_true", help="arm every channel first (it must be calibrated)")
    s.add_argument("--plot", action="store_true", help="also a live plot window (matplotlib; needs a display)")
    s.add_argument("--lsl", action="store_true", help="also stream telemetry and markers on Lab Streaming Layer (docs/lab.md)")
    s.add_argument("--lsl-wait", type=float, default=0.0,
                   help="with --lsl: seconds to wait for a recorder to connect before starting (default 0)")

    s = add("record", cmd_record, "record telemetry to CSV (flushed every second; Ctrl-C stops cleanly)",
            "  steadytouch record session.csv\n  steadytouch record run.csv --seconds 60 --device 'sim://gel?auto=1000,1000,-1670,186000'")
    s.add_argument("file")
    s.add_argument("--overwrite", action="store_true", help="replace FILE if it exists (default: refuse)")
    s.add_argument("--seconds", type=float, help="stop after this long, in (0, 1e9] s (left out: until Ctrl-C or "
                   "device loss)")
    s.add_argument("--arm", action="store_true", help="arm every channel first (it must be calibrated); "
                   "the device is kept alive while recording and disarmed at the end")
    s.add_argument("--lsl", action="store_true", help="also stream telemetry and markers on Lab Streaming Layer (docs/lab.md)")
    s.add_argument("--lsl-wait", type=float, default=0.0,
                   help="with --lsl: seconds to wait for a recorder to connect before starting (default 0)")

    s = add("audit", cmd_audit, "replay a recording through the host reference; non-zero exit on any mismatch",
            "  steadytouch audit session.csv", device=False)
    s.add_argument("file")

    s = add("plot", cmd_plot, "PNG figures from recordings (Fig. 5 layout; --planes for Ep-Rp and Q-Rp)",
            "  steadytouch plot out/peel-akhtar.csv out/peel-open.csv --out peel.png\n  steadytouch plot session.csv --planes",
            device=False)
    s.add_argument("files", nargs="+")
    s.add_argument("--out")
    s.add_argument("--channel", type=int, default=0)
    s.add_argument("--planes", action="store_true")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)

    s = add("arm", cmd_arm, "stimulate while this runs (the first pulse is I0, T0 and measures Rp0); "
            "Ctrl-C, SIGTERM or --seconds disarms; the device stops by itself if the host goes silent",
            "  steadytouch arm\n  steadytouch arm --channel 1 --seconds 60")
    s.add_argument("--channel", type=int, choices=[0, 1, 2, 3], help="default: all channels")
    s.add_argument("--seconds", type=float, help="disarm after this long, in (0, 1e9] s (left out: until Ctrl-C)")
    s = add("disarm", _simple("disarm", _channel), "stop stimulating at once",
            "  steadytouch disarm\n  steadytouch disarm --channel 1")
    s.add_argument("--channel", type=int, choices=[0, 1, 2, 3], help="default: all channels")

    s = add("calibrate", cmd_calibrate, "send I0, T0 and the convergence point (x*, y*)",
            "  steadytouch calibrate --i0-ua 1000 --t0-us 1000 --x-star-ohm -1670 --y-star-pc 186000\n"
            "  steadytouch calibrate --from calibration.json --i0-ua 1000 --t0-us 1000\n"
            "  steadytouch calibrate --interactive --device hid://1209:0001\n"
            "  steadytouch calibrate --interactive --participant sim --device sim://steady --send")
    for k in ("--i0-ua", "--t0-us", "--x-star-ohm", "--y-star-pc"):
        s.add_argument(k, type=int)
    s.add_argument("--from", dest="from_file", help="a calibration.json (from `steadytouch fit`)")
    s.add_argument("--channel", type=int, choices=[0, 1, 2, 3], help="default: all channels")
    g = s.add_argument_group("guided session (the paper's Exp. 1 protocol)")
    g.add_argument("--interactive", action="store_true", help="match sensations with keys, fit, offer to send")
    g.add_argument("--participant", choices=["person", "sim"], default="person", help="sim: the simulated participant answers")
    g.add_argument("--weak-ua", type=int, default=1500, help="reference current of the weak level at 200 us")
    g.add_argument("--strong-ua", type=int, default=2700, help="reference current of the strong level at 200 us")
    g.add_argument("--present-s", type=float, default=0.5, help="length of each presentation (s)")
    g.add_argument("--send", action="store_true", help="send the fitted calibration without asking")
    g.add_argument("--out", default="out", help="folder for session.csv and calibration.json")
    g.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    g.add_argument("--seed", type=int, default=1)

    s = add("limits", _simple("limits", lambda a: a.i_min_ua, lambda a: a.i_max_ua, lambda a: a.t_min_us,
                              lambda a: a.t_max_us, lambda a: a.q_max_pc),
            "set the soft limits (inside the board's hard limits; disarmed only)",
            "  steadytouch limits --i-min-ua 500 --i-max-ua 5000 --t-min-us 100 --t-max-us 4000 --q-max-pc 5000000")
    for k in ("--i-min-ua", "--i-max-ua", "--t-min-us", "--t-max-us", "--q-max-pc"):
        s.add_argument(k, type=int, required=True)

    s = add("mode", _simple("mode", lambda a: MODES[a.mode], lambda a: a.rate_hz),
            "choose the controller (akhtar: the paper; fast: the Newton variant; open, charge, energy, pwlinear: baselines) and the frame rate",
            "  steadytouch mode akhtar\n  steadytouch mode open --rate-hz 50\n"
            "  steadytouch limits --i-min-ua 500 --i-max-ua 5000 --t-min-us 100 --t-max-us 3600 --q-max-pc 5000000\n"
            "  steadytouch mode open --rate-hz 100   (2 channels: 100 Hz needs t_max <= 3600 us)")
    s.add_argument("mode", choices=list(MODES))
    s.add_argument("--rate-hz", type=int, default=0, help=f"{hp.RATE_MIN_HZ}-{hp.RATE_MAX_HZ} Hz, as far as the frame "
                   "allows: rate x the longest frame (each channel's pulse of up to t_max and its work) must stay "
                   "within 1 s; e.g. 2 channels with t_max 8000 us: at most 53 Hz (a lower t_max, `steadytouch "
                   "limits`, allows more); a rate that does not fit is refused naming the rates that do "
                   "(default: unchanged)")

    add("info", cmd_info, "firmware version, board, limits, mode and each channel's calibration",
        "  steadytouch info\n  steadytouch info --device sim://steady")

    s = add("flash", cmd_flash, "compile, install the firmware and its pinned USB libraries on a Pico over its "
            "serial REPL (offline), check that it boots and read the version back",
            "  steadytouch flash --dry-run\n  steadytouch flash --port /dev/ttyACM0\n"
            "  steadytouch flash --online          # once, to fetch the pinned libraries\n"
            "  steadytouch flash --lib-dir usb-libs/ --port socket://127.0.0.1:40123", device=False)
    s.add_argument("--port", help="serial port of the Pico's MicroPython REPL, or a pyserial URL such as "
                   "socket://127.0.0.1:PORT (default: found by USB VID)")
    s.add_argument("--build-dir", default="build/device")
    s.add_argument("--lib-dir", help="folder with the pinned usb-device 0.2.1 + usb-device-hid 0.1.2 sources "
                   "(usb/device/*.py, sha256 checked; default: the cache --online fills)")
    s.add_argument("--online", action="store_true",
                   help="download the pinned libraries from GitHub if they are not in the cache yet")
    s.add_argument("--boot-timeout-s", type=float, default=30.0,
                   help="how long to wait for the board to come back and run after its reset (default 30)")
    s.add_argument("--dry-run", action="store_true", help="compile and list what would be done, copy nothing; "
                   "to say what the new firmware would do with the board's stored correction, "
                   "a board it reaches is stopped (Ctrl-C: a running session ends), its stored correction read over "
                   "its REPL, and the board reset to run its program again")  # = flash.DRY_RUN_TOUCH (not imported)
    s.add_argument("--ignore-stored-correction", action="store_true",
                   help="flash even if the new firmware would ignore the board's stored correction (/vmon_cal.txt): "
                   "it then boots with its hard limits held and its monitor uncorrected until `steadytouch selftest`")
    s.add_argument("--build-only", action="store_true", help="compile only (what `make mpy` does)")
    s.add_argument("--device", default=DEFAULT_URL, help="the board's HID interface, asked for the version after "
                   f"the reset (default {DEFAULT_URL}; emu+tcp://127.0.0.1:PORT for an emulated Pico)")
    s.add_argument("--no-hid-check", action="store_true", help="read the version back over the serial REPL instead "
                   "of HID (also what happens when this computer has no HID backend)")

    s = add("fit", cmd_fit, "fit the lines of constant sensation and their convergence point (x*, y*) (Exp. 1)",
            "  steadytouch fit exp1.csv\n  steadytouch fit exp1.csv --json --out lab/", device=False)
    s.add_argument("file")
    s.add_argument("--out", default="out", help="folder for calibration.json and fit.png (default out/)")
    s.add_argument("--json", action="store_true", help="print the results as JSON")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)

    s = add("skin", cmd_skin, "fit MODE_FAST's electrode model (Rs, beta, Cp) to calibration pulses; --send sets it",
            "  steadytouch skin pulses.csv   (columns i_ua,t_us,rp_ohm; optional sweep: repeated sweeps, averaged)\n"
            "  steadytouch skin exp1.csv --send --channel 0 --device hid://1209:0001")
    s.add_argument("file", help="CSV with i_ua, t_us, rp_ohm per pulse (one person, one site)")
    s.add_argument("--send", action="store_true", help="send the fitted model to the device (disarmed)")
    s.add_argument("--channel", type=int, choices=[0, 1, 2, 3], help="channel (default: all)")
    s = add("sweep", cmd_sweep, "measure the calibration sweeps MODE_FAST's electrode model is fitted to, on one "
            "channel with the electrodes on; then fit them (as `skin`); --send sets the model",
            "  steadytouch sweep sweeps.csv --channel 0 --i0-ua 1000 --t0-us 1000 --device sim://steady\n"
            "  steadytouch sweep sweeps.csv --channel 0 --until-trusted --send --device hid://1209:0001\n"
            "  steadytouch sweep sweeps.csv --channel 0 --more --sweeps 10   (add to the file, fit them all)")
    s.add_argument("csv", help="the CSV to write (sweep, i_ua, t_us, rp_ohm, ltau_q16: a row per pulse, as read)")
    s.add_argument("--channel", type=int, default=0, help="the channel whose electrodes to sweep (default 0)")
    s.add_argument("--i0-ua", type=int, default=None, help="the operating pulse's current (default: the channel's "
                   "calibration)")
    s.add_argument("--t0-us", type=int, default=None, help="the operating pulse's duration (default: the channel's "
                   "calibration)")
    s.add_argument("--sweeps", type=int, default=30, help="sweeps of the 11 pulses (default 30: 330 pulses)")
    s.add_argument("--until-trusted", action="store_true", help="then more, as long as the fit's shape is not known "
                   "to 1 %% and more sweeps can bring it there (skin.sweeps_for_trust; at most 60 in all)")
    s.add_argument("--more", action="store_true", help="add the sweeps to CSV (written by an earlier sweep)")
    s.add_argument("--send", action="store_true", help="send the fitted model to the device (nothing when it is not "
                   "trusted: the device's model is removed)")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    s = add("validate", cmd_validate, "r2 of participant-chosen points against the controller's lines (Exp. 2)",
            "  steadytouch validate exp2.csv --calibration out/calibration.json", device=False)
    s.add_argument("file")
    s.add_argument("--calibration", help="calibration.json from `fit` (else --x-star-ohm/--y-star-pc)")
    s.add_argument("--x-star-ohm", type=float, default=-1670.0)
    s.add_argument("--y-star-pc", type=float, default=186000.0)
    s.add_argument("--json", action="store_true")

    s = add("synth", cmd_synth, "simulated participants: Exp. 1 and Exp. 2 data with a known convergence point",
            "  steadytouch synth --out data/\n  steadytouch synth --participants 20 --seed 7", device=False)
    s.add_argument("--out", default="out")
    s.add_argument("--participants", type=int, default=10)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--x-star-ohm", type=float, default=-1670.0)
    s.add_argument("--y-star-pc", type=float, default=186000.0)
    s.add_argument("--rp-noise", type=float, default=0.01, help="relative Rp measurement noise (default 0.01)")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)

    s = add("selftest", cmd_selftest, "first-run self-test on a resistor in place of the electrodes: fits the "
            "monitor's gain and offset, reports linearity and worst error, stores the correction",
            "  steadytouch selftest --load-ohm 10000 --device sim://steady\n"
            "  steadytouch selftest --load-ohm 10000 --device hid://1209:0001 --save-dir cal/\n"
            "  steadytouch selftest --load-ohm 10000 --device emu://steady")
    s.add_argument("--load-ohm", type=int, required=True, help="the dummy load's resistance (1000-100000 ohm)")
    s.add_argument("--channel", type=int, default=None, help="one channel (default: all)")
    s.add_argument("--pulses", type=int, default=8, help="pulses per test point (default 8)")
    s.add_argument("--no-store", action="store_true", help="report only")
    s.add_argument("--scope", action="store_true", help="also the DAC's own gain: each channel pulses 4500 uA x "
                   "1000 us on the load and asks for the plateau a scope reads across it (mV, on stdin)")
    s.add_argument("--save-dir", default=None, help="also keep a copy of vmon_cal.txt in this folder "
                   "(the device stores its own in its flash)")
    s.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)

    add("devices", cmd_devices, "list steadytouch boards (HID) and Picos (serial) that are connected",
        "  steadytouch devices", device=False)
    return p


# Signals whose exception may have been lost: one that lands at the entry of a Tk callback
# (the live view's window), before tkinter's own try, is swallowed by Tk's C code (seen: a
# SIGTERM to `monitor --plot` ignored until --seconds ran out). Loops that run Tk check it.
_SIGNALLED: list[int] = []


def _terminate(signum, frame):
    _SIGNALLED.append(signum)
    raise Terminated()


def _interrupt(signum, frame):
    _SIGNALLED.append(signum)
    raise KeyboardInterrupt()


def _raise_lost_signal() -> None:
    """Back in a loop after Tk ran: a Ctrl-C / SIGTERM that came meanwhile and did not end the
    loop was swallowed; raise it again (the loop then ends as it would have)."""
    if _SIGNALLED:
        sig = _SIGNALLED[-1]
        _SIGNALLED.clear()
        raise KeyboardInterrupt() if sig == signal.SIGINT else Terminated()


def main(argv=None) -> int:
    a = build_parser().parse_args(argv)
    # SIGTERM and SIGHUP stop like Ctrl-C: every `finally` runs, the device is disarmed
    old = {}
    import threading

    _SIGNALLED.clear()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
            if sig is not None:
                old[sig] = signal.signal(sig, _terminate)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # (not where Ctrl-C is ignored)
            old[signal.SIGINT] = signal.signal(signal.SIGINT, _interrupt)
    from .closedpipe import Quiet

    stdout = sys.stdout
    sys.stdout = Quiet(stdout)  # a reader that goes away (`| head -1`): the work and its files are finished
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # degenerate data is an error of its own, below
            return a.func(a)
    except USER_ERRORS as e:
        print(f"steadytouch: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2
    except Terminated:
        print("steadytouch: terminated", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("steadytouch: interrupted", file=sys.stderr)
        return 130
    finally:
        sys.stdout.flush()
        sys.stdout = stdout
        for sig, h in old.items():
            signal.signal(sig, h)


if __name__ == "__main__":
    sys.exit(main())
