"""The exception base of :mod:`cerpe.synth`."""
from __future__ import annotations

from ..errors import CerpeError


class SynthError(CerpeError, ValueError):
    """Bad generator arguments, an inconsistent output folder, or an impossible world.

    The message names the argument, file or world at fault and, where it helps,
    the fix (e.g. ``--force`` to overwrite a folder generated with other arguments).
    """
