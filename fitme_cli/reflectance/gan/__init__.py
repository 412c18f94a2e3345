"""BRDF-GAN: the branched StyleGAN2 of FitMe Sec. 3.1 (networks, training, metrics, the shipped model)."""
