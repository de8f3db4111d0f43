"""Figures that reproduce the paper (matplotlib, written as PNG)."""
