# steadytouch firmware entry point.
# On the rp2: runs the stimulator loop on the real board (board_rp2).
# In the MicroPython unix VM: runs it on the simulated board, reports framed
# on stdout, commands from stdin:
#   micropython firmware/main.py [--scenario NAME|FILE.csv] [--channels N]
#       [--rate HZ] [--frames N] [--seed S] [--realtime] [--start-us T]
#       [--auto I0,T0,XSTAR,YSTAR] [--mode akhtar|fast|open|charge|energy|pwlinear]
#       [--keepalive-ms MS] [--exit-on-eof] [--ideal-board] [--load-ohm R]
#       [--flash-dir DIR] [--hold]
# The simulated board has the real parts' analog errors unless --ideal-board
# (docs/simulation.md); --load-ohm R puts a resistor on every channel instead of
# the electrodes (the self-test's dummy load); --flash-dir is the simulated
# board's flash: the monitor correction `steadytouch selftest` stores there
# (vmon_cal.txt) is applied from boot on.
# Host loss in the VM: with --exit-on-eof the simulated device stops every
# channel and exits as soon as its stdin closes (the host process is gone);
# the host also asks the kernel to kill it with its parent (PR_SET_PDEATHSIG).
# The keep-alive (default hp.KEEPALIVE_DEFAULT_MS, as on the board) counts the
# simulator's clock: a scripted run with no host on the virtual clock, where
# time runs faster than any host could answer, passes --keepalive-ms 0 (off;
# allowed only here on the simulator's command line, never over the wire).
# --hold (with --realtime): the scenario waits at its time 0, and its frames are not
# counted, until the host's session begins (a SIM_START message on stdin, board_sim):
# a recording then holds the whole scenario however long the host waited before it
# (e.g. for an LSL recorder), and the device runs its frames after that.
import sys

# On the rp2 a boot error is printed on the serial port and kept here (the
# newest one, at most ERROR_LOG_MAX bytes); `steadytouch flash` shows it.
ERROR_LOG = "/last_error.txt"
ERROR_LOG_MAX = 2048


def unlock_heap():
    """Undo every heap_lock(): a Ctrl-C or an error can land inside a heap-locked section."""
    try:
        import micropython
    except ImportError:
        return
    micropython.heap_lock()
    d = micropython.heap_unlock()  # the depth before our lock (returns a small int: no allocation)
    while d:
        d = micropython.heap_unlock()


def report_error(when, e):
    """Print an error on the serial port and keep it in ERROR_LOG."""
    import io

    unlock_heap()
    try:
        import stim as _s

        v = "%d.%d.%d" % _s.FW_VERSION
    except Exception:
        v = "?"
    head = "steadytouch %s stopped %s; every output is off, the REPL is free:\n" % (v, when)
    buf = io.StringIO()
    sys.print_exception(e, buf)
    lines = [ln if len(ln) <= 300 else ln[:297] + "..." for ln in buf.getvalue().splitlines()]
    cut = False
    while len(lines) > 3 and len(head) + sum(len(ln) + 1 for ln in lines) + 6 > ERROR_LOG_MAX:
        lines.pop(1)  # the oldest frames go first; the newest and the message stay
        cut = True
    if cut:
        lines.insert(1, "  ...")
    text = head + "\n".join(lines) + "\n"
    sys.stdout.write(text)
    try:
        with open(ERROR_LOG, "w") as f:
            f.write(text)
    except OSError:  # a full or broken filesystem: the serial port has it
        pass


try:
    import board_config as cfg
    import hid_protocol as hp
    import sensation_core as sc
    import stim
except ImportError as e:  # on the board: a file missing from its flash (run `steadytouch flash`)
    if sys.platform == "rp2":
        report_error("at boot", e)
    raise

USAGE = ("usage: micropython firmware/main.py [--scenario NAME|FILE.csv] [--channels 1-4] [--rate 10-100]"
          " [--frames N] [--seed S] [--realtime] [--start-us T] [--auto I0,T0,XSTAR,YSTAR] [--mode akhtar|fast|open|charge|energy|pwlinear]"
         " [--keepalive-ms 0|%d-%d] [--exit-on-eof] [--ideal-board] [--load-ohm 100-1000000] [--flash-dir DIR]"
         " [--hold]"
         % (hp.KEEPALIVE_MIN_MS, hp.KEEPALIVE_MAX_MS))


