"""Lab Streaming Layer: steadytouch telemetry and markers as LSL outlets (docs/lab.md).

pylsl is optional (the `lab` extra): `require()` imports it or raises one line
saying how to get it, so everything else works without it."""

from __future__ import annotations

from pathlib import Path

LOOPBACK_CFG = Path(__file__).with_name("loopback.cfg")
PIN = "pylsl==1.18.6"


class LslMissing(RuntimeError):
    """--lsl without pylsl (or without the liblsl it ships)."""


def require():
    """The pylsl module, or LslMissing with how to install it."""
    try:
        import pylsl
    except (ImportError, RuntimeError, OSError) as e:  # pylsl raises RuntimeError when it finds no liblsl
        raise LslMissing(f"--lsl needs pylsl: pip install 'steadytouch[lab]' (or pip install {PIN}); "
                         f"`make setup` installs it ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    return pylsl
