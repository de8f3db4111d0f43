"""hbis-torch: Risley-prism foveated imaging (the hybrid bionic image sensor, HBIS)."""

from hbis_torch.config import Camera, Prisms, FoveaSystem
from hbis_torch.errors import HbisInputError

__version__ = "0.1.0"
__all__ = ["Camera", "HbisInputError", "Prisms", "FoveaSystem", "__version__"]
