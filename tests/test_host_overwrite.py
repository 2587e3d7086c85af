"""Outputs that exist already are never replaced without --overwrite (a previous session,
recording or calibration is data): every command that writes files refuses in one line naming
them, before any work, and leaves them as they were; --overwrite replaces them."""

import pytest

from steadytouch.cli import main

AUTO = "auto=1000,1000,-1670,186000"
OLD = "an earlier session: keep me\n"

# argv (with {d} = the folder), the files it writes there
CASES = [
    (["sim", "steady", "--mode", "akhtar", "--out", "{d}"], ["steady-akhtar.csv", "steady.png"]),
    (["sim", "steady", "--out", "{d}", "--no-plot"], ["steady-akhtar.csv", "steady-open.csv"]),
    (["record", "{d}/rec.csv", "--device", f"sim://steady?{AUTO}", "--seconds", "1"], ["rec.csv"]),
    (["calibrate", "--interactive", "--participant", "sim", "--device", "sim://steady", "--present-s", "0.1",
      "--out", "{d}"], ["session.csv", "calibration.json"]),
    (["calibrate", "--interactive", "--participant", "sim", "--device", "sim://steady", "--present-s", "0.1",
      "--out", "{d}"], ["session-partial.csv"]),
    (["synth", "--participants", "2", "--out", "{d}"], ["exp1.csv", "exp2.csv"]),
    (["fit", "{d}/../exp1.csv", "--out", "{d}"], ["calibration.json", "fit.png"]),
    (["plot", "{d}/../rec.csv", "--out", "{d}/fig.png", "--planes"], ["fig.png", "fig-planes.png"]),
    (["selftest", "--load-ohm", "10000", "--device", "sim://steady", "--save-dir", "{d}"], ["vmon_cal.txt"]),
]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """An Exp. 1 file for fit and a recording for plot, beside each case's folder."""
    base = tmp_path_factory.mktemp("inputs")
    assert main(["synth", "--participants", "2", "--out", str(base)]) == 0
    assert main(["sim", "steady", "--mode", "akhtar", "--no-plot", "--out", str(base)]) == 0
    (base / "steady-akhtar.csv").rename(base / "rec.csv")
    return base


@pytest.mark.parametrize("argv, names", CASES, ids=[f"{c[0][0]}-{k}" for k, c in enumerate(CASES)])
def test_an_existing_output_is_refused_and_kept(inputs, capsys, argv, names):
    d = inputs / f"case-{CASES.index((argv, names))}"
    d.mkdir()
    for n in names:
        (d / n).write_text(OLD)
    capsys.readouterr()
    rc = main([x.replace("{d}", str(d)) for x in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "already exist" in err[0] and "--overwrite replaces" in err[0], err
    for n in names:
        assert str(d / n) in err[0], err
        assert (d / n).read_text() == OLD, n
    assert sorted(p.name for p in d.iterdir()) == sorted(names), "a file was written"


def test_overwrite_replaces(inputs, capsys):
    d = inputs / "replace"
    d.mkdir()
    (d / "exp1.csv").write_text(OLD)
    assert main(["synth", "--participants", "2", "--out", str(d), "--overwrite"]) == 0
    assert (d / "exp1.csv").read_text().startswith("participant,")
    (d / "steady-akhtar.csv").write_text(OLD)
    assert main(["sim", "steady", "--mode", "akhtar", "--no-plot", "--out", str(d), "--overwrite"]) == 0
    assert (d / "steady-akhtar.csv").read_text().startswith("# steadytouch recording 1")


def test_every_command_that_writes_files_takes_overwrite():
    from steadytouch.cli import build_parser

    subs = build_parser()._subparsers._group_actions[0].choices
    for name in ("sim", "record", "calibrate", "synth", "fit", "plot", "selftest"):
        assert "--overwrite" in subs[name].format_help(), name
