"""matplotlib, for the commands that draw: an optional dependency (``pip install 'cncgw[engineering]'``).

An edge PC that only runs ``cncgw run`` does not need it (it saves about 80 MB of the install); identification,
estimation and diagnosis plots, ``cncgw simulate plot`` and the demo's figure do. :func:`pyplot` gives
``matplotlib.pyplot`` on the file-only Agg backend, or a :class:`~gateway.errors.GatewayError` saying what to
install.
"""

from __future__ import annotations

from typing import Any

from gateway.errors import GatewayError

INSTALL_HINT = "pip install 'cncgw[engineering]'"


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend; raise :class:`GatewayError` when matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        raise GatewayError(f"plots need matplotlib, which this install leaves out: {INSTALL_HINT}") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def require(option: str) -> None:
    """Refuse ``option`` (e.g. ``--plot``) before any work when matplotlib is not installed.

    Checked first: an identification or a diagnosis takes seconds to minutes, and failing on the figure at its
    end hid what had been done (a model written, its report unprinted).
    """
    if not available():
        raise GatewayError(f"{option}: plots need matplotlib, which this install leaves out: {INSTALL_HINT} "
                           "(or leave out the option)")


def available() -> bool:
    """Whether matplotlib can be imported (without importing it)."""
    from importlib.util import find_spec

    return find_spec("matplotlib") is not None
