"""Physical effects the geometric model lacks: the library and its special cases."""
