"""Figures. Each function imports matplotlib inside, takes ax=None and returns the figure."""
