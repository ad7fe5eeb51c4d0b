"""CERPE: communication-efficient multi-robot relative pose estimation."""
import os as _os

# Idle OpenMP threads sleep instead of spinning (unless the caller chose otherwise). libgomp
# reads this when torch loads it, so it must be set before torch is imported. torch's worker
# spinning after each parallel region kept a core busy while this package's single-threaded
# numpy / OpenCV / poselib work ran on 2 cores: `cerpe bench` (CAD, 640x480) team step 690 ->
# 496 ms for 3 robots and 334 -> 265 ms for 2; the descriptor stage 12 -> 2.6 ms.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
