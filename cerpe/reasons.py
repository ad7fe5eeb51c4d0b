"""Why a pair record has the estimate it has, and the run-time faults a robot counts: one closed vocabulary.

:data:`REASONS`: the tokens of ``PairRecord.reason`` (a ``steps.csv`` column). A reason is zero or more
tokens joined by ``"; "``, each a key of :data:`REASONS`; numbers never go into a reason, they have
columns of their own (``direct_inliers``, ``check_rot_rad``, ``check_trans_m``, ``anchor_step``...).

:data:`DEGRADATIONS`: the names under which run-time faults are counted in ``RobotRecord.degradations``
(a ``robots.csv`` column); the robot keeps going after each.

A record refuses a token that is not listed (:func:`check_reason`, :func:`check_degradations`): a new
reason or fault is added here, with its meaning, or not at all.
"""
from __future__ import annotations

from typing import Iterable

__all__ = ["REASONS", "DEGRADATIONS", "SEPARATOR", "join", "split", "check_reason", "check_degradations",
           "known_degradation", "VocabularyError"]

SEPARATOR = "; "

REASONS: dict[str, str] = {
    # the gate (phase 3)
    "gate-closed": "the descriptors' similarity stayed under the gate threshold: no image was requested",
    "descriptor-missing": "the peer's descriptor of this step was lost and no recent one stands in",
    "descriptor-codec-mismatch": "the peer's descriptor is in another codec than this robot's",
    "descriptor-codebook-mismatch": "the peer's compressed descriptor is of another projection or codebook",
    "descriptor-bad-code": "the peer's compressed descriptor does not decode",
    "descriptor-length-mismatch": "the peer's descriptor has another length",
    "own-descriptor-degenerate": "this robot's frame is blank: its descriptor is zero and the gate stays closed",
    "other-descriptor-degenerate": "the peer's descriptor is zero or not finite (a blank frame)",
    "request-skipped: backoff": "the gate opened, but the pair's requested images placed nothing several times in a "
                                "row: it asks only every few steps (policy.miss_limit)",
    "request-skipped: anchor-fresh": "the gate opened, but the pair's anchor is fresh and certain: the image would "
                                     "not pay (policy.mode pays)",
    "request-skipped: max-requests": "the gate opened, but policy.max_requests peers with higher gate scores were "
                                     "asked this step",
    "request-skipped: peer-shares": "the gate opened, but this robot's images of the peer place nothing while the "
                                    "peer shares its estimates (messages.share_estimates)",
    # the image reply
    "reply-missing": "the image was requested but no reply came (request or reply lost)",
    "reply-undecodable-jpeg": "the image reply does not decode",
    "reply-unknown-reply-codec": "the image reply is in a codec this version does not know",
    "reply-truncated-jpeg": "the image reply is cut short",
    "reply-image-size-mismatch": "the image reply's size contradicts its intrinsics",
    # the direct estimate (phases 4, 8)
    "appearance-mismatch": "the pass placed the peer's view by keypoints, but the images contradict the placement",
    "collaborator-view-not-placed": "the pass did not place the peer's view",
    "own-view-not-placed": "the pass did not place this robot's current view",
    "no-scale": "the pass has no metric scale",
    "registrations-not-usable": "the peer's view was registered only against views this robot no longer has a pose of",
    "shared-estimate": "the estimate is the peer's own, shared and inverted (messages.share_estimates)",
    "registration-pending": "the peer's image is being registered apart from the step (a registrar): its estimate "
                            "lands when ready",
    "registration-late": "the estimate is a registration that landed after the step it was requested at, carried "
                         "to this step with both robots' odometry",
    "registration-late-no-pose": "a registration landed late, but the peer's pose of its step or of this one is "
                                 "unknown: it cannot be carried to this step",
    "anchor-not-stored": "a direct estimate while no pose message of the peer was ever seen: reported, not an anchor",
    "peer-motion-unknown": "online by stamps: the peer's received view is of another instant and how far the peer "
                           "moved since is unknown (no pose of it near this frame's stamp): no direct estimate",
    # anchors and propagation (phase 8)
    "unverified": "nothing has verified the estimate (or the anchor it propagates) yet",
    "unverified-held": "an unverified estimate held back (anchors.report_unverified, or a peer's shared estimate)",
    "unverified-expired": "the last unverified estimate is too old to carry (anchors.max_unverified_steps)",
    "direct-weak": "the direct estimate agrees with the anchor on fewer inliers than anchors.min_inliers: the anchor "
                   "is propagated instead (inliers: direct_inliers)",
    "direct-rejected": "the direct estimate disagrees with the anchor propagated to it: the anchor is propagated "
                       "instead (by how much: check_rot_rad, check_trans_m)",
    "no-anchor": "no anchor to propagate yet",
    "no-pose-of-other": "no pose of the peer was ever seen (online by stamps: none near this frame's stamp): nothing "
                        "to propagate with",
    "peer-absent": "online by stamps: the peer is not up (it has not joined yet, or it left): no descriptor to score",
    "stale-pose": "the peer's pose of this step was lost: its pose is bridged from the last ones seen",
    # the pose graph (backend.kind graph)
    "graph-uninformative": "the graph's predicted rotation sigma is too large to report its estimate",
    "no-direct-estimate-yet": "the pair's graph has no direct estimate yet",
    "graph-empty": "the pair's graph has no node yet",
    # the per-frame baselines
    "too-few-keypoints": "an image has too few keypoints",
    "too-few-matches": "too few matches between the two images",
    "essential-matrix-failed": "no essential matrix fits the matches",
    "too-few-inliers": "too few matches fit the essential matrix (inliers: direct_inliers)",
    "degenerate-pose": "the relative pose is degenerate",
    "not-evaluated": "a step the evaluation skips (evaluation.every): not computed",
}

