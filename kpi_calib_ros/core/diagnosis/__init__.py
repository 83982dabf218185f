"""Diagnosis: out-of-sample error, model and effect choice, candidate effects, validation on new
data.
"""
