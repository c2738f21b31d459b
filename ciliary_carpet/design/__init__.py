"""Inverse design: target flows and the curvature layouts that make them."""
