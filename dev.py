#!/usr/bin/env python3
"""Set up a local virtualenv and run the project's two jobs.

    python3 dev.py demo     the main job: the demo against the bundled simulators
    python3 dev.py test     the whole test suite (ruff, then pytest on 2 cores; the tests that sample on
                            wall time after it, alone; then the numeric tests again under another
                            OpenBLAS kernel, as on another CPU); each phase's time
    python3 dev.py lock     re-resolve constraints.txt to the newest versions pyproject.toml allows
                            (pip-tools, in .venv-lock); ``lock -P numpy`` upgrades one package only

Only a Python >= 3.11 is needed. The first run creates ``.venv`` beside this file and installs the
package with its test extras, every version pinned by ``constraints.txt`` (the lock: the same numpy,
scipy, pymodbus, asyncua on every machine; the wheel itself keeps the ranges in pyproject.toml), with uv
(pip-installed into the venv; pip where uv cannot be had); later
runs reinstall only when ``pyproject.toml`` or ``constraints.txt`` changes. Extra arguments are passed
on (``python3 dev.py test -k profile``, ``python3 dev.py demo --help``).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PY = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".cncgw-installed"
LOCK = ROOT / "constraints.txt"
#: a virtualenv of its own for pip-tools: the lock is written by a tool the tests never see
LOCK_VENV = ROOT / ".venv-lock"
#: the installer of the lock into .venv (pip where it cannot be had): pinned, as everything the suite runs on
UV = "uv==0.13.9"


def _other_kernel() -> str:
    """The OpenBLAS kernel the numeric tests run under a second time: other sums than the default one's.

    Sandybridge (AVX, no FMA: every product rounded before it is added) where the CPU has AVX: 1.6x the
    default Haswell kernel's time on a 400 x 400 product here, where Prescott (no AVX) falls back to Katmai
    and took 3.6x. Prescott on a CPU without AVX, where Sandybridge would stop on an illegal instruction.
    """
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return "Prescott"
    return "SandyBridge" if " avx " in flags or " avx\n" in flags else "Prescott"


OTHER_KERNEL = _other_kernel()
#: pytest processes for the whole suite (pytest-xdist): CI has 2 cores; the tests that sample on wall time
#: (2 ms samplers, scaled clocks) were checked beside one other worker, not more
WORKERS = min(2, os.cpu_count() or 1)


def _ensure_venv() -> None:
    if sys.version_info < (3, 11):
        sys.exit(f"dev.py: Python >= 3.11 is needed, this is {sys.version.split()[0]}")
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes() + LOCK.read_bytes()).hexdigest()
    if PY.exists() and STAMP.exists() and STAMP.read_text().strip() == want:
        return
    start = time.monotonic()
    if not PY.exists():
        print(f"dev.py: creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    print("dev.py: installing cncgw and its test tools into .venv", flush=True)
    how = _install_with_uv() or _install_with_pip()
    STAMP.write_text(want)
    print(f"dev.py: installing with {how} took {time.monotonic() - start:.0f} s", flush=True)


def _install_with_uv() -> str:
    """The lock installed by uv (itself a wheel from the package index, into the venv): "" where it cannot be.

    The same versions as pip installs from ``constraints.txt`` (compared package by package), in 14 s from
    empty caches where pip took 50-96 s on this 2-core PC, most of it pip resolving and unpacking one package
    after another. Where uv cannot be had (no wheel for this platform, an index that does not carry it) or
    fails, pip does the job as before.
    """
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    # a wheel only: where there is none, building uv from source would take Rust and minutes
    if subprocess.call([str(PY), "-m", "pip", "install", "--quiet", "--only-binary", "uv", UV], **quiet) != 0:
        print(f"dev.py: {UV} could not be installed; pip installs instead", flush=True)
        return ""
    # uv reads no pip.conf: the index pip is pointed at by the environment is passed on (a mirror behind a
    # firewall); one set in pip.conf alone is not (uv then takes the lock's versions from PyPI, or fails over to
    # pip below where PyPI is out of reach)
    index = [a for env, flag in (("PIP_INDEX_URL", "--index-url"), ("PIP_EXTRA_INDEX_URL", "--extra-index-url"),
                                 ("PIP_FIND_LINKS", "--find-links"))
             for v in os.environ.get(env, "").split() for a in (flag, v)]
    code = subprocess.call([str(PY), "-m", "uv", "pip", "install", "--quiet", "--python", str(PY), *index,
                            "-c", str(LOCK), "-e", f"{ROOT}[test]"])
    if code != 0:
        print(f"dev.py: uv stopped with code {code}; pip installs instead", flush=True)
        return ""
    return UV


def _install_with_pip() -> str:
    subprocess.run([str(PY), "-m", "pip", "install", "--quiet", "--upgrade", "pip"], check=True)
    subprocess.run([str(PY), "-m", "pip", "install", "--quiet", "-c", str(LOCK), "-e", f"{ROOT}[test]"], check=True)
    return "pip"


def _lock(rest: list[str]) -> int:
    """Rewrite constraints.txt with pip-compile: every package at the newest version the ranges allow."""
    bin_dir = LOCK_VENV / ("Scripts" if os.name == "nt" else "bin")
    py = bin_dir / ("python.exe" if os.name == "nt" else "python")
    if not py.exists():
        print(f"dev.py: creating {LOCK_VENV} for pip-tools", flush=True)
        venv.EnvBuilder(with_pip=True).create(LOCK_VENV)
        subprocess.run([str(py), "-m", "pip", "install", "--quiet", "pip-tools>=7.4"], check=True)
    one = any(a in ("-P", "--upgrade-package") or a.startswith("--upgrade-package=") for a in rest)
    return subprocess.call([str(py), "-m", "piptools", "compile", "--quiet", *([] if one else ["--upgrade"]),
                            "--extra", "test", "--strip-extras", "--no-emit-index-url", "--no-emit-find-links",
                            "--output-file", LOCK.name, "pyproject.toml", *rest], cwd=ROOT,
                           env={**os.environ, "CUSTOM_COMPILE_COMMAND": "python3 dev.py lock"})


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"demo", "test", "lock"}:
        print(__doc__.strip())
        return 2
    job, rest = argv[0], argv[1:]
    if job == "lock":
        return _lock(rest)
    _ensure_venv()
    os.chdir(ROOT)
    if job == "demo":
        return subprocess.call([str(BIN / "cncgw"), "demo", *rest])
    lint = _timed("ruff", [str(PY), "-m", "ruff", "check", "gateway", "drivers", "simulators", "tests", "bench"])
    env = _bytecode_cached()
    if rest:  # a selection as asked, in one process
        return lint or _timed("pytest", [str(PY), "-m", "pytest", *rest], env=env)
    # the whole suite on every core (up to WORKERS), but the tests that sample on wall time (marked
    # ``realtime`` in tests/conftest.py): those after it in one process, alone on the PC. Under xdist each of
    # them waited for the other worker's test to end (a fit of up to 20 s) with its own worker idle, and ran
    # beside that worker's live module fixtures
    workers = ["-n", str(WORKERS)] if WORKERS > 1 else []
    tests = _timed("pytest", [str(PY), "-m", "pytest", *workers, "-m", "not realtime"], env=env)
    realtime = _timed("pytest realtime", [str(PY), "-m", "pytest", "-q", "-m", "realtime"], env=env)
    # fits and filters again on another CPU's arithmetic (another OpenBLAS kernel): what a user on other
    # hardware gets must pass the same physical tolerances, not only this machine's digits
    print(f"dev.py: the numeric tests again with OPENBLAS_CORETYPE={OTHER_KERNEL}", flush=True)
    other_cpu = _timed("numeric again", [str(PY), "-m", "pytest", "-q", *workers, "-m", "numeric and not plumbing"],
                       env={**env, "OPENBLAS_CORETYPE": OTHER_KERNEL})
    return lint or tests or realtime or other_cpu


def _bytecode_cached() -> dict[str, str]:
    """The environment for pytest, compiled modules cached in ``.venv/pycache``.

    With PYTHONDONTWRITEBYTECODE set (as on some CI images and containers) every pytest process and every
    ``cncgw`` child compiled the gateway, the simulators and the tests again (pytest rewriting the tests'
    asserts each time): collecting the suite took 6.7 s a process instead of 2.6 s (measured here). The
    cache is written inside the virtualenv (PYTHONPYCACHEPREFIX), never beside the sources; a prefix the
    user set is kept.
    """
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.setdefault("PYTHONPYCACHEPREFIX", str(VENV / "pycache"))
    return env


def _timed(what: str, cmd: list[str], **kw) -> int:
    """Run ``cmd``; say how long it took (the suite must stay within CI's 10 minutes on 2 cores)."""
    start = time.monotonic()
    code = subprocess.call(cmd, **kw)
    print(f"dev.py: {what} took {time.monotonic() - start:.0f} s", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
