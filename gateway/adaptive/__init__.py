"""Learning in production: probe measurements update the model online, and every estimate carries its band."""

from gateway.adaptive.filter import AdaptiveEstimator, AxisEstimate, DriftSettings, Replay, replay
from gateway.adaptive.probes import Probe, ProbeDecision

__all__ = ["AdaptiveEstimator", "AxisEstimate", "DriftSettings", "Probe", "ProbeDecision", "Replay", "replay"]