DEGRADATIONS: dict[str, str] = {
    "frame:blank": "own frame without texture (descriptor flag low-texture, zero-norm descriptor or grey-level "
                   "std below protocols.BLANK_STD): zero descriptor broadcast, no joint pass, X kept, never kept as "
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
                     "the step rule's ratio and than braking at odometry.max_accel_mps2 allows): the pass's rotation is "
                     "kept, the translation is the last accepted step's at the median speed; the pose graph "
                     "counts the step's odometry as lost",
    "ego:no-keyframe": "the memory is empty after the first step (the first frames were blank)",
    "memory:reinit": "no keyframe could be placed but the current view could: memory restarts from it at the last X",
    "scale:fallback-last": "the memory gave no scale: the last valid one is used",
    "scale:unavailable": "no scale, and none before",
    "scale:unit-no-depth": "no metric depth at all: s = 1 (a depth source that never has metric depth)",
    "scale:skipped-no-backbone-depth": "a keyframe the pass gave no depth for, left out of the scale",
    "scale:skipped-no-metric-depth": "a keyframe without metric depth, left out of the scale",
    "scale:skipped-too-few-pixels": "a keyframe with fewer valid depth pixels than scale.min_pixels, left out of the "
                                    "scale",
    "depth:none": "the depth source had nothing for the current frame",
    "pose:stale": "the other robot's pose of this step is missing: its pose is bridged from the last ones seen "
                  "(constant velocity) for propagation",
    "pose:bridged": "a direct estimate without the other's pose message of this step: the anchor is stored with "
                    "that pose bridged (from the image reply's pose and earlier ones), corrected by the next",
    "pose:bridged-next": "an anchor stored with a bridged pose corrected by interpolation once a later pose came",
    "anchor:not-stored-pose-missing": "a direct estimate while no pose of the other was ever seen: not an anchor",
    "descriptor:missing": "a peer's descriptor of this step did not arrive: the gate scores its last one if at most "
                          "messages.stale_descriptor_steps steps old, else it waits for the next step (closed now); the anchor "
                          "is carried",
    "descriptor:stale-used": "a lost descriptor replaced by the peer's previous one (at most messages.stale_descriptor_steps "
                             "steps old) in the gate",
    "msg:request-retried": "an image request sent again within the step because its reply did not come "
                           "(messages.request_retries)",
    "msg:reply-missing": "the gate opened but no image reply arrived (request or reply lost): no direct estimate "
                         "this step; the pair keeps its anchor",
    "anchor:inconsistent": "a direct estimate that disagrees with the pair's verified anchor propagated to it: "
                           "not an anchor; the anchor's propagation is reported instead",
    "anchor:weak": "a direct estimate that agrees with the pair's anchor but stands on fewer than anchors.min_inliers "
                   "registration inliers: not an anchor; the anchor's propagation is reported instead",
    "anchor:replaced": "anchors.replace_after recent rejected estimates agree with the newest of them: it replaced "
                       "the anchor",
    "direct:appearance-mismatch": "the backbone placed the collaborator's view by keypoints but the images contradict "
                                  "the placement (where it says the views overlap they do not look alike: repeated "
                                  "or mirrored structure): no direct estimate this step, the anchor is carried",
    "anchor:odometry-jump": "one robot's odometry turned by more than anchors.max_odo_rot_step in one step (a lost "
                            "track): the pair forgot its anchor and candidates rather than carry them through it",
    "registration:dropped": "a registration job dropped unrun (the registrar's queue was full: the oldest goes): its "
                            "images give no estimate",
    "registration:failed": "a registration job whose pass failed (raised, or returned a malformed output): no estimate",
    "registration:late-no-pose": "a registration landed late, but the peer's pose of its step or of this one is "
                                 "unknown: not carried to this step",
    "msg:lost": "a frame that did not arrive (in process: dropped by the channel; online: missing at the deadline)",
    "msg:garbled": "a frame that does not decode",
    "msg:unknown-sender": "a frame whose sender index is not the robot it came from",
    "msg:stale-request": "an image request for a step this robot is not at",
    "msg:stale-estimate": "an estimate frame (messages.share_estimates) of another step: not used",
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
    "link:clock-offset": "online by stamps: a peer's stamps are off this robot's clock by more than the clock tolerance "
                         "(once per peer and session): its stamps are mapped into this robot's clock by the offset "
                         "estimated from message arrival",
    "net:peer-restarted": "online: a peer came back in a new session (its odometry restarted): what this robot knew of "
                          "the pair (anchors, poses, graph) is forgotten",
    "pose:extrapolated": "online by stamps: the peer's pose at this frame's stamp extrapolated past its newest pose at "
                         "its last velocity (within stamps.max_extrapolation_s)",
    "pose:too-far": "online by stamps: no pose of the peer near this frame's stamp (its newest is more than "
                    "stamps.max_extrapolation_s away, or the two around it more than stamps.max_pose_gap_s apart): "
                    "nothing is propagated for the pair at this frame",
    "pose:peer-motion-unknown": "online by stamps: the peer's poses at its received view's stamp and at this frame's are "
                                "not both known: its view gives no direct estimate (reason peer-motion-unknown)",
    "input:frame-dropped": "online: a camera frame that came while the robot was busy and was replaced by a newer one "
                           "before it was taken (a robot processes its newest frame)",
    "input:stall": "online: no camera frame for longer than the stall time (cerpe online --stall); counted on the "
                   "first frame after",
    "input:out-of-order": "online: an image whose stamp is not after the last one taken (a clock that jumped back): "
                          "dropped",
    "input:bad-image": "online: an image message that cannot be used (unsupported encoding, cut data, does not "
                       "decode, another size than its camera info): dropped",
    "input:no-camera-info": "online: an image before any usable CameraInfo came: dropped",
    "input:bad-camera-info": "online: a CameraInfo that cannot be used (zeros, NaN, an unsupported distortion model or "
                             "binning): ignored",
    "input:bad-depth": "online: a depth message that cannot be used (unsupported encoding, cut data, another size than "
                       "the colour image): the frame goes without depth",
    "input:no-depth": "online: no depth message within the depth tolerance of the image's stamp: the frame goes "
                      "without depth",
    "input:bad-odometry": "online: an odometry or TF message with NaN or an unusable pose: ignored",
    "input:no-odometry": "online: no odometry pose of the robot at the image's stamp (none within the extrapolation "
                         "bound, or no camera extrinsic): X keeps its value",
    "input:wrong-type": "online: a message of another type than its topic's (the key names another type, or the "
                        "payload does not decode as the topic's type): ignored",
    "graph:degenerate-covariance": "a direct estimate's or the odometry's covariance is zero, not finite or not "
                                   "positive definite: the estimate is not added to the pair's graph",
    "graph:out-of-order": "a direct estimate between poses the graph does not have (the other robot's pose of that "
                          "step is missing, or the step precedes the graph's newest node): not added",
    "graph:solver-failed": "GTSAM threw or returned a non-finite estimate or covariance: the graph restarts from "
                           "its last good estimate (the estimate that caused it is dropped)",
    "graph:not-converged": "the graph did not settle within the noise model's max_iterations updates: the last good estimate "
                           "is kept (the graph restarts from it, the new estimate dropped)",
}


class VocabularyError(ValueError):
    """A reason token or degradation name that is not in the vocabulary (a programming error)."""


def split(reason: str) -> list[str]:
    """The tokens of a reason (empty for ``""``)."""
    return [t for t in str(reason).split(SEPARATOR) if t]


def join(*tokens: str) -> str:
    """Tokens (and joined reasons; empty ones left out) as one reason, each checked."""
    out = [t for r in tokens for t in split(r)]
    for t in out:
        if t not in REASONS:
            raise VocabularyError(f"reason {t!r} is not in cerpe.reasons.REASONS")
    return SEPARATOR.join(out)


def check_reason(reason: str) -> None:
    """Raise :class:`VocabularyError` when a token of ``reason`` is not in :data:`REASONS`."""
    join(reason)


def known_degradation(name: str) -> bool:
    """Whether ``name`` is one of :data:`DEGRADATIONS`."""
    return name in DEGRADATIONS


def check_degradations(names: Iterable[str]) -> None:
    """Raise :class:`VocabularyError` for a name that is not in :data:`DEGRADATIONS`."""
    for n in names:
        if n not in DEGRADATIONS:
            raise VocabularyError(f"degradation {n!r} is not in cerpe.reasons.DEGRADATIONS")
