"""Observation building, blending rule, TD3 assistant training and evaluation against simulated pilots, policy node."""
