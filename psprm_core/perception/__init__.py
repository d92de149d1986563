"""Perception scoring: renderer + real-detector oracle, ray-cast occlusion, neural surrogate."""
