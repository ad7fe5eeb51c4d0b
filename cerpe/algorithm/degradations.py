"""The names under which run-time faults are counted in ``RobotRecord.degradations``.

The robot keeps going after each; ``docs/ARCHITECTURE.md`` lists them too. A name
ending in ``-`` is a prefix (the rest says which case).
"""
from __future__ import annotations

from .graph import GRAPH_DEGRADATIONS

DEGRADATIONS: dict[str, str] = {
    "frame:blank": "own frame without texture (descriptor flag low-texture, zero-norm descriptor or grey-level "
                   "std below min_image_std): zero descriptor broadcast, no joint pass, X kept, never kept as "
                   "keyframe or tracking reference",
    "descriptor:zero-norm": "the descriptor of the own frame is all zero (also counted as frame:blank)",
    "descriptor:wrong-length": "a received descriptor of another length: gate closed for that pair",
    "descriptor:other-zero-norm": "a received descriptor that is zero or not finite (a blank frame): gate closed",
    "descriptor:codec-mismatch": "a received descriptor in another codec than this robot's (full vs a compressed "
                                 "codec of cerpe.compress, or another compressed codec): gate closed for that pair",
    "descriptor:codebook-mismatch": "a compressed descriptor of another projection/codebook version: gate closed "
                                    "for that pair",
    "descriptor:bad-code": "a compressed descriptor whose code does not decode (wrong length, non-positive scale): "
                           "gate closed for that pair",
    "backbone:non-finite-pose": "a view the backbone called placed has a NaN pose: treated as not placed",
    "ego:no-estimate": "the pass placed neither the current view nor a view to chain through, or there is no "
                       "scale: X keeps its value (constant position)",
    "ego:older-keyframe": "odometry chained through an older keyframe (newer views not placed)",
    "ego:step-held": "the step is implausibly slow after the accepted ones (below their median speed by more than "
                     "ego_max_step_ratio and than braking at ego_max_accel_mps2 allows): the pass's rotation is "
                     "kept, the translation is the last accepted step's at the median speed; the pose graph "
                     "counts the step's odometry as lost",
    "ego:no-keyframe": "the memory is empty after the first step (the first frames were blank)",
    "memory:reinit": "no keyframe could be placed but the current view could: memory restarts from it at the last X",
    "scale:fallback-last": "the memory gave no scale: the last valid one is used",
    "scale:unavailable": "no scale, and none before",
    "scale:unit-no-depth": "no metric depth at all: s = 1 (unit_scale_without_depth)",
    "scale:skipped-": "a keyframe without usable metric depth left out of the scale (suffix: why)",
    "depth:none": "the depth source had nothing for the current frame",
    "pose:stale": "the other robot's pose of this step is missing: its pose is bridged from the last ones seen "
                  "(constant velocity) for propagation",
    "pose:bridged": "a direct estimate without the other's pose message of this step: the anchor is stored with "
                    "that pose bridged (from the image reply's pose and earlier ones), corrected by the next",
    "pose:bridged-next": "an anchor stored with a bridged pose corrected by interpolation once a later pose came",
    "anchor:not-stored-pose-missing": "a direct estimate while no pose of the other was ever seen: not an anchor",
    "descriptor:missing": "a peer's descriptor of this step did not arrive: the gate scores its last one if at most "
                          "descriptor_max_age steps old, else it waits for the next step (closed now); the anchor "
                          "is carried",
    "descriptor:stale-used": "a lost descriptor replaced by the peer's previous one (at most descriptor_max_age "
                             "steps old) in the gate",
    "msg:request-retried": "an image request sent again within the step because its reply did not come "
                           "(request_retries)",
    "msg:reply-missing": "the gate opened but no image reply arrived (request or reply lost): no direct estimate "
                         "this step; the pair keeps its anchor",
    "anchor:inconsistent": "a direct estimate that disagrees with the pair's verified anchor propagated to it: "
                           "not an anchor; the anchor's propagation is reported instead",
    "anchor:weak": "a direct estimate that agrees with the pair's anchor but stands on fewer than anchor_min_inliers "
                   "registration inliers: not an anchor; the anchor's propagation is reported instead",
    "anchor:replaced": "anchor_replace_after recent rejected estimates agree with the newest of them: it replaced "
                       "the anchor",
    "direct:appearance-mismatch": "the backbone placed the collaborator's view by keypoints but the images contradict "
                                  "the placement (where it says the views overlap they do not look alike: repeated "
                                  "or mirrored structure): no direct estimate this step, the anchor is carried",
    "anchor:odometry-jump": "one robot's odometry turned by more than anchor_max_odo_rot_step in one step (a lost "
                            "track): the pair forgot its anchor and candidates rather than carry them through it",
    "msg:lost": "a frame that did not arrive (in process: dropped by the channel; online: missing at the deadline)",
    "msg:garbled": "a frame that does not decode",
    "msg:unknown-sender": "a frame whose sender index is not the robot it came from",
    "msg:stale-request": "an image request for a step this robot is not at",
    "msg:stale-reply": "an image reply for another step",
    "msg:undecodable-jpeg": "an image reply whose JPEG (or WebP) does not decode",
    "msg:unknown-reply-codec": "an image reply whose codec id this version does not know: not used, no direct "
                               "estimate",
    "msg:truncated-jpeg": "an image reply whose JPEG has no end marker (truncated): not used, no direct estimate",
    "msg:image-size-mismatch": "an image reply that decodes to another size than its intrinsics (principal point "
                               "off the centre) or below 8x8 pixels: not used, no direct estimate",
    "msg:image-not-held": "online: the owner answered an image request with 'not held' (it has moved on)",
    "net:peer-lost": "online: a peer's session ended without a bye",
    "link:protocol-mismatch": "online: a robot speaks another link protocol or message version (once per robot "
                              "and version): its frames and requests are ignored",
    "link:team-mismatch": "online: a robot of the roster is up in another team (once per robot and team)",
    "link:duplicate-robot": "online: another session uses this robot's id in this team (once)",
    **GRAPH_DEGRADATIONS,
}


def known(name: str) -> bool:
    """Whether ``name`` is one of :data:`DEGRADATIONS` (or starts with one of its prefixes)."""
    return name in DEGRADATIONS or any(k.endswith("-") and name.startswith(k) for k in DEGRADATIONS)
