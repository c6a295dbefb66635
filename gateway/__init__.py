"""cncgw: estimate and compensate CNC machine-tool thermal deformation from signals the CNC already has."""

from pathlib import Path

__version__ = "0.1.0"

#: the bundled profiles and model (``profiles/`` of the repository, through the ``gateway/bundled`` link;
#: copied into the package when it is built, so an installed gateway has them too)
BUNDLED = Path(__file__).resolve().parent / "bundled"
