"""`steadytouch flash` checks the board's stored correction (/vmon_cal.txt, `steadytouch selftest`)
before it changes anything (issue 13, deliverable 4's loose ends): the file is read over the REPL
link and judged by the new firmware's own parser (firmware/vmon_cal.py) for the build's channel
count; one line says what the new firmware will do with it at boot (none stored / loaded / ignored),
and a file it would ignore stops the flash before anything is copied (--ignore-stored-correction
flashes anyway); --dry-run shows the same verdict. The board's link is faked here (the emulated
Pico's case: tests/flash/test_flash_emulated.py)."""

import pytest

import hid_protocol as hp
from steadytouch import boardlib
from steadytouch import cli
from steadytouch import flash as F

HEADER = "steadytouch monitor correction v1\n"
GOOD = HEADER + "0 1011000 150 1006000\n1 990000 -40 0\n3 1000000 0 1000000\n"  # ch3: a 4-channel build's line
OUT_OF_WINDOW = HEADER + "0 1095000 0 0\n1 990000 -40 0\n"  # stored under the old, wider windows
CORRUPT = b"steadytouch monitor correction v1\n0 10110\xff\xfe00\n"
FILES = {"good": GOOD.encode(), "out of window": OUT_OF_WINDOW.encode(), "corrupt": CORRUPT,
         "garbage": b"not a correction\n", "none": None}


class FakeLink:
    """The board's REPL link: answers the correction read with `data`, records what would change the board."""

    def __init__(self, data, log):
        self.data, self.log = data, log

    def eval(self, code):
        assert code == F._READ_VMON, code
        self.log.append("read")
        return self.data

    def hashes(self, paths):
        return {p: "same" for p in paths}  # every file already on the board: nothing to copy

    def exec(self, code):
        self.log.append("exec")
        return ""

    def write(self, path, data):
        self.log.append(("write", path))

    def remove(self, paths):
        self.log.append(("remove", tuple(paths)))

    def reset(self):
        self.log.append("reset")

    def close(self):
        pass


@pytest.fixture
def board(monkeypatch, tmp_path):
    """flash() against a fake board holding `board.data` as /vmon_cal.txt; board.log records what happened."""
    class Board:
        data = None
        log = []

    monkeypatch.setattr(boardlib, "locate", lambda *a: ({}, "from a test"))
    main = tmp_path / "main.py"
    main.write_text("# test\n")

    def build(out, libs=None):
        b = F.Build(out)
        b.files["/main.py"] = main
        return b

    state = F.BoardState(platform="rp2", version=(1, 28, 0), machine="Raspberry Pi Pico with RP2040", mpy=6,
                         log=None)
    monkeypatch.setattr(F, "build", build)
    monkeypatch.setattr(F, "mpy_cross_version", lambda: "mpy-cross")
    monkeypatch.setattr(F, "connect", lambda port, timeout_s, tries=3: (FakeLink(Board.data, Board.log), state))
    monkeypatch.setattr(F, "_deploy", lambda link, b, say: Board.log.append("deploy"))
    monkeypatch.setattr(F, "boot_check", lambda *a, **k: Board.log.append("boot check"))
    monkeypatch.setattr(F, "find_port", lambda: "/dev/ttyACM9")
    return Board


def flash(board, data, *args):
    board.data = data
    board.log.clear()
    return cli.main(["flash", "--port", "PORT", "--no-hid-check", *args])


def test_the_verdict_names_what_the_new_firmware_does_with_each_file():
    n = 2
    v = {k: F.judge_correction(d, n) for k, d in FILES.items()}
    assert [v[k].state for k in FILES] == ["loaded", "ignored", "ignored", "ignored", "none"]
    assert v["good"].line == ("stored correction /vmon_cal.txt: the new firmware loads it at boot (2 channels): ch0 "
                              "monitor gain 1.0110 offset +150 mV, DAC gain 1.0060; ch1 monitor gain 0.9900 offset "
                              "-40 mV, DAC gain not measured (hard limits held x 0.965 while a channel has no DAC "
                              "gain); kept in the file, unused by this build: ch3")
    four = F.judge_correction(FILES["good"], 4).line  # a 4-channel build loads ch3's line
    assert "ch2 none; ch3 monitor gain 1.0000 offset +0 mV, DAC gain 1.0000" in four and "kept in the file" not in four
    bad = v["out of window"]
    assert bad.why.startswith("correction file line 2: gain 1095000 ppm") and "out of range" in bad.why
    assert "the accepted window: monitor gain 0.91-1.09, offset -1200..+1200 mV, DAC gain 0.965-1.035" in bad.line
    assert bad.line.endswith("the board would boot with its hard limits held x 0.965 and every monitor uncorrected")
    assert v["corrupt"].why == "correction file: not ASCII text" and "first line must be" in v["garbage"].why
    assert "none on the board (/vmon_cal.txt)" in v["none"].line and "held x 0.965" in v["none"].line
    for c in v.values():
        assert "\n" not in c.line


