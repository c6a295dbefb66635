"""Paths the tests share (importable: pytest puts tests/ on sys.path)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROFILES = ROOT / "profiles"
SHARED_DATA = ROOT.parent / "shared" / "data"
