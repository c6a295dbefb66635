"""Imports run down the layers: drivers < profile, model, store, acquisition < the live package < commands.

Read from the source with ``ast`` (every import, also those inside functions, which a run would only
meet on some paths), so a new upward import fails here rather than as an import cycle on an edge PC.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests_paths import ROOT

#: what a driver may use of the gateway: errors, the clock, the profile's table reader (nothing above)
DRIVER_MAY_IMPORT = ("gateway.errors", "gateway.clock", "gateway.tomlcheck")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(path: Path) -> set[str]:
    """Every module ``path`` imports (relative imports resolved), at module level or inside functions."""
    return imports_in(path.read_text(encoding="utf-8"), module_name(path), package=path.name == "__init__.py")


def imports_in(source: str, module: str, *, package: bool = False) -> set[str]:
    parent = module if package else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = parent.split(".")[: len(parent.split(".")) - node.level + 1]
                base = ".".join([*up, base]) if base else ".".join(up)
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)  # "from gateway import live" imports gateway.live
    return out


def modules(*folders: str) -> dict[str, set[str]]:
    return {module_name(p): imports(p) for f in folders for p in sorted((ROOT / f).rglob("*.py"))}


def under(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def test_nothing_below_the_live_package_imports_it():
    upward = [f"{m} imports {i}" for m, imps in modules("gateway", "drivers", "simulators").items()
              if not (under(m, "gateway.live") or under(m, "gateway.commands") or m == "gateway.cli")
              for i in sorted(imps) if under(i, "gateway.live")]
    assert upward == []


def test_the_live_package_and_everything_below_it_leave_the_commands_alone():
    upward = [f"{m} imports {i}" for m, imps in modules("gateway", "drivers", "simulators").items()
              if not (under(m, "gateway.commands") or m in ("gateway.cli", "gateway.__main__"))
              for i in sorted(imps) if under(i, "gateway.commands") or i == "gateway.cli"]
    assert upward == []


def test_inside_the_live_package_only_the_runtime_wires_the_parts_together():
    wired = [f"{m} imports {i}" for m, imps in modules("gateway/live").items()
             for i in sorted(imps) if i == "gateway.live.runtime" and m != "gateway.live.runtime"]
    assert wired == []


def test_drivers_use_only_the_gateway_s_errors_clock_and_table_reader():
    reached = [f"{m} imports {i}" for m, imps in modules("drivers").items()
               for i in sorted(imps) if under(i, "gateway") and not any(under(i, ok) for ok in DRIVER_MAY_IMPORT)]
    assert reached == []


def test_the_walk_sees_imports_inside_functions_and_relative_ones():
    # the checks above are only as good as this reader: a deferred or relative import of the live package is seen
    source = """
import json
from gateway.windows import WindowRecord


def export():
    from ..live.probes import ProbeReader
    from .. import live
"""
    found = imports_in(source, "gateway.model.model")
    assert {"json", "gateway.windows", "gateway.live.probes", "gateway.live.probes.ProbeReader",
            "gateway.live"} <= found
    assert imports_in("from .audit import Alarms", "gateway.live", package=True) >= {"gateway.live.audit"}
