"""steadytouch host tooling: references, transports, analysis."""

from sensation_core import VERSION as __version__  # noqa: F401
