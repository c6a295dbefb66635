"""The thermal model: terms, paths, the one discretisation, and model files."""

from gateway.model.discrete import Section
from gateway.model.model import (
    DiscreteModel,
    ModelStepper,
    PathTF,
    ThermalModel,
    load_model,
    model_to_toml,
    save_model,
)
from gateway.model.terms import FirstOrder, SecondOrder, Term

__all__ = [
    "DiscreteModel", "FirstOrder", "ModelStepper", "PathTF", "SecondOrder", "Section", "Term",
    "ThermalModel", "load_model", "model_to_toml", "save_model",
]
