"""The ``backbone`` sub-tree of cerpe's configuration: which plug-ins run, and what a user may set of them.

``models`` picks the plug-ins: ``offline`` (XFeat, the SALAD-style descriptor over it and the
classical multi-view backbone, :mod:`cerpe.backbones.offline`; what ``make paper`` and every test
run) or ``paper`` (VGGT + SALAD/DINOv2 + Metric3Dv2 from the user's weights,
:mod:`cerpe.backbones.paper_profile`). Only the group of the chosen models is read.

Every other value of these components is a named constant in the module that uses it (with
its reason); the paper models' architectures are their adapters' own ``default_conf``.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..knobs import Group, group, knob
from .xfeat_net import PRECISIONS

__all__ = ["BackboneConfig", "OfflineConfig", "DescriptorConfig", "DenseConfig", "CrossConfig",
           "PaperModelsConfig", "MODELS", "CROSS_MATCHERS", "METRIC3D_MODELS"]

MODELS = ("offline", "paper")
CROSS_MATCHERS = ("aliked", "xfeat", "none")
METRIC3D_MODELS = ("metric3d_vit_small", "metric3d_vit_large", "metric3d_vit_giant2")


@dataclass(frozen=True)
class DescriptorConfig(Group):
    """The offline descriptor's fitted data (:class:`cerpe.backbones.descriptor.XFeatSaladDescriptor`)."""

    centres: str | None = knob(None, "k-means centres .npz the local features are assigned to "
                                     "(None: the shipped cerpe/data/xfeat_salad_centres.npz)")
    mean: str = knob("shipped", "mean descriptor subtracted before the final normalisation: 'shipped' "
                                "(cerpe/data/xfeat_salad_mean.npz), 'none', or the path of another .npz")


@dataclass(frozen=True)
class DenseConfig(Group):
    """Dense RGB-D refinement of the current pose on its depth-prior view (:mod:`cerpe.backbones.rgbd_align`)."""

    refine: bool = knob(True, "refine the current view's P3P pose on every pixel of its depth-prior view")
    stride: int = knob(8, "every stride-th reference pixel (both directions) takes part, px", low=1)
    iterations: int = knob(12, "Gauss-Newton steps per pyramid level", low=1)
    levels: int = knob(3, "pyramid levels (1: full resolution only; each halves the image)", low=1)
    use_depth: bool = knob(True, "add the depth residual to the grey-level one (false: photometric only)")


# Why CrossConfig's defaults:
# enabled "without-depth": on only for passes whose own views have no depth. On RGB-only data the joint
# pass places few collaborators; on RGB-D the learned stage costs several times a step and places no more.
# fallback: where registration is off (RGB-D), a collaborator the joint pass did not place is registered
# apart, both stages, when the robot asks (View.try_hard: it holds no anchor of the sender; failed tries
# back off). So the costly stage runs for pairs not anchored yet, and ever more rarely while nothing places.
# min_inliers (learned stage, essential matrix) goes with ALIKED at max_side_px and max_keypoints: wrong
# registrations of wide-baseline pairs stay under it. More keypoints cost more per pair and place no more
# at a safe threshold.
# min_inliers_pnp is lower: a wrong P3P pose on metric depth must also fit the depths. A half turn on a
# street whose two sides look alike (the typical wrong pose) stays under it.
@dataclass(frozen=True)
class CrossConfig(Group):
    """Cross-robot registration of collaborator views against single own views (:mod:`.offline.cross`)."""

    enabled: bool | str = knob("without-depth", "register collaborators apart from the joint pass: true, false, "
                                                "or 'without-depth' (only on passes whose own views have no depth)",
                               choices=(True, False, "without-depth"))
    fallback: bool = knob(True, "where registration is off, register a collaborator the joint pass left "
                                "unplaced when the robot asks (View.try_hard)")
    matcher: str = knob("aliked", "learned stage after the mutual-NN one: 'aliked' (ALIKED + LightGlue), "
                                  "'xfeat' (LighterGlue over XFeat) or 'none'", choices=CROSS_MATCHERS)
    min_inliers: int = knob(65, "essential-matrix inliers a learned-stage registration needs, count", low=1)
    min_inliers_pnp: int = knob(50, "P3P inliers a learned-stage registration on metric depth needs "
                                    "(the fallback: either stage), count", low=1)
    min_inliers_mnn: int = knob(15, "verified inliers a mutual-NN-stage registration needs, count", low=1)
    max_views: int = knob(3, "own views the learned stage tries (most mutual-NN matches first), count", low=1)
    max_keypoints: int = knob(1024, "keypoints per image of the learned stage, count", low=1)
    max_side_px: int = knob(640, "ALIKED downscales an image to this longest side, px", low=1)
    appearance_check: bool = knob(True, "judge a metric collaborator placement on few inliers by how its "
                                        "image agrees with the own view's moved pixels")
    appearance_min_ncc: float = knob(0.5, "normalised cross-correlation of grey levels a judged placement "
                                          "needs, in [-1, 1]", low=-1.0, high=1.0)
    appearance_min_ncc_highpass: float = knob(0.2, "the same of high-passed grey levels (texture only), "
                                                   "in [-1, 1]", low=-1.0, high=1.0)


