"""One error hierarchy for the whole project.

Every error a user can cause (a bad profile, recording, model file, register value, CLI argument) is a
:class:`GatewayError`; the CLI prints it as one line and exits non-zero, never with a traceback.
Programming errors (bad arguments from our own code) stay ``ValueError``/``TypeError``.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class GatewayError(Exception):
    """Root of every error the gateway reports to a user."""

    exit_code = 1


class UsageError(GatewayError):
    """A command-line argument that argparse cannot check by itself (a range, a combination)."""

    exit_code = 2


class ProfileError(GatewayError):
    """A machine profile is invalid.

    The message holds every problem found, one per line, each naming the file, line and key path, so a
    user fixes them all in one round instead of one per run.
    """

    exit_code = 3

    @property
    def problems(self) -> list[str]:
        return str(self).splitlines()


class RecordingError(GatewayError):
    """A recording file cannot be read as the profile says (names file, row and column)."""

    exit_code = 4


class ModelError(GatewayError):
    """A model file is invalid, or does not fit the profile it is used with."""

    exit_code = 5


class IdentificationError(GatewayError):
    """Identification cannot proceed (e.g. the paper's separation conditions fail)."""

    exit_code = 6


class SimulationError(GatewayError):
    """A scenario is invalid or the simulated machine cannot run it."""

    exit_code = 7


class ServeError(SimulationError):
    """A simulated device cannot start serving (its port in use, no pseudo-terminal).

    A server that cannot start: exit 1 as for any server, not 7 (a bad scenario).
    """

    exit_code = 1


class DriverError(GatewayError):
    """A device driver failed: it names the device and, where it applies, the channel."""

    exit_code = 8


class DeviceTimeout(DriverError):
    """A device did not answer in time."""


class DeviceRefused(DriverError):
    """A device answered a write with a refusal (a Modbus exception): nothing of that write was applied.

    The link itself is fine: :meth:`drivers.base.Driver.write` keeps the connection open.
    """


class CompensationError(GatewayError):
    """A compensation value could not be written safely."""

    exit_code = 9


#: what ``cncgw`` exits with; ``cncgw --help`` and the README show this table
EXIT_CODES: tuple[tuple[int, str], ...] = (
    (0, "success"),
    (1, "failed for another reason (an output exists without --force, a server cannot start, ...)"),
    (2, "usage: an unknown command or option, a bad argument value"),
    (3, "bad profile (every problem listed with file:line, key, value, expected)"),
    (4, "bad recording (file, line and column named)"),
    (5, "bad model file, or a model that does not fit the profile"),
    (6, "identification cannot proceed"),
    (7, "simulation: a bad scenario"),
    (8, "a device failed or did not answer (driver, device and channel named)"),
    (9, "compensation could not be written safely to the CNC"),
    (10, "diagnosis cannot proceed"),
    (130, "interrupted (Ctrl-C)"),
    (141, "output pipe closed (e.g. | head)"),
)


def exit_codes_text() -> str:
    """The exit-code table as plain text, for ``cncgw --help``."""
    return "exit codes:\n" + "\n".join(f"  {code:>3}  {meaning}" for code, meaning in EXIT_CODES)


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """Return ``' (did you mean "x"?)'`` for the closest choice, or ``''`` when none is close."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f' (did you mean "{close[0]}"?)' if close else ""


def expected_one_of(choices: Iterable[str]) -> str:
    """Format a list of allowed values for an error message: ``one of "a", "b"``."""
    return "one of " + ", ".join(f'"{c}"' for c in choices)
