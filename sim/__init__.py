"""Simulated devices satisfying the acquisition protocols. Not built yet: see the hardware
issue."""
