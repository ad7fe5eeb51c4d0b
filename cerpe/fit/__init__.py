"""Fitting the files shipped in ``cerpe/data/`` on development data (``cerpe fit``).

One module per step, each ``main(conf, paths) -> Path`` (the file written) with a
``default_conf`` (its keys mirror the command's options) and a ``Paths``
dataclass (the data read, the file written):

* :mod:`.descriptor`: the offline descriptor's k-means centres and its mean descriptor;
* :mod:`.projection`: the projection and product quantiser of the compressed descriptor codecs;
* :mod:`.thresholds`: the gate's and the memory's thresholds ``tau``, ``tau_m``, ``tau_k``.

:mod:`.calibrate` holds the threshold calibration's samples and rule, :mod:`.descriptor_codecs`
the cached descriptors of development sets and the gate's ROC AUC per codec. Never the
paper-default suite (seed 0: test data).
"""
from __future__ import annotations

from pathlib import Path

from ..errors import CerpeError

DATA_DIR = Path(__file__).resolve().parents[1] / "data"  # the shipped files (cerpe/data/)


class FitError(CerpeError, ValueError):
    """A fit cannot run: a paper seed or setting, no images, too few descriptors, a bad option."""
