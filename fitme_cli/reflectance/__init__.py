"""Reflectance: the skin albedo / specular / normal maps, their augmentation, and (later) BRDF-GAN."""
