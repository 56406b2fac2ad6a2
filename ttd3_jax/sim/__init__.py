"""The simulator: quadrotor dynamics, reference tracks, the tracking env and its config.

Layer 1: imports nothing else of the package.
"""
