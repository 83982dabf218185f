"""Optimum experimental design (eq. 24): problem, criteria, constraints, exchange algorithm, NLP
refinement.
"""