@dataclass(frozen=True)
class OfflineConfig(Group):
    """The offline plug-ins: XFeat, the SALAD-style descriptor and the classical multi-view backbone."""

    # `cerpe bench --all-encounters` measures the latency/accuracy trade-off of more keypoints; the
    # descriptor aggregates the best 1024 either way
    keypoints: int = knob(1024, "XFeat keypoints per image (shared by descriptor and backbone), count", low=1)
    # bf16 changes the descriptors' cosines by about 2e-5 and the keypoints chosen at the margin; the
    # tables are made in fp32, so they do not depend on whether a CPU has bfloat16 (cerpe.backbones.xfeat_net)
    precision: str = knob("fp32", "XFeat's deeper convolutions: 'fp32', 'bf16' (bfloat16, about 8 ms less per "
                                  "640x480 frame on a CPU that has it natively) or 'auto' (bf16 where the CPU has "
                                  "avx512_bf16 or AMX, else fp32)", choices=PRECISIONS)
    descriptor: DescriptorConfig = group(DescriptorConfig, "the SALAD-style global descriptor over XFeat")
    min_inliers: int = knob(25, "inliers an image pair needs (essential matrix, or the current view's "
                                "P3P on a depth prior), count", low=1)
    pnp_px: float = knob(3.0, "absolute-pose RANSAC inlier threshold of views placed on the points, px",
                         low=0.0, low_open=True)
    ransac_max_iterations: int = knob(4000, "most RANSAC iterations of one pose estimate, count", low=1)
    # 2: the static scene and one other (a moving object, a facade one window off); a third was the
    # vote's rarely, and each costs a RANSAC on outliers and a vote
    motion_hypotheses: int = knob(2, "rigid motions RANSAC looks for on a depth prior before the dense vote, "
                                     "count", low=1)
    mask_moving: bool = knob(True, "pixels the chosen motion did not explain (a moving object) do not vote "
                                   "in later passes")
    frame_scale: bool = knob(True, "carry a running per-frame depth scale in the memos for priors that "
                                   "report a scale sigma (monocular depth)")
    dense: DenseConfig = group(DenseConfig, "dense RGB-D refinement of the current pose")
    cross: CrossConfig = group(CrossConfig, "cross-robot registration of collaborator views")


@dataclass(frozen=True)
class PaperModelsConfig(Group):
    """The paper's models from user-supplied weights (``docs/PAPER_MODELS.md``)."""

    device: str = knob("auto", "where the models run: 'auto' (CUDA when present, else CPU), 'cpu', 'cuda', "
                               "'cuda:N'")
    weights_dir: str | None = knob(None, "folder holding the weight files under their release names "
                                         "(None: $CERPE_WEIGHTS_DIR)")
    metric3d_model: str = knob("metric3d_vit_small", "Metric3Dv2 size (the paper does not say which)",
                               choices=METRIC3D_MODELS)
    check_memory: bool = knob(True, "refuse to start when the device has too little memory for VGGT-1B")


@dataclass(frozen=True)
class BackboneConfig(Group):
    """Which plug-ins (descriptor, pose backbone) run, and their settings."""

    models: str = knob("offline", "the plug-ins: 'offline' (XFeat, the SALAD-style descriptor, the classical "
                                  "multi-view backbone; run here) or 'paper' (VGGT + SALAD/DINOv2 + Metric3Dv2 "
                                  "from the user's weights)", choices=MODELS)
    offline: OfflineConfig = group(OfflineConfig, "the offline plug-ins (models: offline)")
    paper: PaperModelsConfig = group(PaperModelsConfig, "the paper's models (models: paper)")
