"""Acquisition: timestamped streams, pairing points with joint states, coupled controller joints."""
