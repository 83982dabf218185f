"""Numerical core: robot model, error parameters, kinematics, estimation and design.

numpy, scipy, casadi and pinocchio only: never rclpy, message types or file formats.
One sub-package per family, each importing only from those before it: ``errors`` <
``model`` < ``measurement`` < ``effects`` < ``acquisition`` < ``collision`` <
``estimation`` < ``simulation`` < ``diagnosis`` < ``design`` < ``campaigns``
(``test/test_layers.py`` checks the order).
"""
