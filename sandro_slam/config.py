"""Typed configuration of the SLAM plugin, with a YAML round trip (configs/default.yaml)."""

from __future__ import annotations

from typing import Any, Literal

from kiss_icp.config.parser import KISSConfig
from pydantic import BaseModel, Field

from sandro_core.config import SandroConfig, StrictModel, YamlConfig

REFERENCE_ODOMETRY_VOXEL = 1.0  # [m] KISS-ICP's voxel at scale 1 (its own default: max_range / 100 at 100 m)
REFERENCE_NOISE_BOUND = 1.0  # [m] SANDRO's inlier bound for submap registration at scale 1


def scaled(reference: float, description: str, zero_allowed: bool = False) -> Any:
    """A length [m] that follows the scene: None (the default) means `reference` x `SlamConfig.scale`."""
    return Field(
        None,
        **({"ge": 0.0} if zero_allowed else {"gt": 0.0}),
        description=f"{description} (None: {reference:g} x scale)",
        json_schema_extra={"reference": reference},
    )


class OdometryGicpConfig(StrictModel):
    """The odometry's second registration: each KISS-ICP pose refined with VGICP (small_gicp) against a map of
    Gaussian voxels (`sandro_slam.odometry.GaussianMapRefiner`)."""

    enabled: bool = Field(True, description="refine every KISS-ICP pose with VGICP")
    # Finer voxels narrow VGICP's reach (a 128-beam drive lost its way at a corner); coarser ones blur thin
    # structure such as a garage's pillars (docs/benchmarks.md, "The Gaussian map at 1.5 voxels").
    resolution: float | None = scaled(1.5, "voxel [m] of the Gaussian map")
    source_voxel: float | None = scaled(0.5, "voxel [m] the scan is downsampled to before its covariances")
    max_distance: float | None = scaled(3.0, "correspondence distance [m]")
    max_iterations: int = Field(20, ge=1, description="Gauss-Newton iterations per scan")
    motion_prior: float = Field(
        0.03,
        ge=0.0,
        lt=1.0,
        description="translation directions whose information (rotation marginalised) is below this share of the "
        "largest follow the constant-velocity prediction, with a prior of that strength (0: none; "
        "`odometry.with_motion_prior`)",
    )


class KeyframeConfig(StrictModel):
    """When a new keyframe starts, and what its submap holds."""

    distance: float | None = scaled(10.0, "travel [m] that starts a new keyframe")
    angle_deg: float = Field(30.0, gt=0.0, description="rotation [deg] that starts a new keyframe")
    # As fine as registration uses (the ICP source is voxelised as finely, FPFH keypoints are coarser).
    submap_voxel: float | None = scaled(0.5, "voxel size [m] of the stored submap")
    submap_radius: float | None = scaled(30.0, "submap points farther than this [m] are dropped")


class LoopDetectionConfig(StrictModel):
    """Which keyframe pairs are tried as loop closures, and where that work runs."""

    radius: float | None = scaled(
        25.0, "candidates whose submaps' middles lie within this distance [m] of the new keyframe's"
    )
    exclude_recent: float | None = scaled(50.0, "skip keyframes fewer than this many metres back", True)
    max_candidates: int = Field(2, ge=1, description="nearest candidates registered per keyframe")
    max_loops_per_keyframe: int = Field(2, ge=1, description="stop registering candidates after this many loops")
    guided_loops: int = Field(
        0,
        ge=0,
        description="where two of a keyframe's verified loops agree, register up to this many more of its nearest "
        "radius candidates (the next after the `max_candidates` nearest, and those SANDRO failed on) by ICP alone "
        "from the pose the first loop predicts (0: none; 2 helps spinning-LiDAR drives back along their way and "
        "costs others accuracy, docs/benchmarks.md)",
    )
    guided_tolerance: float | None = scaled(
        0.1,
        "two loops agree within this distance [m] (and 2 deg) of the pose the first predicts; a guided loop is kept "
        "within this distance (and 0.1 deg) of it",
    )
    use_map_closures: bool = Field(True, description="add MapClosures place-recognition candidates")
    map_closures_min_inliers: int = Field(5, ge=1, description="ORB inliers a MapClosures candidate needs")
    map_closures_radius: float | None = scaled(30.0, "submap points within this range [m] form its density map")
    map_closures_resolution: float | None = scaled(0.5, "pixel size [m] of the MapClosures density maps")
    map_closures_spacing: float | None = scaled(
        15.0,
        "MapClosures sees a keyframe only this far [m] along the path from the last one it saw (its density maps "
        "span 2 x map_closures_radius)",
        True,
    )
    max_drift: float = Field(
        0.1,
        ge=0.0,
        description="a verified loop may place its keyframe at most `radius` plus this share of the path travelled "
        "between the two keyframes away from the current estimate (place recognition finds revisits beyond the "
        "radius; what lies further is taken for an alias of repeated structure)",
    )
    ring_key_candidates: int = Field(
        1, ge=0, description="earlier keyframes with the most similar ring keys registered per keyframe (0: none)"
    )
    ring_key_radius: float | None = scaled(30.0, "submap points within this range [m] form its ring key")
    in_background: bool = Field(
        True,
        description="OfflineSlam, on more than one core: loop closure in a worker process at the lowest CPU "
        "priority, on the cycles the odometry leaves idle (the same results)",
    )


