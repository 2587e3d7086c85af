"""Bad input corpus: every file-reading subcommand x malformed files, and bad
numbers on the command line. Each case must end in exactly one clear stderr
line (no traceback), a non-zero exit, and no output file. Run in-process
through cli.main(argv): one interpreter for the whole corpus."""

import pytest

from steadytouch.cli import main

HUGE = "9" * 140_000  # one CSV field over the csv module's 131072-character limit
EXP1_HEAD = "participant,condition,t_us,i_ua,rp_ohm\n"
EXP2_HEAD = "participant,condition,trial,initial,t_us,i_ua,rp_ohm\n"
GOOD_EXP1 = EXP1_HEAD + "".join(f"P1,weak,{t},{round(2000 * (t / 200) ** -0.5)},{20000 - 10 * t}\n"
                                for t in range(200, 701, 50))
REC_HEAD = ("# steadytouch recording 1\n# i_min_ua: 100\n# i_max_ua: 10000\n# t_min_us: 20\n# t_max_us: 8000\n"
            "# q_max_pc: 10000000\n# i0_ua: 1000\n# t0_us: 1000\n# x_star_ohm: -1670\n# y_star_pc: 186000\n"
            "seq,time_us,channel,i_ua,t_us,vp_mv,rp_ohm,status,stop,mode,me_ua2ms,mq_target_fc_per_ohm,"
            "mq_last_fc_per_ohm,next_i_ua,next_t_us,flags,overruns,loop_us\n")
REC_ROW = "{k},{t},0,1000,1000,20000,20000,0,0,4,1000000,8000000,8000000,1000,1000,1,0,100\n"

# name -> file content (str or bytes)
FILES = {
    "empty.csv": "",
    "binary.csv": bytes(range(256)) * 8,
    "latin1.csv": "participant,condition,t_us,i_ua,rp_ohm\nP\xe9,weak,200,1000,1000\n".encode("latin-1"),
    "huge_field.csv": EXP1_HEAD + f"P1,weak,200,{HUGE},1000\n",
    "huge_quoted.csv": EXP1_HEAD + f'P1,"{HUGE}",200,1000,1000\n',
    "short_row.csv": EXP1_HEAD + "P1,weak,200\n",
    "nan.csv": EXP1_HEAD + "".join(f"P1,weak,{t},nan,1000\n" for t in (200, 300)),
    "inf.csv": EXP1_HEAD + "".join(f"P1,weak,{t},1000,inf\n" for t in (200, 300)),
    "huge_values.csv": EXP1_HEAD + "".join(f"P1,weak,{t},1e300,{1e300}\n" for t in (200, 300, 400, 500, 600)),
    "negative.csv": EXP1_HEAD + "P1,weak,200,-5,1000\nP1,weak,300,5,1000\n",
    "identical.csv": EXP1_HEAD + "P1,weak,200,1000,5000\n" * 11,
    "constant_rp.csv": EXP1_HEAD + "".join(f"P1,weak,{t},{3000 - 2 * t},5000\n" for t in range(200, 701, 50)),
    "constant_q.csv": EXP1_HEAD + "".join(f"P1,weak,{t},{600000 // t},{5000 + t}\n" for t in (200, 300, 400, 500, 600)),
    "no_header.csv": "1,2,3\n4,5,6\n",
    "exp2_nan.csv": EXP2_HEAD + "P1,weak,1,1,200,1000,5000\nP1,weak,1,0,300,nan,5000\n",
    "list.json": "[1, 2, 3]",
    "strings.json": '{"x_star_ohm": "abc", "y_star_pc": "12", "i0_ua": "1000", "t0_us": "1000"}',
    "nan.json": '{"x_star_ohm": NaN, "y_star_pc": 1000}',
    "huge.json": '{"x_star_ohm": 1e300, "y_star_pc": 1000}',
    "bad.json": "{not json",
    "binary.json": b"\x00\xff\x00",
    "rec_empty.csv": "",
    "rec_binary.csv": b"\x89PNG\r\n\x1a\n" + bytes(300),
    "rec_huge.csv": REC_HEAD + REC_ROW.format(k=0, t=0).replace("20000,20000", HUGE + ",20000"),
    "rec_nan.csv": REC_HEAD + REC_ROW.format(k=0, t=0).replace("20000,20000", "nan,20000"),
    "rec_only_ch0.csv": REC_HEAD + "".join(REC_ROW.format(k=k, t=20000 * k) for k in range(5)),
    "rec_bad_limits.csv": REC_HEAD.replace("t_min_us: 20", "t_min_us: 99999") + REC_ROW.format(k=0, t=0),
    "scen_1e9.csv": "time_s,contact,hydration\n0,1,1\n1e9,1,1\n",
    "scen_nan.csv": "time_s,contact,hydration\n0,1,1\nnan,1,1\n",
    "scen_binary.csv": bytes(range(256)),
    "scen_empty.csv": "",
    "scen_huge.csv": "time_s,contact,hydration\n0,1,1\n" + HUGE + ",1,1\n",
}

