"""Measurement model: tracker points (eq. 3, 4) and tracked 6-DoF poses."""