class LoopRegistrationConfig(StrictModel):
    """Registration and verification of one candidate pair of submaps."""

    fpfh_voxel: float | None = scaled(1.25, "voxel [m] of the FPFH keypoints")
    fpfh_max_nn: int = Field(50, ge=1, description="neighbours per FPFH descriptor (its cost grows linearly with it)")
    sandro: SandroConfig = Field(
        default_factory=SandroConfig,
        description=f"the solver; its noise_bound None means {REFERENCE_NOISE_BOUND:g} m x scale here",
    )
    icp_refine: bool = Field(
        True,
        description="point-to-plane ICP from the SANDRO transform, then again with a Tukey kernel at the scale of "
        "its residuals",
    )
    icp_max_distance: float | None = scaled(1.0, "ICP correspondence distance [m]")
    icp_voxel: float | None = scaled(0.5, "voxel [m] of both submaps' points in ICP and the overlap check")
    min_inliers: int = Field(20, ge=3, description="SANDRO inliers a loop needs")
    min_overlap: float = Field(
        0.3,
        ge=0.0,
        le=1.0,
        description="share of the source's ICP points within icp_max_distance of the target's, aligned",
    )


class GraphConfig(StrictModel):
    """The pose graph and its robust optimisation."""

    mode: Literal["batch", "incremental"] = "batch"
    robust: Literal["gnc_tls", "gnc_gm", "none"] = "gnc_tls"
    inlier_probability: float = Field(
        0.99, gt=0.0, lt=1.0, description="chi-square probability of a loop's whitened error being an inlier"
    )
    noise_scale: Literal["given", "estimated"] = Field(
        "estimated",
        description="loops' covariances as given, or also a second robust pass rescaled by the "
        "variance factor of the loops the first keeps, taken when it keeps most of them and fits them clearly "
        "better (for covariances not to scale)",
    )
    estimate_odometry_noise: Literal["never", "given_odometry", "always"] = Field(
        "given_odometry",
        description="when to scale the odometry covariances to fit the loops (variance component estimation): for "
        "the poses of another front end, whose quality the model below cannot know (docs/back-end.md)",
    )
    loop_submap_noise: bool = Field(
        True,
        description="once the loops are decided, weigh each kept loop with its registration covariance plus the "
        "odometry covariance of each of its two keyframes: a loop aligns two submaps, each only as rigid as the "
        "odometry within its keyframe (docs/back-end.md)",
    )
    prior_sigma: float = Field(1e-3, gt=0.0, description="std of the first pose, rad and m")
    odometry_translation_sigma_per_m: float = Field(0.01, gt=0.0, description="[m] per m travelled")
    odometry_rotation_sigma_per_m: float = Field(0.001, gt=0.0, description="[rad] per m travelled")
    odometry_sigma_floor: float = Field(0.01, gt=0.0, description="[m] and [rad], added to both")


