"""Numpy Gaussian renderer for ERP, Yin/Yang and perspective views (no torch)."""