CASES = [
    # fit
    *[(["fit", f, "--out", "{out}"], w) for f, w in [
        ("empty.csv", "empty"), ("binary.csv", "binary"), ("latin1.csv", "UTF-8"), ("huge_field.csv", "huge_field.csv"),
        ("huge_quoted.csv", "huge_quoted.csv row 2"), ("short_row.csv", "row 2"), ("nan.csv", "i_ua"), ("inf.csv", "rp_ohm"),
        ("huge_values.csv", "out of range"), ("negative.csv", "positive"), ("identical.csv", "same Rp"),
        ("constant_rp.csv", "same Rp"), ("constant_q.csv", "same charge"), ("no_header.csv", "missing column"),
        ("nosuch.csv", "no such"), ("list.json", "missing column")]],
    # validate
    *[(["validate", f], w) for f, w in [
        ("empty.csv", "empty"), ("binary.csv", "binary"), ("huge_field.csv", "huge_field.csv"), ("exp2_nan.csv", "i_ua")]],
    (["validate", "good_exp1.csv", "--x-star-ohm", "nan"], "x-star-ohm nan out of range"),
    (["validate", "good_exp1.csv", "--y-star-pc", "inf"], "y-star-pc inf out of range"),
    (["validate", "good_exp1.csv", "--calibration", "list.json"], "not a list"),
    (["validate", "good_exp1.csv", "--calibration", "strings.json"], "x_star_ohm must be a finite number"),
    (["validate", "good_exp1.csv", "--calibration", "nan.json"], "x_star_ohm must be a finite number"),
    (["validate", "good_exp1.csv", "--calibration", "bad.json"], "not a readable calibration JSON"),
    (["validate", "good_exp1.csv", "--calibration", "binary.json"], "binary"),
    (["validate", "good_exp1.csv", "--calibration", "huge.json"], "out of range"),
    # skin
    *[(["skin", f], w) for f, w in [
        ("empty.csv", "needs the columns"), ("binary.csv", "binary"), ("huge_field.csv", "huge_field.csv"),
        ("short_row.csv", "row 2: column i_ua is missing"), ("nan.csv", "i_ua"), ("huge_values.csv", "out of range"),
        ("identical.csv", "durations")]],
    # audit and plot
    *[(["audit", f], w) for f, w in [
        ("rec_empty.csv", "no column header"), ("rec_binary.csv", "binary"), ("rec_huge.csv", "out of range (a 32-bit field)"),
        ("rec_nan.csv", "not a whole number"), ("rec_bad_limits.csv", "limits in the header"), ("nosuch.csv", "no such")]],
    *[(["plot", f, "--out", "{out}/x.png"], w) for f, w in [
        ("rec_empty.csv", "no column header"), ("rec_binary.csv", "binary"), ("rec_nan.csv", "not a whole number")]],
    (["plot", "rec_only_ch0.csv", "--planes", "--channel", "1", "--out", "{out}/x.png"], "no pulses on channel 1"),
    (["plot", "rec_only_ch0.csv", "--channel", "7", "--out", "{out}/x.png"], "--channel 7 out of range"),
    # sim and sim:// scenarios
    *[(["sim", f, "--out", "{out}", "--no-plot"], w) for f, w in [
        ("scen_1e9.csv", "out of range: a scenario runs 0..3600 s"), ("scen_nan.csv", "out of range"),
        ("scen_binary.csv", "scen_binary.csv: a binary file"), ("scen_empty.csv", "header"),
        ("scen_huge.csv", "out of range"), ("nope.csv", "no such scenario file nope.csv"),
        ("nosuch", "unknown scenario")]],
    (["sim", "steady", "--t0-us", "1", "--out", "{out}"], "t0_us=1 out of range"),
    (["sim", "steady", "--i0-ua", "66536", "--out", "{out}"], "i0_ua=66536 out of range"),
    (["monitor", "--device", "sim://nope.csv"], "no such scenario file nope.csv"),
    (["record", "{out}/r.csv", "--device", "sim://scen_1e9.csv"], "out of range"),
    (["record", "{out}/r.csv", "--device", "sim://scen_binary.csv"], "binary"),
    # device commands: refused before any device is opened (the default hid:// device is absent here)
    (["mode", "akhtar", "--rate-hz", "300"], "rate_hz=300 out of range: the device accepts 10..100 Hz"),
    (["mode", "open", "--rate-hz", "5"], "rate_hz=5 out of range"),
    (["limits", "--i-min-ua", "500", "--i-max-ua", "65537", "--t-min-us", "100", "--t-max-us", "4000",
      "--q-max-pc", "5000000"], "i_max_ua=65537 out of range"),
    (["limits", "--i-min-ua", "500", "--i-max-ua", "5000", "--t-min-us", "1", "--t-max-us", "4000",
      "--q-max-pc", "5000000"], "t_min_us=1 out of range"),
    (["limits", "--i-min-ua", "500", "--i-max-ua", "5000", "--t-min-us", "100", "--t-max-us", "4000",
      "--q-max-pc", str(2**32)], "q_max_pc=4294967296 out of range"),
    (["calibrate", "--i0-ua", "66536", "--t0-us", "1000", "--x-star-ohm", "-1670", "--y-star-pc", "186000"],
     "i0_ua=66536 out of range"),
    (["calibrate", "--i0-ua", "1000", "--t0-us", "1", "--x-star-ohm", "0", "--y-star-pc", "0"], "t0_us=1 out of range"),
    (["calibrate", "--i0-ua", "1000", "--t0-us", "1000", "--x-star-ohm", "5", "--y-star-pc", "0"], "x_star_ohm=5"),
    (["calibrate", "--from", "strings.json"], "must be a finite number"),
    (["calibrate", "--from", "list.json", "--i0-ua", "1000", "--t0-us", "1000"], "not a list"),
    (["calibrate", "--from", "nan.json", "--i0-ua", "1000", "--t0-us", "1000"], "finite number"),
    (["calibrate", "--from", "huge.json", "--i0-ua", "1000", "--t0-us", "1000"], "out of range"),
    (["calibrate", "--from", "binary.json"], "binary"),
    (["calibrate", "--from", "nosuch.json"], "no such"),
    # synth and argument mistakes
    (["synth", "--participants", "0", "--out", "{out}"], "--participants 0 out of range"),
    (["synth", "--rp-noise", "nan", "--out", "{out}"], "--rp-noise nan out of range"),
    (["synth", "--x-star-ohm", "inf", "--out", "{out}"], "--x-star-ohm inf out of range"),
    (["record", "{out}/r.csv", "--seconds", "nan"], "--seconds nan out of range"),
    # --seconds 0 is not "forever" (left out, they run until Ctrl-C): refused with the range, before the device
    *[([cmd, *extra, "--seconds", v], f"--seconds {v} out of range: a number of seconds in (0, 1e9]; leave --seconds "
       "out to run until Ctrl-C") for cmd, extra in (("record", ["{out}/r.csv"]), ("arm", []), ("monitor", []))
      for v in ("0", "-1", "inf")],
    (["mode", "akhtar", "--rate-hz", "nan"], "invalid int value"),
    (["arm", "--channel", "9"], "invalid choice"),
]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    d = tmp_path_factory.mktemp("corpus")
    for name, content in FILES.items():
        p = d / name
        (p.write_bytes if isinstance(content, bytes) else p.write_text)(content)
    (d / "good_exp1.csv").write_text(GOOD_EXP1)
    return d