MODE_NAMES = {"open": sc.MODE_OPEN_LOOP, "charge": sc.MODE_CONSTANT_CHARGE, "energy": sc.MODE_CONSTANT_ENERGY,
              "pwlinear": sc.MODE_PULSE_WIDTH_LINEAR, "akhtar": sc.MODE_AKHTAR, "fast": sc.MODE_FAST}
_VALUED = ("--scenario", "--channels", "--rate", "--frames", "--seed", "--start-us", "--mode", "--auto", "--keepalive-ms",
           "--load-ohm", "--flash-dir")


class UsageError(Exception):
    pass


def _int(opt, s, lo, hi):
    try:
        v = int(s)
    except ValueError:
        raise UsageError("%s: %r is not a whole number" % (opt, s))
    if not lo <= v <= hi:
        raise UsageError("%s=%d out of range [%d, %d]" % (opt, v, lo, hi))
    return v


def parse(argv):
    o = {"scenario": "peel", "channels": cfg.N_CHANNELS, "rate": cfg.RATE_HZ, "frames": -1, "seed": 1,
         "realtime": False, "start": 0, "auto": None, "mode": sc.MODE_AKHTAR,
         "keepalive_ms": hp.KEEPALIVE_DEFAULT_MS, "exit_on_eof": False, "ideal": False, "load_ohm": 0,
         "flash_dir": None, "hold": False}
    k = 0
    while k < len(argv):
        a = argv[k]
        if a in ("-h", "--help"):
            raise UsageError(USAGE)
        if a == "--realtime":
            o["realtime"] = True
            k += 1
            continue
        if a == "--exit-on-eof":
            o["exit_on_eof"] = True
            k += 1
            continue
        if a == "--ideal-board":
            o["ideal"] = True
            k += 1
            continue
        if a == "--hold":
            o["hold"] = True
            k += 1
            continue
        if a not in _VALUED:
            raise UsageError("unknown option %s\n%s" % (a, USAGE))
        if k + 1 >= len(argv):
            raise UsageError("%s needs a value\n%s" % (a, USAGE))
        v = argv[k + 1]
        if a == "--scenario":
            o["scenario"] = v
        elif a == "--channels":
            o["channels"] = _int(a, v, 1, 4)
        elif a == "--rate":
            o["rate"] = _int(a, v, stim.RATE_MIN_HZ, stim.RATE_MAX_HZ)
        elif a == "--frames":
            o["frames"] = _int(a, v, 1, 1 << 29)
        elif a == "--seed":
            o["seed"] = _int(a, v, 0, 1 << 29)
        elif a == "--start-us":
            o["start"] = _int(a, v, 0, (1 << 30) - 1)
        elif a == "--load-ohm":
            o["load_ohm"] = _int(a, v, 100, 1000000)
        elif a == "--flash-dir":
            o["flash_dir"] = v
        elif a == "--mode":
            if v not in MODE_NAMES:
                raise UsageError("--mode must be one of %s, not %r" % (", ".join(MODE_NAMES), v))
            o["mode"] = MODE_NAMES[v]
        elif a == "--keepalive-ms":
            ms = _int(a, v, 0, hp.KEEPALIVE_MAX_MS)
            if ms and ms < hp.KEEPALIVE_MIN_MS:
                raise UsageError("--keepalive-ms=%d out of range: 0 (off) or [%d, %d]"
                                 % (ms, hp.KEEPALIVE_MIN_MS, hp.KEEPALIVE_MAX_MS))
            o["keepalive_ms"] = ms
        elif a == "--auto":
            parts = v.split(",")
            if len(parts) != 4:
                raise UsageError("--auto takes I0_UA,T0_US,XSTAR_OHM,YSTAR_PC, e.g. 1000,1000,-1670,186000")
            o["auto"] = [_int("--auto", p, -(1 << 29), 1 << 29) for p in parts]
        else:
            raise UsageError("unknown option %s\n%s" % (a, USAGE))
        k += 2
    if o["hold"] and not o["realtime"]:  # on the virtual clock a held device would spin out frames
        raise UsageError("--hold needs --realtime (a host starts the scenario in its own time)")
    return o


