"""Typed configuration of the SLAM plugin, with a YAML round trip (configs/default.yaml)."""

from __future__ import annotations

from typing import Literal

from kiss_icp.config.parser import KISSConfig
from pydantic import Field, model_validator

from sandro_core.config import SandroConfig, StrictModel, YamlConfig


class KeyframeConfig(StrictModel):
    """When a new keyframe starts, and what its submap holds."""

    distance: float = Field(10.0, gt=0.0, description="travel [m] that starts a new keyframe")
    angle_deg: float = Field(30.0, gt=0.0, description="rotation [deg] that starts a new keyframe")
    # 0.5 m: as fine as registration uses (the ICP source is voxelised at 0.5 m, FPFH keypoints are coarser).
    submap_voxel: float = Field(0.5, gt=0.0, description="voxel size [m] of the stored submap")
    submap_radius: float = Field(30.0, gt=0.0, description="submap points farther than this [m] are dropped")


class LoopDetectionConfig(StrictModel):
    """Which keyframe pairs are tried as loop closures, and where that work runs."""

    radius: float = Field(25.0, gt=0.0, description="candidates within this distance [m] of the new keyframe")
    exclude_recent: float = Field(50.0, ge=0.0, description="skip keyframes fewer than this many metres back")
    max_candidates: int = Field(2, ge=1, description="nearest candidates registered per keyframe")
    max_loops_per_keyframe: int = Field(2, ge=1, description="stop registering candidates after this many loops")
    use_map_closures: bool = Field(True, description="add MapClosures place-recognition candidates")
    map_closures_min_inliers: int = Field(5, ge=1, description="ORB inliers a MapClosures candidate needs")
    map_closures_radius: float = Field(
        30.0, gt=0.0, description="submap points within this range [m] form its density map"
    )
    map_closures_spacing: float = Field(
        15.0,
        ge=0.0,
        description="MapClosures sees a keyframe only this far [m] along the path from the last one it "
        "saw (its density maps span 2 x map_closures_radius)",
    )
    in_background: bool = Field(
        True,
        description="OfflineSlam, on more than one core: loop closure in a worker process at the lowest CPU "
        "priority, on the cycles the odometry leaves idle (the same results)",
    )


class LoopRegistrationConfig(StrictModel):
    """Registration and verification of one candidate pair of submaps."""

    fpfh_voxel: float = Field(1.25, gt=0.0, description="voxel [m] of the FPFH keypoints")
    fpfh_max_nn: int = Field(50, ge=1, description="neighbours per FPFH descriptor (its cost grows linearly with it)")
    sandro: SandroConfig = Field(default_factory=lambda: SandroConfig(noise_bound=1.0))
    icp_refine: bool = Field(True, description="point-to-plane ICP from the SANDRO transform")
    icp_max_distance: float = Field(1.0, gt=0.0, description="ICP correspondence distance [m]")
    icp_voxel: float = Field(
        0.5, gt=0.0, description="voxel [m] of the source submap points ICP aligns onto the target's keypoints"
    )
    min_inliers: int = Field(20, ge=3, description="SANDRO inliers a loop needs")
    min_overlap: float = Field(
        0.3, ge=0.0, le=1.0, description="share of those source points within icp_max_distance of target keypoints"
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
    descriptor_radius: float = Field(30.0, gt=0.0, description="radius [m] of the ring-key place descriptor")
    consistency_translation: float = Field(
        1.0, gt=0.0, description="two loops agree when their session transforms move keyframes less than this [m]"
    )
    consistency_rotation_deg: float = Field(2.0, gt=0.0, description="... and differ by less than this [deg]")
    min_loops: int = Field(
        3, ge=1, description="agreeing inter-session loops, kept by the robust back end, that join two sessions"
    )
    guided_radius: float = Field(
        10.0, ge=0.0, description="once aligned, register keyframe pairs this close [m] (0: no guided search)"
    )
    max_free_space_conflict: float = Field(
        0.03,
        ge=0.0,
        le=1.0,
        description="refuse a voted alignment whose agreeing loops put a median share above this of the submap "
        "keypoints where the other session saw free space (an aliased place; docs/merge.md)",
    )
    free_space_voxel: float = Field(0.5, gt=0.0, description="voxel [m] of the free-space test")
    conflict_loops: int = Field(12, ge=1, description="agreeing loops (most inliers first) the free-space test checks")
    map_voxel: float = Field(0.5, gt=0.0, description="voxel [m] of the merged map sandro-merge writes")


class SlamConfig(YamlConfig):
    """Everything `OfflineSlam` and `LoopClosureModule` need; `odometry` is KISS-ICP's own config."""

    odometry: KISSConfig = Field(default_factory=KISSConfig)
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    loops: LoopDetectionConfig = Field(default_factory=LoopDetectionConfig)
    registration: LoopRegistrationConfig = Field(default_factory=LoopRegistrationConfig)
    graph: GraphConfig = Field(default_factory=GraphConfig)
    merge: MergeConfig = Field(default_factory=MergeConfig)

    @model_validator(mode="after")
    def _odometry_voxel(self) -> SlamConfig:
        # KISS-ICP's own default: a voxel of max_range / 100 (KISSConfig() alone leaves it None).
        if self.odometry.mapping.voxel_size is None:
            self.odometry.mapping.voxel_size = self.odometry.data.max_range / 100.0
        return self
