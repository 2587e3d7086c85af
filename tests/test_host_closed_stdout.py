"""A reader that goes away (`steadytouch sim peel --out D | head -1`): the command finishes its
work and writes its files, says nothing more and exits with its own code; it printed
"steadytouch: [Errno 32] Broken pipe", exited 2 and wrote no files."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

EXE = str(Path(sys.executable).parent / "steadytouch")


def closed_stdout(*args):
    """Run with a stdout whose reader is already gone: the first write fails (EPIPE), as after `| head -0`."""
    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run([EXE, *args], stdout=w, stderr=subprocess.PIPE, text=True, timeout=300, cwd=ROOT)
    finally:
        os.close(w)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("data")
    for argv in (["synth", "--participants", "3", "--out", str(d)], ["fit", str(d / "exp1.csv"), "--out", str(d)],
                 ["sim", "steady", "--mode", "akhtar", "--no-plot", "--out", str(d)]):
        assert subprocess.run([EXE, *argv], capture_output=True, timeout=300, cwd=ROOT).returncode == 0, argv
    return d


@pytest.mark.parametrize("argv, files", [
    (["sim", "steady", "--out", "{o}"], ["steady-akhtar.csv", "steady-open.csv", "steady.png"]),
    (["synth", "--participants", "3", "--out", "{o}"], ["exp1.csv", "exp2.csv"]),
    (["fit", "{d}/exp1.csv", "--out", "{o}"], ["calibration.json", "fit.png"]),
    (["fit", "{d}/exp1.csv", "--out", "{o}", "--json"], ["calibration.json", "fit.png"]),
    (["audit", "{d}/steady-akhtar.csv"], []),
    (["validate", "{d}/exp2.csv", "--calibration", "{d}/calibration.json"], []),
    (["validate", "{d}/exp2.csv", "--json"], []),
], ids=["sim", "synth", "fit", "fit-json", "audit", "validate", "validate-json"])
def test_a_closed_stdout_finishes_the_work_and_the_files_quietly(data, tmp_path, argv, files):
    o = tmp_path / "o"
    p = closed_stdout(*[a.replace("{o}", str(o)).replace("{d}", str(data)) for a in argv])
    assert p.returncode == 0 and p.stderr == "", p.stderr
    for f in files:
        assert (o / f).stat().st_size > 0, f
    if files:
        assert sorted(x.name for x in o.iterdir()) == sorted(files)  # and no temporary file