def auto_start(s, o, now):
    """Calibrate, set the mode and arm every channel, through the command handler; then GET_INFO
    (its report tells a recording the limits in force: held on a board with no DAC gain)."""
    b = bytearray(hp.REPORT_LEN)
    i0, t0, x, y = o["auto"]
    for rep in (hp.cmd_set_mode(b, o["mode"]), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, i0, t0, x, y),
                hp.cmd_arm(bytearray(64), hp.CH_ALL), hp.cmd_get_info(bytearray(64))):
        res = s.handle(rep, now)
        s.board.send(s.tx)
        if res != hp.RES_OK:
            raise UsageError("--auto: " + auto_refused(s, rep[0], res, s.tx[hp.O_DETAIL], i0, t0, x, y))
    s.sync_outputs()


def auto_refused(s, cmd, res, detail, i0, t0, x, y):
    """Why the device refused --auto's command: the value and the range it accepts (the soft
    limits), and, only when the held hard limits are the cause, that they are held and why."""
    lim = s.lim
    held = s.no_dac_gain() and (s.held_limit(0) < i0 <= s.hard_i or s.held_limit(1) < i0 * t0 <= s.hard_q)
    why = ""
    if held and s.takes_dac_gain():
        why = (" (its hard limits are held at %d uA, %d pC: no DAC gain was measured; the board's own are %d uA, "
               "%d pC; `steadytouch selftest --load-ohm OHMS --scope` measures it and lifts the hold: the limits are then "
               "the board's own x the gain / 1.035)"
               % (s.held_limit(0), s.held_limit(1), s.hard_i, s.hard_q))
    elif held:
        why = (" (its hard limits are held at %d uA, %d pC: no DAC gain is applied, this board's DAC path "
               "takes none; the board's own are %d uA, %d pC)" % (s.held_limit(0), s.held_limit(1), s.hard_i,
                                                                  s.hard_q))
    if cmd == hp.CMD_CALIBRATE and res == hp.RES_OUT_OF_RANGE:
        if detail == hp.O_ARG:
            return "I0 %d uA out of range: the device accepts %d..%d uA%s" % (i0, lim[0], lim[1], why)
        if detail == hp.O_ARG + 2 and lim[2] <= t0 <= lim[3]:
            return ("I0 x T0 = %d pC out of range: the device accepts up to %d pC%s" % (i0 * t0, lim[4], why))
        if detail == hp.O_ARG + 2:
            return "T0 %d us out of range: the device accepts %d..%d us" % (t0, lim[2], lim[3])
        if detail == hp.O_ARG + 4:
            return "XSTAR %d ohm out of range: the device accepts %d..0 ohm" % (x, sc.X_STAR_MIN_OHM)
        if detail == hp.O_ARG + 8:
            return "YSTAR %d pC out of range: the device accepts 0..%d pC (below I0 x T0)" % (y, i0 * t0 - 1)
    return "the device refused command 0x%02x (result %d, byte %d)%s" % (cmd, res, detail, why)


def main_sim(argv):
    import board_sim
    import sim_electrode

    o = parse(argv)
    try:
        scen = sim_electrode.scenario(o["scenario"])
    except (ValueError, OSError) as e:
        raise UsageError(str(e))
    clock = board_sim.RealClock() if o["realtime"] else board_sim.VirtualClock(o["start"])
    usb = board_sim.StdioUSB()
    # the flash folder: the monitor correction read at boot (a missing or corrupt file leaves
    # the monitors uncorrected, GET_INFO says which), written by CMD_SET_VMON
    board = board_sim.SimBoard(cfg, clock, scen, o["channels"], o["seed"], usb, ideal=o["ideal"],
                               load_ohm=o["load_ohm"], flash_dir=o["flash_dir"])
    s = stim.Stimulator(board, clock, cfg, o["channels"], o["rate"], keepalive_ms=o["keepalive_ms"])
    board.held = o["hold"]  # until the host's SIM_START (usb.on_sim): the scenario at time 0, no frame counted
    usb.on_sim = board.sim
    if o["auto"]:
        auto_start(s, o, clock.ticks_us())
    frames = o["frames"]
    if frames < 0:
        frames = int(scen.duration_s * s.rate_hz)
    # real time: one frame per step, so a closed stdin is seen within a frame
    step = 1 if o["realtime"] else 50
    while frames > 0:
        chunk = step if frames > step else frames
        held = board.held
        s.run(chunk)
        usb.flush()
        if not held:
            frames -= chunk
        if o["exit_on_eof"] and usb.eof:  # the host is gone: stop stimulating, exit
            s.stop_all(hp.STOP_KEEPALIVE)
            usb.flush()
            return 0
    if s.errors:
        sys.stderr.write("firmware error: %r\n" % (s.last_error,))
        return 1
    return 0


