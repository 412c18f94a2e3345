"""Fitting a face to photos (FitMe Sec. 3.4): initialisation, losses, inversion and tuning."""
