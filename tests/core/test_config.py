"""SandroConfig: YAML round trip and validation."""

from pathlib import Path

import pydantic
import pytest

from sandro_core import SandroConfig

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_yaml_round_trip(tmp_path):
    config = SandroConfig(noise_bound=0.3, num_splits=6, split_strategy="spatial")
    config.to_yaml(tmp_path / "c.yaml")
    assert SandroConfig.from_yaml(tmp_path / "c.yaml") == config


def test_shipped_configs_match_the_code():
    assert SandroConfig.from_yaml(CONFIGS / "sandro.yaml") == SandroConfig()
    assert SandroConfig.from_yaml(CONFIGS / "sandro_paper.yaml") == SandroConfig.paper()


def test_unknown_key_is_an_error(tmp_path):
    (tmp_path / "bad.yaml").write_text("num_splitz: 3\n")
    with pytest.raises(pydantic.ValidationError, match="num_splitz"):
        SandroConfig.from_yaml(tmp_path / "bad.yaml")


def test_out_of_range_is_an_error():
    with pytest.raises(pydantic.ValidationError):
        SandroConfig(beta=1.5)


def test_slam_config_round_trip(tmp_path):
    from sandro_slam import SlamConfig

    assert SlamConfig.from_yaml(CONFIGS / "default.yaml") == SlamConfig()
    config = SlamConfig()
    config.graph.mode = "incremental"
    config.registration.sandro.num_splits = 2
    config.to_yaml(tmp_path / "slam.yaml")
    assert SlamConfig.from_yaml(tmp_path / "slam.yaml") == config
