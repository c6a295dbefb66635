"""Accepted hypotheses into the model: derived inputs and path terms of the same transfer-function model.

A component with gain c adds, to the path from each of its parts' inputs, the part's terms scaled by c
behind the part's dead time. A path has one dead time for all its terms, so a part whose dead time
differs from the path's goes to a second path through a :class:`~gateway.model.inputs.Same` input (the
factor again). Terms with the same dynamics are merged. The model's prediction is then exactly the
identified model plus the accepted contributions diagnosis fitted.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from gateway.diagnose.search import Term
from gateway.model.inputs import DerivedInput, Flag, Product, Same, Sum
from gateway.model.model import PathTF, ThermalModel
from gateway.model.terms import FirstOrder, SecondOrder
from gateway.model.terms import Term as ModelTerm


def extend_model(model: ThermalModel, terms: Mapping[str, Sequence[Term]], *,
                 info: Mapping[str, Any] | None = None) -> ThermalModel:
    """``model`` with every accepted physics term added (artefacts are not physics and stay out)."""
    inputs: list[DerivedInput] = list(model.inputs)
    names = set(model.input_names)
    added: dict[tuple[str, str], list[ModelTerm]] = {}
    delays: dict[tuple[str, str], float] = {}

    def path_delay(axis: str, name: str) -> float | None:
        """The dead time the path already has, or None when it has no terms yet."""
        if (axis, name) in delays:
            return delays[(axis, name)]
        if name in model.input_names and model.path(axis, name).terms:
            return model.path(axis, name).delay_s
        return None

    defined = {d.name: d for d in inputs}
    for axis, axis_terms in terms.items():
        for t in axis_terms:
            if t.trial.hypothesis.artefact:
                continue
            rename: dict[str, str] = {}
            for d in t.setting.chain:
                # names encode the parameters; a clash with another definition gets a suffix
                d = _renamed_sources(d, rename)
                name = d.name
                while name in defined and defined[name] != replace(d, name=name):
                    name += "_"
                if name != d.name:
                    rename[d.name] = name
                    d = replace(d, name=name)
                if name not in defined:
                    inputs.append(d)
                    names.add(name)
                    defined[name] = d
            for comp, c in zip(t.setting.components, t.gains, strict=True):
                for part in comp.parts:
                    target = rename.get(part.input, part.input)
                    have = path_delay(axis, target)
                    if have is not None and abs(have - part.delay_s) > 1e-9:
                        source = target
                        target = f"{source}_delay{round(part.delay_s)}s"
                        if target not in names:
                            inputs.append(Same(name=target, of=source, note=f"{source} behind its own dead time"))
                            names.add(target)
                    added.setdefault((axis, target), []).extend(term.with_gain(float(c) * term.gain)
                                                                for term in part.terms)
                    delays[(axis, target)] = part.delay_s
    probe = replace(model, inputs=tuple(inputs), paths=dict(model.paths))  # every (axis, input) path exists
    paths = []
    for (axis, name), new in added.items():
        old = probe.path(axis, name)
        paths.append(PathTF(axis=axis, factor=name, terms=merge_terms((*old.terms, *new)),
                            delay_s=delays[(axis, name)], sd=old.sd))
    return probe.with_paths(paths, info={**model.info, **(info or {})})


def _renamed_sources(d: DerivedInput, rename: Mapping[str, str]) -> DerivedInput:
    """``d`` reading renamed inputs under their new names."""
    if isinstance(d, Product | Sum):
        return replace(d, of=tuple(rename.get(x, x) for x in d.of))
    if isinstance(d, Flag | Same):
        return replace(d, of=rename.get(d.of, d.of))
    return d


def merge_terms(terms: Sequence[ModelTerm]) -> tuple[ModelTerm, ...]:
    """Terms with identical dynamics summed into one; terms whose gains cancel dropped."""
    out: dict[tuple[object, ...], ModelTerm] = {}
    for t in terms:
        key: tuple[object, ...] = ((t.kind, t.tau_s) if isinstance(t, FirstOrder)
                                   else (t.kind, t.zeta, t.omega_rad_s) if isinstance(t, SecondOrder) else (id(t),))
        out[key] = out[key].with_gain(out[key].gain + t.gain) if key in out else t
    return tuple(t for t in out.values() if t.gain != 0.0)
