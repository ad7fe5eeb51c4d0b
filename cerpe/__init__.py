"""CERPE: communication-efficient multi-robot relative pose estimation."""
import os as _os

# Idle OpenMP threads sleep instead of spinning (unless the caller chose otherwise). libgomp
# reads this when torch loads it, so it must be set before torch is imported. torch's workers
# spinning after each parallel region keep a core busy while this package's single-threaded
# numpy / OpenCV / poselib work runs. `cerpe bench` prints the team step with the setting it
# ran under (compare `OMP_WAIT_POLICY=ACTIVE cerpe bench`).
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
