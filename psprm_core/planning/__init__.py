"""Planners (PS-PRM and baselines), graph search and trajectory timing."""
