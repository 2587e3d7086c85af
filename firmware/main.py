# steadytouch firmware entry point.
# On the rp2: runs the stimulator loop on the real board (board_rp2).
# In the MicroPython unix VM: runs it on the simulated board, reports framed
# on stdout, commands from stdin:
#   micropython firmware/main.py [--scenario NAME|FILE.csv] [--channels N]
#       [--rate HZ] [--frames N] [--seed S] [--realtime] [--start-us T]
#       [--auto I0,T0,XSTAR,YSTAR] [--mode akhtar|fast|open|charge|energy|pwlinear]
#       [--keepalive-ms MS] [--exit-on-eof]
# Host loss in the VM: with --exit-on-eof the simulated device stops every
# channel and exits as soon as its stdin closes (the host process is gone);
# the host also asks the kernel to kill it with its parent (PR_SET_PDEATHSIG).
# The keep-alive (default hp.KEEPALIVE_DEFAULT_MS, as on the board) counts the
# simulator's clock: a scripted run with no host on the virtual clock, where
# time runs faster than any host could answer, passes --keepalive-ms 0 (off;
# allowed only here on the simulator's command line, never over the wire).
import sys

import board_config as cfg
import hid_protocol as hp
import sensation_core as sc
import stim

USAGE = ("usage: micropython firmware/main.py [--scenario NAME|FILE.csv] [--channels 1-4] [--rate 10-100]"
          " [--frames N] [--seed S] [--realtime] [--start-us T] [--auto I0,T0,XSTAR,YSTAR] [--mode akhtar|fast|open|charge|energy|pwlinear]"
         " [--keepalive-ms 0|%d-%d] [--exit-on-eof]" % (hp.KEEPALIVE_MIN_MS, hp.KEEPALIVE_MAX_MS))


MODE_NAMES = {"open": sc.MODE_OPEN_LOOP, "charge": sc.MODE_CONSTANT_CHARGE, "energy": sc.MODE_CONSTANT_ENERGY,
              "pwlinear": sc.MODE_PULSE_WIDTH_LINEAR, "akhtar": sc.MODE_AKHTAR, "fast": sc.MODE_FAST}
_VALUED = ("--scenario", "--channels", "--rate", "--frames", "--seed", "--start-us", "--mode", "--auto", "--keepalive-ms")


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
         "keepalive_ms": hp.KEEPALIVE_DEFAULT_MS, "exit_on_eof": False}
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
    return o


def auto_start(s, o, now):
    """Calibrate, set the mode and arm every channel, through the command handler."""
    b = bytearray(hp.REPORT_LEN)
    i0, t0, x, y = o["auto"]
    for rep in (hp.cmd_set_mode(b, o["mode"]), hp.cmd_calibrate(bytearray(64), hp.CH_ALL, i0, t0, x, y),
                hp.cmd_arm(bytearray(64), hp.CH_ALL)):
        res = s.handle(rep, now)
        s.board.send(s.tx)
        if res != hp.RES_OK:
            raise UsageError("--auto: the device refused command 0x%02x with result %d (detail byte %d)"
                             % (rep[0], res, s.tx[hp.O_DETAIL]))
    s.sync_outputs()


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
    board = board_sim.SimBoard(cfg, clock, scen, o["channels"], o["seed"], usb)
    s = stim.Stimulator(board, clock, cfg, o["channels"], o["rate"], keepalive_ms=o["keepalive_ms"])
    if o["auto"]:
        auto_start(s, o, clock.ticks_us())
    frames = o["frames"]
    if frames < 0:
        frames = int(scen.duration_s * s.rate_hz)
    # real time: one frame per step, so a closed stdin is seen within a frame
    step = 1 if o["realtime"] else 50
    while frames > 0:
        chunk = step if frames > step else frames
        s.run(chunk)
        usb.flush()
        frames -= chunk
        if o["exit_on_eof"] and usb.eof:  # the host is gone: stop stimulating, exit
            s.stop_all(hp.STOP_KEEPALIVE)
            usb.flush()
            return 0
    if s.errors:
        sys.stderr.write("firmware error: %r\n" % (s.last_error,))
        return 1
    return 0


def main_rp2():
    import board_rp2

    board = board_rp2.Board(cfg)
    s = stim.Stimulator(board, board_rp2.Clock(), cfg)
    try:
        s.run()
    finally:
        board.stop_all()


if sys.platform == "rp2":
    main_rp2()
elif __name__ == "__main__":
    try:
        rc = main_sim(sys.argv[1:])
    except UsageError as e:
        sys.stderr.write("steadytouch firmware: %s\n" % e)
        rc = 2
    sys.exit(rc)
