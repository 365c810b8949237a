"""The registration solvers the benchmark compares, all with the call shape of `sandro_core.baselines`:
`fn(source, target, noise_bound) -> T_target_source` on (N, 3) correspondences [m]."""

from __future__ import annotations

import numpy as np

from pipelines.bench.baselines import BASELINES, Solver
from pipelines.simulation.correspondences import make_problem
from sandro_core import SandroConfig, register


def sandro(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """SANDRO with the project's default configuration and the given noise bound [m]."""
    return register(source, target, SandroConfig(noise_bound=noise_bound)).transformation


def sandro_paper(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """SANDRO as Algorithm 1 of the paper (`SandroConfig.paper()`), with the given noise bound [m]."""
    config = SandroConfig.paper()
    config.noise_bound = noise_bound
    return register(source, target, config).transformation


def sandro_paper_no_split(source: np.ndarray, target: np.ndarray, noise_bound: float) -> np.ndarray:
    """Algorithm 1 of the paper with one split: what the splitting strategy adds."""
    config = SandroConfig.paper()
    config.noise_bound = noise_bound
    config.num_splits = 1
    return register(source, target, config).transformation


SOLVERS: dict[str, Solver] = {
    "sandro": sandro,
    "sandro_paper": sandro_paper,
    "sandro_paper_1split": sandro_paper_no_split,
    **BASELINES,
}


def warm_up(solver: Solver) -> None:
    """Call `solver` once on a tiny synthetic problem, so that JIT compilation stays out of timings."""
    problem = make_problem(np.random.default_rng(0), 100, 0.5, "uniform")
    solver(problem.source, problem.target, problem.noise_bound)