def test_the_verdict_is_the_firmwares_own_boot_rule():
    """The host judges with firmware/vmon_cal.py itself: ignored exactly when the firmware's boot_load says BAD."""
    import sys

    from conftest import FIRMWARE

    sys.path.insert(0, str(FIRMWARE))
    try:
        import vmon_cal
    finally:
        sys.path.remove(str(FIRMWARE))
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "vmon_cal.txt"
        for name, data in FILES.items():
            if data is None:
                continue
            p.write_bytes(data)
            _, state = vmon_cal.boot_load(str(p), 2)
            assert (state == hp.VMON_BAD) == (F.judge_correction(data, 2).state == "ignored"), name


L0, L1 = "0 1000000 0 1000000", "1 1000000 0 1000000"
H = HEADER.rstrip("\n")
# files CPython's and MicroPython's own str/int rules read differently (review rev-lims F1): unicode line
# breaks and spaces, non-ASCII digits, UTF-8 MicroPython does not check, numbers past CPython's 4300 digits
HOSTILE = {
    "crlf": (H + "\r\n" + L0 + "\r\n" + L1 + "\r\n").encode(),
    "cr": (H + "\r" + L0 + "\r" + L1 + "\r").encode(),
    "formfeed": (H + "\x0c" + L0 + "\n").encode(),
    "vt": (H + "\n" + L0 + "\x0b" + L1 + "\n").encode(),
    "nel": (H + "\n" + L0 + "\x85" + L1 + "\n").encode(),
    "u2028": (H + "\n" + L0 + "\u2028" + L1 + "\n").encode(),
    "nbsp": (H + "\n0\xa01000000 0 1000000\n").encode(),
    "arabic": (H + "\n\u0660 1000000 0 1000000\n").encode(),
    "fullwidth": (H + "\n\uff10 1000000 0 1000000\n").encode(),
    "u3000": (H + "\n0\u30001000000 0 1000000\n").encode(),
    "huge ch": (H + "\n" + "9" * 5000 + " 1000000 0 1000000\n" + L0 + "\n").encode(),
    "overlong": H.encode() + b"\n# \xc0\xaf\n" + L0.encode() + b"\n",
    "surrogate": H.encode() + b"\n# \xed\xa0\x80\n" + L0.encode() + b"\n",
    "latin1": H.encode() + b"\n# caf\xe9\n" + L0.encode() + b"\n",
    "x1c": (H + "\n0\x1c1000000 0 1000000\n").encode(),
    "underscore": (H + "\n0 1_000_000 0 1_000_000\n").encode(),
    "plus": (H + "\n+0 +1000000 +0 +1000000\n").encode(),
    "leading zeros": (H + "\n00 01000000 00 01000000\n").encode(),
    "ch 4": (H + "\n4 1000000 0 1000000\n").encode(),
    "ch 99": (H + "\n99 1000000 0 1000000\n").encode(),
    "bom": ("\ufeff" + H + "\n" + L0 + "\n").encode(),
    "header tab": (H + "\t\n" + L0 + "\n").encode(),
    "tabs": (H + "\n0\t1000000\t0\t1000000\n").encode(),
    "nul in comment": (H + "\n# \x00\n" + L0 + "\n").encode(),
    "0x": (H + "\n0 0xF4240 0 0\n").encode(),
    "no newline": (H + "\n" + L0).encode(),
    "empty": b"",
}


