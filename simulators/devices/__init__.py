"""Simulated devices (see simulators/live.py for the contract between machine and devices)."""