def _all_off(board_rp2, s):
    """Latch every channel and drive every output low, whatever failed."""
    try:
        if s is not None:
            if s.locked:  # stopped inside a frame section: interrupts back on (stim._leave)
                s.locked = 0
                if s._irq_on is not None:
                    s._irq_on(0)
            s.stop_all(hp.STOP_INTERNAL)
    finally:
        board_rp2.outputs_off(cfg)


class CtrlC:
    """Ctrl-C read from the serial port between frames, instead of MicroPython's
    KeyboardInterrupt: that one is raised wherever the interpreter is, and one
    that lands in a USB transfer callback is printed and swallowed by the USB
    stack while the loop runs on (seen on the emulated Pico)."""

    def __init__(self, stream=None):
        import select

        stream = stream or sys.stdin
        self.poller = select.poll()
        self.poller.register(stream, select.POLLIN)
        self.rd = getattr(stream, "buffer", stream)
        self.c3 = b"\x03" if self.rd is not stream else "\x03"

    def pressed(self):
        """Allocates nothing while no byte waits; reads one byte when one does."""
        for _ in self.poller.ipoll(0):
            return self.rd.read(1) == self.c3
        return False


def run_until_ctrl_c(s, ctrl_c):
    """Frame after frame on the same deadline grid until Ctrl-C arrives."""
    import micropython

    micropython.kbd_intr(-1)  # Ctrl-C is now a byte on stdin, read by ctrl_c
    try:
        while not ctrl_c.pressed():
            s.run(1)
    finally:
        micropython.kbd_intr(3)


def main_rp2():
    """Boot the stimulator. Safe and recoverable (docs/hardware.md, "Boot and
    maintenance"): the watchdog starts only once the board is set up; an error
    at boot or outside a frame leaves every output off, pauses the watchdog and
    returns to the REPL (no reset loop) after reporting; Ctrl-C on the serial
    port (what mpremote sends first) stops stimulation the same way, so a
    running board can always be reached. Stimulation needs this loop to push
    every pulse, so nothing is stimulated while the REPL has the board."""
    import board_rp2

    board_rp2.watchdog_pause()  # still running after a soft reset: no reset while we set up
    s = None
    try:
        board = board_rp2.Board(cfg)  # enables the watchdog last
        s = stim.Stimulator(board, board_rp2.Clock(), cfg)
        stim.RUNNING = s  # what `steadytouch flash` reads back over the REPL after its Ctrl-C
        print("steadytouch %d.%d.%d running; Ctrl-C stops stimulation and frees the REPL" % stim.FW_VERSION)
        import gc

        gc.collect()  # the set-up's garbage goes now, not in an automatic collection inside a first frame
        run_until_ctrl_c(s, CtrlC())
        raise KeyboardInterrupt
    except KeyboardInterrupt:  # from run_until_ctrl_c, or a Ctrl-C during the set-up
        unlock_heap()
        board_rp2.watchdog_pause()
        _all_off(board_rp2, s)
        print("steadytouch: stopped by Ctrl-C; every output is off, the watchdog is paused. "
              "machine.reset() starts the stimulator again")
    except BaseException as e:  # a boot error, or one outside a frame (stim.run handles those inside)
        unlock_heap()
        board_rp2.watchdog_pause()
        try:
            _all_off(board_rp2, s)
        finally:
            report_error("at boot" if s is None or not s.started else "while running", e)


if sys.platform == "rp2":
    main_rp2()
elif __name__ == "__main__":
    try:
        rc = main_sim(sys.argv[1:])
    except UsageError as e:
        sys.stderr.write("steadytouch firmware: %s\n" % e)
        rc = 2
    sys.exit(rc)
