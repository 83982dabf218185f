"""Numerical core: robot model, error parameters, kinematics, estimation and design.

numpy, scipy, casadi and pinocchio only: never rclpy, message types or file formats.
"""