def test_the_hosts_verdict_is_the_boot_of_the_firmware_in_the_micropython_vm(tmp_path):
    """judge_correction (CPython) and vmon_cal.boot_load run by MicroPython itself agree on every file,
    hostile ones included: loaded exactly when the board's boot loads it, with the same values."""
    from fw_harness import run_fw

    files = dict(HOSTILE, **{k: v for k, v in FILES.items() if v is not None})
    names = sorted(files)
    for k, name in enumerate(names):
        (tmp_path / f"{k}.txt").write_bytes(files[name])
    _, res, _ = run_fw(f"""
import vmon_cal
out = []
for k in range({len(names)}):
    v, st = vmon_cal.boot_load({str(tmp_path)!r} + "/%d.txt" % k, 2)
    out.append([st, v])
result(out=out)
""")
    board = dict(zip(names, res[0]["out"]))
    want = {hp.VMON_LOADED: "loaded", hp.VMON_BAD: "ignored", hp.VMON_NONE: "none"}
    sys_path = __import__("sys").path
    from conftest import FIRMWARE

    sys_path.insert(0, str(FIRMWARE))
    try:
        import vmon_cal
    finally:
        sys_path.remove(str(FIRMWARE))
    wrong = {n: (F.judge_correction(files[n], 2).state, want[board[n][0]]) for n in names
             if F.judge_correction(files[n], 2).state != want[board[n][0]]}
    assert not wrong, wrong
    for n in names:  # the same values as the board loads
        if board[n][0] == hp.VMON_LOADED:
            assert [tuple(v) if v else None for v in board[n][1]] == vmon_cal.parse(files[n], 2), n
    # the strict rules: ASCII only, lines end in \n, \r\n or \r, fields apart by spaces or tabs,
    # ASCII digits with an optional sign, channels 0..3
    loaded = sorted(n for n in names if board[n][0] == hp.VMON_LOADED)
    assert loaded == ["cr", "crlf", "good", "header tab", "leading zeros", "no newline", "nul in comment", "plus",
                      "tabs"], loaded


@pytest.mark.parametrize("name", ["good", "none"])
def test_a_file_the_new_firmware_loads_or_none_is_one_line_and_the_flash_goes_on(board, capsys, name):
    assert flash(board, FILES[name]) == 0
    out = capsys.readouterr().out
    step5 = [ln for ln in out.splitlines() if ln.startswith("[5/8] ")]
    assert step5 == ["[5/8] " + F.judge_correction(FILES[name], F.build_channels()).line], out
    assert board.log == ["read", "deploy", "boot check"]


