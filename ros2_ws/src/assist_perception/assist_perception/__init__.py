"""Depth noise model, RGB-D dataset generation, denoising CM-VAE and the encoder node."""