@pytest.mark.parametrize("argv, words", CASES, ids=[" ".join(c[0][:2]) + f"-{k}" for k, c in enumerate(CASES)])
def test_bad_input_is_one_clear_line_and_no_file(corpus, tmp_path, monkeypatch, capsys, argv, words):
    monkeypatch.chdir(corpus)
    out = tmp_path / "out"
    out.mkdir()
    args = [a.replace("{out}", str(out)) for a in argv]
    try:
        rc = main(args)
    except SystemExit as e:  # argparse: usage mistakes
        rc = e.code
    err = capsys.readouterr().err
    assert rc not in (0, None), err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("steadytouch"), err
    assert words in lines[0], err
    assert sorted(p.name for p in out.iterdir()) == [], "an output file was written"


def test_seconds_help_says_what_leaving_it_out_does():
    from steadytouch.cli import build_parser

    subs = build_parser()._subparsers._group_actions[0].choices
    for name in ("record", "arm", "monitor"):
        h = " ".join(subs[name].format_help().split())
        assert "in (0, 1e9] s (left out: until Ctrl-C" in h, name


def test_the_good_file_of_the_corpus_is_accepted(corpus, tmp_path, monkeypatch, capsys):
    """The corpus' baseline is valid: the failures above are the files', not the harness'."""
    monkeypatch.chdir(corpus)
    assert main(["validate", "good_exp1.csv", "--x-star-ohm", "-1670", "--y-star-pc", "186000"]) != 0  # exp1 has no trial
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["synth", "--participants", "2", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["exp1.csv", "exp2.csv"]
    assert main(["fit", str(out / "exp1.csv"), "--out", str(out), "--json"]) == 0
    j = capsys.readouterr().out
    assert "NaN" not in j and "Infinity" not in j and '"x_star_ohm"' in j
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "exp1.csv", "exp2.csv", "fit.png"]
    assert main(["validate", str(out / "exp2.csv"), "--calibration", str(out / "calibration.json")]) == 0
    assert main(["plot", "rec_only_ch0.csv", "--planes", "--out", str(out / "r.png")]) == 0
    assert {"r.png", "r-planes.png"} <= {p.name for p in out.iterdir()}
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "a temporary file was left behind"


