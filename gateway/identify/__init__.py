"""Identification: from experiment recordings to a thermal model.

Two methods:

- ``joint`` (default, :mod:`gateway.identify.joint`): all paths of an axis fitted at once over all
  experiments, with per-experiment offsets, structure choice and parameter uncertainties.
- ``paper`` (:mod:`gateway.identify.paper`): the paper's procedure, faithfully: V^-1 separation of
  co-varying factors, then a second-order fit of each separated response by steepest descent with a
  numerical gradient. Kept as the reference baseline.
"""

from gateway.identify.api import IdentifyResult, identify

__all__ = ["IdentifyResult", "identify"]
