"""Collision: capsules (eq. 20-22), their fit to URDF geometry, independent checks, link pairs to
skip.
"""