def test_audit_names_the_row_of_a_value_the_core_refuses(corpus, tmp_path, capsys):
    f = tmp_path / "mode99.csv"
    f.write_text(REC_HEAD + REC_ROW.format(k=0, t=0) + REC_ROW.format(k=1, t=20000).replace(",0,0,4,", ",0,0,99,"))
    assert main(["audit", str(f)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "mode99.csv: data row 2: mode=99 out of range" in err[0], err


@pytest.mark.parametrize("field, value", [("t_us", 3000000000), ("t_us", 2**31), ("i_ua", -(2**31) - 5), ("i_ua", 20001)])
def test_audit_names_a_recorded_pulse_past_the_cores_limits(corpus, tmp_path, capsys, field, value):
    """A recording whose pulse is past the core's envelope (a corrupt or edited file): one line
    naming the row, the value and the range, no traceback (review of session 16: the controller's
    words raised OverflowError there)."""
    row = REC_ROW.format(k=2, t=40000).split(",")
    row[3 if field == "i_ua" else 4] = str(value)
    f = tmp_path / "big.csv"
    # flags: armed + a calibration pulse, twice (two that agree give Rp0: hid_protocol.cal_rp0)
    cal = "".join(REC_ROW.format(k=k, t=20000 * k).replace(",1,0,100\n", ",9,0,100\n") for k in (0, 1))
    f.write_text(REC_HEAD + cal + ",".join(row))
    assert main(["audit", str(f)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"big.csv: data row 3: {field}={value} out of range 0.." in err[0], err


def test_an_interrupted_sim_keeps_every_completed_run(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the second mode runs: the first mode's CSV, complete, is kept (it said "-> path" and then
    "no file written", and the folder was empty); the unfinished run leaves nothing, no temporary file either."""
    import steadytouch.cli as cli

    calls = []
    real = cli.run_firmware

    def fake_run(*a, **k):
        calls.append(a)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C while the second mode runs
        return real(*a, **k)

    monkeypatch.setattr(cli, "run_firmware", fake_run)
    out = tmp_path / "out"
    assert main(["sim", "gel-step", "--out", str(out)]) == 130
    std = capsys.readouterr()
    assert "interrupted" in std.err and len(calls) == 2
    kept = out / "gel-step-akhtar.csv"
    assert [p.name for p in out.iterdir()] == [kept.name]  # no open-loop CSV, no figure, no temporary file
    assert f"-> {kept}" in std.out and "no file for the open run" in std.out
    assert f"interrupted: kept {kept} (the runs that completed)" in std.out
    capsys.readouterr()
    assert main(["audit", str(kept)]) == 0 and "bit-exact" in capsys.readouterr().out  # complete, not cut


@pytest.mark.parametrize("url, words", [
    ("sim://steady?channels=9", "--channels=9 out of range [1, 4]"),
    ("sim://steady?channels=x", "channels, seed and frames take whole numbers"),
    ("sim://steady?mode=bogus", "mode is akhtar, fast, open"),
    # an option the URL does not take (a typo) or a value it does not know was silently ignored
    ("sim://steady?chanels=4", "unknown option chanels; it takes channels=1-4; seed=a whole number; frames="),
    ("sim://steady?channels=2&Seed=3&x=1", "unknown options Seed, x; it takes channels=1-4;"),
    ("sim://steady?realtime=maybe", "realtime=maybe is not one of 1|0 (also yes|no, true|false)"),
    ("emu://steady?chanels=4", "unknown option chanels; it takes scenario=a scenario name or .csv file; channels=1-4"),
    ("tcp://nowhere", "unknown device"),
])
def test_bad_device_urls_are_one_line(url, words, capsys):
    assert main(["info", "--device", url]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


@pytest.mark.parametrize("channel", [5, 2])
def test_audit_and_plot_refuse_a_row_on_a_channel_the_recording_does_not_have(tmp_path, capsys, channel):
    """A row on a channel the 2-channel recording does not have (an edited or corrupt file) was skipped: a
    mismatch on it disappeared and audit said bit-exact. Now audit and plot name the line and the channels."""
    assert main(["sim", "steady", "--mode", "akhtar", "--channels", "2", "--out", str(tmp_path), "--no-plot"]) == 0
    f = tmp_path / "steady-akhtar.csv"
    lines = f.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if not line.startswith("#")) + 150
    cells = lines[k].split(",")
    cells[13] = str(int(cells[13]) + 1)  # next_i_ua: a mismatch
    lines[k] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    assert main(["audit", str(f)]) == 1 and "1 MISMATCH" in capsys.readouterr().out
    cells[2] = str(channel)
    lines[k] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    for argv in (["audit", str(f)], ["plot", str(f), "--out", str(tmp_path / "x.png")]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"line {k + 1}: channel {channel} is not one of the recording's channels " \
            "(it has channels 0..1)" in err[0], err
    assert not (tmp_path / "x.png").exists()


def test_a_sim_recording_names_the_firmware_version_info_reports(tmp_path, capsys):
    """`sim`'s CSV header said `firmware: 0.1.0` (the host package's version) while `info --device sim://steady`
    reports the firmware's own (firmware/stim.py FW_VERSION)."""
    from steadytouch.device import Device
    from steadytouch.flash import fw_version
    from steadytouch.record import read_recording
    from steadytouch.transport import open_transport

    with open_transport("sim://steady") as t:
        reported = Device(t).info().firmware
    assert reported == fw_version()
    assert main(["sim", "steady", "--mode", "akhtar", "--no-plot", "--out", str(tmp_path)]) == 0
    assert read_recording(tmp_path / "steady-akhtar.csv")[0]["firmware"] == reported
