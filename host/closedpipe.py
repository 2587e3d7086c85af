"""Output to a reader that went away (`steadytouch sim peel | head -1`): the command
finishes its work and writes its files; what it would still print goes nowhere.

`Quiet(sys.stdout)` passes everything through; on the first BrokenPipeError it points
the file descriptor at /dev/null (the usual Python idiom, so the interpreter's last
flush at exit raises nothing either) and goes on quietly."""

from __future__ import annotations

import os


class Quiet:
    def __init__(self, stream):
        self.stream = stream
        self.reader_gone = False

    def write(self, text: str) -> int:
        try:
            return self.stream.write(text)
        except BrokenPipeError:
            self._gone()
            return len(text)

    def flush(self) -> None:
        try:
            self.stream.flush()
        except BrokenPipeError:
            self._gone()
            try:
                self.stream.flush()  # what was buffered goes to /dev/null now
            except (OSError, ValueError):
                pass

    def _gone(self) -> None:
        self.reader_gone = True
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(null, self.stream.fileno())
            finally:
                os.close(null)
        except (OSError, ValueError, AttributeError):  # no file descriptor (a test's capture): nothing to redirect
            pass

    def __getattr__(self, name):  # isatty, fileno, encoding, ...
        return getattr(self.stream, name)
