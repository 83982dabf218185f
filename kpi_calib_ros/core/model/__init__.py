"""Robot model: the URDF chain, error parameters, symbolic kinematics, DH report."""
