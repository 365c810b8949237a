"""sandro_core: correspondence-based global point cloud registration with the SANDRO solver."""

from sandro_core.config import PruningConfig, SandroConfig
from sandro_core.registration import register
from sandro_core.result import RegistrationResult

__all__ = ["PruningConfig", "RegistrationResult", "SandroConfig", "register"]
