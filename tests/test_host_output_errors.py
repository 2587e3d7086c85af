"""Output mistakes and failures in one line naming the file and what to do, never a raw errno or a
temporary file's name: a folder or a device given for a file, a file for a folder, a folder that does
not exist, a full disk while recording, a channel the device does not have."""

import errno

import pytest

import steadytouch.record as record
from steadytouch.cli import main
from steadytouch.record import read_recording

AUTO = "auto=1000,1000,-1670,186000"


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    d = tmp_path_factory.mktemp("rec")
    assert main(["sim", "steady", "--mode", "akhtar", "--no-plot", "--out", str(d)]) == 0
    return d / "steady-akhtar.csv"


def one_line(capsys, rc, argv):
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, (argv, err)
    assert ".tmp" not in err[0] and "Errno" not in err[0] and "Format" not in err[0], err
    return err[0]


@pytest.mark.parametrize("out, words", [
    ("{d}", "{d} is a folder: give a file name for the output, e.g. {d}/steady-akhtar.png"),
    ("/dev/full", "/dev/full is not a regular file"),
    ("nodir/x.png", "nodir/x.png: the folder nodir does not exist"),
    ("{d}/fig", "--out {d}/fig: a figure's file name ends in .png (or .pdf, .svg)"),
])
@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_plot_out_mistakes(rec, tmp_path, capsys, monkeypatch, out, words, overwrite):
    monkeypatch.chdir(tmp_path)
    d = tmp_path / "d"
    d.mkdir()
    out, words = out.replace("{d}", str(d)), words.replace("{d}", str(d))
    argv = ["plot", str(rec), "--out", out, *overwrite]
    assert words in one_line(capsys, main(argv), argv)
    assert list(d.iterdir()) == [] and not (tmp_path / "nodir").exists()


@pytest.mark.parametrize("argv", [["sim", "steady", "--no-plot"], ["synth"], ["fit", "exp1.csv"]])
def test_a_file_given_for_an_out_folder(capsys, argv):
    argv = [*argv, "--out", "/dev/null"]
    assert "--out /dev/null: not a folder (a file of that name exists)" in one_line(capsys, main(argv), argv)


@pytest.mark.parametrize("name, words", [("{d}", "{d} is a folder: give a file name for the output, e.g. "
                                                  "{d}/recording.csv"),
                                         ("{d}/no/r.csv", "{d}/no/r.csv: the folder {d}/no does not exist")])
def test_record_to_a_folder_or_into_a_missing_one(tmp_path, capsys, name, words):
    argv = ["record", name.replace("{d}", str(tmp_path)), "--device", "sim://steady", "--overwrite"]
    assert words.replace("{d}", str(tmp_path)) in one_line(capsys, main(argv), argv)


class FullDisk:
    """A file that takes what is written until its n-th flush, then fails as a full disk does."""

    def __init__(self, f, n):
        self.f, self.n, self.pending = f, n, []

    def write(self, text):
        self.pending.append(text)
        return len(text)

    def flush(self):
        self.n -= 1
        if self.n <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.f.write("".join(self.pending))
        self.pending = []
        self.f.flush()

    def close(self):
        self.f.close()

    @property
    def closed(self):
        return self.f.closed


def test_record_on_a_full_disk_names_the_file_and_the_rows_saved(tmp_path, capsys, monkeypatch):
    out = tmp_path / "r.csv"
    monkeypatch.setattr(record, "open", lambda *a, **k: FullDisk(open(*a, **k), 3), raising=False)
    rc = main(["record", str(out), "--device", f"sim://steady?{AUTO}", "--seconds", "10"])
    std = capsys.readouterr()
    rows = read_recording(out)[1]  # what the file holds: every row it says it saved, complete
    assert len(rows) >= 20
    err = std.err.strip().splitlines()
    assert rc == 1 and len(err) == 1, std.err
    assert err[0] == (f"steadytouch: {out}: cannot write (No space left on device): the recording stopped; "
                      f"{len(rows)} rows saved in it")
    assert f"saved {len(rows)} rows to {out}" in std.out and "disarmed" in std.out


@pytest.mark.parametrize("argv, words", [
    (["arm", "--channel", "3", "--device", "sim://steady"], "arm: channel 3 out of range: the device has channels 0..1"),
    (["disarm", "--channel", "2", "--device", "sim://steady"], "disarm: channel 2 out of range: the device has "
                                                               "channels 0..1"),
    (["disarm", "--channel", "1", "--device", "sim://steady?channels=1"], "channel 1 out of range: the device has "
                                                                         "channel 0"),
])
def test_a_channel_the_device_does_not_have_names_the_range(capsys, argv, words):
    assert words in one_line(capsys, main(argv), argv)
