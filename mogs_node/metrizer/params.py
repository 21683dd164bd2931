"""Parameters and output of the depth metrizer (MSC, paper III-B + CDR, paper III-C)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mogs_node.errors import ConfigError
from mogs_node.metrizer.consensus import ConsensusParams
from mogs_node.metrizer.refinement import CdrParams

__all__ = ["MASK_PLANE_SUPPORTS", "MODES", "MetrizedDepth", "MetrizerNodeParams", "MetrizerParams"]

F64 = NDArray[np.float64]


MODES = ("full", "no_msc", "no_msc_cdr")  # see docs/metrizer.md, ablation modes
# which depth pixels the whole-mask plane pass fits and reaches from (docs/metrizer.md, "Planes
# from measured support only"): every pixel with a depth, the prior's pixels, or all but the
# metrizer's own fills near sparse points
MASK_PLANE_SUPPORTS = ("all", "measured", "no_point_fills")


@dataclass(frozen=True)
class MetrizerParams:
    """Parameters of the metrizer (MSC + CDR); nested dataclasses hold the stage parameters."""

    d_min_m: float = 0.1  # smallest output depth [m]; features nearer are dropped
    d_max_m: float = 80.0  # largest output depth [m] (sky and far pixels); features beyond dropped
    n_min: int = 9  # III-B: a mask with fewer features is under-supported and merges
    rho_contiguity: float = 0.1  # III-B: merge only when |z_i - z_u| <= rho z_i (median depths)
    border_vote_radius: int = 1  # feature association: vote in a (2r+1)^2 window on mask borders
    sample_stride: int = 6  # CDR data terms use every stride-th pixel in x and y (+ tiny masks)
    model_extrapolation: float = 2.0  # model depth used within [z_min / f, z_max * f] of inliers
    hole_model_extrapolation: float = 1.25  # the same f for pixels without prior (no gate there)
    fallback_global: bool = True  # per object: the global affine where the object's own result
    # does not explain its features better (degrees-of-freedom corrected, see _fallback_to_global)
    fallback_untestable: bool = True  # ... and objects with too few features to test always
    fallback_failed_share: float = 0.5  # ... also when more than this share of the tested
    # objects fell back
    min_anchor_features: int = 5  # a non-metric prior with fewer features (with a prior) that
    # anchor its global affine gives no metric depth at all (it would be a guessed scale)
    fallback_min_features: int = 18  # ... untestable objects also when the frame has fewer
    # features with a prior than this (their calibration follows thin neighbouring evidence)
    hole_model_radius: float = 0.03  # a pixel without prior takes its object's model depth only
    # within this fraction of the image width of one of the object's own features
    hole_fill_radius: float = 0.02  # ... the edge-aware fill of the features only within this
    mask_plane_fill: bool = True  # departure: an object's pixels still without depth get its
    # plane (inverse depth affine in u, v) when the plane explains its depth pixels (fill.py)
    mask_plane_min_share: float = 0.3  # ... at least this share of the object has a depth
    mask_plane_inlier_rel: float = 0.02  # ... half of those within this relative depth of it
    mask_plane_min_depth_m: float = 5.0  # ... and their (geometric) mean depth at least this
    mask_plane_max_gap: float = 0.0  # > 0: as confident_plane_max_gap, for this pass
    mask_plane_colour_gap: float = 0.0  # > 0: as confident_plane_colour_gap, for this pass
    # (with mask_plane_max_gap 0: every filled pixel needs the inliers' colour)
    mask_plane_support: str = "no_point_fills"  # which depth pixels it fits, counts, reaches
    # from (issue 16, session 17): "all"; "measured" (the prior's); "no_point_fills" (all but
    # the fills near sparse points, fill_holes, that no plane pass replaced)
    confident_planes: bool = False  # departure (issue 16): before that, an object's plane
    # fitted to its pixels of prior confidence >= confident_plane_fit_conf replaces its pixels
    # below confident_plane_replace_below and fills its holes (fill.PlaneSelect), when at least
    confident_plane_fit_conf: float = 0.4
    confident_plane_replace_below: float = 0.3
    confident_plane_min_share: float = 0.02  # ... this share of the object is fitted,
    confident_plane_min_pixels: int = 20  # ... at least this many pixels,
    confident_plane_inlier_rel: float = 0.03  # ... half of them within this of the plane
    confident_plane_max_gap: float = 0.0  # > 0: only pixels within this fraction of the image
    # width of an inlier of their object get its plane
    confident_plane_colour_gap: float = 0.0  # > 0 (issue 16, session 16): pixels farther than
    # that but within this fraction of the width get it where their colour is one of the
    # inliers' (at least confident_plane_colour_share of them in its bin, fill.colour_share_of)
    confident_plane_colour_share: float = 0.1  # (the whole-mask pass's colour test too)
    road_camera_height_m: float = float("nan")  # departure (issue 16): > 0 the camera's height
    # above a planar road; with the keyframe's pose (MetrizerInputs.T_world_cam) the road plane
    # then gives depth to road objects and objects standing on the road (ground.py)
    road_up_world: tuple[float, float, float] | None = (0.0, 0.0, 1.0)  # world "up" (a
    # gravity-aligned world); None: road_up_cam, fixed in the camera frame
    road_up_cam: tuple[float, float, float] = (0.0, -1.0, 0.0)
    road_objects: bool = True  # road objects' empty pixels get the plane (ground.py)
    road_agree_rel: float = 0.05  # a pixel agrees with the plane within this relative depth
    road_max_depth_m: float = 40.0  # road farther than this gets no depth
    road_snap_rel: float = 0.0  # > 0 (departure, ground.py): pixels of road objects within this
    # relative depth of the road plane get the plane's depth (a learned prior's road is warped)
    ground_contact: bool = False  # objects standing on road pixels: a vertical plane through
    # the contact line for their empty pixels, when their confident pixels agree with it
    ground_contact_check_rel: float = 0.1
    t_abs_ref_depth_m: float = 10.0  # median feature depth for which consensus.t_abs_m is meant
    fill_method: str = "nearest"  # pixels without prior and shape: "nearest" consistent feature
    # of the same object, or "edge_aware" (FGS normalised convolution of the features)
    fill_seed_gate: float = 0.3  # a fill seed must be within this relative depth of the median
    # of its nearest features (of 8) within fill_seed_radius (x image width), and have >= 2 there
    fill_seed_radius: float = 0.1
    model_prior_gate: float = 0.3  # eq. (7) uses a model pixel only within this relative
    # distance of the globally aligned prior (the pixel is then plausibly on the model's surface)
    feature_prior_gate: float = 0.5  # eq. (7) feature rows: drop a feature whose depth is more than
    # (1 + gate) times off the globally aligned prior (occlusion-boundary / mismatched features)
    model_edge_gate: float = 0.5  # the same gate within prior_edge_radius px of a prior depth edge
    model_edge_min_conf: float = 0.9  # ... for shapes with eq.-(5) confidence at least this
    prior_edge_rel: float = 0.05  # a prior depth edge: relative gradient above this per pixel
    prior_edge_radius: int = (
        4  # [px] neighbourhood of prior depth edges (blurred by learned priors)
    )
    residual_field: bool = True  # departure: smooth multiplicative correction after CDR
    residual_sigma_frac: float = 0.05  # its Gaussian width, fraction of the image width
    residual_model_weight: float = 0.05  # weight of a model-output sample vs a feature (1)
    residual_shrink: float = 1.0  # the field decays to 1 (no correction) where it has less
    # evidence than this many features per Gaussian footprint (as anchor_shrink)
    absorb: bool = True  # departure: groups without a shape join a neighbour's shape that fits
    local_anchor: bool = True  # departure: eq. (8) anchors to the globally aligned prior times a
    # smooth field of the geometric evidence (model depth, features) relative to it
    anchor_shrink: float = 1.0  # that field decays to 0 where it has less evidence than this
    # many features per Gaussian footprint (pseudo-observation of "no correction")
    absorb_prior_gate: float = 0.15  # featureless groups: model vs globally aligned prior
    absorb_sample_below: int = 5  # groups with fewer features also use sample-pixel evidence
    shape_prior_check: bool = True  # departure 22 (holdout.py): a shape must also explain its
    # object's prior samples (calibrated by the object's features): at least consensus.tau of
    # them within model_output_gate, else it is dropped
    model_output: bool = True  # departure: output the model depth where it agrees (below)
    model_output_gate: float = 0.1  # output the model depth where it is within this relative
    # distance of the calibrated prior (accepted shapes only); else the calibrated prior
    sky_depth_frac: float = 0.9  # a prior pixel is "far" beyond this fraction of d_max (globally)
    sky_far_fraction: float = 0.6  # a featureless object is sky when this share of it is far
    global_huber: float = 0.05  # Huber width (relative) of the global affine alignment
    metric_identity_test: bool = False  # departure 23 (off: measured both ways, docs): a metric
    # prior's global affine is kept only when it explains the features better than the identity
    # (2 parameters corrected for)
    global_shift_prior: float = 0.05  # departure: weak pull of its shift to 0 (pure scale)
    sky_anchor: float = 0.0  # > 0 (departure, relative inverse-depth priors): the sky's prior
    # value maps to inverse depth 0, a pseudo-observation with this share of the features' weight
    # in the global affine (refitted once sky is found; docs/metrizer.md "The sky pins the shift")
    fill_scale: float = 0.5  # resolution factor of the edge-aware fill
    fill_lambda: float = 50.0  # edge-aware fill: smoothing strength (FGS lambda)
    fill_sigma_color: float = 8.0  # edge-aware fill: colour edge scale (FGS sigma)
    # dense metric anchors (MetrizerInputs.anchor_*; dense_anchors.py, issue 16): a metric depth
    # map beside a relative prior gives extra sparse points, one per stride x stride cell of
    # confidence >= min_conf, none within gap (fraction of the image width) of a frontend point,
    # weighted weight * confidence (docs/metrizer.md "Dense metric anchors")
    dense_anchor_stride: int = 8
    dense_anchor_min_conf: float = 0.3
    dense_anchor_gap: float = 0.025
    dense_anchor_weight: float = 0.3
    # departure (issue 16, edge_snap.py): pixels within edge_snap_radius px of a prior depth edge
    # (relative gradient > edge_snap_rel per pixel) and within edge_snap_boundary_px of another
    # object take the output of the nearest pixel of their object outside that band (a learned
    # prior blurs depth edges; docs/metrizer.md "Depth edges snapped to their object")
    edge_snap: bool = False
    edge_snap_rel: float = 0.1
    edge_snap_radius: int = 1
    edge_snap_boundary_px: int = 4
    # departure (issue 16, mask_split.py): each mask is cut along the prior's depth edges
    # (relative gradient > mask_split_rel per pixel, dilated by mask_split_radius px) into
    # connected pieces of at least mask_split_min_frac of the image; the band goes back to the
    # nearest piece of its mask (docs/metrizer.md "Masks split along the prior's depth edges")
    mask_split: bool = False
    mask_split_rel: float = 0.1
    mask_split_radius: int = 1
    mask_split_min_frac: float = 2e-4
    seed: int = 0  # RANSAC random seed (results are deterministic per input)
    consensus: ConsensusParams = ConsensusParams()  # Algorithm 1 parameters
    cdr: CdrParams = CdrParams()  # eqs. (6)-(11) parameters

    def __post_init__(self) -> None:
        if not (0 < self.d_min_m < self.d_max_m and np.isfinite(self.d_max_m)):
            raise ConfigError("MetrizerParams: need 0 < d_min_m < d_max_m < inf")
        if not self.anchor_shrink >= 0:
            raise ConfigError(
                f"MetrizerParams: anchor_shrink >= 0 required, got {self.anchor_shrink}"
            )
        if not (
            0 <= self.confident_plane_fit_conf <= 1 and 0 <= self.confident_plane_replace_below <= 1
        ):
            raise ConfigError("MetrizerParams: confident_plane_* confidences must be in [0, 1]")
        h = self.road_camera_height_m
        if h == h and not (0 < h < float("inf")):
            raise ConfigError(f"MetrizerParams: road_camera_height_m > 0 or NaN, got {h}")
        if not (
            self.dense_anchor_stride >= 1
            and 0 <= self.dense_anchor_min_conf <= 1
            and self.dense_anchor_gap >= 0
            and 0 <= self.dense_anchor_weight < float("inf")
        ):
            raise ConfigError(
                "MetrizerParams: dense_anchor_stride >= 1, dense_anchor_min_conf in [0, 1], "
                "dense_anchor_gap >= 0 and a finite dense_anchor_weight >= 0 required"
            )
        if not (
            self.edge_snap_rel > 0
            and self.edge_snap_radius >= 0
            and self.edge_snap_boundary_px >= 0
        ):
            raise ConfigError(
                "MetrizerParams: edge_snap_rel > 0, edge_snap_radius >= 0 and "
                "edge_snap_boundary_px >= 0 required"
            )
        if not 0 <= self.sky_anchor < float("inf"):
            raise ConfigError(f"MetrizerParams: finite sky_anchor >= 0, got {self.sky_anchor}")
        gaps = (
            self.confident_plane_max_gap,
            self.confident_plane_colour_gap,
            self.mask_plane_max_gap,
            self.mask_plane_colour_gap,
        )
        if not (
            all(0 <= g < float("inf") for g in gaps) and 0 < self.confident_plane_colour_share <= 1
        ):
            raise ConfigError(
                "MetrizerParams: finite *_max_gap / *_colour_gap >= 0 and "
                "confident_plane_colour_share in (0, 1] required"
            )
        if self.mask_plane_support not in MASK_PLANE_SUPPORTS:
            raise ConfigError(
                f"MetrizerParams: mask_plane_support must be one of {MASK_PLANE_SUPPORTS}, "
                f"got {self.mask_plane_support!r}"
            )
        if not 0 <= self.road_snap_rel < 1:
            raise ConfigError(f"MetrizerParams: road_snap_rel in [0, 1), got {self.road_snap_rel}")
        if not (self.mask_split_rel > 0 and self.mask_split_radius >= 0):
            raise ConfigError("MetrizerParams: mask_split_rel > 0 and mask_split_radius >= 0")
        if not 0 <= self.mask_split_min_frac < 1:
            raise ConfigError("MetrizerParams: mask_split_min_frac in [0, 1) required")
        if self.n_min < 1 or self.sample_stride < 1 or self.rho_contiguity < 0:
            raise ConfigError("MetrizerParams: n_min >= 1, sample_stride >= 1, rho >= 0 required")


@dataclass
class MetrizedDepth:
    """Output of :func:`metrize_depth`."""

    depth_m: NDArray[np.float32]  # [H, W] metric z-depth, in (0, d_max]; 0 = no value
    confidence: NDArray[np.float32]  # [H, W] in [0, 1]; 0 where depth_m is 0
    object_labels: NDArray[np.int32]  # [H, W] object id after merging (every pixel has one)
    object_model: NDArray[np.int8]  # [M] 0 none, 1 plane, 2 cylinder, 3 ellipsoid
    object_affine: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))  # [M, 2]
    object_confidence: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # [M] eq. 5
    stats: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class MetrizerNodeParams:
    """Parameters of the metrizer node."""

    mode: str = "full"  # "full" | "no_msc" | "no_msc_cdr" (ablations)
    max_wait_s: float = 2.0  # silence of a worker beyond its backlog that gives it up [s]
    stall_factor: float = 2.0  # times the worker's output interval per keyframe queued at it
    first_wait_s: float = 60.0  # least wait before a worker's first output (start-up) [s]
    max_pending: int = 32  # keyframes waiting at most; beyond, the oldest is processed early
    poll_period_s: float = 0.05  # how often timed-out keyframes are checked [s]
    metrizer: dict[str, Any] = field(default_factory=dict)  # MetrizerParams fields (flat ones)
    consensus: dict[str, Any] = field(default_factory=dict)  # ConsensusParams fields
    cdr: dict[str, Any] = field(default_factory=dict)  # CdrParams fields
    keyframe_topic: str = "/frontend/keyframe"  # input keyframes
    masks_topic: str = "/seg/masks"  # input instance masks
    prior_topic: str = "/prior/depth"  # input dense prior
    out_topic: str = "/metrizer/depth"  # output metric depth
    camera_info_topic: str = "/camera/info"  # the source's camera height above the road, used
    # for metrizer.road_camera_height_m unless the launch file sets it ("" = off)
    anchor_topic: str = ""  # a metric depth map (a second prior node, flow backend) as dense
    # metric anchors beside a relative prior; a keyframe then waits for it too ("" = off)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"metrizer.mode: expected one of {MODES}, got {self.mode!r}")
        waits = (self.max_wait_s, self.stall_factor, self.first_wait_s)
        if not all(0 <= w < float("inf") for w in waits):
            raise ConfigError(
                "metrizer: max_wait_s, stall_factor and first_wait_s must be finite and >= 0, "
                f"got {waits}"
            )
        if self.max_pending < 1 or self.poll_period_s <= 0:
            raise ConfigError("metrizer: max_pending >= 1, poll_period_s > 0")
