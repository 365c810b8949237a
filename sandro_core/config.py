"""Typed configuration of the SANDRO solver, with a YAML round trip."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

SplitStrategy = Literal["contiguous", "random", "spatial"]


class StrictModel(BaseModel):
    """A configuration section: unknown keys and invalid values are errors, also on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class YamlConfig(StrictModel):
    """A top-level configuration that loads from and dumps to YAML."""

    @classmethod
    def from_yaml(cls, path: str | Path) -> YamlConfig:
        """Load from a YAML file; unknown keys are an error (pydantic.ValidationError)."""
        data = yaml.safe_load(Path(path).read_text()) or {}
        return cls.model_validate(data)

    @classmethod
    def load(cls, path: str | Path | None) -> YamlConfig:
        """`from_yaml(path)`, or the defaults for None; any problem is a ValueError of one line naming the file
        (what a command line reports)."""
        if path is None:
            return cls()
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"no such config file: {path}")
        try:
            return cls.from_yaml(path)
        except yaml.YAMLError as error:
            raise ValueError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
        except ValidationError as error:
            first = error.errors()[0]
            where = ".".join(str(part) for part in first["loc"]) or "top level"
            more = f" (and {error.error_count() - 1} more)" if error.error_count() > 1 else ""
            raise ValueError(f"{path}: {where}: {first['msg']}{more}") from None

    def to_yaml(self, path: str | Path) -> None:
        Path(path).write_text(yaml.safe_dump(self.model_dump(), sort_keys=False))


class PruningConfig(StrictModel):
    """Consensus stage: pairwise length consistency between correspondences.

    Two correspondences (p_i, q_i) and (p_j, q_j) are consistent when
    | ||p_i - p_j|| - ||q_i - q_j|| | <= pair_threshold * noise_bound. Memory stays O(N): each seed's
    consistent set is built on the fly and capped at `max_set_size`.
    """

    enabled: bool = True
    pair_threshold: float = Field(
        1.0, gt=0.0, description="length-consistency threshold, in noise bounds (2 is the worst case)"
    )
    max_seeds: int = Field(1000, ge=1, description="correspondences whose consistency degree is counted")
    max_clique_seeds: int = Field(128, ge=1, description="highest-degree seeds whose cliques are searched")
    batch_size: int = Field(8, ge=1, description="seeds tried per batch, best first")
    miss_probability: float = Field(
        1e-2,
        gt=0.0,
        lt=1.0,
        description="stop trying seeds once a structure as common as the best is this unlikely to be missed",
    )
    max_set_size: int = Field(64, ge=8, description="cap on one seed's consistent set (subsampled above it)")
    threads_above: int = Field(
        20_000_000, ge=0, description="use all cores when seeds x correspondences reach this many pair checks"
    )
    keep_ratio: float = Field(
        0.3, gt=0.0, le=1.0, description="keep hypotheses scoring at least this fraction of the best one"
    )


class SandroConfig(YamlConfig):
    """Parameters of `sandro_core.register`.

    Lengths are in the units of the input points (metres for LiDAR); `alpha` is a squared length.
    The default is the project's improved solver; `SandroConfig.paper()` is Algorithm 1 of the paper.
    """

    noise_bound: float | None = Field(
        None, gt=0.0, description="inlier residual bound [m]; None: estimated from the target points"
    )
    num_splits: int = Field(4, ge=1, description="sub-sets the correspondences are split into")
    split_strategy: SplitStrategy = "random"
    min_split_size: int = Field(30, ge=3, description="fewer splits are used when sub-sets would be smaller")
    alpha0: float | None = Field(
        None, gt=0.0, description="initial GNC scale [m^2]; None: the largest squared residual at the start"
    )
    alpha_floor: bool = Field(True, description="stop decaying alpha at noise_bound^2 (False: the paper)")
    beta: float = Field(0.7, gt=0.0, lt=1.0, description="alpha <- alpha * beta after each iteration")
    epsilon: float = Field(1e-6, gt=0.0, description="stop when the loss changes less than this")
    relative_epsilon: bool = Field(True, description="epsilon relative to the loss (False: absolute, the paper)")
    max_iterations: int = Field(200, ge=1)
    rescore: bool = Field(True, description="pick the split whose transform scores best on all correspondences")
    refine: bool = Field(True, description="refine the winning transform on all correspondences")
    pruning: PruningConfig = Field(default_factory=PruningConfig)
    min_inliers: int = Field(6, ge=3, description="fewer inliers than this make the result invalid")
    seed: int = 0

    @classmethod
    def paper(cls) -> SandroConfig:
        """Algorithm 1 of the paper, literally: fixed alpha0 decaying without floor, absolute epsilon,
        4 contiguous equal splits, the split with the lowest own loss wins, no pruning, no refinement."""
        return cls(
            num_splits=4,
            split_strategy="contiguous",
            min_split_size=3,
            alpha0=100.0,
            alpha_floor=False,
            beta=0.9,
            epsilon=1e-6,
            relative_epsilon=False,
            max_iterations=1000,
            rescore=False,
            refine=False,
            pruning=PruningConfig(enabled=False),
        )