class MergeConfig(StrictModel):
    """Joining sessions recorded at different times (`sandro_slam.merge_sessions`, `sandro-merge`)."""

    candidates_per_keyframe: int = Field(3, ge=1, description="place-recognition candidates per keyframe")
    max_candidate_pairs: int = Field(
        60, ge=1, description="place-recognition pairs registered per pair of sessions, best first"
    )
    descriptor_radius: float | None = scaled(30.0, "radius [m] of the ring-key place descriptor")
    consistency_translation: float | None = scaled(
        1.0, "two loops agree when their session transforms move keyframes less than this [m]"
    )
    consistency_rotation_deg: float = Field(2.0, gt=0.0, description="... and differ by less than this [deg]")
    min_loops: int = Field(
        3, ge=1, description="agreeing inter-session loops, kept by the robust back end, that join two sessions"
    )
    guided_radius: float | None = scaled(
        10.0, "once aligned, register keyframe pairs this close [m] (0: no guided search)", True
    )
    max_free_space_conflict: float = Field(
        0.03,
        ge=0.0,
        le=1.0,
        description="refuse a voted alignment whose agreeing loops put a median share above this of the submap "
        "keypoints where the other session saw free space (an aliased place; docs/merge.md)",
    )
    free_space_voxel: float | None = scaled(0.5, "voxel [m] of the free-space test")
    conflict_loops: int = Field(12, ge=1, description="agreeing loops (most inliers first) the free-space test checks")
    map_voxel: float | None = scaled(0.5, "voxel [m] of the merged map sandro-merge writes")
    variance_components: bool = Field(
        True,
        description="once the loops are decided, scale each session's factors and the inter-session loops by the "
        "variance factor their residuals show, relative to the first session's (docs/merge.md)",
    )


class SlamConfig(YamlConfig):
    """Everything `OfflineSlam` and `LoopClosureModule` need; `odometry` is KISS-ICP's own config.

    Lengths left None follow the scene: `resolved(scale)` sets each to its reference value (for street-scale
    outdoor scenes) times `scale`; `OfflineSlam` measures the scale from the first scans (`scene_scale`) unless
    `scale` is set. Lengths set explicitly are used as they are.
    """

    scale: float | None = Field(
        None,
        gt=0.0,
        description="length scale of the scene (1: streets, ~0.2: rooms) for the lengths left None; None: "
        "measured from the first scans",
    )
    odometry: KISSConfig = Field(
        default_factory=KISSConfig,
        description=f"KISS-ICP's config; its mapping.voxel_size None means {REFERENCE_ODOMETRY_VOXEL:g} m x scale",
    )
    odometry_gicp: OdometryGicpConfig = Field(default_factory=OdometryGicpConfig)
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    loops: LoopDetectionConfig = Field(default_factory=LoopDetectionConfig)
    registration: LoopRegistrationConfig = Field(default_factory=LoopRegistrationConfig)
    graph: GraphConfig = Field(default_factory=GraphConfig)
    merge: MergeConfig = Field(default_factory=MergeConfig)
    refine: bool | Literal["auto"] = Field(
        "auto",
        description="sandro-slam: a second pass after the first, every scan deskewed again and registered onto the "
        "map of the loop-corrected submaps (`OfflineSlam.refine`); auto: where the sensor sways (a walker, a hand: "
        "`refine.pays`)",
    )
    sweep_times: Literal["auto", "none", "clockwise", "counterclockwise"] = Field(
        "auto",
        description="OfflineSlam, clouds without per-point times: none: taken as deskewed; clockwise or "
        "counterclockwise: raw sweeps of a spinning sensor turning that way seen from above, each sweep starting "
        "behind it, given per-point times from the azimuth (`sweep_times`; not for a swaying sensor); auto: the "
        "direction told from the first scans where they look raw, else none (`sweep_times.detected_rotation`)",
    )

    @property
    def is_resolved(self) -> bool:
        """Whether every length has a value (`resolved` has been applied or every length was set)."""
        return self.scale is not None and not _unset_lengths(self)

    def resolved(self, scale: float | None = None) -> SlamConfig:
        """A copy with `scale` set (the argument, else `self.scale`, else 1) and every length left None set to its
        reference value times that scale."""
        scale = float(scale if scale is not None else self.scale if self.scale is not None else 1.0)
        config = self.model_copy(deep=True)
        config.scale = scale
        for model, name, reference in _unset_lengths(config):
            setattr(model, name, reference * scale)
        return config


def _unset_lengths(config: BaseModel) -> list[tuple[BaseModel, str, float]]:
    """(section, field name, reference value) of every scaled length (see `scaled`) left None, in every section;
    also the odometry voxel and SANDRO's noise bound."""
    unset = []
    for name, field in type(config).model_fields.items():
        value = getattr(config, name)
        if isinstance(value, BaseModel):
            unset += _unset_lengths(value)
        elif value is None and isinstance(field.json_schema_extra, dict) and "reference" in field.json_schema_extra:
            unset.append((config, name, field.json_schema_extra["reference"]))
    if isinstance(config, SlamConfig):
        if config.odometry.mapping.voxel_size is None:
            unset.append((config.odometry.mapping, "voxel_size", REFERENCE_ODOMETRY_VOXEL))
        if config.registration.sandro.noise_bound is None:
            unset.append((config.registration.sandro, "noise_bound", REFERENCE_NOISE_BOUND))
    return unset
