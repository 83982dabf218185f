"""Estimation: constrained least squares with KPI variables (eq. 13, 19), covariance, priors,
robust statistics, outliers, precision.
"""
