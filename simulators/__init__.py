"""Bundled simulators: a physical machine model behind device servers that speak the real protocols."""