@pytest.mark.parametrize("name", ["out of window", "corrupt", "garbage"])
def test_a_file_the_new_firmware_would_ignore_stops_before_anything_is_copied(board, capsys, name):
    assert flash(board, FILES[name]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in cap.err, cap.err
    assert "stopped before copying anything: the board's stored correction /vmon_cal.txt would be ignored by " \
           f"firmware {F.fw_version()} (" in err[0]
    assert "--ignore-stored-correction" in err[0] and "steadytouch selftest" in err[0]
    assert F.judge_correction(FILES[name], 2).why in err[0]
    assert "[5/8] stored correction /vmon_cal.txt: the new firmware would ignore it at boot" in cap.out
    assert board.log == ["read", "reset"]  # nothing written, nothing removed; the board runs what it ran


def test_ignore_stored_correction_flashes_anyway_and_says_what_to_run(board, capsys):
    assert flash(board, FILES["out of window"], "--ignore-stored-correction") == 0
    out = capsys.readouterr().out
    assert "flashing anyway (--ignore-stored-correction): run `steadytouch selftest" in out
    assert board.log == ["read", "deploy", "boot check"]


@pytest.mark.parametrize("name, rc", [("good", 0), ("none", 0), ("out of window", 2), ("corrupt", 2)])
def test_dry_run_shows_the_same_verdict_and_copies_nothing(board, capsys, name, rc):
    assert flash(board, FILES[name], "--dry-run") == rc
    cap = capsys.readouterr()
    verdict = F.judge_correction(FILES[name], F.build_channels())
    assert f"on PORT now (read over its REPL; its program was stopped for it and restarted): {verdict.line}" in cap.out
    assert board.log == ["read", "reset"]
    # review rev-lims F5: it said "nothing was sent" while it stopped, read and reset the board: now it says so
    assert "nothing was sent" not in cap.out
    assert "dry run: nothing is copied, removed or written; a board it reaches is stopped (Ctrl-C: a running " \
           "session ends), its stored correction read over its REPL, and the board reset to run its program again" \
        in cap.out
    if rc:
        assert len(cap.err.strip().splitlines()) == 1 and "flash would stop here, before copying anything" in cap.err
        assert "--ignore-stored-correction" in cap.err
    assert flash(board, FILES[name], "--dry-run", "--ignore-stored-correction") == 0


def test_dry_run_without_a_board_says_the_correction_was_not_checked(board, capsys, monkeypatch):
    def no_board(port, timeout_s, tries=3):
        raise F.FlashError(f"no board at {port} (could not open port)")

    monkeypatch.setattr(F, "connect", no_board)
    assert cli.main(["flash", "--port", "PORT", "--dry-run"]) == 0
    assert "stored correction: not checked (no board reached: no board at PORT" in capsys.readouterr().out


def test_flash_reads_no_more_of_the_file_than_the_firmware_and_judges_a_longer_one_ignored():
    """Review rev-lims F2: one cap (vmon_cal.CAL_MAX_BYTES) for boot, the store's kept lines and flash's read."""
    import ast

    cap = F.firmware_module("vmon_cal").CAL_MAX_BYTES
    reads = [n for n in ast.walk(ast.parse(F._READ_VMON)) if isinstance(n, ast.Call)
             and getattr(n.func, "attr", None) == "read"]
    assert [ast.literal_eval(n.args[0]) for n in reads] == [cap + 1]
    good = FILES["good"] + b"#" * (cap - len(FILES["good"]) - 1) + b"\n"
    assert F.judge_correction(good, 2).state == "loaded"
    c = F.judge_correction(good + b"\n", 2)
    assert c.state == "ignored" and c.why == f"correction file: longer than {cap} bytes", c


class UnreadableLink(FakeLink):
    """The board cannot give the file: its read raises (MemoryError on the board) or answers another OSError."""

    def eval(self, code):
        assert code == F._READ_VMON, code
        self.log.append("read")
        if self.data == "raise":
            raise F.FlashError("the board at PORT failed: MemoryError: memory allocation failed, allocating 70144 "
                               "bytes")
        return self.data  # 'OSError 5'


@pytest.mark.parametrize("how", ["raise", "OSError 5"])
@pytest.mark.parametrize("extra, rc", [([], 2), (["--ignore-stored-correction"], 0), (["--dry-run"], 2),
                                       (["--dry-run", "--ignore-stored-correction"], 0)])
def test_a_file_flash_cannot_read_stops_it_resets_the_board_and_the_flag_overrides(board, capsys, monkeypatch, how,
                                                                                   extra, rc):
    """Review rev-lims F3: a read that failed left the board stopped in its raw REPL (no reset), the flag did not
    help, and any OSError read as "none stored". Now: "unreadable", one line, the board reset on every exit."""
    state = F.BoardState(platform="rp2", version=(1, 28, 0), machine="Raspberry Pi Pico with RP2040", mpy=6, log=None)
    monkeypatch.setattr(F, "connect", lambda port, timeout_s, tries=3: (UnreadableLink(board.data, board.log), state))
    assert flash(board, how, *extra) == rc
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err and "none on the board" not in cap.out
    assert "stored correction /vmon_cal.txt: cannot be read over the REPL (" in cap.out
    if rc:
        err = cap.err.strip().splitlines()
        assert len(err) == 1 and "/vmon_cal.txt could not be read (" in err[0] and IGNORE in err[0], cap.err
    if "--dry-run" in extra:
        assert board.log == ["read", "reset"]
    else:
        assert board.log == (["read", "reset"] if rc else ["read", "deploy", "boot check"])


IGNORE = "--ignore-stored-correction"


@pytest.mark.parametrize("fail_at", ["check", "deploy"])
def test_flash_resets_the_board_it_stopped_on_every_exit_before_the_boot_check(board, capsys, monkeypatch, fail_at):
    if fail_at == "check":
        monkeypatch.setattr(F, "connect", lambda port, timeout_s, tries=3: (FakeLink(None, board.log), F.BoardState(
            platform="rp2", version=(1, 19, 1), machine="Raspberry Pi Pico with RP2040", mpy=6, log=None)))
    else:
        def deploy(link, b, say):
            board.log.append("deploy")
            raise F.FlashError("the board's copy of /main.py does not match the build (full flash?): run flash again")
        monkeypatch.setattr(F, "_deploy", deploy)
    assert flash(board, None) == 2
    assert board.log == (["reset"] if fail_at == "check" else ["read", "deploy", "reset"])


def test_the_boards_read_tells_no_file_from_one_it_cannot_read(micropython, tmp_path):
    """_READ_VMON itself, run by MicroPython: no file -> None; a path it cannot read (a folder) -> 'OSError N'."""
    import subprocess

    (tmp_path / "adir").mkdir()
    (tmp_path / "f.txt").write_bytes(FILES["good"])
    out = []
    for name in ("none.txt", "adir", "f.txt"):
        code = F._READ_VMON.replace(repr(F.VMON_PATH), repr(str(tmp_path / name)))
        assert code != F._READ_VMON
        p = subprocess.run([micropython, "-c", code], capture_output=True, text=True, timeout=30)
        assert p.returncode == 0, p.stderr
        out.append(__import__("ast").literal_eval(p.stdout.strip()))
    assert out[0] is None and out[2] == FILES["good"]
    assert isinstance(out[1], str) and out[1].startswith("OSError ") and out[1] != "OSError 2", out


def test_dry_runs_help_says_what_it_does_to_a_board(capsys):
    with pytest.raises(SystemExit):
        cli.main(["flash", "--help"])
    assert F.DRY_RUN_TOUCH in " ".join(capsys.readouterr().out.split())
