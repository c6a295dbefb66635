"""cncgw: estimate and compensate CNC machine-tool thermal deformation from signals the CNC already has."""

__version__ = "0.1.0"
